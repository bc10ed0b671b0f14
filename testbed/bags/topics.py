"""Topic and frame names, as the real drivers on a Jackal with a Velodyne and a D435i publish them.

``velodyne_pointcloud`` publishes ``/velodyne_points``; ``realsense2_camera`` with
``align_depth`` publishes the colour stream and the depth aligned to it under
``/camera``; the Jackal base publishes wheel odometry from its velocity controller
and the EKF (``robot_localization``) output on ``/odometry/filtered``. Ground truth
and the stack's results go on topics of their own so a real robot's bag never
carries them by accident.
"""
from __future__ import annotations

LIDAR = "/velodyne_points"
LIDAR_PACKETS = "/velodyne_packets"  # velodyne_driver's raw packets (velodyne_msgs/VelodyneScan)
RGB = "/camera/color/image_raw"
RGB_INFO = "/camera/color/camera_info"
DEPTH = "/camera/aligned_depth_to_color/image_raw"
DEPTH_INFO = "/camera/aligned_depth_to_color/camera_info"
RGB_COMPRESSED = RGB + "/compressed"  # image_transport's compressed plugin (PNG here: lossless)
DEPTH_COMPRESSED = DEPTH + "/compressedDepth"  # image_transport's compressed_depth plugin (16-bit PNG)
TF = "/tf"
TF_STATIC = "/tf_static"
WHEEL_ODOM = "/jackal_velocity_controller/odom"
FILTERED_ODOM = "/odometry/filtered"
GT_BASE_POSE = "/ground_truth/base_pose"
GT_OBJECTS = "/ground_truth/objects"
GT_IMAGE_OBJECTS = "/ground_truth/image_objects"  # per camera frame: each object seen from the camera (JSON)
LABELS = "/dopeslam/labels"
MAP = "/dopeslam/map"
TRAJECTORY = "/dopeslam/trajectory"
METADATA = "/dopeslam/metadata"

# Frames (DESIGN.md, REP-103/105).
WORLD = "world"
MAP_FRAME = "map"
ODOM_FRAME = "odom"
BASE = "base_link"
VELODYNE = "velodyne"
CAMERA = "camera_color_optical_frame"

# Names the reader tries, in order, when a topic is not given.
LIDAR_CANDIDATES = (LIDAR, LIDAR_PACKETS, "/points_raw", "/ouster/points", "/os_cloud_node/points", "/lidar/points")
RGB_CANDIDATES = (RGB, RGB_COMPRESSED, "/camera/rgb/image_raw")
DEPTH_CANDIDATES = (DEPTH, DEPTH_COMPRESSED, "/camera/depth/image_rect_raw", "/camera/depth/image_raw")
ODOM_CANDIDATES = (WHEEL_ODOM, FILTERED_ODOM, "/odom")
# Topics of our own results: never taken for sensor input.
RESULT_TOPICS = (LABELS, MAP, GT_OBJECTS)

"""The rosbag boundary: episodes out to ROS 1 / ROS 2 bags, and any robot's bag back in.

- ``writer.BagWriter``: stream LidarScan / CameraFrame / WheelOdometry (plus
  ground truth and the stack's results) into a bag, as the real drivers publish.
- ``reader.BagReader``: the stack's messages, intrinsics and extrinsics from a
  bag, ours or a real robot's.
- ``convert``: ROS message <-> numpy conversions; ``topics``: the names;
  ``salvage``: recovering truncated bags; ``errors``: what goes wrong.
"""
from .convert import Cuboid
from .errors import (BagError, BagReadError, BagWriteError, CorruptBagError, MissingExtrinsicError,
                     MissingTopicError, UnsupportedEncodingError)
from .reader import BagReader, GroundTruth
from .writer import BagWriter, bag_size, infer_format

__all__ = [
    "BagError", "BagReadError", "BagReader", "BagWriteError", "BagWriter", "CorruptBagError", "Cuboid",
    "GroundTruth", "MissingExtrinsicError", "MissingTopicError", "UnsupportedEncodingError", "bag_size",
    "infer_format",
]

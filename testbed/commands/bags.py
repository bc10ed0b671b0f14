"""``dopeslam record [SCENARIO] --bag PATH [--format ros1|ros2] [--storage sqlite3|mcap] --seed N [--duration S]``
and ``dopeslam replay BAG --out DIR [--lidar-topic T] [--rgb-topic T] [--depth-topic T] [--camera-info-topic T]
[--input rgb|depth] [--fpr/--no-fpr] [--stages 1-6] [--weights W] [--policy P] [--detector MODULE:CLASS]
[--odometry NAME|MODULE:CLASS]``."""
from __future__ import annotations

from stack.errors import UsageError
from testbed.commands.options import REPLAY_APPLIES, add_config_options, config_error, config_from_args
from testbed.commands.run import CONFIG_DEFAULT, add_dope_options, add_odometry_option, add_view_options, open_view


def register(sub) -> None:
    p = sub.add_parser("record", help="record an episode to a rosbag (driver topics + ground truth)")
    p.add_argument("scenario", nargs="?", default=None, help="bundled name or TOML path (default: the default scenario)")
    p.add_argument("--bag", required=True, help="output bag: ROS 1 'NAME.bag' file or ROS 2 directory")
    p.add_argument("--format", choices=["ros1", "ros2"], default=None,
                   help="default: ros1 when --bag ends in .bag, else ros2")
    p.add_argument("--storage", choices=["sqlite3", "mcap"], default="mcap", help="ROS 2 storage (default mcap)")
    p.add_argument("--images", choices=["raw", "compressed"], default="compressed",
                   help="camera topics: lossless PNG CompressedImage (.../compressed, .../compressedDepth; "
                        "default) or raw sensor_msgs/Image")
    p.add_argument("--lidar", choices=["points", "packets"], default=None,
                   help="LiDAR topic: PointCloud2 on /velodyne_points, or the VLP-32C's data packets on "
                        "/velodyne_packets (velodyne_msgs/VelodyneScan; lossless, ~7x smaller; the Velodyne then "
                        "publishes packets: ranges in 4 mm steps). Default: packets where the scenario's "
                        "[sensors] lidar_packets is on, else points")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's)")
    p.add_argument("--light", type=float, default=None, help="override the scenario's light level (0-1)")
    p.add_argument("--force", action="store_true", help="replace an existing bag")
    p.add_argument("--fault", dest="faults", action="append", default=[], metavar="NAME=VALUE",
                   help="a sensor fault over the scenario's [faults] (docs/faults.md): the bag carries the "
                        "messages as the faulty drivers publish them")
    p.set_defaults(func=record)

    p = sub.add_parser("replay", help="run the stack offline on a rosbag (ours or a real robot's): "
                                      "report, labels.xlsx, map.png")
    p.add_argument("bag", help="ROS 1 .bag file, ROS 2 bag directory, or .mcap/.db3 file")
    p.add_argument("--out", default="out/replay")
    p.add_argument("--lidar-topic", default=None, help="PointCloud2 topic (default /velodyne_points or the only one)")
    p.add_argument("--rgb-topic", default=None, help="colour Image/CompressedImage topic")
    p.add_argument("--depth-topic", default=None, help="depth Image topic, aligned to colour (16UC1 mm or 32FC1 m)")
    p.add_argument("--camera-info-topic", default=None, help="CameraInfo of the colour stream")
    p.add_argument("--policy", default=None,
                   help="labelling policy: last, last-fpr, best-score, robust-mean (default), ..., or MODULE:FUNCTION")
    p.add_argument("--detector", default=None, metavar="MODULE:CLASS",
                   help="your detector instead of DOPE (a class constructed with no arguments, with "
                        "detect(frame) -> list[Detection]); --input, --stages, --fpr and --weights then do not apply")
    add_odometry_option(p)
    p.add_argument("--dope-every", type=int, default=None, help="run DOPE on every N-th image (default 1)")
    p.add_argument("--sequential", action="store_true",
                   help="run the detector in the message loop (default: ahead of it, on a second reader in a thread)")
    p.add_argument("--odometry-only", action="store_true",
                   help="the LiDAR odometry alone: no images read, no detector (trajectory, LiDAR map and "
                        "map.png; labels.xlsx stays empty)")
    p.add_argument("--results-bag", default=None, help="where the results bag goes (default OUT/results_bag); "
                   "an existing path is refused unless --force, the input bag always")
    p.add_argument("--force", action="store_true", help="replace an existing --results-bag")
    p.add_argument("--T-base-lidar", dest="T_base_lidar", default=None, metavar="X,Y,Z,ROLL,PITCH,YAW",
                   help="the LiDAR's pose on the robot (m, deg) when /tf_static lacks or misstates it")
    p.add_argument("--T-base-camera", dest="T_base_camera", default=None, metavar="X,Y,Z,ROLL,PITCH,YAW",
                   help="the colour optical frame's pose on the robot (m, deg), as --T-base-lidar")
    p.add_argument("--base-frame", default=None, help="the robot's frame in /tf_static (default base_link)")
    p.add_argument("--max-bad-messages", type=int, default=10,
                   help="messages per topic that cannot be converted which are skipped and reported (or 1 %% of "
                        "the topic's, if more) before the replay stops")
    p.add_argument("--loop-closure", action="store_true",
                   help="close loops (key frames from the colour images + LiDAR) and place labels on the corrected trajectory")
    p.add_argument("--vocabulary", default=None, help="place-recognition vocabulary .npz (default: the bundled one)")
    add_dope_options(p, defaults=False, unset=CONFIG_DEFAULT)
    add_config_options(p)
    p.add_argument("--json", action="store_true", help="print the report (report.json's content) as JSON on stdout (logs on stderr)")
    add_view_options(p)
    p.set_defaults(func=replay)


def record(args) -> int:
    import json

    from testbed.record import record_episode

    if args.format == "ros1" and not args.bag.endswith(".bag"):
        raise UsageError(f"--bag {args.bag}: a ROS 1 bag's name must end in .bag")
    if args.format == "ros2" and args.bag.endswith(".bag"):
        raise UsageError(f"--bag {args.bag}: a ROS 2 bag is a directory; its name must not end in .bag")
    from testbed.commands.run import check_dynamic_options

    bad = check_dynamic_options(args, "record")
    if bad is not None:
        return bad
    summary = record_episode(args.scenario, args.bag, args.format, args.storage, args.seed, args.duration,
                             args.light, overwrite=args.force, faults=args.faults, images=args.images,
                             lidar=args.lidar)
    print(json.dumps(summary, indent=2))
    return 0


def parse_pose(text: str | None, option: str):
    """``X,Y,Z,ROLL,PITCH,YAW`` (metres, degrees; rotations about the fixed x, y, z axes) as a 4x4
    transform; else a one-line DopeSlamError naming the option."""
    if text is None:
        return None
    import math

    import numpy as np
    from scipy.spatial.transform import Rotation

    from stack.errors import DopeSlamError

    try:
        v = [float(x) for x in text.replace(" ", ",").split(",") if x]
    except ValueError:
        v = []
    if len(v) != 6 or not all(math.isfinite(x) for x in v) or max(abs(x) for x in v[:3]) > 10:
        raise DopeSlamError(f"{option} {text!r}: expected X,Y,Z,ROLL,PITCH,YAW (six finite numbers: metres "
                            "within 10 m, degrees)")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", v[3:], degrees=True).as_matrix()
    T[:3, 3] = v[:3]
    return T


def replay(args) -> int:
    import sys

    from stack.config import ConfigError
    from stack.interfaces import ImportPathError, load_detector, odometry_factory, resolve_policy
    from testbed.commands.options import finish_outputs, refuse_unapplied
    from testbed.replay import BagTopics, print_replay_summary, replay_bag

    try:
        config = config_from_args(args)  # [run] is the simulator's: read, not used here
        refuse_unapplied(config, REPLAY_APPLIES, "replay")
    except ConfigError as e:
        return config_error("replay", e)
    d, c = config.detector, config.components
    try:
        policy = resolve_policy(config.store.policy)
        # the DOPE detector (no --set components.detector) is built by replay_bag: in its detector process
        # only, where it runs in one
        detector = load_detector(c.detector) if c.detector and not args.odometry_only else None
        odometry_factory(c.odometry)
    except ImportPathError as e:
        print(f"dopeslam replay: --{e}", file=sys.stderr)
        return 2
    if args.results_bag is not None:
        from testbed.io import check_new_output

        check_new_output(args.results_bag, "--results-bag", force=args.force, inputs=[args.bag])
    if args.max_bad_messages < 0:
        raise UsageError(f"--max-bad-messages: expected an integer >= 0, got {args.max_bad_messages}")
    topics = BagTopics(args.lidar_topic, args.rgb_topic, args.depth_topic, args.camera_info_topic,
                       base_frame=args.base_frame, T_base_lidar=parse_pose(args.T_base_lidar, "--T-base-lidar"),
                       T_base_camera=parse_pose(args.T_base_camera, "--T-base-camera"),
                       max_bad_messages=args.max_bad_messages)
    from testbed.commands.run import check_loop_closure
    from testbed.progress import watching

    bad = check_loop_closure(config.loop_closure.enabled, "replay")
    if bad is not None:
        return bad
    view, bad = open_view(args, "replay")
    if bad is not None:
        return bad
    try:
        with watching(view):
            report = replay_bag(args.bag, args.out, input_mode=d.input, stages=d.stages, fpr=d.fpr,
                                weights=d.weights, policy=policy, topics=topics, dope_every=d.every,
                                parallel=not args.sequential, results_bag=args.results_bag,
                                loop_closure=config.loop_closure.enabled, vocabulary=config.loop_closure.vocabulary,
                                detector=detector, odometry=c.odometry, odometry_only=args.odometry_only,
                                odometry_config=config.odometry, keyframes=d.keyframes(), detector_config=d)
    except ImportPathError as e:  # the odometry's constructor failed
        print(f"dopeslam replay: --{e}", file=sys.stderr)
        return 2
    finish_outputs(config.stack(), args.out, report, report["_detector"], seed=report.get("seed"))
    args.json_result = report  # --json (testbed/cli.py)
    print_replay_summary(report)
    print(f"wrote {args.out}/report.json, config.toml, labels.xlsx, labels.json, map.png, estimate_tum.txt"
          + (", groundtruth_tum.txt" if report["ground_truth"]["trajectory"] else "")
          + f", {args.results_bag or args.out + '/results_bag'}")
    return 0


"""The node's ROS 2 transport (rclpy): raw (CDR) subscriptions deserialized with rosbags, as when
a rosbag2 is read, and raw publications serialized with rosbags; the message packages of the
ROS 2 install give the types to subscribe and publish with.

Lidars and the IMU are subscribed best-effort (they match reliable publishers too),
/tf_static transient-local (late joiners get it). Without tf2_msgs (a minimal install) /tf
is not read: the extrinsics then come from the robot YAML's `lidars:` or `--extrinsic`.
"""

from __future__ import annotations

import importlib
import signal
import threading

from torchsoil.node.body import IMU, OUTPUTS, POINTCLOUD2, TFMESSAGE, NodeBody


def message_class(typename: str):
    """The ROS 2 Python class of `typename` (pkg/msg/Name); None when its package is not installed."""
    pkg, _, name = typename.split("/")
    try:
        return getattr(importlib.import_module(f"{pkg}.msg"), name)
    except (ImportError, AttributeError):
        return None


def run(robot, settings, out, resume: bool = False, argv: list[str] | None = None, name: str = "torchsoil") -> int:
    """Run the node until SIGINT or SIGTERM: subscribe, process, publish; at shutdown the last
    windows and the run's outputs. argv: ROS arguments (`--ros-args -r from:=to ...`)."""
    try:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
    except ImportError:
        raise ImportError("ROS 2 is not installed: source /opt/ros/<distro>/setup.bash, or `pip install ros-rclpy "
                          "ros-sensor-msgs ros-diagnostic-msgs ros-nav-msgs ros-std-msgs` (docs/node.md)") from None
    from torchsoil.geo.gridmap import typestore

    store = typestore()           # ROS 2 types, grid_map_msgs included
    args = list(argv or [])
    k = args.index("--ros-args") if "--ros-args" in args else len(args)
    args = ["--ros-args", *[a for r in args[:k] for a in ("-r", r)], *args[k + 1:]]   # from:=to as ROS 1 gives them
    rclpy.init(args=["torchsoil", *args])
    node = rclpy.create_node(name)
    log = node.get_logger()
    gridmap = settings.node.gridmap != "off" and message_class(OUTPUTS["grid_map"][0]) is not None
    if settings.node.gridmap == "on" and not gridmap:
        log.warning("grid_map_msgs is not installed: no ~/terrain/grid_map (apt install ros-$ROS_DISTRO-grid-map-msgs)")
    publish = _publishers(node, store, gridmap)
    body = NodeBody(robot, settings, out, publish, store, resume=resume, gridmap=gridmap, log=log.info)
    subs = _subscribe(node, store, body, settings)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    body.start()
    log.info(f"listening on {', '.join(s.topic_name for s in subs)}; writing {out}")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    while not stop.is_set() and rclpy.ok():
        executor.spin_once(timeout_sec=0.1)
    body.stop()                      # the last windows are still published
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _publishers(node, store, gridmap: bool):
    """publish(key, typename, msg) over a publisher per OUTPUTS entry whose type is installed."""
    pubs = {}
    for key, (typename, topic, _) in OUTPUTS.items():
        cls = message_class(typename)
        if key == "grid_map" and not gridmap:
            continue
        if cls is None:
            node.get_logger().warning(f"{typename} is not installed: {topic} not published")
            continue
        pubs[key] = node.create_publisher(cls, topic, 10)
    lock = threading.Lock()

    def publish(key: str, typename: str, msg) -> None:
        pub = pubs.get(key)
        if pub is not None:
            with lock:
                pub.publish(bytes(store.serialize_cdr(msg, typename)))

    return publish


def _subscribe(node, store, body: NodeBody, settings) -> list:
    """Raw subscriptions of the lidars, /tf, /tf_static and the IMU, handed to body.receive."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

    def callback(topic: str, typename: str):
        def take(raw: bytes):
            try:
                msg = store.deserialize_cdr(raw, typename)
            except Exception as e:
                body.health.problem("decode", f"{topic}: {type(e).__name__}: {e}")
                return
            body.receive(topic, typename, msg)
        return take

    r = settings.pipeline.read
    best_effort = ReliabilityPolicy.RELIABLE if settings.node.reliable else qos_profile_sensor_data.reliability
    latched = QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
    inputs = [(r.front_topic, POINTCLOUD2, QoSProfile(depth=settings.node.queue, reliability=best_effort)),
              (r.back_topic, POINTCLOUD2, QoSProfile(depth=settings.node.queue, reliability=best_effort)),
              ("/tf", TFMESSAGE, QoSProfile(depth=100)), (r.tf_topic, TFMESSAGE, latched)]
    if body.imu_topic:
        inputs.append((body.imu_topic, IMU, QoSProfile(depth=1000, reliability=best_effort)))
    subs = []
    for topic, typename, qos in {t[0]: t for t in inputs}.values():
        cls = message_class(typename)
        if cls is None:
            hint = " (extrinsics from the robot YAML `lidars:` or --extrinsic)" if typename == TFMESSAGE else ""
            node.get_logger().warning(f"{typename} is not installed: {topic} not read{hint}")
            continue
        subs.append(node.create_subscription(cls, topic, callback(topic, typename), qos, raw=True))
    return subs

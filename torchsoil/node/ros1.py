"""The node's ROS 1 transport (rospy): raw subscriptions deserialized with rosbags (from the
message definitions the publishers send, as when a ROS 1 bag is read), raw publications
serialized with rosbags under the definitions and MD5 sums of ROS 1's message packages.

rospy from Debian's packages (`apt install ros-core python3-rospy`) lives in the system
Python's dist-packages; a Python of another prefix finds it there (`DEBIAN_ROS`).
"""

from __future__ import annotations

import signal
import sys
import threading

from torchsoil.io.pointcloud import LIVOX_CUSTOM
from torchsoil.node.body import IMU, OUTPUTS, POINTCLOUD2, TFMESSAGE, NodeBody

DEBIAN_ROS = "/usr/lib/python3/dist-packages"


def import_rospy():
    """rospy and genpy, from this Python or Debian's dist-packages; ImportError saying how to
    install ROS 1 when neither has it."""
    try:
        import genpy
        import rospy
    except ImportError:
        if DEBIAN_ROS not in sys.path:
            sys.path.append(DEBIAN_ROS)
        try:
            import genpy
            import rospy
        except ImportError:
            raise ImportError("ROS 1 is not installed: on Debian `apt install ros-core python3-rospy "
                              "python3-sensor-msgs python3-tf2-msgs python3-diagnostic-msgs python3-nav-msgs`, "
                              "or source your ROS 1 setup.bash") from None
    return rospy, genpy


def ros1_name(typename: str) -> str:
    """sensor_msgs/msg/PointCloud2 -> sensor_msgs/PointCloud2."""
    return typename.replace("/msg/", "/")


def ros2_name(typename: str) -> str:
    """sensor_msgs/PointCloud2 -> sensor_msgs/msg/PointCloud2."""
    pkg, _, name = typename.partition("/")
    return typename if "/msg/" in typename else f"{pkg}/msg/{name}"


def private(topic: str) -> str:
    """`~/soil` (the ROS 2 spelling of a private name) as rospy's `~soil`."""
    return "~" + topic[2:] if topic.startswith("~/") else topic


def raw_publisher(rospy, genpy, store, topic: str, typename: str, latch: bool = False):
    """A rospy Publisher of already-serialized messages of `typename` (a rosbags ROS 1 type)."""
    text, md5 = store.generate_msgdef(typename, ros_version=1)

    class Raw(genpy.Message):
        __slots__ = ("buff",)
        _slot_types = ("string",)
        _type, _md5sum, _full_text, _has_header = ros1_name(typename), md5, text, False

        def __init__(self, buff: bytes = b""):
            self.buff = buff

        def serialize(self, b):
            b.write(self.buff)

    return rospy.Publisher(topic, Raw, queue_size=10, latch=latch), Raw


class Decoder:
    """Raw ROS 1 messages to rosbags objects, each type registered from its publisher's
    message definition the first time it is seen."""

    def __init__(self, store):
        self.store = store
        self.lock = threading.Lock()

    def __call__(self, raw) -> tuple[str, object]:
        header = raw._connection_header
        typename = ros2_name(header["type"])
        with self.lock:
            if typename not in self.store.types:
                from rosbags.typesys import get_types_from_msg

                self.store.register(get_types_from_msg(header["message_definition"], typename))
        return typename, self.store.deserialize_ros1(raw._buff, typename)


def typestore():
    """rosbags' ROS 1 (Noetic) typestore with tf2_msgs/TFMessage, which it lacks."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TFMESSAGE))
    return store


def run(robot, settings, out, resume: bool = False, argv: list[str] | None = None, name: str = "torchsoil") -> int:
    """Run the node until SIGINT or SIGTERM (or rosnode kill): subscribe, process, publish;
    at shutdown the last windows and the run's outputs. argv: ROS remappings (`from:=to`,
    `__name:=`, `__ns:=`)."""
    rospy, genpy = import_rospy()
    store = typestore()
    rospy.init_node(name, argv=["torchsoil"] + list(argv or []), disable_signals=True)
    if settings.node.gridmap == "on":
        rospy.logwarn("torchsoil: grid_map_msgs/GridMap is published under ROS 2 only; the terrain goes out as "
                      "PointCloud2 and OccupancyGrid")
    pubs = {}
    for key, (typename, topic, _) in OUTPUTS.items():
        if key == "grid_map":
            continue
        pubs[key] = raw_publisher(rospy, genpy, store, private(topic), typename)
    lock = threading.Lock()

    def publish(key: str, typename: str, msg) -> None:
        pub, Raw = pubs[key]
        with lock:
            pub.publish(Raw(store.serialize_ros1(msg, typename)))

    body = NodeBody(robot, settings, out, publish, store, resume=resume, gridmap=False, log=rospy.loginfo)
    decode = Decoder(store)
    wanted = {POINTCLOUD2, TFMESSAGE, IMU, *LIVOX_CUSTOM}

    def callback(topic: str):
        def take(raw):
            try:
                typename, msg = decode(raw)
            except Exception as e:
                body.health.problem("decode", f"{topic}: {type(e).__name__}: {e}")
                return
            if typename in wanted:
                body.receive(topic, typename, msg)
        return take

    r = settings.pipeline.read
    lidars = (r.front_topic, r.back_topic)
    inputs = [*lidars, "/tf", r.tf_topic] + ([body.imu_topic] if body.imu_topic else [])
    subs = [rospy.Subscriber(t, rospy.AnyMsg, callback(t), queue_size=settings.node.queue if t in lidars else 1000,
                             buff_size=2 ** 26, tcp_nodelay=True) for t in dict.fromkeys(inputs)]
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    body.start()
    rospy.loginfo(f"torchsoil: listening on {', '.join(s.resolved_name for s in subs)}; writing {out}")
    while not stop.is_set() and not rospy.is_shutdown():
        stop.wait(0.2)
    for s in subs:
        s.unregister()
    body.stop()
    rospy.signal_shutdown("torchsoil node stopped")
    return 0

"""Extrinsics as real bags carry them, written here with rosbags' own types and serializers:
/tf only (ROS 1 static_transform_publisher), split over /tf_static and /tf, chains, leading
slashes, two lidars in one frame, and per-topic extrinsics."""

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

from torchsoil.io.bag import BagError, read_recording
from torchsoil.io.extrinsics import extrinsics_for
from torchsoil.pipeline.run import process_bag
from torchsoil.robot import paper_platform
from torchsoil.settings import PipelineConfig, ReadConfig

FRONT, BACK = "/lidar_front/points", "/lidar_back/points"


def typestore(ros1):
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


def header(ts, t, frame):
    T = ts.types
    extra = {"seq": 0} if "seq" in T["std_msgs/msg/Header"].__dataclass_fields__ else {}
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(t % 1 * 1e9)),
                                    frame_id=frame, **extra)


def cloud(ts, t, frame, n=64, seed=0):
    """A PointCloud2 of n random points, x y z float32 only."""
    T = ts.types
    xyz = np.random.default_rng(seed).normal(size=(n, 3)).astype("<f4")
    fields = [T["sensor_msgs/msg/PointField"](name=a, offset=4 * i, datatype=7, count=1) for i, a in enumerate("xyz")]
    return T["sensor_msgs/msg/PointCloud2"](header=header(ts, t, frame), height=1, width=n, fields=fields,
                                            is_bigendian=False, point_step=12, row_step=12 * n,
                                            data=xyz.view(np.uint8).reshape(-1), is_dense=True)


def tf(ts, t, links):
    """TFMessage of (parent, child, [x, y, z], [roll, pitch, yaw]) links."""
    T = ts.types
    out = []
    for parent, child, xyz, rpy in links:
        q = Rotation.from_euler("xyz", rpy).as_quat()
        out.append(T["geometry_msgs/msg/TransformStamped"](
            header=header(ts, t, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))))
    return T["tf2_msgs/msg/TFMessage"](transforms=out)


def write(path, messages, ros1=False):
    """messages: (topic, msgtype, time [s], message); ROS 1 .bag or ROS 2 sqlite3."""
    ts = typestore(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, ser = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, ser = Writer(path, version=8), ts.serialize_cdr
    conns = {}
    with writer:
        for topic, msgtype, t, msg in sorted(messages, key=lambda m: m[2]):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], int(t * 1e9), ser(msg, msgtype))
    return path


def clouds(ts, front_frame, back_frame, n=3):
    return [m for k in range(n) for m in (
        (FRONT, "sensor_msgs/msg/PointCloud2", 10 + 0.1 * k, cloud(ts, 10 + 0.1 * k, front_frame, seed=k)),
        (BACK, "sensor_msgs/msg/PointCloud2", 10.05 + 0.1 * k, cloud(ts, 10.05 + 0.1 * k, back_frame, seed=9 + k)))]


def pose(xyz, rpy):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    T[:3, 3] = xyz
    return T


def test_tf_only_as_ros1_static_transform_publisher_writes_it(tmp_path):
    """ROS 1: the extrinsics repeated at 10 Hz on /tf, no /tf_static at all."""
    ts = typestore(True)
    links = [("base_link", "lidar_front", [0.9, 0, 0.8], [0, 0.3, 0]),
             ("base_link", "lidar_back", [-0.9, 0.1, 0.8], [0, 0.3, np.pi])]
    msgs = clouds(ts, "lidar_front", "lidar_back") + [
        ("/tf", "tf2_msgs/msg/TFMessage", 9.95 + 0.1 * k, tf(ts, 9.95 + 0.1 * k, links)) for k in range(4)]
    rec = read_recording(write(tmp_path / "r.bag", msgs, ros1=True))
    ext = extrinsics_for(rec, ReadConfig(), {FRONT: "lidar_front", BACK: "lidar_back"})
    np.testing.assert_allclose(ext[FRONT], pose([0.9, 0, 0.8], [0, 0.3, 0]), atol=1e-12)
    np.testing.assert_allclose(ext[BACK][:3, 3], [-0.9, 0.1, 0.8], atol=1e-12)


def test_chain_split_over_tf_static_and_tf_composes(tmp_path):
    """Ouster: base_link -> os_sensor (the robot's URDF, /tf_static) -> os_lidar (the driver,
    /tf), the clouds in os_lidar. os_sensor at (1, 0, 1) turned 90 deg left; os_lidar 36 mm
    above it turned 180 deg: os_lidar's x axis points along -y of base_link, so its point
    (1, 0, 0) is at (1, -1, 1.036)."""
    ts = typestore(False)
    msgs = clouds(ts, "os_lidar", "lidar_back") + [
        ("/tf_static", "tf2_msgs/msg/TFMessage", 9.9, tf(ts, 9.9, [
            ("base_link", "os_sensor", [1, 0, 1], [0, 0, np.pi / 2]),
            ("base_link", "lidar_back", [-1, 0, 1], [0, 0, np.pi])])),
        ("/tf", "tf2_msgs/msg/TFMessage", 9.95,
         tf(ts, 9.95, [("os_sensor", "os_lidar", [0, 0, 0.036], [0, 0, np.pi])])),
        # a moving frame on /tf does no harm
        ("/tf", "tf2_msgs/msg/TFMessage", 10.0, tf(ts, 10.0, [("odom", "base_link", [5, 5, 0], [0, 0, 1])]))]
    rec = read_recording(write(tmp_path / "r", msgs))
    T = extrinsics_for(rec, ReadConfig(), {FRONT: "os_lidar", BACK: "lidar_back"})[FRONT]
    np.testing.assert_allclose(T @ [1, 0, 0, 1], [1, -1, 1.036, 1], atol=1e-12)
    np.testing.assert_allclose(T @ [0, 1, 0, 1], [2, 0, 1.036, 1], atol=1e-12)


def test_tf_static_wins_over_tf_for_one_frame(tmp_path):
    ts = typestore(False)
    msgs = clouds(ts, "lidar_front", "lidar_back") + [
        ("/tf", "tf2_msgs/msg/TFMessage", 9.9, tf(ts, 9.9, [("base_link", "lidar_front", [7, 7, 7], [0, 0, 0])])),
        ("/tf_static", "tf2_msgs/msg/TFMessage", 9.95, tf(ts, 9.95, [
            ("base_link", "lidar_front", [1, 2, 3], [0, 0, 0]), ("base_link", "lidar_back", [0, 0, 0], [0, 0, 0])]))]
    rec = read_recording(write(tmp_path / "r", msgs))
    np.testing.assert_allclose(rec.extrinsics["lidar_front"][:3, 3], [1, 2, 3])


@pytest.mark.parametrize("in_tf, in_cloud", [(True, False), (False, True)])
def test_leading_slashes_are_ignored(tmp_path, in_tf, in_cloud):
    ts = typestore(True)
    s_tf, s_cloud = ("/" if in_tf else ""), ("/" if in_cloud else "")
    msgs = clouds(ts, s_cloud + "lidar_front", s_cloud + "lidar_back") + [
        ("/tf", "tf2_msgs/msg/TFMessage", 9.9, tf(ts, 9.9, [
            (s_tf + "base_link", s_tf + "lidar_front", [1, 0, 0], [0, 0, 0]),
            (s_tf + "base_link", s_tf + "lidar_back", [-1, 0, 0], [0, 0, 0])]))]
    rec = read_recording(write(tmp_path / "r.bag", msgs, ros1=True), base_frame="/base_link")
    ext = extrinsics_for(rec, ReadConfig(), {FRONT: rec.front[0].frame, BACK: rec.back[0].frame})
    assert ext[FRONT][0, 3] == 1 and ext[BACK][0, 3] == -1


def test_two_lidars_in_one_frame_are_refused_with_the_frame_named(tmp_path):
    """Both drivers left at their default frame: per-frame extrinsics would give the back lidar
    the front's pose; the run stops naming the frame, both topics and the way out."""
    ts = typestore(False)
    msgs = clouds(ts, "os_sensor", "/os_sensor") + [
        ("/tf_static", "tf2_msgs/msg/TFMessage", 9.9, tf(ts, 9.9, [("base_link", "os_sensor", [1, 0, 1], [0, 0, 0])]))]
    path = write(tmp_path / "r", msgs)
    with pytest.raises(ValueError, match=r"'/lidar_front/points' and '/lidar_back/points' both publish in frame "
                                         r"'os_sensor'.*lidars: \{/lidar_front/points: .*--extrinsic TOPIC"):
        process_bag(path, paper_platform())
    # a per-frame override does not help: it still names one pose for two sensors
    cfg = ReadConfig(extrinsics={"os_sensor": (1, 0, 1, 0, 0, 0)})
    with pytest.raises(ValueError, match="both publish in frame 'os_sensor'"):
        extrinsics_for(read_recording(path), cfg, {FRONT: "os_sensor", BACK: "/os_sensor"})
    # one topic given on its own is enough: the other keeps the frame's pose
    cfg = ReadConfig(extrinsics={"lidar_back/points": (-1, 0, 1, 0, 0, np.pi)})
    ext = extrinsics_for(read_recording(path), cfg, {FRONT: "os_sensor", BACK: "/os_sensor"})
    np.testing.assert_allclose(ext[FRONT][:3, 3], [1, 0, 1])
    np.testing.assert_allclose(ext[BACK], pose([-1, 0, 1], [0, 0, np.pi]), atol=1e-12)


def test_missing_frame_is_named_with_the_frames_known(tmp_path):
    ts = typestore(False)
    msgs = clouds(ts, "velodyne", "lidar_back") + [
        ("/tf_static", "tf2_msgs/msg/TFMessage", 9.9, tf(ts, 9.9, [("base_link", "lidar_back", [0, 0, 0], [0, 0, 0]),
                                                                  ("mount", "velodyne", [0, 0, 0], [0, 0, 0])]))]
    rec = read_recording(write(tmp_path / "r", msgs))
    with pytest.raises(ValueError, match=r"no extrinsic for frame 'velodyne' of '/lidar_front/points'.*lidar_back"):
        extrinsics_for(rec, ReadConfig(), {FRONT: "velodyne", BACK: "lidar_back"})


def test_per_topic_extrinsics_run_with_both_lidars_in_one_frame(tmp_path):
    """The toy scene's two lidars both publish in `os_sensor`; /tf_static gives that frame the
    front lidar's pose. With the poses given per topic (robot YAML keys) the run tracks the
    1 m/s drive; without them it is refused (above)."""
    from tests.pipeline.toyscene import ToyScene
    from torchsoil.io.extrinsics import extrinsics_from_robot_yaml
    from torchsoil.io.write import write_bag

    scene = ToyScene(columns=128)
    msgs = scene.messages(4.0)
    for _, m in msgs:
        m.header.frame_id = "os_sensor"
    path = write_bag(tmp_path / "b", msgs, {"os_sensor": scene.extrinsics["lidar_front"]})
    lines = ["lidars:"]
    for name, T in scene.extrinsics.items():
        v = [*T[:3, 3], *Rotation.from_matrix(T[:3, :3]).as_euler("xyz")]
        lines.append(f"  /{name}/points: [{', '.join(repr(float(x)) for x in v)}]")
    (tmp_path / "robot.yaml").write_text("\n".join(lines) + "\n")
    cfg = PipelineConfig().replace(read={"extrinsics": extrinsics_from_robot_yaml(tmp_path / "robot.yaml")})
    res = process_bag(path, paper_platform(), cfg)
    assert res.terrain.poses[-1, 1] == pytest.approx(3.9, abs=0.05)  # 1 m/s for 3.9 s
    assert np.isfinite(res.terrain.h_back).sum() > 100


def test_several_imu_topics_need_a_choice(tmp_path):
    ts = typestore(False)
    T = ts.types
    V = T["geometry_msgs/msg/Vector3"]

    def imu(t):
        return T["sensor_msgs/msg/Imu"](
            header=header(ts, t, "imu_link"), orientation=T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1),
            orientation_covariance=np.zeros(9), angular_velocity=V(x=0.1, y=0, z=0),
            angular_velocity_covariance=np.zeros(9), linear_acceleration=V(x=0, y=0.5, z=9.8),
            linear_acceleration_covariance=np.zeros(9))

    msgs = clouds(ts, "lidar_front", "lidar_back") + [
        (topic, "sensor_msgs/msg/Imu", 10 + 0.01 * k, imu(10 + 0.01 * k))
        for topic in ("/imu/data", "/os_cloud_node/imu") for k in range(5)]
    path = write(tmp_path / "r", msgs)
    with pytest.raises(BagError, match=r"several IMU topics \['/imu/data', '/os_cloud_node/imu'\]"):
        read_recording(path)
    rec = read_recording(path, imu_topic="/imu/data")
    assert rec.imu.frame == "imu_link" and rec.imu.topic == "/imu/data"
    np.testing.assert_allclose(rec.imu.t, 10 + 0.01 * np.arange(5))
    np.testing.assert_allclose(rec.imu.acc, [[0, 0.5, 9.8]] * 5)
    np.testing.assert_allclose(rec.imu.gyro, [[0.1, 0, 0]] * 5)
    assert read_recording(path, imu_topic="none").imu is None
    with pytest.raises(BagError, match="'/imu' not found"):
        read_recording(path, imu_topic="/imu")

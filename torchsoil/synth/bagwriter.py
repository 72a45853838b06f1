"""rosbag2 output through `rosbags`: PointCloud2 lidar sweeps, sensor_msgs/Imu,
sensor_msgs/NavSatFix and /tf_static (docs/formats.md section 1), in sqlite3 or mcap storage
(mcap optionally with zstd chunk compression)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_typestore

POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                        ("t", "<u4"), ("ring", "<u2")])
_DATATYPE = {"<f4": 7, "<u4": 6, "<u2": 4}   # sensor_msgs/PointField constants

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
_T = TYPESTORE.types
_ZERO = QosTime(0, 0)
TF_STATIC_QOS = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                    _ZERO, _ZERO, QosLiveliness.AUTOMATIC, _ZERO, False)


def stamp(t_ns: int):
    """builtin_interfaces/Time from integer nanoseconds."""
    return _T["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))


def pointcloud2(points: np.ndarray, frame_id: str, t_ns: int):
    """A PointCloud2 from a structured array of POINT_DTYPE: (N,) unorganized, or (H, W)
    organized (rows = rings; no-return points NaN, and then is_dense is false)."""
    if points.dtype != POINT_DTYPE:
        raise ValueError(f"points must have dtype {POINT_DTYPE}, got {points.dtype}")
    if points.ndim not in (1, 2):
        raise ValueError(f"points must be (N,) or (H, W), got shape {points.shape}")
    height, width = points.shape if points.ndim == 2 else (1, len(points))
    PF = _T["sensor_msgs/msg/PointField"]
    fields = [PF(name=n, offset=POINT_DTYPE.fields[n][1], datatype=_DATATYPE[POINT_DTYPE.fields[n][0].str],
                 count=1) for n in POINT_DTYPE.names]
    data = np.frombuffer(np.ascontiguousarray(points).tobytes(), dtype=np.uint8)
    header = _T["std_msgs/msg/Header"](stamp=stamp(t_ns), frame_id=frame_id)
    return _T["sensor_msgs/msg/PointCloud2"](
        header=header, height=height, width=width, fields=fields, is_bigendian=False,
        point_step=POINT_DTYPE.itemsize, row_step=POINT_DTYPE.itemsize * width, data=data,
        is_dense=bool(np.isfinite(points["x"]).all()))


def tf_message(transforms: list[tuple[str, str, np.ndarray, np.ndarray]], t_ns: int):
    """TFMessage from (parent, child, translation (3,), quaternion xyzw (4,)) tuples."""
    G = _T["geometry_msgs/msg/TransformStamped"]
    out = []
    for parent, child, xyz, q in transforms:
        tr = _T["geometry_msgs/msg/Transform"](
            translation=_T["geometry_msgs/msg/Vector3"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
            rotation=_T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
        out.append(G(header=_T["std_msgs/msg/Header"](stamp=stamp(t_ns), frame_id=parent),
                     child_frame_id=child, transform=tr))
    return _T["tf2_msgs/msg/TFMessage"](transforms=out)


def imu_message(frame_id: str, t_ns: int, acc, gyro, acc_var: float, gyro_var: float):
    """sensor_msgs/Imu with specific force acc (3,) [m/s^2] and rate gyro (3,) [rad/s]; no
    orientation estimate (orientation_covariance[0] = -1, REP 145); variances per axis."""
    V = _T["geometry_msgs/msg/Vector3"]
    return _T["sensor_msgs/msg/Imu"](
        header=_T["std_msgs/msg/Header"](stamp=stamp(t_ns), frame_id=frame_id),
        orientation=_T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.array([-1.0] + [0.0] * 8),
        angular_velocity=V(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
        angular_velocity_covariance=np.diag([gyro_var] * 3).reshape(-1),
        linear_acceleration=V(x=float(acc[0]), y=float(acc[1]), z=float(acc[2])),
        linear_acceleration_covariance=np.diag([acc_var] * 3).reshape(-1))


def navsatfix_message(frame_id: str, t_ns: int, lat: float, lon: float, alt: float, var_h: float, var_v: float,
                      status: int = 2):
    """sensor_msgs/NavSatFix at (lat, lon) [deg], ellipsoidal height alt [m], with a diagonal
    ENU covariance (var_h east and north, var_v up, m^2; COVARIANCE_TYPE_DIAGONAL_KNOWN) and
    NavSatStatus `status` (2: GBAS, as RTK receivers report a fixed solution), GPS service."""
    return _T["sensor_msgs/msg/NavSatFix"](
        header=_T["std_msgs/msg/Header"](stamp=stamp(t_ns), frame_id=frame_id),
        status=_T["sensor_msgs/msg/NavSatStatus"](status=int(status), service=1),
        latitude=float(lat), longitude=float(lon), altitude=float(alt),
        position_covariance=np.diag([var_h, var_h, var_v]).reshape(-1).astype(np.float64),
        position_covariance_type=2)


class BagWriter:
    """Write lidar sweeps and static transforms to a new rosbag2 directory.

    Use as a context manager; `storage` is "sqlite3" or "mcap"; `compress` (mcap only)
    zstd-compresses the mcap chunks, which ROS 2 tools read natively.
    """

    def __init__(self, path: str | Path, storage: str = "mcap", compress: bool = True):
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"bag output {self.path} already exists; remove it or choose another path")
        plugins = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
        if storage not in plugins:
            raise ValueError(f"storage must be sqlite3 or mcap, got {storage!r}")
        self.writer = Writer(self.path, version=8, storage_plugin=plugins[storage])  # Iron and later
        if compress and storage == "mcap":
            self.writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self.connections: dict[str, object] = {}

    def __enter__(self) -> BagWriter:
        self.writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self.writer.close()

    def _conn(self, topic: str, msgtype: str, qos=()):
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=TYPESTORE,
                                                                 offered_qos_profiles=qos)
        return self.connections[topic]

    def write_cloud(self, topic: str, frame_id: str, points: np.ndarray, stamp_ns: int, log_ns: int) -> None:
        """points: (N,) or (H, W) POINT_DTYPE; stamp_ns: header stamp (sweep start); log_ns: bag time."""
        msg = pointcloud2(points, frame_id, stamp_ns)
        conn = self._conn(topic, "sensor_msgs/msg/PointCloud2")
        self.writer.write(conn, int(log_ns), TYPESTORE.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))

    def write_message(self, topic: str, msgtype: str, msg, log_ns: int) -> None:
        """Any message of a type TYPESTORE knows, or its CDR bytes (e.g. a cloud in another driver's layout)."""
        conn = self._conn(topic, msgtype)
        raw = msg if isinstance(msg, bytes) else TYPESTORE.serialize_cdr(msg, msgtype)
        self.writer.write(conn, int(log_ns), raw)

    def write_tf_static(self, transforms, stamp_ns: int) -> None:
        msg = tf_message(transforms, stamp_ns)
        conn = self._conn("/tf_static", "tf2_msgs/msg/TFMessage", (TF_STATIC_QOS,))
        self.writer.write(conn, int(stamp_ns), TYPESTORE.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))

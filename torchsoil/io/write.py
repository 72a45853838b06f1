"""Write small recordings with `rosbags` (round-trip tests, converted data).

`encode(...)` builds a PointCloud2 with a chosen field layout (order, padding, endianness,
organization); `write_bag(path, sweeps, extrinsics, storage=...)` writes a ROS 2 bag
(sqlite3 or mcap) or, for `storage="ros1"`, a ROS 1 `.bag` file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

# (name, numpy kind, PointField datatype)
FIELDS = {"x": ("f4", 7), "y": ("f4", 7), "z": ("f4", 7), "intensity": ("f4", 7),
          "t": ("u4", 6), "ring": ("u2", 4)}


def _typestore(ros1: bool):
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        from rosbags.typesys import get_types_from_msg

        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                       "tf2_msgs/msg/TFMessage"))
    return ts


def _header(ts, stamp: float, frame: str):
    Header = ts.types["std_msgs/msg/Header"]
    sec = int(np.floor(stamp))
    time = ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((stamp - sec) * 1e9)))
    extra = {"seq": 0} if "seq" in Header.__dataclass_fields__ else {}
    return Header(stamp=time, frame_id=frame, **extra)


def encode(xyz, t_ns, stamp: float, frame: str, ring=None, intensity=None, *, ts=None,
           order=("x", "y", "z", "intensity", "t", "ring"), pad: int = 0, row_pad: int = 0,
           big_endian: bool = False, height: int = 1):
    """(N, 3) points [m] and (N,) uint32 point times [ns after stamp] -> PointCloud2 message.

    order: field order in memory; pad: extra bytes after each point; row_pad: extra bytes
    after each row; height: rows of an organized cloud (N must divide by it).
    """
    ts = ts or _typestore(False)
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    n = len(xyz)
    if n % height:
        raise ValueError(f"{n} points do not fill {height} rows")
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
            "intensity": np.zeros(n) if intensity is None else intensity,
            "t": np.asarray(t_ns), "ring": np.zeros(n) if ring is None else ring}
    e = ">" if big_endian else "<"
    offsets, off = {}, 0
    for name in order:
        offsets[name] = off
        off += np.dtype(FIELDS[name][0]).itemsize
    point_step = off + pad
    dt = np.dtype({"names": list(order), "formats": [e + FIELDS[k][0] for k in order],
                   "offsets": [offsets[k] for k in order], "itemsize": point_step})
    arr = np.zeros(n, dtype=dt)
    for name in order:
        arr[name] = cols[name]
    width = n // height
    row_step = width * point_step + row_pad
    data = np.zeros((height, row_step), dtype=np.uint8)
    data[:, : width * point_step] = arr.view(np.uint8).reshape(height, -1)

    PointField = ts.types["sensor_msgs/msg/PointField"]
    PointCloud2 = ts.types["sensor_msgs/msg/PointCloud2"]
    header = _header(ts, stamp, frame)
    fields = [PointField(name=k, offset=offsets[k], datatype=FIELDS[k][1], count=1) for k in order]
    return PointCloud2(header=header, height=height, width=width, fields=fields,
                       is_bigendian=big_endian, point_step=point_step, row_step=row_step,
                       data=data.reshape(-1), is_dense=False)


def tf_message(extrinsics: dict[str, np.ndarray], stamp: float, base_frame: str = "base_link",
               ts=None):
    """{child frame: (4, 4) base_T_child} -> tf2_msgs/TFMessage."""
    ts = ts or _typestore(False)
    T = ts.types
    out = []
    for child, M in extrinsics.items():
        q = Rotation.from_matrix(np.asarray(M)[:3, :3]).as_quat()
        out.append(T["geometry_msgs/msg/TransformStamped"](
            header=_header(ts, stamp, base_frame),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))))
    return T["tf2_msgs/msg/TFMessage"](transforms=out)


def write_bag(path: str | Path, sweeps: list[tuple[str, object]],
              extrinsics: dict[str, np.ndarray] | None = None, storage: str = "sqlite3",
              base_frame: str = "base_link") -> Path:
    """Write a bag.

    sweeps: (topic, message) pairs; a message is a PointCloud2 from `encode` (written as
        sensor_msgs/msg/PointCloud2) and is timestamped with its header stamp.
    extrinsics: optional {frame: base_T_frame} written once on /tf_static.
    storage: "sqlite3" or "mcap" (ROS 2 directory) or "ros1" (ROS 1 file).
    """
    path = Path(path)
    ros1 = storage == "ros1"
    ts = _typestore(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
        serialize = ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[storage]
        writer = Writer(path, version=9, storage_plugin=plugin)
        serialize = ts.serialize_cdr
    msgtypes = {}
    with writer:
        conns = {}

        def conn(topic, msgtype):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            return conns[topic]

        first = min((float(m.header.stamp.sec) + 1e-9 * m.header.stamp.nanosec
                     for _, m in sweeps), default=0.0)
        if extrinsics:
            msg = tf_message(extrinsics, first, base_frame, ts)
            writer.write(conn("/tf_static", "tf2_msgs/msg/TFMessage"), int(first * 1e9),
                         serialize(msg, "tf2_msgs/msg/TFMessage"))
        for topic, msg in sweeps:
            msgtype = msgtypes.setdefault(topic, msg.__msgtype__)
            stamp = int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)
            if ros1:
                msg = _to_ros1(msg, ts)
            writer.write(conn(topic, msgtype), stamp, serialize(msg, msgtype))
    return path


def _to_ros1(msg, ts):
    """ROS 2 PointCloud2 -> ROS 1 (its header has a seq field)."""
    T = ts.types
    h = msg.header
    header = _header(ts, h.stamp.sec + 1e-9 * h.stamp.nanosec, h.frame_id)
    fields = [T["sensor_msgs/msg/PointField"](name=f.name, offset=f.offset, datatype=f.datatype,
                                              count=f.count) for f in msg.fields]
    return T["sensor_msgs/msg/PointCloud2"](
        header=header, height=msg.height, width=msg.width, fields=fields,
        is_bigendian=msg.is_bigendian, point_step=msg.point_step, row_step=msg.row_step,
        data=msg.data, is_dense=msg.is_dense)

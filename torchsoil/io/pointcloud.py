"""sensor_msgs/PointCloud2 to numpy, without per-point Python loops.

Any field layout is accepted: fields in any order and at any offset, padding between
points (`point_step`) and at the end of rows (`row_step`), big- or little-endian data,
organized (height > 1) or unorganized clouds. Points without a return (NaN or all-zero
x, y, z) are dropped. Per-point times are read in any common driver's convention
(torchsoil.io.pointtime), and Livox CustomMsg sweeps are read as well.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np

from torchsoil.io.pointtime import TIME_FIELDS, Convention, PointTimeError, RawTimes, check, infer, relative

# sensor_msgs/PointField datatype codes -> numpy kinds
_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


class Cloud(NamedTuple):
    """One decoded sweep.

    xyz:   (N, 3) float32 point coordinates in the sensor frame, m.
    t:     (N,) float32 capture time of each point after `stamp`, s (zeros without a time field).
    stamp: sweep time, s: the header stamp, or the sweep start when read from a recording
           (torchsoil.io.bag moves end-stamped sweeps to their start).
    frame: header frame_id.
    n_raw: number of points in the message before invalid returns were dropped.
    """

    xyz: np.ndarray
    t: np.ndarray
    stamp: float
    frame: str
    n_raw: int


def point_dtype(fields, point_step: int, big_endian: bool) -> np.dtype:
    """numpy structured dtype of one point from the PointField list."""
    order = ">" if big_endian else "<"
    names, formats, offsets = [], [], []
    for f in fields:
        if f.datatype not in _DTYPES:
            raise ValueError(f"field '{f.name}' has unknown PointField datatype {f.datatype}")
        if f.name in names:
            raise ValueError(f"field '{f.name}' appears twice")
        count = max(int(f.count), 1)
        fmt = order + _DTYPES[f.datatype]
        names.append(f.name)
        formats.append((fmt, (count,)) if count > 1 else fmt)
        offsets.append(int(f.offset))
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                   "itemsize": int(point_step)})
    return dt


def structured_points(msg) -> np.ndarray:
    """(height * width,) structured array of the message's points (all fields, native order)."""
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    n = height * width
    if n == 0:
        dt = point_dtype(msg.fields, max(point_step, 1), bool(msg.is_bigendian))
        return np.zeros(0, dtype=dt)
    if point_step <= 0 or row_step < width * point_step:
        raise ValueError(f"inconsistent layout: point_step {point_step}, row_step {row_step}, "
                         f"width {width}")
    dt = point_dtype(msg.fields, point_step, bool(msg.is_bigendian))
    for name, (fdt, off) in dt.fields.items():
        if off + fdt.itemsize > point_step:
            raise ValueError(f"field '{name}' (offset {off}) overruns point_step {point_step}")
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    need = (height - 1) * row_step + width * point_step
    if data.size < need:
        raise ValueError(f"truncated data: {data.size} bytes for {height}x{width} points "
                         f"(row_step {row_step}) needing {need}")
    if row_step == width * point_step:
        buf = data[: n * point_step]
    else:  # drop the padding at the end of each row
        rows = np.lib.stride_tricks.as_strided(data, shape=(height, width * point_step),
                                               strides=(row_step, 1))
        buf = np.ascontiguousarray(rows).reshape(-1)
    return np.frombuffer(buf.tobytes() if not buf.flags.c_contiguous else buf, dtype=dt)


class RawCloud(NamedTuple):
    """One decoded sweep before its time convention is known: xyz (N, 3) float32 of the points
    with a return, times: their RawTimes (pointtime), frame, n_raw as in Cloud."""

    xyz: np.ndarray
    times: RawTimes
    frame: str
    n_raw: int


def time_field(names: list[str], setting: str = "auto") -> str | None:
    """The per-point time field among `names`: the setting ('auto': the first of
    pointtime.TIME_FIELDS present; 'none': no field), or None."""
    if setting == "none":
        return None
    if setting != "auto":
        if setting not in names:
            raise ValueError(f"time field '{setting}' (pipeline.read.times) not in the cloud (fields: {names})")
        return setting
    return next((f for f in TIME_FIELDS if f in names), None)


def _returns(xyz: np.ndarray) -> np.ndarray:
    """(N,) True where the point (N, 3) is a return: x, y, z finite and not all zero (column
    by column: numpy's reductions along rows of three are slow)."""
    x, y, z = xyz.T
    return np.isfinite(x) & np.isfinite(y) & np.isfinite(z) & ((x != 0) | (y != 0) | (z != 0))


def decode_raw(msg, time_setting: str = "auto") -> RawCloud:
    """PointCloud2 message -> RawCloud with invalid returns dropped; time_setting: the
    topic's time_field setting ('auto', 'none' or a field name).

    Raises ValueError if x, y or z is missing or the byte layout is inconsistent.
    """
    names = [f.name for f in msg.fields]
    for axis in "xyz":
        if axis not in names:
            raise ValueError(f"PointCloud2 has no '{axis}' field (fields: {names})")
    pts = structured_points(msg)
    xyz = np.empty((len(pts), 3), dtype=np.float32)
    for k, axis in enumerate("xyz"):
        xyz[:, k] = pts[axis]
    keep = _returns(xyz)
    field = time_field(names, time_setting)
    values = pts[field][keep].astype(np.float64) if field else np.zeros(0)
    kind = pts.dtype[field].base.kind if field else ""
    times = RawTimes(field, values, kind, int(msg.header.stamp.sec), int(msg.header.stamp.nanosec))
    return RawCloud(xyz[keep], times, str(msg.header.frame_id), len(pts))


LIVOX_CUSTOM = ("livox_ros_driver2/msg/CustomMsg", "livox_ros_driver/msg/CustomMsg")
# Livox-SDK/livox_ros_driver2 msg/CustomMsg.msg and msg/CustomPoint.msg (livox_ros_driver: the same)
LIVOX_MSG = """std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
CustomPoint[] points
"""
LIVOX_POINT = """uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""


def register_livox(typestore) -> None:
    """Add the Livox CustomMsg / CustomPoint definitions (both packages) to a rosbags typestore."""
    from rosbags.typesys import get_types_from_msg

    types = {}
    for pkg in ("livox_ros_driver2", "livox_ros_driver"):
        types.update(get_types_from_msg(LIVOX_POINT, f"{pkg}/msg/CustomPoint"))
        types.update(get_types_from_msg(LIVOX_MSG.replace("CustomPoint", f"{pkg}/CustomPoint"), f"{pkg}/msg/CustomMsg"))
    typestore.register(types)


# one CustomPoint: CDR aligns each element to 4 bytes (stride 20), ROS 1 packs it (19)
_LIVOX_POINT = {"names": ["offset_time", "x", "y", "z"], "formats": ["<u4", "<f4", "<f4", "<f4"],
                "offsets": [0, 4, 8, 12]}
LIVOX_POINT_CDR = np.dtype({**_LIVOX_POINT, "itemsize": 20})
LIVOX_POINT_ROS1 = np.dtype({**_LIVOX_POINT, "itemsize": 19})


class _Stamp(NamedTuple):
    sec: int
    nanosec: int


class _Header(NamedTuple):
    stamp: _Stamp
    frame_id: str


class LivoxScan(NamedTuple):
    """A CustomMsg parsed straight from its bytes: header, timebase (ns) and points, a
    structured array with offset_time, x, y, z."""

    header: _Header
    timebase: int
    points: np.ndarray


def parse_livox(raw: bytes, ros1: bool) -> LivoxScan:
    """CustomMsg bytes (ROS 2 little-endian CDR, or ROS 1) -> LivoxScan, without a Python object
    per point. Raises ValueError on a truncated or big-endian message."""
    buf = memoryview(raw)
    if ros1:
        _, sec, nsec, n_frame = struct.unpack_from("<4I", buf, 0)
        pos = 16 + n_frame
        frame = bytes(buf[16:pos]).decode()
        timebase, _, count = struct.unpack_from("<QI4xI", buf, pos)
        pos, dt = pos + 20, LIVOX_POINT_ROS1
    else:
        if bytes(buf[:2]) != b"\x00\x01":
            raise ValueError("CustomMsg is not little-endian CDR")
        sec, nsec, n_frame = struct.unpack_from("<iII", buf, 4)
        frame = bytes(buf[16:16 + n_frame]).rstrip(b"\x00").decode()
        pos = 4 + -(-(12 + n_frame) // 8) * 8                     # timebase is 8-byte aligned
        timebase, _, count = struct.unpack_from("<QI4xI", buf, pos)
        pos, dt = pos + 20, LIVOX_POINT_CDR
    need = pos + count * dt.itemsize - (dt.itemsize - 19 if count else 0)
    if len(buf) < need:
        raise ValueError(f"CustomMsg truncated: {len(buf)} bytes for {count} points needing {need}")
    body = bytes(buf[pos:need]) + b"\x00" * (dt.itemsize - 19 if count else 0)
    return LivoxScan(_Header(_Stamp(sec, nsec), frame), timebase, np.frombuffer(body, dt, count))


def decode_livox(msg) -> RawCloud:
    """livox_ros_driver2/msg/CustomMsg (and livox_ros_driver's; a rosbags message or a LivoxScan)
    -> RawCloud: offset_time, uint32 ns after `timebase` (uint64 ns), given as ns after the
    header stamp."""
    n = len(msg.points)
    if isinstance(msg.points, np.ndarray):
        p = msg.points
        a = np.stack([p["offset_time"].astype(np.float64), p["x"], p["y"], p["z"]], 1).reshape(n, 4)
    else:
        a = np.array([(p.offset_time, p.x, p.y, p.z) for p in msg.points], dtype=np.float64).reshape(n, 4)
    xyz = a[:, 1:].astype(np.float32)
    keep = _returns(xyz)
    sec, nanosec = int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)
    base = float(int(msg.timebase) - (sec * 1_000_000_000 + nanosec))
    times = RawTimes("offset_time", a[keep, 0] + base, "u", sec, nanosec, (("ns", "stamp"),))
    return RawCloud(xyz[keep], times, str(msg.header.frame_id), n)


def to_cloud(raw: RawCloud, conv: Convention, period: float | None = None) -> Cloud:
    """RawCloud -> Cloud read with `conv`: stamp = header stamp + conv.offset (the sweep start),
    t = point times after it. Raises PointTimeError when the times do not fit a sweep."""
    r = raw.times
    stamp = float(r.sec) + 1e-9 * float(r.nanosec)
    if conv.field is not None and r.field != conv.field:
        raise PointTimeError(f"this sweep has no '{conv.field}' field, unlike the others of its topic")
    if conv.field is None:
        t = np.zeros(len(raw.xyz), dtype=np.float32)
    else:
        rel = relative(r, conv.unit, conv.base)
        check(rel, period)
        t = (rel - conv.offset).astype(np.float32)
    return Cloud(raw.xyz, t, stamp + conv.offset, raw.frame, raw.n_raw)


def decode(msg, convention: Convention | None = None) -> Cloud:
    """PointCloud2 (or Livox CustomMsg) message -> Cloud with invalid returns dropped.

    convention: how to read the point times (pointtime.Convention); None: inferred from this
    message alone, with t relative to the header stamp (stamp = header stamp).
    Raises ValueError if x, y or z is missing or the byte layout is inconsistent, and
    PointTimeError when the point times cannot be understood.
    """
    raw = decode_livox(msg) if hasattr(msg, "timebase") else decode_raw(msg)
    if convention is None:
        convention = infer("", [raw.times])._replace(offset=0.0)
    return to_cloud(raw, convention)

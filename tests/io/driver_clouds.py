"""sensor_msgs/PointCloud2 sweeps laid out byte for byte the way real lidar drivers write them.

Built from raw numpy structured arrays and the `rosbags` message classes (never with
torchsoil.io.write), so the decoder is checked against the drivers, not against the
project's own encoder. Each builder returns a `DriverCloud`: the message plus what a reader
must get back from it (xyz of the points with a return, in message order, and each point's
capture time in seconds AFTER the header stamp, possibly negative).

Layouts, from the drivers' sources (files named at each builder):

- ouster-ros (default `original` point): x0 y4 z8 f32, intensity16 f32, t20 u32,
  reflectivity24 u16, ring26 u16 (u8 before 0.10), ambient28 u16, range32 u32;
  point_step 48. Organized by default (height = beams), no return = NaN xyz. Stamp: scan
  start; `t` = uint32 ns after it.
- velodyne_pointcloud XYZIRT: x0 y4 z8 intensity12 f32, ring16 u16, time18 f32;
  point_step 22. Unorganized by default (no return skipped); organized: width = lasers,
  height = firings, no return = NaN xyz. Stamp: LAST packet; `time` = float32 s relative
  to it (about -0.1 .. 0).
- HesaiLidar_ROS_2.0: x0 y4 z8 intensity12 f32, ring16 u16, timestamp18 f64;
  point_step 26; unorganized. Stamp: frame start; `timestamp` = float64 absolute s.
- rslidar_sdk XYZIRT: x0 y4 z8 intensity12 f32, ring16 u16, timestamp18 f64;
  point_step 26. Organized when dense_points is false (width = rings, height = columns,
  no return = NaN xyz). Stamp: first point (shipped config) or last point (driver
  default); `timestamp` = float64 absolute s.
- livox_ros_driver2 (PointCloud2, xfer_format 0): x0 y4 z8 intensity12 f32, tag16 u8,
  line17 u8, timestamp18 f64; point_step 26 (packed); unorganized, no return = all-zero
  xyz. Stamp: first point (base_time); `timestamp` = float64 absolute ns.

No driver above pads the end of a row (row_step = width * point_step) or writes big-endian
data; `ouster(row_pad=..., big_endian=True)` makes such variants to check that the decoder
honours the header fields anyway.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
PointCloud2 = TYPESTORE.types["sensor_msgs/msg/PointCloud2"]
PointField = TYPESTORE.types["sensor_msgs/msg/PointField"]
Header = TYPESTORE.types["std_msgs/msg/Header"]
Time = TYPESTORE.types["builtin_interfaces/msg/Time"]

# numpy kind -> sensor_msgs/PointField datatype
DATATYPE = {"i1": PointField.INT8, "u1": PointField.UINT8, "i2": PointField.INT16, "u2": PointField.UINT16,
            "i4": PointField.INT32, "u4": PointField.UINT32, "f4": PointField.FLOAT32, "f8": PointField.FLOAT64}

SWEEP = 0.1  # s, one revolution at 10 Hz


class DriverCloud(NamedTuple):
    """One sweep as a driver publishes it.

    msg: the PointCloud2 (rosbags ROS 2 Humble class). points: the structured array written,
    (height * width,) in message order. valid: (height * width,) bool, points with a return.
    xyz: (M, 3) float32 of the valid points. t: (M,) float64 capture time after the header
    stamp, s. stamp: header stamp, s (float64). time_field: the field holding per-point time.
    stamp_convention: where the header stamp sits in the sweep, in words.
    """

    msg: object
    points: np.ndarray
    valid: np.ndarray
    xyz: np.ndarray
    t: np.ndarray
    stamp: float
    time_field: str
    stamp_convention: str


def layout(fields: list[tuple[str, str, int]], point_step: int, big_endian: bool = False) -> np.dtype:
    """numpy dtype of one point: (name, kind, offset) triples and the byte size of a point."""
    order = ">" if big_endian else "<"
    return np.dtype({"names": [f[0] for f in fields], "formats": [order + f[1] for f in fields],
                     "offsets": [f[2] for f in fields], "itemsize": point_step})


def point_fields(fields: list[tuple[str, str, int]]) -> list:
    return [PointField(name=n, offset=o, datatype=DATATYPE[k], count=1) for n, k, o in fields]


def stamp_of(sec: int, nanosec: int) -> float:
    return sec + nanosec * 1e-9


def message(points: np.ndarray, fields, height: int, width: int, sec: int, nanosec: int, frame: str,
            is_dense: bool, big_endian: bool = False, row_pad: int = 0):
    """PointCloud2 holding `points` (height * width structured records) row after row, each
    row followed by `row_pad` zero bytes."""
    step = points.dtype.itemsize
    rows = np.frombuffer(points.tobytes(), np.uint8).reshape(height, width * step)
    data = np.concatenate([rows, np.zeros((height, row_pad), np.uint8)], axis=1).reshape(-1)
    return PointCloud2(header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame), height=height,
                       width=width, fields=point_fields(fields), is_bigendian=big_endian, point_step=step,
                       row_step=width * step + row_pad, data=data.copy(), is_dense=is_dense)


def _rays(n_rows: int, n_cols: int, rng: np.random.Generator, fov_deg: float = 30.0):
    """Unit rays of a spinning lidar (rows = beams from top to bottom, columns = azimuth) and
    ranges 1.5-25 m: (n_rows, n_cols, 3) float64 points."""
    el = np.radians(np.linspace(fov_deg / 2, -fov_deg / 2, n_rows))[:, None]
    az = np.linspace(0, 2 * math.pi, n_cols, endpoint=False)[None, :]
    r = rng.uniform(1.5, 25.0, (n_rows, n_cols))
    return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el) + 0 * az], -1)


# ---------------------------------------------------------------------------------- Ouster
OUSTER_FIELDS = [("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("intensity", "f4", 16), ("t", "u4", 20),
                 ("reflectivity", "u2", 24), ("ring", "u2", 26), ("ambient", "u2", 28), ("range", "u4", 32)]
# ouster-ros before 0.10 (commit 0a47076, Dec 2022): `uint8_t ring`, the other offsets unchanged
OUSTER_FIELDS_LEGACY = [f if f[0] != "ring" else ("ring", "u1", 26) for f in OUSTER_FIELDS]


def ouster(beams: int = 16, columns: int = 64, organized: bool = True, no_return: float = 0.15, seed: int = 0,
           sec: int = 1_700_000_000, nanosec: int = 250_000_000, legacy_ring: bool = False,
           big_endian: bool = False, row_pad: int = 0, frame: str = "os_sensor") -> DriverCloud:
    """ouster-ros default (`original`) point type.

    Layout: ouster-ros include/ouster_ros/os_point.h (struct EIGEN_ALIGN16 _Point:
    PCL_ADD_POINT4D = x, y, z + 4 bytes padding; intensity f32; t u32; reflectivity u16;
    ring u16; ambient u16; range u32 aligned to 32; sizeof 36 rounded up to 48 by the
    16-byte alignment), written by pcl::toROSMsg (offsets = offsetof, point_step = sizeof).
    Sweep: src/point_cloud_compose.h scan_to_cloud_f: organized (default `organized: true`)
    clouds keep every pixel, height = beams, width = columns, is_dense false when a pixel
    has no return, whose xyz are NaN (src/impl/cartesian.h cartesianT with invalid =
    quiet_NaN, src/point_cloud_processor.h); unorganized clouds skip those pixels (height 1).
    t = column timestamp - scan_ts, ns after the header stamp: scan_ts is the first column's
    time (extrapolated when that column is missing; src/lidar_packet_handler.h
    compute_scan_ts_0/_n). With timestamp_mode TIME_FROM_ROS_TIME the header holds the
    receive time instead, and t stays relative to scan_ts: not modelled here.
    """
    rng = np.random.default_rng(seed)
    fields = OUSTER_FIELDS_LEGACY if legacy_ring else OUSTER_FIELDS
    dt = layout(fields, 48, big_endian)
    xyz = _rays(beams, columns, rng).astype(np.float32)
    hit = rng.random((beams, columns)) >= no_return
    t_col = (np.arange(columns) * (int(SWEEP * 1e9) // columns)).astype(np.uint32)     # ns after the stamp
    pts = np.zeros((beams, columns), dt)
    pts["x"], pts["y"], pts["z"] = (np.where(hit, xyz[..., k], np.float32(np.nan)) for k in range(3))
    pts["intensity"] = np.where(hit, rng.uniform(0, 3000, hit.shape), 0).astype(np.float32)
    pts["t"] = t_col[None, :]
    pts["reflectivity"] = np.where(hit, rng.integers(0, 255, hit.shape), 0)
    pts["ring"] = np.arange(beams)[:, None]
    pts["ambient"] = rng.integers(0, 2000, hit.shape)
    pts["range"] = np.where(hit, np.round(np.linalg.norm(xyz, axis=-1) * 1000), 0).astype(np.uint32)
    if organized:
        flat, valid, height, width = pts.reshape(-1), hit.reshape(-1), beams, columns
    else:
        flat = pts[hit]                                  # row-major, pixels without a return skipped
        valid, height, width = np.ones(len(flat), bool), 1, len(flat)
    msg = message(flat, fields, height, width, sec, nanosec, frame, is_dense=bool(valid.all()),
                  big_endian=big_endian, row_pad=row_pad)
    good = flat[valid]
    return DriverCloud(msg, flat, valid, np.stack([good["x"], good["y"], good["z"]], 1).astype(np.float32),
                       good["t"].astype(np.float64) * 1e-9, stamp_of(sec, nanosec), "t",
                       "scan start (first column); t: uint32 ns after the stamp")


# -------------------------------------------------------------------------------- Velodyne
VELODYNE_FIELDS = [("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("intensity", "f4", 12), ("ring", "u2", 16),
                   ("time", "f4", 18)]


def velodyne(lasers: int = 16, firings: int = 48, organized: bool = False, out_of_range: float = 0.1, seed: int = 1,
             sec: int = 1_700_000_010, nanosec: int = 987_654_321, frame: str = "velodyne") -> DriverCloud:
    """velodyne_pointcloud, PointcloudXYZIRT / OrganizedCloudXYZIRT (ROS 1 master and ROS 2).

    Layout: velodyne_pointcloud/src/conversions/pointcloudXYZIRT.cc (ROS 2:
    src/lib/pointcloudXYZIRT.cpp) passes x, y, z, intensity FLOAT32, ring UINT16, time
    FLOAT32 to DataContainerBase (include/velodyne_pointcloud/datacontainerbase.h), which
    packs them with sensor_msgs addPointField: no padding, point_step 22.
    Unorganized (default): height 1, is_dense true, out-of-range returns skipped.
    Organized (organize_cloud: true): width = lasers, one row per firing, out-of-range
    returns written with NaN x, y, z, intensity, is_dense false (organized_cloudXYZIRT.cc).
    Stamp: velodyne_driver/src/driver/driver.cc stamps the scan with the LAST packet
    (timestamp_first_packet false by default); rawdata unpack sets time = firing offset +
    (packet stamp - scan stamp): seconds relative to the stamp, about -0.1 .. 0.
    """
    rng = np.random.default_rng(seed)
    dt = layout(VELODYNE_FIELDS, 22)
    xyz = np.transpose(_rays(lasers, firings, rng), (1, 0, 2)).astype(np.float32)     # (firings, lasers, 3)
    ok = rng.random((firings, lasers)) >= out_of_range
    # lasers of one firing 2.304 us apart (VLP-16); the last firing is at the stamp (last packet)
    t = (np.arange(1, firings + 1)[:, None] * (SWEEP / firings) + np.arange(lasers)[None, :] * 2.304e-6 - SWEEP)
    pts = np.zeros((firings, lasers), dt)
    for k, a in enumerate("xyz"):
        pts[a] = np.where(ok, xyz[..., k], np.float32(np.nan))
    pts["intensity"] = np.where(ok, rng.uniform(0, 255, ok.shape), np.nan).astype(np.float32)
    pts["ring"] = np.arange(lasers)[None, :]
    pts["time"] = t.astype(np.float32)
    if organized:
        flat, valid, height, width = pts.reshape(-1), ok.reshape(-1), firings, lasers
    else:
        flat = pts[ok]
        valid, height, width = np.ones(len(flat), bool), 1, len(flat)
    msg = message(flat, VELODYNE_FIELDS, height, width, sec, nanosec, frame, is_dense=not organized)
    good = flat[valid]
    return DriverCloud(msg, flat, valid, np.stack([good["x"], good["y"], good["z"]], 1),
                       good["time"].astype(np.float64), stamp_of(sec, nanosec), "time",
                       "last packet (sweep end); time: float32 s relative to the stamp, about -0.1 .. 0")


# ----------------------------------------------------------------------------------- Hesai
HESAI_FIELDS = [("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("intensity", "f4", 12), ("ring", "u2", 16),
                ("timestamp", "f8", 18)]


def _absolute_seconds_stamp(start: float) -> tuple[int, int]:
    """Header stamp the Hesai and Robosense ROS 2 drivers write for a float64 time in s."""
    sec = int(math.floor(start))
    return sec, int(round((start - sec) * 1e9))


def hesai(channels: int = 32, columns: int = 40, seed: int = 2, start: float = 1_700_000_020.123456,
          frame: str = "hesai_lidar") -> DriverCloud:
    """HesaiLidar_ROS_2.0, src/manager/source_driver_ros2.hpp ToRosMsg(const LidarDecodedFrame&):
    x, y, z, intensity FLOAT32, ring UINT16, timestamp FLOAT64 via addPointField (packed,
    point_step 26), height 1, is_dense false. Stamp: frame_start_timestamp (sec = floor,
    nanosec = round(frac * 1e9)); timestamp: absolute seconds of each point.
    """
    rng = np.random.default_rng(seed)
    dt = layout(HESAI_FIELDS, 26)
    xyz = np.transpose(_rays(channels, columns, rng, fov_deg=40.0), (1, 0, 2)).reshape(-1, 3).astype(np.float32)
    n = len(xyz)
    pts = np.zeros(n, dt)
    pts["x"], pts["y"], pts["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    pts["intensity"] = rng.uniform(0, 255, n).astype(np.float32)
    pts["ring"] = np.tile(np.arange(channels), columns)
    pts["timestamp"] = start + np.repeat(np.arange(columns), channels) * (SWEEP / columns) + \
        np.tile(np.arange(channels), columns) * 1.0e-6
    sec, nanosec = _absolute_seconds_stamp(start)
    msg = message(pts, HESAI_FIELDS, 1, n, sec, nanosec, frame, is_dense=False)
    return DriverCloud(msg, pts, np.ones(n, bool), xyz, (pts["timestamp"] - sec) - nanosec * 1e-9,
                       stamp_of(sec, nanosec), "timestamp",
                       "frame start; timestamp: float64 absolute s")


# ------------------------------------------------------------------------------- Robosense
ROBOSENSE_FIELDS = HESAI_FIELDS   # same names, kinds and offsets (addPointField, packed), point_step 26


def robosense(rings: int = 16, columns: int = 36, dense: bool = False, stamp_at: str = "first",
              no_return: float = 0.1, seed: int = 3, start: float = 1_700_000_030.5,
              frame: str = "rslidar") -> DriverCloud:
    """rslidar_sdk with POINT_TYPE XYZIRT, src/source/source_pointcloud_ros.hpp toRosMsg (ROS 2):
    x, y, z, intensity FLOAT32, ring UINT16, timestamp FLOAT64 via addPointField (packed,
    point_step 26). dense_points false (config/config.yaml default): every pixel is kept,
    no-return ones with NaN xyz, and (ros_send_by_rows false) the ROS cloud has width =
    rings and height = columns, points in firing order (column after column); dense_points
    true: returns only, height 1. Stamp: rs_msg.timestamp = the first point's time with
    ts_first_point true (the shipped config.yaml), the last point's otherwise (the
    driver's default, doc/intro/03_hiding_parameters_intro.md); timestamp: absolute s.
    """
    rng = np.random.default_rng(seed)
    dt = layout(ROBOSENSE_FIELDS, 26)
    xyz = np.transpose(_rays(rings, columns, rng), (1, 0, 2)).astype(np.float32)       # (columns, rings, 3)
    hit = rng.random((columns, rings)) >= no_return
    ts = start + np.arange(columns)[:, None] * (SWEEP / columns) + np.arange(rings)[None, :] * 3.0e-6
    pts = np.zeros((columns, rings), dt)
    for k, a in enumerate("xyz"):
        pts[a] = np.where(hit, xyz[..., k], np.float32(np.nan))
    pts["intensity"] = np.where(hit, rng.uniform(0, 255, hit.shape), 0).astype(np.float32)
    pts["ring"] = np.arange(rings)[None, :]
    pts["timestamp"] = ts
    if dense:
        flat = pts[hit]
        valid, height, width = np.ones(len(flat), bool), 1, len(flat)
    else:
        flat, valid, height, width = pts.reshape(-1), hit.reshape(-1), columns, rings
    stamp_time = float(flat["timestamp"][0] if stamp_at == "first" else flat["timestamp"][-1])
    sec, nanosec = _absolute_seconds_stamp(stamp_time)
    msg = message(flat, ROBOSENSE_FIELDS, height, width, sec, nanosec, frame, is_dense=dense)
    good = flat[valid]
    return DriverCloud(msg, flat, valid, np.stack([good["x"], good["y"], good["z"]], 1),
                       (good["timestamp"] - sec) - nanosec * 1e-9, stamp_of(sec, nanosec), "timestamp",
                       f"{stamp_at} point (ts_first_point: {str(stamp_at == 'first').lower()}); "
                       "timestamp: float64 absolute s")


# ----------------------------------------------------------------------------------- Livox
LIVOX_FIELDS = [("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("intensity", "f4", 12), ("tag", "u1", 16),
                ("line", "u1", 17), ("timestamp", "f8", 18)]


def livox(n: int = 960, lines: int = 4, no_return: float = 0.1, seed: int = 4,
          base_ns: int = 1_700_000_040_200_000_000, frame: str = "livox_frame") -> DriverCloud:
    """livox_ros_driver2, PointCloud2 output (xfer_format 0): src/lddc.cpp
    InitPointcloud2MsgHeader sets offsets x0 y4 z8 intensity12 tag16 line17 timestamp18 and
    point_step = sizeof(LivoxPointXyzrtlt) = 26 (src/comm/comm.h, #pragma pack(1)); height 1,
    is_dense true. Points come straight from the packets (src/comm/pub_handler.cpp): a
    zero-depth return stays in the cloud as x = y = z = 0. Stamp: base_time = the first
    point's time in ns (ROS 2: rclcpp::Time(ns)); timestamp: absolute ns as float64 (so
    only good to 256 ns around 1.7e18 ns: the expected times are taken from the stored
    float64 values).
    """
    rng = np.random.default_rng(seed)
    dt = layout(LIVOX_FIELDS, 26)
    # non-repetitive pattern: rays over a 360 x 59 degree field, 1-40 m
    az = rng.uniform(0, 2 * math.pi, n)
    el = np.radians(rng.uniform(-7, 52, n))
    r = rng.uniform(1.0, 40.0, n)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1).astype(np.float32)
    hit = rng.random(n) >= no_return
    hit[0] = True
    xyz[~hit] = 0.0
    point_interval_ns = int(SWEEP * 1e9) // n
    pts = np.zeros(n, dt)
    pts["x"], pts["y"], pts["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    pts["intensity"] = np.where(hit, rng.integers(0, 255, n), 0).astype(np.float32)
    pts["tag"] = np.where(hit, 0, 0x30)
    pts["line"] = np.arange(n) % lines
    pts["timestamp"] = (base_ns + np.arange(n, dtype=np.int64) * point_interval_ns).astype(np.float64)
    sec, nanosec = divmod(base_ns, 1_000_000_000)
    msg = message(pts, LIVOX_FIELDS, 1, n, sec, nanosec, frame, is_dense=True)
    good = pts[hit]
    return DriverCloud(msg, pts, hit, xyz[hit], (good["timestamp"] - float(base_ns)) * 1e-9,
                       stamp_of(sec, nanosec), "timestamp",
                       "first point (base_time); timestamp: float64 absolute ns")




# ------------------------------------------------------------------------ Livox CustomMsg
# Livox-SDK/livox_ros_driver2 msg/CustomMsg.msg and msg/CustomPoint.msg, verbatim fields
LIVOX_CUSTOM_MSG = """std_msgs/Header header    # ROS standard message header
uint64 timebase           # The time of first point
uint32 point_num          # Total number of pointclouds
uint8  lidar_id           # Lidar device id number
uint8[3]  rsvd            # Reserved use
CustomPoint[] points      # Pointcloud data
"""
LIVOX_CUSTOM_POINT = """uint32 offset_time      # offset time relative to the base time
float32 x               # X axis, unit:m
float32 y               # Y axis, unit:m
float32 z               # Z axis, unit:m
uint8 reflectivity      # reflectivity, 0~255
uint8 tag               # livox tag
uint8 line              # laser number in lidar
"""
LIVOX_CUSTOM = "livox_ros_driver2/msg/CustomMsg"


def _register_livox():
    from rosbags.typesys import get_types_from_msg

    types = get_types_from_msg(LIVOX_CUSTOM_POINT, "livox_ros_driver2/msg/CustomPoint")
    types.update(get_types_from_msg(LIVOX_CUSTOM_MSG.replace("CustomPoint[]", "livox_ros_driver2/CustomPoint[]"),
                                    LIVOX_CUSTOM))
    TYPESTORE.register(types)


_register_livox()


def livox_custom(n: int = 960, lines: int = 4, no_return: float = 0.1, seed: int = 5,
                 base_ns: int = 1_700_000_050_300_000_000, frame: str = "livox_frame") -> DriverCloud:
    """livox_ros_driver2 CustomMsg output (xfer_format 1): src/lddc.cpp PublishCustomPointcloud
    sets timebase = the packet's base_time (ns of the first point), header.stamp =
    rclcpp::Time(timebase), point_num, lidar_id, and per point offset_time = point time -
    base_time (uint32 ns), x, y, z, reflectivity, tag, line; zero-depth returns stay as
    x = y = z = 0. `points` here is a structured array of what was written (offset_time, x,
    y, z); msgtype: LIVOX_CUSTOM.
    """
    rng = np.random.default_rng(seed)
    az, el, r = rng.uniform(0, 2 * math.pi, n), np.radians(rng.uniform(-7, 52, n)), rng.uniform(1.0, 40.0, n)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1).astype(np.float32)
    hit = rng.random(n) >= no_return
    hit[0] = True
    xyz[~hit] = 0.0
    off = (np.arange(n) * (int(SWEEP * 1e9) // n)).astype(np.uint32)
    P = TYPESTORE.types["livox_ros_driver2/msg/CustomPoint"]
    pts = [P(offset_time=int(o), x=float(p[0]), y=float(p[1]), z=float(p[2]), reflectivity=int(rng.integers(0, 255)),
             tag=0 if h else 0x30, line=k % lines) for k, (o, p, h) in enumerate(zip(off, xyz, hit, strict=True))]
    sec, nanosec = divmod(base_ns, 1_000_000_000)
    msg = TYPESTORE.types[LIVOX_CUSTOM](
        header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame), timebase=base_ns, point_num=n,
        lidar_id=1, rsvd=np.zeros(3, np.uint8), points=pts)
    rec = np.zeros(n, [("offset_time", "<u4"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    rec["offset_time"], rec["x"], rec["y"], rec["z"] = off, xyz[:, 0], xyz[:, 1], xyz[:, 2]
    return DriverCloud(msg, rec, hit, xyz[hit], off[hit].astype(np.float64) * 1e-9, stamp_of(sec, nanosec),
                       "offset_time", "first point (timebase); offset_time: uint32 ns after timebase")


TYPESTORE1 = get_typestore(Stores.ROS1_NOETIC)     # ROS 1: std_msgs/Header with its uint32 seq
TYPESTORE1.register({k: v for k, v in TYPESTORE.fielddefs.items() if k.startswith("livox_ros_driver2/")})


def ros1_message(msg, msgtype: str, seq: int):
    """The same message in ROS 1 Noetic classes (a Header with seq), as a ROS 1 driver publishes it."""
    T = TYPESTORE1.types
    h = msg.header
    header = T["std_msgs/msg/Header"](seq=seq, stamp=T["builtin_interfaces/msg/Time"](
        sec=h.stamp.sec, nanosec=h.stamp.nanosec), frame_id=h.frame_id)
    cls = T[msgtype]
    return cls(**{f: header if f == "header" else getattr(msg, f) for f in cls.__dataclass_fields__
                  if f != "__msgtype__"})


def sweep_at(driver: str, start_ns: int, seed: int = 0, **kw) -> DriverCloud:
    """A sweep of `driver` whose first point is captured at `start_ns` (integer ns), written with
    that driver's stamp convention ("robosense_last": the last-point stamp; "velodyne": the
    last firing sits at the stamp)."""
    sec, nanosec = divmod(start_ns, 1_000_000_000)
    if driver == "ouster":
        return ouster(sec=sec, nanosec=nanosec, seed=seed, **kw)
    if driver == "velodyne":   # first firing 1/48 sweep after the stamp - 0.1 s
        end = start_ns - int(SWEEP * 1e9) // 48 + int(SWEEP * 1e9)
        return velodyne(sec=end // 1_000_000_000, nanosec=end % 1_000_000_000, seed=seed, **kw)
    if driver == "hesai":
        return hesai(start=start_ns * 1e-9, seed=seed, **kw)
    if driver.startswith("robosense"):
        return robosense(start=start_ns * 1e-9, seed=seed, stamp_at="last" if driver.endswith("last") else "first",
                         **kw)
    if driver == "livox":
        return livox(base_ns=start_ns, seed=seed, **kw)
    if driver == "livox_custom":
        return livox_custom(base_ns=start_ns, seed=seed, **kw)
    raise ValueError(driver)


def msgtype(c: DriverCloud) -> str:
    return LIVOX_CUSTOM if hasattr(c.msg, "timebase") else "sensor_msgs/msg/PointCloud2"


def write_bag(path, topics: dict, storage: str = "sqlite3"):
    """A bag with rosbags' own writer and serializer: {topic: [DriverCloud, ...]} (ROS 2
    sqlite3 / mcap, or ROS 1 when `storage` is "ros1"); bag time = header stamp + 10 ms."""
    msgs = sorted(((c.stamp, topic, c) for topic, cs in topics.items() for c in cs), key=lambda m: m[0])
    if storage == "ros1":
        from rosbags.rosbag1 import Writer as Writer1

        with Writer1(path) as w:
            conns = {t: w.add_connection(t, msgtype(cs[0]), typestore=TYPESTORE1) for t, cs in topics.items()}
            for seq, (stamp, topic, c) in enumerate(msgs):
                w.write(conns[topic], int(round(stamp * 1e9)) + 10_000_000,
                        TYPESTORE1.serialize_ros1(ros1_message(c.msg, msgtype(c), seq), msgtype(c)))
        return path
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {topic: w.add_connection(topic, msgtype(cs[0]), typestore=TYPESTORE) for topic, cs in topics.items()}
        for stamp, topic, c in msgs:
            w.write(conns[topic], int(round(stamp * 1e9)) + 10_000_000, TYPESTORE.serialize_cdr(c.msg, msgtype(c)))
    return path


DRIVERS = {"ouster": ouster, "velodyne": velodyne, "hesai": hesai, "robosense": robosense, "livox": livox,
           "livox_custom": livox_custom}

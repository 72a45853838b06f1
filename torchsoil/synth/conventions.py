"""The recorder's sweeps rewritten in the layouts and stamp conventions of common lidar drivers
(docs/formats.md section 1; the layouts as in tests/io/driver_clouds.py, from the drivers' sources).

    ouster            t uint32 ns after the stamp; stamp = sweep start (the recorder's own layout)
    velodyne          time float32 s relative to the stamp; stamp = last firing
    hesai             timestamp float64 absolute s; stamp = sweep start
    robosense_start   timestamp float64 absolute s; stamp = first point
    robosense_end     timestamp float64 absolute s; stamp = last point
    livox             timestamp float64 absolute ns; stamp = first point (PointCloud2)
    livox_custom      livox_ros_driver2/msg/CustomMsg: timebase = first point, offset_time ns
    mixed             front lidar ouster (start-stamped), back lidar velodyne (end-stamped)
"""

from __future__ import annotations

import numpy as np

from torchsoil.synth.bagwriter import POINT_DTYPE, TYPESTORE, pointcloud2, stamp

CONVENTIONS = ("ouster", "velodyne", "hesai", "robosense_start", "robosense_end", "livox", "livox_custom", "mixed")
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
LIVOX_CUSTOM = "livox_ros_driver2/msg/CustomMsg"

_XYZI = [("x", "<f4", 0), ("y", "<f4", 4), ("z", "<f4", 8), ("intensity", "<f4", 12)]
LAYOUTS = {   # (name, numpy type, offset), point_step: packed, as the drivers' addPointField / pragma pack
    "velodyne": (_XYZI + [("ring", "<u2", 16), ("time", "<f4", 18)], 22),
    "hesai": (_XYZI + [("ring", "<u2", 16), ("timestamp", "<f8", 18)], 26),
    "livox": (_XYZI + [("tag", "u1", 16), ("line", "u1", 17), ("timestamp", "<f8", 18)], 26),
}
_DATATYPE = {"u1": 2, "<u2": 4, "<u4": 6, "<f4": 7, "<f8": 8}


def driver_of(convention: str, lidar: str) -> str:
    """The driver layout one lidar ('lidar_front' or 'lidar_back') is written in."""
    if convention not in CONVENTIONS:
        raise ValueError(f"unknown convention {convention!r}; known: {', '.join(CONVENTIONS)}")
    if convention == "mixed":
        return "ouster" if lidar == "lidar_front" else "velodyne"
    return convention


def _cloud(points: np.ndarray, fields, frame: str, t_ns: int):
    """PointCloud2 of any structured array (N,) or (H, W) with the PointField list `fields`."""
    height, width = points.shape if points.ndim == 2 else (1, len(points))
    PF, T = TYPESTORE.types["sensor_msgs/msg/PointField"], TYPESTORE.types
    step = points.dtype.itemsize
    return T["sensor_msgs/msg/PointCloud2"](
        header=T["std_msgs/msg/Header"](stamp=stamp(t_ns), frame_id=frame), height=height, width=width,
        fields=[PF(name=n, offset=o, datatype=_DATATYPE[k], count=1) for n, k, o in fields], is_bigendian=False,
        point_step=step, row_step=step * width, data=np.frombuffer(points.tobytes(), np.uint8),
        is_dense=bool(np.isfinite(points["x"]).all()))


_CUSTOM_POINT = np.dtype({"names": ["offset_time", "x", "y", "z", "line"],      # CDR: elements 4-byte aligned
                          "formats": ["<u4", "<f4", "<f4", "<f4", "u1"], "offsets": [0, 4, 8, 12, 18], "itemsize": 20})


def _livox_custom(pts: np.ndarray, frame: str, first_ns: int, t0: int) -> bytes:
    """CDR bytes of a livox_ros_driver2 CustomMsg (written without a Python object per point:
    the message with no points, its sequence length patched, the packed points appended)."""
    from torchsoil.io.pointcloud import register_livox

    if LIVOX_CUSTOM not in TYPESTORE.types:
        register_livox(TYPESTORE)
    flat = pts.reshape(-1)
    body = np.zeros(len(flat), _CUSTOM_POINT)
    for n in ("x", "y", "z"):
        body[n] = np.nan_to_num(flat[n], nan=0.0)
    body["offset_time"], body["line"] = flat["t"].astype(np.int64) - t0, flat["ring"] % 256
    empty = TYPESTORE.types[LIVOX_CUSTOM](
        header=TYPESTORE.types["std_msgs/msg/Header"](stamp=stamp(first_ns), frame_id=frame), timebase=first_ns,
        point_num=len(flat), lidar_id=0, rsvd=np.zeros(3, np.uint8), points=[])
    raw = bytes(TYPESTORE.serialize_cdr(empty, LIVOX_CUSTOM))
    return raw[:-4] + np.uint32(len(flat)).tobytes() + body.tobytes()[:-1 if len(flat) else None]


def driver_message(points: np.ndarray, frame: str, start_ns: int, driver: str) -> tuple[str, object]:
    """One recorder sweep (POINT_DTYPE (N,) or (H, W); `t` ns after `start_ns`, the sweep start in
    bag-clock ns) as `driver` writes it: (message type, message, or its CDR bytes for livox_custom)."""
    if points.dtype != POINT_DTYPE:
        raise ValueError(f"points must have dtype {POINT_DTYPE}, got {points.dtype}")
    if driver == "ouster":
        return POINTCLOUD2, pointcloud2(points, frame, start_ns)
    t = points["t"].astype(np.int64)
    first, last = (int(t.min()), int(t.max())) if t.size else (0, 0)
    if driver == "livox_custom":
        return LIVOX_CUSTOM, _livox_custom(points, frame, start_ns + first, first)
    fields, step = LAYOUTS["hesai" if driver.startswith("robosense") else driver]
    out = np.zeros(points.shape, np.dtype({"names": [f[0] for f in fields], "formats": [f[1] for f in fields],
                                           "offsets": [f[2] for f in fields], "itemsize": step}))
    for n in ("x", "y", "z", "intensity"):
        out[n] = points[n]
    if driver == "velodyne":
        out["ring"], out["time"] = points["ring"], ((t - last) * 1e-9).astype(np.float32)
        return POINTCLOUD2, _cloud(out, fields, frame, start_ns + last)
    if driver == "livox":   # zero-depth returns stay in the cloud at the origin
        for n in ("x", "y", "z"):
            out[n] = np.nan_to_num(out[n], nan=0.0)
        out["line"], out["timestamp"] = points["ring"] % 256, (start_ns + t).astype(np.float64)
        return POINTCLOUD2, _cloud(out, fields, frame, start_ns + first)
    out["ring"] = points["ring"]
    out["timestamp"] = (start_ns // 1_000_000_000 + ((start_ns % 1_000_000_000) + t) * 1e-9)
    head = {"hesai": 0, "robosense_start": first, "robosense_end": last}[driver]
    return POINTCLOUD2, _cloud(out, fields, frame, start_ns + head)


def rewrite_recording(src, dst, convention: str, storage: str = "mcap") -> None:
    """Copy a recorder bag (its own `ouster` layout) to a new bag `dst` with every sweep
    rewritten in `convention` (same points, same capture times); /tf_static copied."""
    from pathlib import Path

    from rosbags.highlevel import AnyReader

    from torchsoil.synth.bagwriter import TF_STATIC_QOS, BagWriter

    with AnyReader([Path(src)], default_typestore=TYPESTORE) as reader, BagWriter(dst, storage=storage) as bag:
        for conn, log_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype != POINTCLOUD2:
                bag.writer.write(bag._conn(conn.topic, conn.msgtype, (TF_STATIC_QOS,)), log_ns, raw)
                continue
            if msg.point_step != POINT_DTYPE.itemsize or [f.name for f in msg.fields] != list(POINT_DTYPE.names):
                raise ValueError(f"{src}: {conn.topic} is not in the recorder's own layout")
            pts = np.frombuffer(bytes(msg.data), POINT_DTYPE).reshape(msg.height, msg.width)
            pts = pts[0] if msg.height == 1 else pts
            frame = str(msg.header.frame_id)
            start_ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            bag.write_message(conn.topic, *driver_message(pts, frame, start_ns, driver_of(convention, frame)), log_ns)

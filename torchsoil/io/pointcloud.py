"""sensor_msgs/PointCloud2 to numpy, without per-point Python loops.

Any field layout is accepted: fields in any order and at any offset, padding between
points (`point_step`) and at the end of rows (`row_step`), big- or little-endian data,
organized (height > 1) or unorganized clouds. Points without a return (NaN or all-zero
x, y, z) are dropped.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# sensor_msgs/PointField datatype codes -> numpy kinds
_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


class Cloud(NamedTuple):
    """One decoded sweep.

    xyz:   (N, 3) float32 point coordinates in the sensor frame, m.
    t:     (N,) float32 capture time of each point after `stamp`, s (zeros without a `t` field).
    stamp: header stamp, s.
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


def decode(msg) -> Cloud:
    """PointCloud2 message -> Cloud with invalid returns dropped.

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
    if "t" in names:
        t = pts["t"].astype(np.float64)
        if np.issubdtype(pts.dtype["t"], np.integer):
            t = t * 1e-9  # nanoseconds after the header stamp (FORMATS.md section 1)
        t = t.astype(np.float32)
    else:
        t = np.zeros(len(pts), dtype=np.float32)
    keep = np.all(np.isfinite(xyz), axis=1) & np.any(xyz != 0, axis=1)
    stamp = float(msg.header.stamp.sec) + 1e-9 * float(msg.header.stamp.nanosec)
    return Cloud(xyz[keep], t[keep], stamp, str(msg.header.frame_id), len(pts))

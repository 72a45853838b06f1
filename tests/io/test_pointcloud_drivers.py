"""PointCloud2 decoding of sweeps laid out the way real drivers write them (tests/io/driver_clouds.py),
built from raw bytes and the rosbags message classes, not with torchsoil.io.write.

What is asserted is what torchsoil.io.pointcloud documents today: xyz of every point with a
return, exactly, in message order (NaN or all-zero points dropped), the header stamp and
frame, the raw point count, and for the FORMATS.md layout (Ouster's `t`, uint32 ns after
the stamp) the per-point time in seconds. The other drivers' time fields are the subject
of a separate change; their expected times are in the fixtures, unused here.
"""

import struct

import numpy as np
import pytest

from tests.io import driver_clouds as dc
from torchsoil.io.bag import read_recording
from torchsoil.io.pointcloud import decode

# (name, datatype code, offset) per driver, copied from the drivers' sources (see driver_clouds)
F32, F64, U8, U16, U32 = 7, 8, 2, 4, 6
SOURCE_LAYOUTS = {
    "ouster": ([("x", F32, 0), ("y", F32, 4), ("z", F32, 8), ("intensity", F32, 16), ("t", U32, 20),
                ("reflectivity", U16, 24), ("ring", U16, 26), ("ambient", U16, 28), ("range", U32, 32)], 48),
    "velodyne": ([("x", F32, 0), ("y", F32, 4), ("z", F32, 8), ("intensity", F32, 12), ("ring", U16, 16),
                  ("time", F32, 18)], 22),
    "hesai": ([("x", F32, 0), ("y", F32, 4), ("z", F32, 8), ("intensity", F32, 12), ("ring", U16, 16),
               ("timestamp", F64, 18)], 26),
    "robosense": ([("x", F32, 0), ("y", F32, 4), ("z", F32, 8), ("intensity", F32, 12), ("ring", U16, 16),
                   ("timestamp", F64, 18)], 26),
    "livox": ([("x", F32, 0), ("y", F32, 4), ("z", F32, 8), ("intensity", F32, 12), ("tag", U8, 16),
               ("line", U8, 17), ("timestamp", F64, 18)], 26),
}
# struct formats of the time and ring fields, to read the fixture's bytes back independently
TIME_FORMAT = {"ouster": ("<I", 20), "velodyne": ("<f", 18), "hesai": ("<d", 18), "robosense": ("<d", 18),
               "livox": ("<d", 18)}

VARIANTS = {
    "ouster_organized": lambda: dc.ouster(),
    "ouster_unorganized": lambda: dc.ouster(organized=False),
    "ouster_ring_uint8": lambda: dc.ouster(legacy_ring=True),
    "velodyne": lambda: dc.velodyne(),
    "velodyne_organized": lambda: dc.velodyne(organized=True),
    "hesai": lambda: dc.hesai(),
    "robosense_organized_first_point_stamp": lambda: dc.robosense(),
    "robosense_dense_last_point_stamp": lambda: dc.robosense(dense=True, stamp_at="last"),
    "livox": lambda: dc.livox(),
}


# is_dense as each driver sets it: not a promise about the points (Livox says true and keeps
# zero-depth returns at the origin; Hesai always says false)
IS_DENSE = {"ouster_organized": False, "ouster_unorganized": True, "ouster_ring_uint8": False,
            "velodyne": True, "velodyne_organized": False, "hesai": False,
            "robosense_organized_first_point_stamp": False, "robosense_dense_last_point_stamp": True,
            "livox": True}


def driver_of(variant: str) -> str:
    return variant.split("_")[0]


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_fixture_bytes_follow_the_driver_source(variant):
    """The fixture itself: field table, point_step, row_step and the bytes of one point."""
    c = VARIANTS[variant]()
    m = c.msg
    fields, step = SOURCE_LAYOUTS[driver_of(variant)]
    if variant == "ouster_ring_uint8":
        fields = [f if f[0] != "ring" else ("ring", U8, 26) for f in fields]
    assert [(f.name, f.datatype, f.offset, f.count) for f in m.fields] == [(*f, 1) for f in fields]
    assert m.point_step == step and m.row_step == m.width * step and not m.is_bigendian
    assert len(m.data) == m.height * m.row_step
    i = int(np.flatnonzero(c.valid)[0])
    data = bytes(m.data)
    assert struct.unpack_from("<fff", data, i * step) == tuple(float(v) for v in c.xyz[0])
    fmt, off = TIME_FORMAT[driver_of(variant)]
    assert struct.unpack_from(fmt, data, i * step + off)[0] == c.points[c.time_field][i]
    assert bool(m.is_dense) == IS_DENSE[variant]


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_xyz_decoded_exactly_and_no_returns_dropped(variant):
    c = VARIANTS[variant]()
    out = decode(c.msg)
    np.testing.assert_array_equal(out.xyz, c.xyz)
    assert out.xyz.dtype == np.float32
    assert out.n_raw == c.msg.height * c.msg.width == len(c.points)
    assert out.stamp == pytest.approx(c.stamp, abs=1e-6) and out.frame == c.msg.header.frame_id
    assert len(out.t) == len(out.xyz)


@pytest.mark.parametrize("variant", ["ouster_organized", "velodyne_organized",
                                     "robosense_organized_first_point_stamp", "livox"])
def test_clouds_with_no_return_points_lose_exactly_those(variant):
    c = VARIANTS[variant]()
    assert 0 < (~c.valid).sum() < len(c.valid)
    out = decode(c.msg)                 # whatever is_dense says (true for Livox)
    assert len(out.xyz) == c.valid.sum() < out.n_raw
    assert np.isfinite(out.xyz).all() and (np.abs(out.xyz).sum(1) > 0).all()


@pytest.mark.parametrize("variant", ["ouster_organized", "ouster_unorganized", "ouster_ring_uint8"])
def test_ouster_point_time_is_seconds_after_the_stamp(variant):
    c = VARIANTS[variant]()
    out = decode(c.msg)
    np.testing.assert_allclose(out.t, c.t, rtol=1e-6, atol=1e-9)
    # one 10 Hz revolution, starting at the stamp
    assert out.t.min() == 0.0 and 0.095 < out.t.max() < 0.1


@pytest.mark.parametrize("big_endian, row_pad", [(True, 0), (False, 5), (True, 12)])
def test_ouster_layout_big_endian_and_padded_rows(big_endian, row_pad):
    """No driver here writes these, but the header allows them: the decoder must honour them."""
    c = dc.ouster(big_endian=big_endian, row_pad=row_pad)
    assert c.msg.is_bigendian == big_endian and c.msg.row_step == 64 * 48 + row_pad
    out = decode(c.msg)
    np.testing.assert_array_equal(out.xyz, c.xyz)
    np.testing.assert_allclose(out.t, c.t, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_foreign_clouds_through_a_bag_written_by_rosbags(tmp_path, storage):
    """An Ouster front and a Velodyne back sweep, serialized and written by rosbags' own writer,
    come back through torchsoil.io.bag unchanged."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    front = [dc.ouster(seed=s, nanosec=100_000_000 * s) for s in range(2)]
    back = [dc.velodyne(seed=10 + s, sec=1_700_000_000, nanosec=150_000_000 + 100_000_000 * s) for s in range(2)]
    path = tmp_path / "bag"
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    ts = dc.TYPESTORE
    with Writer(path, version=9, storage_plugin=plugin) as w:
        cf = w.add_connection("/lidar_front/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        cb = w.add_connection("/lidar_back/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        for f, b in zip(front, back, strict=True):
            w.write(cf, int(round(f.stamp * 1e9)), ts.serialize_cdr(f.msg, "sensor_msgs/msg/PointCloud2"))
            w.write(cb, int(round(b.stamp * 1e9)), ts.serialize_cdr(b.msg, "sensor_msgs/msg/PointCloud2"))
    rec = read_recording(path)
    assert rec.problems == [] and len(rec.front) == len(rec.back) == 2
    for got, want in zip(rec.front, front, strict=True):
        np.testing.assert_array_equal(got.xyz, want.xyz)
        np.testing.assert_allclose(got.t, want.t, rtol=1e-6, atol=1e-9)
        assert got.stamp == pytest.approx(want.stamp, abs=1e-6) and got.frame == "os_sensor"
    for got, want in zip(rec.back, back, strict=True):
        np.testing.assert_array_equal(got.xyz, want.xyz)
        assert got.stamp == pytest.approx(want.stamp, abs=1e-6) and got.frame == "velodyne"

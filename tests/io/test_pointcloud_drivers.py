"""PointCloud2 decoding of sweeps laid out the way real drivers write them (tests/io/driver_clouds.py),
built from raw bytes and the rosbags message classes, not with torchsoil.io.write.

What is asserted: xyz of every point with a return, exactly, in message order (NaN or
all-zero points dropped), the header stamp and frame, the raw point count, and each point's
capture time in every driver's convention (units, sign, relative or absolute): decode()
gives it after the header stamp; a recording gives it after the sweep start, the stamp of
every stream being moved there (pointtime, stream). Times that cannot be understood, or two
lidars in different clocks, are refused with the topic and field named.
"""

import struct

import numpy as np
import pytest

from tests.io import driver_clouds as dc
from torchsoil.io.bag import BagError, read_recording
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
    "livox_custom": lambda: dc.livox_custom(),
}


# is_dense as each driver sets it: not a promise about the points (Livox says true and keeps
# zero-depth returns at the origin; Hesai always says false)
IS_DENSE = {"ouster_organized": False, "ouster_unorganized": True, "ouster_ring_uint8": False,
            "velodyne": True, "velodyne_organized": False, "hesai": False,
            "robosense_organized_first_point_stamp": False, "robosense_dense_last_point_stamp": True,
            "livox": True, "livox_custom": None}


def driver_of(variant: str) -> str:
    return variant.split("_")[0]


@pytest.mark.parametrize("variant", sorted(set(VARIANTS) - {"livox_custom"}))
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
    assert out.n_raw == len(c.points)
    if hasattr(c.msg, "height"):
        assert out.n_raw == c.msg.height * c.msg.width
    assert out.stamp == pytest.approx(c.stamp, abs=1e-6) and out.frame == c.msg.header.frame_id
    assert len(out.t) == len(out.xyz)


@pytest.mark.parametrize("variant", ["ouster_organized", "velodyne_organized",
                                     "robosense_organized_first_point_stamp", "livox", "livox_custom"])
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


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_point_times_of_every_driver_after_the_header_stamp(variant):
    """Units, sign and reference of each driver's time field: decode() gives s after the stamp."""
    c = VARIANTS[variant]()
    out = decode(c.msg)
    assert out.stamp == pytest.approx(c.stamp, abs=1e-6)
    # absolute float64 s / ns lose ~0.25 us at 1.7e9 s; relative fields are exact to float32
    np.testing.assert_allclose(out.t, c.t, atol=5e-7 if c.time_field == "timestamp" else 1e-8, rtol=0)
    assert 0.09 < out.t.max() - out.t.min() < 0.1


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_foreign_clouds_through_a_bag_written_by_rosbags(tmp_path, storage):
    """An Ouster front (stamped at the sweep start) and a Velodyne back (stamped at its end),
    serialized and written by rosbags' own writer: xyz unchanged, each point at its true
    capture time, and both streams stamped at their sweep starts."""
    front = [dc.ouster(seed=s, nanosec=100_000_000 * s) for s in range(3)]
    back = [dc.velodyne(seed=10 + s, sec=1_700_000_000, nanosec=150_000_000 + 100_000_000 * s) for s in range(3)]
    path = dc.write_bag(tmp_path / "bag", {"/lidar_front/points": front, "/lidar_back/points": back}, storage)
    rec = read_recording(path)
    assert rec.problems == [] and len(rec.front) == len(rec.back) == 3
    for got, want in zip(rec.front, front, strict=True):
        np.testing.assert_array_equal(got.xyz, want.xyz)
        np.testing.assert_allclose(got.t, want.t, rtol=1e-6, atol=1e-9)
        assert got.stamp == pytest.approx(want.stamp, abs=1e-6) and got.frame == "os_sensor"
    for got, want in zip(rec.back, back, strict=True):
        np.testing.assert_array_equal(got.xyz, want.xyz)
        assert got.frame == "velodyne"
        # the first firing, 0.1 s - 1/48 sweep before the last-packet stamp, is the sweep start
        assert got.stamp == pytest.approx(want.stamp - 0.1 + 0.1 / 48, abs=1e-6)
        np.testing.assert_allclose(got.stamp + got.t.astype(np.float64), want.stamp + want.t, atol=1e-6)
        assert got.t.min() == pytest.approx(0.0, abs=1e-6)
    assert "end" in rec.conventions["/lidar_back/points"] and "start" in rec.conventions["/lidar_front/points"]


STAMP_AT = {"ouster": "start", "velodyne": "end", "hesai": "start", "robosense": "start", "robosense_last": "end",
            "livox": "start", "livox_custom": "start"}


# ROS 1 for the Velodyne and the CustomMsg, the conventions most often recorded in ROS 1 bags
@pytest.mark.parametrize("driver, storage", [(d, s) for d in sorted(STAMP_AT) for s in ("sqlite3", "mcap")]
                         + [("velodyne", "ros1"), ("livox_custom", "ros1")])
def test_every_driver_against_an_ouster_through_a_bag(tmp_path, driver, storage):
    """The back lidar in each driver's convention, sweeps starting 20 ms after the Ouster's:
    each back sweep is stamped at its first point, its points at their true times, and
    pairs with the front sweep of the same revolution."""
    t0 = 1_700_000_000_000_000_000
    front = [dc.sweep_at("ouster", t0 + k * 100_000_000, seed=k) for k in range(6)]
    back = [dc.sweep_at(driver, t0 + 20_000_000 + k * 100_000_000, seed=20 + k) for k in range(6)]
    name = "r.bag" if storage == "ros1" else "r"
    rec = read_recording(dc.write_bag(tmp_path / name, {"/lidar_front/points": front, "/lidar_back/points": back},
                                      storage))
    assert rec.problems == [] and len(rec.back) == 6
    conv = rec.conventions["/lidar_back/points"]
    assert f"sweep {STAMP_AT[driver]}" in conv and f"'{back[0].time_field}'" in conv
    for k, (got, want) in enumerate(zip(rec.back, back, strict=True)):
        np.testing.assert_array_equal(got.xyz, want.xyz)
        absolute = want.stamp + want.t
        np.testing.assert_allclose(got.stamp + got.t.astype(np.float64), absolute, atol=1e-6, rtol=0)
        # the sweep start (within one column of the first point) for every convention
        assert got.stamp == pytest.approx(absolute.min(), abs=0.004)
        assert got.stamp - rec.front[k].stamp == pytest.approx(0.02, abs=0.004)


def test_clouds_without_point_times_get_one_note(tmp_path):
    """A driver that publishes de-skewed clouds (no time field) is legitimate: one line says so."""
    fields = [("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("intensity", "f4", 12)]
    sweeps = []
    for k in range(4):
        c = dc.ouster(seed=k, nanosec=100_000_000 * k)
        pts = np.zeros(len(c.xyz), dc.layout(fields, 16))
        pts["x"], pts["y"], pts["z"] = c.xyz.T
        msg = dc.message(pts, fields, 1, len(pts), c.msg.header.stamp.sec, c.msg.header.stamp.nanosec, "deskewed",
                         True)
        sweeps.append(c._replace(msg=msg))
    rec = read_recording(dc.write_bag(tmp_path / "r", {"/lidar_front/points": sweeps[:],
                                                       "/lidar_back/points": sweeps}))
    notes = [p for p in rec.problems if "no per-point time" in p]
    assert len(notes) == 2 and "/lidar_back/points" in notes[1] and len(rec.problems) == 2
    assert all((c.t == 0).all() for c in rec.front + rec.back)
    assert rec.front[1].stamp == pytest.approx(sweeps[1].stamp, abs=1e-6)


def _ouster_with_time(t_values: np.ndarray, kind: str, k: int = 0, sec: int = 1_700_000_000) -> dc.DriverCloud:
    """An Ouster sweep whose `t` field is replaced by `t_values` (one per column) of numpy kind `kind`."""
    c = dc.ouster(seed=k, sec=sec, nanosec=100_000_000 * k, organized=False)
    fields = [(n, kind if n == "t" else f, o) for n, f, o in dc.OUSTER_FIELDS]
    step = 56 if kind == "f8" else 48
    fields = [(n, f, o if n != "t" else 40) for n, f, o in fields] if kind == "f8" else fields
    pts = np.zeros(len(c.points), dc.layout(fields, step))
    for n in c.points.dtype.names:
        pts[n] = c.points[n] if n != "t" else t_values[c.points["t"] // (100_000_000 // 64)]
    msg = dc.message(pts, fields, 1, len(pts), sec, 100_000_000 * k, "os_sensor", True)
    return c._replace(msg=msg)


@pytest.mark.parametrize("unit", ["absolute s", "us", "ms"])
def test_a_t_field_in_another_unit_is_read_by_its_values(tmp_path, unit):
    """`t` as float64 absolute s (the issue's last row), or as uint32 us or float32 ms after the stamp."""
    col = np.arange(64) * (0.1 / 64)
    sweeps = []
    for k in range(5):
        stamp = 1_700_000_000 + 0.1 * k
        vals, kind = {"absolute s": (stamp + col, "f8"), "us": (np.round(col * 1e6), "u4"),
                      "ms": (col * 1e3, "f4")}[unit]
        sweeps.append(_ouster_with_time(vals, kind, k))
    rec = read_recording(dc.write_bag(tmp_path / "r", {"/lidar_front/points": sweeps,
                                                       "/lidar_back/points": sweeps}))
    for got, want in zip(rec.front, sweeps, strict=True):
        np.testing.assert_allclose(got.t, want.t, atol=1e-6)       # want.t: the column times, s after the stamp
        assert got.stamp == pytest.approx(want.stamp, abs=1e-6)


def test_garbage_times_are_refused_naming_topic_and_field(tmp_path):
    rng = np.random.default_rng(0)
    sweeps = [_ouster_with_time(rng.integers(0, 2**32, 64).astype(np.uint32), "u4", k) for k in range(5)]
    good = [dc.ouster(seed=k, nanosec=100_000_000 * k) for k in range(5)]
    path = dc.write_bag(tmp_path / "r", {"/lidar_front/points": good, "/lidar_back/points": sweeps})
    with pytest.raises(BagError, match=r"'/lidar_back/points': per-point time field 't' \(unsigned integer\) "
                                       r"cannot be understood.*pipeline.read.times"):
        read_recording(path)


def test_one_sweep_with_garbage_times_is_skipped_and_named(tmp_path):
    good = [dc.ouster(seed=k, nanosec=100_000_000 * k) for k in range(8)]
    bad = list(good)
    bad[6] = _ouster_with_time(np.arange(64, dtype=np.uint32) * 50_000_000, "u4", 6)     # 3.2 s "sweep"
    rec = read_recording(dc.write_bag(tmp_path / "r", {"/lidar_front/points": good, "/lidar_back/points": bad}))
    assert len(rec.back) == 7 and len(rec.problems) == 1
    assert rec.problems[0].startswith("/lidar_back/points sweep 6 at t=") and "do not fit" in rec.problems[0]


def test_lidars_in_different_clocks_are_refused(tmp_path):
    """An Ouster on its internal clock (stamps from 1970) beside a lidar stamped in ROS time."""
    front = [dc.ouster(seed=k, sec=1234, nanosec=100_000_000 * k) for k in range(5)]
    back = [dc.sweep_at("hesai", 1_700_000_000_000_000_000 + k * 100_000_000, seed=k) for k in range(5)]
    path = dc.write_bag(tmp_path / "r", {"/lidar_front/points": front, "/lidar_back/points": back})
    with pytest.raises(BagError, match=r"different clocks \('/lidar_front/points' stamps 1970-01-01 00:20:34.*"
                                       r"'/lidar_back/points' stamps 2023-11-14.*TIME_FROM_ROS_TIME"):
        read_recording(path)


def test_point_times_in_another_clock_than_the_stamp_are_refused(tmp_path):
    """Hesai points timed by the lidar's clock (1970 + 20 s) under a ROS-time header stamp."""
    back = []
    for k in range(5):
        c = dc.sweep_at("hesai", 1_700_000_000_000_000_000 + k * 100_000_000, seed=k)
        c.msg.data = c.msg.data.copy()
        pts = np.frombuffer(c.msg.data, c.points.dtype)
        pts["timestamp"] -= 1_699_999_980.0
        back.append(c)
    front = [dc.sweep_at("ouster", 1_700_000_000_000_000_000 + k * 100_000_000, seed=k) for k in range(5)]
    path = dc.write_bag(tmp_path / "r", {"/lidar_front/points": front, "/lidar_back/points": back})
    with pytest.raises(BagError, match=r"'timestamp' \(float\).*sits -1\.7e\+09 s from the header stamp.*"
                                       r"different clocks"):
        read_recording(path)


@pytest.mark.parametrize("setting, error", [
    ({"time_unit": "ms"}, r"limited to unit ms"),
    ({"stamp": "end"}, r"settings say the header stamp marks the sweep end.*the sweep start"),
    ({"time_field": "intensity"}, r"time field 'intensity'|cannot be understood"),
])
def test_settings_that_contradict_the_times_are_refused(tmp_path, setting, error):
    from torchsoil.settings import TopicTime

    sweeps = [dc.ouster(seed=k, nanosec=100_000_000 * k) for k in range(5)]
    path = dc.write_bag(tmp_path / "r", {"/lidar_front/points": sweeps, "/lidar_back/points": sweeps})
    with pytest.raises(BagError, match=error):
        read_recording(path, times={"/lidar_back/points": TopicTime(**setting)})


def test_settings_fix_a_convention_the_values_leave_open(tmp_path):
    """time_field none: de-skewed clouds; stamp end: their stamps move back one period."""
    from torchsoil.settings import TopicTime

    sweeps = [dc.ouster(seed=k, nanosec=100_000_000 * k) for k in range(5)]
    path = dc.write_bag(tmp_path / "r", {"/lidar_front/points": sweeps, "/lidar_back/points": sweeps})
    rec = read_recording(path, times={"/lidar_back/points": TopicTime(time_field="none", stamp="end")})
    assert all((c.t == 0).all() for c in rec.back) and any("time_field: none" in p for p in rec.problems)
    assert [c.stamp for c in rec.back] == pytest.approx([c.stamp - 0.1 for c in sweeps], abs=1e-6)

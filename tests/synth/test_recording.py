"""End to end: a small recording, read back with rosbags, checked against the truth."""

import json

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from torchsoil.settings import SettingsError
from torchsoil.synth.bagwriter import POINT_DTYPE
from torchsoil.synth.lidar import KIND_CYLINDER, KIND_GROUND, base_poses_at, scan
from torchsoil.synth.record import T0_NS, iter_sweeps, lidars_for, make_recording, scene_for, sidecar, with_lidar
from torchsoil.synth.scenario import build_truth, load_scenario

SCN = {"name": "small", "trajectory": {"segments": [{"straight": 4.5, "speed": 1.0}]},
       "terrain": {"margin": 4.0},
       "soil": {"base": {"d": 0.03, "chi": 0.3, "beta_deg": 30.0}},
       "landmarks": {"poles": 6, "trunks": 3, "shed": True, "fence": True},
       "lidar": {"columns": 512}}
DURATION = 4.0


def read_bag(path):
    """{topic: [(bag time ns, message)]}."""
    out = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        for c, t, raw in r.messages():
            out.setdefault(c.topic, []).append((t, c.msgtype, r.deserialize(raw, c.msgtype)))
    return out


def cloud_points(msg) -> np.ndarray:
    assert msg.point_step == POINT_DTYPE.itemsize
    assert [(f.name, f.offset) for f in msg.fields] == [(n, POINT_DTYPE.fields[n][1]) for n in POINT_DTYPE.names]
    return np.frombuffer(bytes(msg.data), dtype=POINT_DTYPE, count=msg.width * msg.height)


@pytest.fixture(scope="session")  # tests/conftest.py SHARED_FIXTURES: built once per worker
def rec(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "small"
    stats = make_recording(SCN, out, seed=3, duration=DURATION)
    return out, stats, read_bag(out)


def test_bag_layout_and_sidecars(rec):
    out, stats, msgs = rec
    assert set(msgs) == {"/tf_static", "/lidar_front/points", "/lidar_back/points", "/imu/data", "/gnss/fix"}
    assert {m[1] for m in msgs["/lidar_front/points"]} == {"sensor_msgs/msg/PointCloud2"}
    assert len(msgs["/lidar_front/points"]) == len(msgs["/lidar_back/points"]) == 40
    # the truth is beside the bag, never inside it
    inside = {p.name for p in out.iterdir()}
    assert not any("truth" in n or "pair" in n for n in inside)
    for suffix in ("robot.yaml", "truth.npz", "truth.json", "pair.npz"):
        assert sidecar(out, suffix).is_file()
    meta = json.loads(sidecar(out, "truth.json").read_text())
    assert meta["seed"] == 3 and meta["bag_time_of_t0_ns"] == T0_NS
    assert meta["expected_verdict"] == "adequate" and meta["effects"] == {}
    assert stats["points"] > 1e5


def test_truth_states_the_expected_verdict_in_the_foreign_truth_s_shape(rec):
    from torchsoil.synth.truthfile import load_truth

    out, _, _ = rec
    truth = load_truth(out)
    assert truth.meta["expected"] == truth.expected == {"verdict": "adequate", "missing_physics": None,
                                                        "cross_track": None, "covariate": None}


def test_tf_static_holds_the_extrinsics(rec):
    out, _, msgs = rec
    (t, typ, msg), = msgs["/tf_static"]
    assert typ == "tf2_msgs/msg/TFMessage"
    got = {tf.child_frame_id: tf for tf in msg.transforms}
    truth = build_truth(SCN, 3)
    for spec in lidars_for(truth):
        tf = got[spec.name]
        assert tf.header.frame_id == "base_link"
        tr, q = tf.transform.translation, tf.transform.rotation
        np.testing.assert_allclose([tr.x, tr.y, tr.z], spec.xyz)
        R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        np.testing.assert_allclose(R, spec.transform()[:3, :3], atol=1e-12)


def test_bag_reads_back_exactly_the_points_written(rec):
    """Regenerating the sweeps from the same scenario and seed gives, message by message,
    exactly the bytes in the bag (so generation is also deterministic)."""
    _, _, msgs = rec
    truth = build_truth(SCN, 3)
    expected = list(iter_sweeps(truth, 3, DURATION))
    got = {"lidar_front": iter(msgs["/lidar_front/points"]), "lidar_back": iter(msgs["/lidar_back/points"])}
    for ts, spec, pts in expected:
        bag_t, _, msg = next(got[spec.name])
        assert msg.header.frame_id == spec.name
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert stamp == T0_NS + round(ts * 1e9)
        assert bag_t >= stamp
        np.testing.assert_array_equal(cloud_points(msg), pts)
    assert all(next(it, None) is None for it in got.values())


def test_imu_reads_gravity_and_the_turn_rate_in_its_own_frame(rec):
    """/imu/data at 100 Hz in imu_link (tf_static: turned 90 deg left in base_link). On the
    straight drive at constant speed the specific force, turned into the world with the true
    attitude and the bag's extrinsic, averages (0, 0, +9.807) m/s^2 within the unit's 1 mg
    bias; the gyro shows no turn beyond its bias (0.05 deg/s); samples scatter by the
    white noise (100 ug/sqrt(Hz) at 100 Hz: 0.0098 m/s^2), not more."""
    out, _, msgs = rec
    imu = msgs["/imu/data"]
    assert {m[1] for m in imu} == {"sensor_msgs/msg/Imu"}
    assert len(imu) == pytest.approx(100 * DURATION, abs=2)
    assert all(m.header.frame_id == "imu_link" and m.orientation_covariance[0] == -1 for _, _, m in imu)
    (_, _, tfm), = msgs["/tf_static"]
    q = {t.child_frame_id: t.transform for t in tfm.transforms}["imu_link"].rotation
    R_bi = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    np.testing.assert_allclose(R_bi, Rotation.from_euler("z", np.pi / 2).as_matrix(), atol=1e-12)
    t = np.array([(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec - T0_NS) / 1e9 for _, _, m in imu])
    f = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for _, _, m in imu])
    w = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for _, _, m in imu])
    truth = build_truth(SCN, 3)
    _, R_wb = base_poses_at(truth.traj.poses, t)
    f_world = np.einsum("nij,jk,nk->ni", R_wb, R_bi, f)
    steady = (t > 0.5) & (t < DURATION - 0.5)
    np.testing.assert_allclose(f_world[steady].mean(0), [0, 0, 9.80665], atol=0.04)
    assert np.abs(np.degrees(w[steady].mean(0))).max() < 0.2
    assert 0.005 < np.std(f[steady, 0] - np.mean(f[steady, 0])) < 0.03


def test_points_carry_capture_times_across_the_sweep(rec):
    _, _, msgs = rec
    for topic in ("/lidar_front/points", "/lidar_back/points"):
        for _, _, msg in msgs[topic][::10]:
            p = cloud_points(msg)
            assert p["t"].min() < 5_000_000 and p["t"].max() > 95_000_000   # ns within 100 ms
            assert np.all(np.isfinite(p["x"])) and set(np.unique(p["ring"])) <= set(range(32))
            assert len(np.unique(p["ring"])) > 16 and p["intensity"].max() > 0


def test_motion_distortion_is_present_and_per_point_poses_undo_it():
    """Pole returns land on the pole surface when each point is placed with the pose at its
    own capture time, and up to ~v * 0.1 s off when the whole sweep uses its start pose."""
    truth = build_truth(SCN, 3)
    scene, spec = scene_for(truth), lidars_for(truth)[0]
    rng = np.random.default_rng(0)
    own, start = [], []
    for ts in (1.0, 2.0, 3.0):
        sw = scan(scene, spec, truth.traj.poses, ts, rng, range_noise=0.0, dropout=0.0)
        ok = sw["kind"] == KIND_CYLINDER
        t = ts + sw["t_ns"][ok] / 1e9
        pb = sw["xyz"][ok].astype(np.float64) @ spec.transform()[:3, :3].T + np.asarray(spec.xyz)
        for times, acc in ((t, own), (np.full_like(t, ts), start)):
            pos, R = base_poses_at(truth.traj.poses, times)
            pw = np.einsum("nij,nj->ni", R, pb) + pos
            cyl = truth.landmarks.cylinders
            d = np.hypot(pw[:, None, 0] - cyl[None, :, 0], pw[:, None, 1] - cyl[None, :, 1]) - cyl[None, :, 2]
            acc.append(np.abs(d).min(1))
    own, start = np.concatenate(own), np.concatenate(start)
    assert len(own) > 100
    assert np.percentile(own, 95) < 0.003
    assert np.percentile(start, 95) > 0.03


def test_back_lidar_accumulated_with_true_poses_reproduces_the_deformed_surface(rec):
    """Back-lidar ground points from the bag, placed with the true poses and the bag's own
    extrinsics, averaged per cell, match the true surface after the wheels: no bias beyond
    1 mm, and a per-cell spread at the level of the range noise."""
    out, _, msgs = rec
    truth = build_truth(SCN, 3)
    w = truth.world
    (_, _, tfm), = msgs["/tf_static"]
    tf = {t.child_frame_id: t.transform for t in tfm.transforms}["lidar_back"]
    Rs = Rotation.from_quat([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]).as_matrix()
    ts = np.array([tf.translation.x, tf.translation.y, tf.translation.z])
    X, Y = w.grid.shape
    acc, cnt = np.zeros(X * Y), np.zeros(X * Y)
    for _, _, msg in msgs["/lidar_back/points"]:
        p = cloud_points(msg)
        stamp = (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec - T0_NS) / 1e9
        t = stamp + p["t"] / 1e9
        xyz = np.column_stack([p["x"], p["y"], p["z"]]).astype(np.float64) @ Rs.T + ts
        pos, R = base_poses_at(truth.traj.poses, t)
        pw = np.einsum("nij,nj->ni", R, xyz) + pos
        ij = w.grid.index(pw[:, :2])
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < X) & (ij[:, 1] >= 0) & (ij[:, 1] < Y)
        ij, pw, t = ij[ok], pw[ok], t[ok]
        done = (w.visit_time[:, ij[:, 0], ij[:, 1]] <= t[None]).all(0)     # after the wheels
        flat = ij[done, 0] * Y + ij[done, 1]
        np.add.at(acc, flat, pw[done, 2])
        np.add.at(cnt, flat, 1)
    cells = (cnt >= 4).reshape(X, Y) & (w.n_visits == 1) & (w.h_after < w.h_before - 0.01)
    assert cells.sum() > 200                     # rut cells seen after the wheels passed
    err = (acc.reshape(X, Y) / np.maximum(cnt.reshape(X, Y), 1) - w.h_after)[cells]
    assert abs(err.mean()) < 0.0015  # m; grazing beams on rut walls bias rut cells a little upward
    assert np.sqrt(np.mean(err**2)) < 0.006
    # before the wheels the same cells were higher: the back lidar did see the deformation
    assert (w.h_before[cells] - w.h_after[cells]).mean() > 0.015


def test_ground_points_lie_on_the_truth_at_their_capture_time():
    truth = build_truth(SCN, 3)
    scene, specs = scene_for(truth), lidars_for(truth)
    rng = np.random.default_rng(1)
    w = truth.world
    for spec in specs:
        sw = scan(scene, spec, truth.traj.poses, 2.0, rng, range_noise=0.0, dropout=0.0)
        ok = sw["kind"] == KIND_GROUND
        t = 2.0 + sw["t_ns"][ok] / 1e9
        pb = sw["xyz"][ok].astype(np.float64) @ spec.transform()[:3, :3].T + np.asarray(spec.xyz)
        pos, R = base_poses_at(truth.traj.poses, t)
        pw = np.einsum("nij,nj->ni", R, pb) + pos
        f = truth.field
        ij = f.index(pw[:, :2])
        h = truth.h_field[ij[:, 0], ij[:, 1]]
        near = np.all(np.abs(pw[:, :2] - (np.asarray(f.origin) + ij * f.dx)) < 0.002, axis=1)
        inside_corr = ((ij[:, 0] - truth.corridor[0] >= 0) & (ij[:, 0] - truth.corridor[0] < w.grid.shape[0])
                       & (ij[:, 1] - truth.corridor[1] >= 0) & (ij[:, 1] - truth.corridor[1] < w.grid.shape[1]))
        sel = near & ~inside_corr                # untouched field, points near cell centres
        assert sel.sum() > 50
        assert np.abs(pw[sel, 2] - h[sel]).max() < 0.004


def test_sqlite3_storage_and_refusing_to_overwrite(tmp_path):
    out = tmp_path / "tiny"
    make_recording(SCN, out, seed=0, duration=0.25, storage="sqlite3")
    msgs = read_bag(out)
    assert len(msgs["/lidar_front/points"]) == 2
    assert any(p.suffix == ".db3" for p in out.iterdir())
    with pytest.raises(FileExistsError, match="already exists"):
        make_recording(SCN, out, seed=0, duration=0.25)


def test_bad_lidar_and_bag_settings_are_refused(tmp_path):
    from torchsoil.synth.bagwriter import BagWriter
    from torchsoil.synth.lidar import LidarSpec

    with pytest.raises(ValueError, match="lidar lidar_top: columns"):
        LidarSpec("lidar_top", (0, 0, 1), (0, 0, 0), columns=4)
    with pytest.raises(ValueError, match="rate_hz"):
        LidarSpec("lidar_top", (0, 0, 1), (0, 0, 0), rate_hz=0.0)
    with pytest.raises(ValueError, match="storage must be sqlite3 or mcap"):
        BagWriter(tmp_path / "b", storage="parquet")
    with pytest.raises(SettingsError, match=r"`synth.lidar.columns` = 300"):
        make_recording(SCN, tmp_path / "c", columns=300)
    assert not (tmp_path / "c").exists()
    scn = load_scenario(SCN)
    assert with_lidar(scn) is scn
    assert with_lidar(scn, columns=2048, organized=True).lidar == scn.lidar.replace(columns=2048, organized=True)


def test_lidar_geometry_of_the_platform():
    """32 rings over 45 deg; the front lidar sees the ground ahead, the back lidar behind,
    neither sees ground under the chassis, and they overlap little."""
    truth = build_truth(SCN, 3)
    front, back = lidars_for(truth)
    el = np.degrees(front.elevations())
    assert len(el) == 32 and el[0] == pytest.approx(22.5) and el[-1] == pytest.approx(-22.5)
    scene = scene_for(truth)
    rng = np.random.default_rng(0)
    for spec, sign in ((front, 1), (back, -1)):
        sw = scan(scene, spec, truth.traj.poses, 1.0, rng, 0.0, 0.0)
        g = sw["kind"] == KIND_GROUND
        pb = sw["xyz"][g].astype(np.float64) @ spec.transform()[:3, :3].T + np.asarray(spec.xyz)
        under = (np.abs(pb[:, 0]) < 0.76) & (np.abs(pb[:, 1]) < 0.6)
        assert not under.any()
        assert np.mean(sign * pb[:, 0] > 0) > 0.9           # on its own side
        near = np.hypot(pb[:, 0], pb[:, 1]) < 4.0
        assert np.mean(sign * pb[near, 0] > 0.69) > 0.9       # near ground: mostly beyond its axle


def test_truth_file_round_trip(rec):
    from torchsoil.grid import Grid
    from torchsoil.synth.truthfile import load_truth

    out, _, _ = rec
    tf = load_truth(out)
    w = build_truth(SCN, 3).world
    np.testing.assert_array_equal(tf["h_after"], w.h_after.astype(np.float32))
    np.testing.assert_array_equal(tf["n_visits"], w.n_visits)
    assert tf.grid == w.grid and tf.t0 == T0_NS / 1e9 and tf.meta["scenario"] == "small"
    assert tf.scenario == load_scenario(SCN) and tf.scenario.lidar.columns == 512
    # resampling onto a shifted grid of the same cell size picks the same cells
    g = w.grid.crop(5, 50, 7, 60)
    np.testing.assert_array_equal(tf.on_grid("h_after", g), w.h_after[5:50, 7:60].astype(np.float32))
    far = Grid(0.02, (1000.0, 1000.0), (3, 3))
    assert np.isnan(tf.on_grid("h_after", far)).all()
    with pytest.raises(FileNotFoundError, match="no truth file"):
        load_truth(out.parent / "elsewhere")


def test_organized_clouds_keep_the_beam_image(tmp_path):
    out = tmp_path / "org"
    make_recording(SCN, out, seed=5, duration=0.2, organized=True)
    msgs = read_bag(out)
    truth = build_truth(with_lidar(load_scenario(SCN), organized=True), 5)
    expected = list(iter_sweeps(truth, 5, 0.2))
    got = msgs["/lidar_front/points"] + msgs["/lidar_back/points"]
    assert len(got) == len(expected) == 4
    for _, _, msg in got:
        assert (msg.height, msg.width) == (32, 512) and msg.is_dense is False
        p = cloud_points(msg).reshape(32, 512)
        assert np.array_equal(p["ring"], np.broadcast_to(np.arange(32)[:, None], (32, 512)))
        assert 0.3 < np.isnan(p["x"]).mean() < 0.8             # sky and dropouts
    front = [e for e in expected if e[1].name == "lidar_front"]
    assert cloud_points(msgs["/lidar_front/points"][0][2]).tobytes() == front[0][2].tobytes()   # NaN-safe


def test_gnss_fixes_are_the_antenna_on_the_datum_with_rtk_noise(rec):
    """Each fix, projected with pyproj, lies where the datum puts the antenna (base_link's true
    pose plus the antenna's offset, by hand) within the RTK noise the covariance states."""
    from pyproj import Transformer

    from torchsoil.synth.truthfile import load_truth

    out, _, msgs = rec
    truth = load_truth(out)
    datum, gnss = truth.meta["datum"], truth.meta["gnss"]
    fixes = [m for _, _, m in msgs["/gnss/fix"]]
    assert len(fixes) == int(DURATION * gnss["rate_hz"]) + 1
    assert {f.status.status for f in fixes} == {2} and {f.position_covariance_type for f in fixes} == {2}
    assert fixes[0].position_covariance[0] == pytest.approx(gnss["sigma_h"] ** 2)
    t = np.array([f.header.stamp.sec + 1e-9 * f.header.stamp.nanosec for f in fixes]) - truth.t0
    poses = truth["poses"]
    x, y, yaw = (np.interp(t, poses[:, 0], poses[:, k]) for k in (1, 2, 6))
    ax, ay, _ = gnss["xyz"]
    px, py = x + np.cos(yaw) * ax - np.sin(yaw) * ay, y + np.sin(yaw) * ax + np.cos(yaw) * ay
    c, s, k = np.cos(datum["yaw"]), np.sin(datum["yaw"]), datum["scale"]
    want = np.column_stack([datum["east"] + k * (c * px - s * py), datum["north"] + k * (s * px + c * py)])
    e, n = Transformer.from_crs("EPSG:4326", f"EPSG:{datum['epsg']}", always_xy=True).transform(
        [f.longitude for f in fixes], [f.latitude for f in fixes])
    err = np.column_stack([e, n]) - want
    assert np.abs(err).max() < 5 * gnss["sigma_h"]
    assert np.std(err) == pytest.approx(gnss["sigma_h"], rel=0.5)
    tf = {tr.child_frame_id: tr.transform.translation for tr in msgs["/tf_static"][0][2].transforms}
    assert [tf["gnss_link"].x, tf["gnss_link"].y, tf["gnss_link"].z] == pytest.approx(gnss["xyz"])

"""A season: several sessions (recordings of other days) on one field, the world carried from
one session to the next, each recording in its own map frame (synth.scenario.build_season,
synth.record.make_season)."""

import json
import math

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy.ndimage import map_coordinates

from torchsoil.jobs.record import record
from torchsoil.settings import SettingsError
from torchsoil.synth.record import T0_NS, make_season
from torchsoil.synth.scenario import build_season, load_scenario, season_pair
from torchsoil.synth.trajectory import planar_path
from torchsoil.synth.truthfile import load_truth
from torchsoil.synth.world import simulate_world

HARDENING = {"multi_pass_hardening": {"form": "saturating", "k": -0.6, "x_s": 1.0}}
# three sessions on one 3 m lane: out along y = 0, back along y = 0.03 a day later, out again
# along y = 0 (without GNSS) two days later
SEASON = {"name": "small_season", "trajectory": {"segments": [{"straight": 3.0, "speed": 1.0}]},
          "later_sessions": [{"gap": 86400.0, "start": [3.0, 0.03, 180.0], "segments": [{"straight": 3.0}]},
                             {"gap": 172800.0, "start": [0.0, 0.0, 0.0], "segments": [{"straight": 3.0}],
                              "gnss": False}],
          "terrain": {"margin": 1.5}, "landmarks": {"poles": 3, "trunks": 1, "shed": True, "fence": False},
          "soil": {"base": {"d": 0.03, "chi": 0.2, "beta_deg": 30.0}}, "effects": HARDENING,
          "lidar": {"columns": 512}}
FLAT = {"terrain": {"relief": {"amplitude": 0.0}, "micro": {"rms": 0.0}, "margin": 0.5},
        "landmarks": {"poles": 0, "trunks": 0, "shed": False, "fence": False}}
RADIUS = 0.07      # paper platform: footprint radius (wheel_width 0.14 / 2), m
DURATION = 1.0     # s of each session in the bags


@pytest.fixture(scope="module")
def season():
    return build_season(SEASON, seed=1)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("season") / "small"
    stats = make_season(SEASON, out, seed=1, duration=DURATION)
    return out, stats


def read_bag(path):
    out = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        for c, t, raw in r.messages():
            out.setdefault(c.topic, []).append((t, r.deserialize(raw, c.msgtype)))
    return out


def stamp(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_later_sessions_are_validated():
    with pytest.raises(SettingsError, match=r"synth\.later_sessions\.0\.start"):
        load_scenario({"later_sessions": [{"segments": [{"straight": 2.0}]}]})
    with pytest.raises(SettingsError, match=r"synth\.later_sessions\.0\.gap"):
        load_scenario({"later_sessions": [{"start": [0, 0, 0], "segments": [{"straight": 2.0}], "gap": -1.0}]})
    scn = load_scenario(SEASON)
    assert [s.gap for s in scn.later_sessions] == [86400.0, 172800.0]
    assert [s.gnss for s in scn.later_sessions] == [True, False]


def _straights(segments, start):
    """(x, y, yaw_deg) at the start and end of each straight of a path, by planar_path over
    the segments up to it."""
    out = []
    for i, seg in enumerate(segments):
        if seg.straight is not None:
            a, _ = planar_path(segments[:i], start) if i else (np.array([[0.0, *start]]), None)
            b, _ = planar_path(segments[:i + 1], start)
            out.append((a[-1, 1], a[-1, 2], math.degrees(a[-1, 3]) % 360, b[-1, 1], b[-1, 2]))
    return np.array(out)


def test_shipped_field_seasons_drive_the_rows_both_ways():
    """field_season: session 1 drives lanes y = 0, 1.05, 2.1 m over x in [0, 8] m, +x, -x, +x,
    joined by Omega turns of radius 1.5 m (out by alpha, cos alpha = (w + 2R) / 4R, round by
    180 + 2 alpha); session 2, a day later, starts at the far end and drives them the other way
    3 cm further along +y. field_season_null is the same without the hardening."""
    scn, null = load_scenario("field_season"), load_scenario("field_season_null")
    assert list(scn.effects) == ["multi_pass_hardening"] and null.effects == {}
    assert null.replace(effects=scn.effects, name=scn.name, description=scn.description) == scn
    (later,) = scn.later_sessions
    assert later.gap == 86400.0
    alpha = math.degrees(math.acos((1.05 + 2 * 1.5) / (4 * 1.5)))
    turns = [s for s in scn.trajectory.segments if s.arc is not None]
    assert {s.arc for s in turns} == {1.5}
    assert sorted({abs(s.angle_deg) for s in turns}) == pytest.approx([alpha, 180 + 2 * alpha], abs=1e-3)
    one = _straights(scn.trajectory.segments, (0.0, 0.0, 0.0))
    two = _straights(later.segments, (later.start[0], later.start[1], math.radians(later.start[2])))
    # x0, y0, heading, x1, y1 of each lane
    np.testing.assert_allclose(one, [[0, 0, 0, 8, 0], [8, 1.05, 180, 0, 1.05], [0, 2.1, 0, 8, 2.1]], atol=2e-4)
    np.testing.assert_allclose(two, [[8, 2.13, 180, 0, 2.13], [0, 1.08, 0, 8, 1.08], [8, 0.03, 180, 0, 0.03]],
                               atol=2e-4)


def test_a_drive_split_into_two_sessions_leaves_the_ground_of_the_whole_drive():
    """Out along a lane, round a keyhole, back on the same ruts: driven at once, or as two
    sessions split after the keyhole (the second from where the first stopped), the ground left
    on the lane is the same, hardening included (its second pass is the second session's). A
    second session that does not carry the first's passes (a fresh SoilState) digs its second
    pass as a first and leaves ruts deeper by millimetres."""
    loop = [{"arc": 1.5, "angle_deg": -60}, {"arc": 1.5, "angle_deg": 300}, {"arc": 1.5, "angle_deg": -60}]
    base = {**FLAT, "soil": {"base": {"d": 0.03, "chi": 0.2, "beta_deg": 30.0}}, "effects": HARDENING}
    (whole,) = build_season({**base, "trajectory": {"segments": [{"straight": 3.0}, *loop, {"straight": 3.0}]}})
    split = whole.traj.poses[np.argmin(np.abs(whole.traj.arc - (3.0 + 1.5 * math.radians(420))))]
    assert split[1:3] == pytest.approx([3.0, 0.0], abs=0.01) and split[6] == pytest.approx(math.pi, abs=1e-3)
    first, second = build_season({**base, "trajectory": {"segments": [{"straight": 3.0}, *loop]},
                                  "later_sessions": [{"gap": 3600.0, "start": [split[1], split[2], 180.0],
                                                      "segments": [{"straight": 3.0}]}]})
    xs, ys = whole.world.grid.centers()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    lane = (X > 0.5) & (X < 2.0) & (np.abs(Y) < 0.8)
    ij = second.world.grid.index(np.stack([X[lane], Y[lane]], -1))
    at = (ij[:, 0], ij[:, 1])
    dug = whole.world.h_after[lane] - whole.world.h_before[lane]
    assert dug.min() < -0.02                                   # the ruts are there
    assert np.abs(second.world.h_after[at] - whole.world.h_after[lane]).max() < 5e-4
    assert (second.start.passes[at] == first.world.end.passes[at]).all()
    assert (second.world.end.passes[at] == whole.world.end.passes[lane]).all()
    assert set(np.unique(whole.world.end.passes[lane])) == {0, 2}
    fresh = simulate_world(second.world.grid, first.world.end.h, second.traj, second.robot, second.scenario.soil,
                           second.scenario.effects, second.scenario.world)
    assert np.abs(fresh.h_after[at] - whole.world.h_after[lane]).max() > 5e-3


def test_each_session_starts_on_the_ground_the_one_before_left(season):
    one, two, three = season
    assert [t.session for t in season] == [1, 2, 3] and {t.sessions for t in season} == {3}
    assert one.world.grid == two.world.grid == three.world.grid
    np.testing.assert_array_equal(two.world.h_before, one.world.h_after)
    np.testing.assert_array_equal(three.world.h_before, two.world.h_after)
    assert (one.start.passes == 0).all()
    np.testing.assert_array_equal(three.start.passes, two.world.end.passes)
    np.testing.assert_array_equal(three.start.visits, one.world.n_visits + two.world.n_visits)
    # a session's own visits restart: the second's lane cells have one visit each, not two
    assert two.world.n_visits.max() == 1 and (three.start.visits.max() == 2)


def test_the_clock_gaps_and_map_frames(season):
    """Session k's clock: the end of k - 1 plus the gap (a 3 m straight at 1 m/s sampled at
    100 Hz ends at t = 2.99 s). T_world_map: base_link at t = 0, turned upright about the
    vertical only; on flat ground exactly the start pose."""
    one, two, three = season
    assert one.traj.duration == pytest.approx(2.99)
    assert [t.clock for t in season] == pytest.approx([0.0, 2.99 + 86400.0, 2 * 2.99 + 86400.0 + 172800.0])
    for t in season:
        T = t.T_world_map
        np.testing.assert_allclose(T[:3, 3], t.traj.poses[0, 1:4], atol=1e-12)
        np.testing.assert_allclose(T[:3, 2], [0, 0, 1], atol=1e-12)         # levelled: z is up
        assert abs(math.remainder(math.atan2(T[1, 0], T[0, 0]) - t.traj.poses[0, 6], 2 * math.pi)) < 1e-3
        assert np.abs(t.traj.poses[0, 4:6]).max() > 1e-4                     # on the relief: tilted start
    a, b = build_season({**SEASON, **FLAT, "later_sessions": SEASON["later_sessions"][:1]}, seed=1)
    np.testing.assert_allclose(a.T_world_map, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(b.T_world_map, [[-1, 0, 0, 3.0], [0, -1, 0, 0.03], [0, 0, 1, 0], [0, 0, 0, 1]],
                               atol=1e-12)


def test_each_pair_is_in_its_own_map_frame_on_the_ground_left_before(season):
    """Session 2's pair, noise-free: its poses put into the world by T_world_map are the true
    ones, and its H_f, carried through T_world_map_1^-1 T_world_map_2 into session 1's map, is
    session 1's H_b where session 1 dug (not its H_f: the ruts are there)."""
    one, two, _ = season
    p1, p2 = (season_pair(t, seed=1, noise=0.0) for t in (one, two))
    assert int(p2["session"]) == 2
    T1, T2 = one.T_world_map, two.T_world_map
    rows = p2["poses"]
    assert rows[0, 1:4] == pytest.approx([0, 0, 0], abs=1e-12) and abs(rows[0, 6]) < 1e-3
    world = np.column_stack([rows[:, 1:4], np.ones(len(rows))]) @ T2.T
    np.testing.assert_allclose(world[:, :3], two.traj.poses[:, 1:4], atol=1e-9)
    np.testing.assert_allclose(rows[:, 0], two.traj.poses[:, 0])            # the session's own clock
    dx = float(p2["dx"])
    X, Y = np.meshgrid(*(p2["origin"][i] + dx * np.arange(p2["h_front"].shape[i]) for i in (0, 1)), indexing="ij")
    p = np.stack([X, Y, p2["h_front"], np.ones_like(X)], -1) @ (np.linalg.inv(T1) @ T2).T
    at = np.stack([(p[..., 0] - p1["origin"][0]) / dx, (p[..., 1] - p1["origin"][1]) / dx])
    back, front = (map_coordinates(p1[k].astype(np.float64), at, order=1, cval=np.nan) for k in ("h_back", "h_front"))
    dug = np.abs(back - front) > 0.003
    assert dug.sum() > 2000
    rms = np.sqrt(np.mean((p[..., 2] - back)[dug] ** 2))
    assert rms < 1e-3
    assert np.sqrt(np.mean((p[..., 2] - front)[dug] ** 2)) > 5 * rms


def test_a_season_recording_clocks_datum_and_layout(recorded):
    """DIR/session_K bags on the season's clock (session K's stamps start at T0 + its clock);
    the GNSS fixes of every session lie where the one datum puts the true antenna; a session
    whose scenario says gnss: false has none."""
    from pyproj import Transformer

    out, stats = recorded
    meta = json.loads((out / "season.json").read_text())
    assert [s["name"] for s in meta["sessions"]] == ["session_1", "session_2", "session_3"]
    assert [s["gnss"] for s in meta["sessions"]] == [True, True, False]
    assert set(stats) == {"session_1", "session_2", "session_3", "total_s"}
    datum = meta["datum"]
    for s in meta["sessions"]:
        path = out / s["name"]
        truth = load_truth(path)
        assert truth.meta["bag_time_of_t0_ns"] == s["bag_time_of_t0_ns"] == T0_NS + round(s["clock_s"] * 1e9)
        assert truth.meta["datum"] == datum and truth.meta["season"]["session"] == s["session"]
        np.testing.assert_allclose(truth["T_world_map"], s["T_world_map"])
        msgs = read_bag(path)
        front = msgs["/lidar_front/points"]
        assert len(front) == int(DURATION * 10) and stamp(front[0][1]) == s["bag_time_of_t0_ns"]
        assert ("/gnss/fix" in msgs) == s["gnss"]
        if not s["gnss"]:
            continue
        fixes = [m for _, m in msgs["/gnss/fix"]]
        t = (np.array([stamp(f) for f in fixes]) - s["bag_time_of_t0_ns"]) / 1e9
        poses = truth["poses"]
        x, y, yaw = (np.interp(t, poses[:, 0], poses[:, k]) for k in (1, 2, 6))
        ax, ay, _ = truth.meta["gnss"]["xyz"]
        px, py = x + np.cos(yaw) * ax - np.sin(yaw) * ay, y + np.sin(yaw) * ax + np.cos(yaw) * ay
        c, sn, k = np.cos(datum["yaw"]), np.sin(datum["yaw"]), datum["scale"]
        want = np.column_stack([datum["east"] + k * (c * px - sn * py), datum["north"] + k * (sn * px + c * py)])
        e, n = Transformer.from_crs("EPSG:4326", f"EPSG:{datum['epsg']}", always_xy=True).transform(
            [f.longitude for f in fixes], [f.latitude for f in fixes])
        assert np.abs(np.column_stack([e, n]) - want).max() < 0.05
    clock = [s["clock_s"] for s in meta["sessions"]]
    assert clock[1] - clock[0] - meta["sessions"][0]["duration_s"] == pytest.approx(86400.0)
    assert clock[2] - clock[1] - meta["sessions"][1]["duration_s"] == pytest.approx(172800.0)


def test_passes_before_a_session_count_the_earlier_footprints(recorded):
    """passes_before_session (on the pair's grid): the earlier sessions whose wheel footprint
    (radius 7 cm about the wheel's path) covered the cell; visits_before_session: those that
    came within the wheels' reach (35 cm: the footprint plus relax_margin wheel widths). By
    hand at x = 1.5 m: session 1's left wheels run along y = 0.5, session 2's right wheels (3 cm
    over, driving back) along y = 0.53."""
    out, _ = recorded
    paths = [0.5, 0.53]                                  # y of sessions 1 and 2's wheels near y = 0.5
    # world y: (passes before session 2, before session 3)
    by_hand = {0.5: (1, 2), 0.40: (0, 0), 0.585: (0, 1), 0.0: (0, 0)}
    for k in (2, 3):
        tr = load_truth(out / f"session_{k}")
        dx, T = float(tr["dx"]), tr["T_world_map"]
        for y, want in by_hand.items():
            m = np.linalg.inv(T) @ np.array([1.5, y, 0.0, 1.0])           # the pair cell nearest (1.5, y)
            i, j = np.round((m[:2] - tr["pair_origin"]) / dx).astype(int)
            centre = T @ np.array([*(tr["pair_origin"] + dx * np.array([i, j])), 0.0, 1.0])
            wy = tr.grid.origin[1] + dx * tr.grid.index(centre[:2])[1]   # and the world cell nearest it
            dist = np.abs(wy - np.array(paths[: k - 1]))
            assert (np.abs(dist - RADIUS) > 0.004).all(), "a cell clear of a footprint's edge"
            assert int(tr["passes_before_session"][i, j]) == want[k - 2] == int((dist <= RADIUS).sum())
            assert int(tr["visits_before_session"][i, j]) == (0 if y == 0.0 else k - 1)
    one = load_truth(out / "session_1")
    assert (one["passes_before_session"] == 0).all() and (one["visits_before_session"] == 0).all()


def test_record_writes_a_season_into_a_directory(tmp_path):
    scn = {**SEASON, **FLAT, "later_sessions": SEASON["later_sessions"][:1]}
    with pytest.raises(ValueError, match="directory"):
        record(scn, tmp_path / "season.npz", pair_only=True)
    with pytest.raises(ValueError, match="one session"):
        record({**scn, "later_sessions": []}, tmp_path / "single.npz", pair_only=True, sessions=[2])
    record(scn, tmp_path / "s", pair_only=True, sessions=[2])
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == [
        "season.json", "session_2.pair.npz", "session_2.truth.json", "session_2.truth.npz"]
    with pytest.raises(FileExistsError):
        record(scn, tmp_path / "s", pair_only=True, sessions=[2])
    with np.load(tmp_path / "s" / "session_2.pair.npz") as pair:
        assert int(pair["session"]) == 2
    assert load_truth(tmp_path / "s" / "session_2").meta["season"]["session"] == 2

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from tests.drive_by_hand import racetrack
from tests.synthetic_pair import sim_pair
from torchsoil.estimate.windows import (
    WindowStore,
    _latest_hit,
    _stopped,
    front_view,
    path_index,
    plan_windows,
    prepare_window,
)
from torchsoil.grid import Grid
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.robot import paper_platform
from torchsoil.settings import EstimatorConfig
from torchsoil.sim import SimConfig
from torchsoil.sim.geometry import wheel_positions


def test_plan_windows():
    w = plan_windows(4.0, 0.8, 0.4)
    assert len(w) == 9 and w[0].s0 == 0 and w[-1].s1 == pytest.approx(4.0)
    assert all(b.s0 - a.s0 == pytest.approx(0.4) for a, b in zip(w, w[1:], strict=False))
    assert plan_windows(0.5, 0.8, 0.4) == []
    with pytest.raises(ValueError):
        plan_windows(4.0, 0.0, 0.4)


@pytest.fixture(scope="module")
def pair():
    return sim_pair(length=3.0)[0]


def test_path_index(pair):
    idx = path_index(pair.grid, pair.poses, pair.robot, 1.6)
    x, y = pair.grid.centers()
    j = np.argmin(abs(y))
    s = idx.s[:, j]
    on = np.isfinite(s)
    assert np.all(np.diff(s[on]) >= 0)  # arc length grows along a straight drive
    i = np.argmin(abs(x - 1.5))
    assert s[i] == pytest.approx(1.5, abs=0.02)
    jw = np.argmin(abs(y - 0.503))
    assert idx.wheel_dist[i, jw] < 0.02 and idx.offset[i, jw] == pytest.approx(0.5, abs=0.02)


def test_prepare_window_masks(pair):
    idx = path_index(pair.grid, pair.poses, pair.robot, 1.6)
    spec = plan_windows(3.0, 0.8, 0.4)[2]
    wd = prepare_window(pair, idx, spec, EstimatorConfig(), SimConfig())
    assert wd.flags == ()
    i0, i1, j0, j1 = wd.crop
    x, _ = pair.grid.crop(*wd.crop).centers()
    ground_x = x[wd.ground.numpy().any(1)]
    assert ground_x.min() >= spec.s0 - 0.03 and ground_x.max() <= spec.s1 + 0.03
    assert (wd.weight.numpy() > 0).sum() > 0.9 * (wd.ground.numpy() & (wd.weight.numpy() > 0)).sum()
    assert not (wd.floor.numpy() & (wd.weight.numpy() > 0)).any()  # beside the rut, not in it


def test_a_window_holds_its_crop_and_not_the_whole_grid(pair):
    """A window's ground is the cells whose arc length falls in its span, within half the
    corridor of the path (as read off the full grid), and every tensor it keeps owns only
    the crop's memory: a view into a full-grid array would keep that array alive per window,
    memory that grows with the drive's length times its grid."""
    idx = path_index(pair.grid, pair.poses, pair.robot, 1.6)
    est = EstimatorConfig()
    for spec in plan_windows(3.0, 0.8, 0.4)[1:4]:
        full = (idx.s >= spec.s0) & (idx.s < spec.s1) & (idx.offset <= est.corridor / 2)
        np.testing.assert_array_equal(idx.ground(spec.s0, spec.s1, est.corridor), np.argwhere(full))
        wd = prepare_window(pair, idx, spec, est, SimConfig())
        i0, i1, j0, j1 = wd.crop
        np.testing.assert_array_equal(wd.ground.numpy(), full[i0:i1, j0:j1])
        for name in ("h_front", "h_ref", "h_back", "h_measured", "weight", "floor", "ground"):
            t = getattr(wd, name)
            assert t.untyped_storage().nbytes() == t.numel() * t.element_size(), name


def test_unmeasured_window_is_flagged(pair):
    idx = path_index(pair.grid, pair.poses, pair.robot, 1.6)
    spec = plan_windows(3.0, 0.8, 0.4)[2]
    holed = sim_pair(length=3.0)[0]
    x, _ = holed.grid.centers()
    holed.h_back[(x > spec.s0 - 0.1) & (x < spec.s1 + 0.1)] = np.nan
    wd = prepare_window(holed, idx, spec, EstimatorConfig(), SimConfig())
    assert "few_valid" in wd.flags
    holed.h_front[:] = np.nan
    assert prepare_window(holed, idx, spec, EstimatorConfig(), SimConfig()) is None


def test_stopped():
    t = np.arange(0, 4, 0.1)
    moving = np.column_stack([t, t, 0 * t, 0 * t, 0 * t, 0 * t, 0 * t])
    assert not _stopped(moving, 0.05, 0.5)
    x = np.where(t < 1, t, np.where(t < 2, 1.0, t - 1))
    still = np.column_stack([t, x, 0 * t, 0 * t, 0 * t, 0 * t, 0 * t])
    assert _stopped(still, 0.05, 0.5)


def test_ground_driven_twice_belongs_to_the_last_pass(pair):
    """Out along +x and back over the same line: the cells take the return pass's arc length."""
    t = np.arange(0, 6.0001, 0.05)
    x = np.where(t <= 3, t, 6 - t)
    yaw = np.where(t <= 3, 0.0, np.pi)
    poses = np.column_stack([t, x, 0 * t, 0 * t, 0 * t, 0 * t, yaw])
    idx = path_index(pair.grid, poses, pair.robot, 1.6)
    xs, ys = pair.grid.centers()
    j = np.argmin(abs(ys))
    for xc in (0.2, 0.6, 1.0):  # nearer the turning point the two passes are one
        i = np.argmin(abs(xs - xc))
        assert idx.s[i, j] == pytest.approx(6.0 - xc, abs=0.05)
    straight = path_index(pair.grid, pair.poses, pair.robot, 1.6)  # one pass: nearest point
    i = np.argmin(abs(xs - 1.5))
    assert straight.s[i, j] == pytest.approx(1.5, abs=0.05)


def test_ground_belongs_to_the_last_pass_whose_wheels_went_over_it(pair):
    """Out along y = 0, a tight U-turn, back along y = 0.5 (half the track, a lane change):
    the return's base_link runs over the first pass's left rut, which its wheels (at y = 0
    and 1) leave alone, and its left wheel runs between the first pass's ruts, nearer the
    first pass's base_link. Worked by hand at x = 1.5: the left rut keeps the first pass's
    arc length 1.5 m, the strip between the ruts takes the return's, 3 + pi 0.25 + 1.5 m;
    the right rut, untouched on the way back, and the return's right rut are unchanged."""
    out = np.linspace(0, 3, 61)
    a = np.linspace(-np.pi / 2, np.pi / 2, 31)[1:]
    back = np.linspace(3, 0, 61)[1:]
    x = np.concatenate([out, 3 + 0.25 * np.cos(a), back])
    y = np.concatenate([0 * out, 0.25 + 0.25 * np.sin(a), 0.5 + 0 * back])
    yaw = np.concatenate([0 * out, a + np.pi / 2, np.pi + 0 * back])
    t = np.concatenate([[0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    poses = np.column_stack([t, x, y, 0 * t, 0 * t, 0 * t, yaw])
    idx = path_index(pair.grid, poses, pair.robot, 1.6)
    xs, ys = pair.grid.centers()
    i = np.argmin(abs(xs - 1.5))
    s_at = {yc: idx.s[i, np.argmin(abs(ys - yc))] for yc in (-0.5, 0.0, 0.5, 1.0)}
    back_s = 3 + np.pi * 0.25 + 1.5
    assert s_at[0.5] == pytest.approx(1.5, abs=0.05)        # under the return's base_link, not its wheels
    assert s_at[0.0] == pytest.approx(back_s, abs=0.05)     # under the return's left wheel
    assert s_at[-0.5] == pytest.approx(1.5, abs=0.05)
    assert s_at[1.0] == pytest.approx(back_s, abs=0.05)


def test_latest_hit_matches_a_search_of_every_point():
    """The binned backward search against all (K, N) points at once, on a path that crosses
    itself (a figure eight, two wheels), with one radius for all cells and one per cell: the
    latest point index within the radius, -1 where none is."""
    rng = np.random.default_rng(3)
    u = np.linspace(0, 4 * np.pi, 1500)
    centre = np.column_stack([2 * np.sin(u / 2), np.sin(u)])
    points = np.stack([centre + [0, 0.3], centre - [0, 0.3]])               # (2, N, 2)
    cells = rng.uniform([-2.5, -1.5], [2.5, 1.5], (3000, 2))
    dist = np.linalg.norm(points[:, None] - cells[None, :, None], axis=-1)   # (K, C, N)
    for radius in (0.1, rng.uniform(0.0, 0.4, len(cells))):
        within = (dist <= np.broadcast_to(radius, (len(cells),))[None, :, None]).any(0)
        want = np.where(within.any(1), within.shape[1] - 1 - np.argmax(within[:, ::-1], 1), -1)
        got = _latest_hit(cells, points, radius)
        assert (want >= 0).sum() > 500 and (want < 0).sum() > 100
        np.testing.assert_array_equal(got, want)


def _ruts(grid: Grid, poses: np.ndarray, robot, depth: float, sigma: float = 0.03) -> np.ndarray:
    """(X, Y) Gaussian troughs `depth` m deep along every wheel path of the poses."""
    w = wheel_positions(poses[:, [0, 1, 2, 6]], robot.wheels[:, :2]).reshape(-1, 2)
    xs, ys = grid.centers()
    cells = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    dist = cKDTree(w).query(cells)[0].reshape(grid.shape)
    return -depth * np.exp(-0.5 * (dist / sigma) ** 2)


@pytest.fixture(scope="module")
def lap_and_a_half():
    """A racetrack driven once and then along its first 2 m again (tests.drive_by_hand), on
    rough ground: H_b with 25 mm ruts everywhere; H_f either untouched (a first view) or
    with the first lap's 15 mm ruts where the second lap comes back (the view before it)."""
    robot, dx = paper_platform(), 0.02
    poses = racetrack()
    x0, y0 = poses[:, 1:3].min(0) - 1.2
    x1, y1 = poses[:, 1:3].max(0) + 1.2
    grid = Grid.covering(x0, y0, x1, y1, dx)
    rng = np.random.default_rng(3)
    ground = 0.004 * rng.standard_normal(grid.shape)
    final = ground + _ruts(grid, poses, robot, 0.025)
    arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(poses[:, 1:3], axis=0), axis=1))])
    first_lap = poses[arc < 2.5]                               # the ground the end comes back over
    shown = ground + _ruts(grid, first_lap, robot, 0.015)

    def pair(h_front):
        noisy = h_front + 0.003 * rng.standard_normal(grid.shape)
        return TerrainPair(dx, np.array(grid.origin), noisy.astype(np.float32),
                           (final + 0.003 * rng.standard_normal(grid.shape)).astype(np.float32), poses,
                           robot.wheels, robot.wheel_width)

    return pair(ground), pair(shown), robot


def test_front_view_is_told_from_the_maps(lap_and_a_half):
    first, last, robot = lap_and_a_half
    idx = path_index(first.grid, first.poses, robot, 1.6)
    view, info = front_view(first, idx)
    assert view == "first_view" and abs(info["ratio"]) < 0.15 and info["cells"] > 200
    view, info = front_view(last, idx)
    assert view == "last_visit" and 0.4 < info["ratio"] < 0.8          # 15 mm of 25 mm shown


def test_a_single_pass_has_nothing_to_tell(pair):
    view, info = front_view(pair, path_index(pair.grid, pair.poses, pair.robot, 1.6))
    assert view == "last_visit" and info["cells"] == 0


def test_a_first_view_window_drives_the_earlier_visit_first(lap_and_a_half):
    first, _, robot = lap_and_a_half
    idx = path_index(first.grid, first.poses, robot, 1.6)
    arc_end = float(idx.arc[-1])
    again = [w for w in plan_windows(arc_end, 0.8, 0.4) if w.s0 > arc_end - 1.5][0]   # back over the start
    once = plan_windows(arc_end, 0.8, 0.4)[12]                                      # the far straight
    for spec, n_earlier in ((again, 1), (once, 0)):
        wd = prepare_window(first, idx, spec, EstimatorConfig(), SimConfig(), view="first_view")
        assert len(wd.earlier) == n_earlier
        t_own = wd.geom.poses[:, 0]
        for g in wd.earlier:                                  # the first lap, long before
            assert float(g.poses[:, 0].max()) < float(t_own.min()) - 5.0
        assert prepare_window(first, idx, spec, EstimatorConfig(), SimConfig()).earlier == ()


def test_a_window_simulates_every_wheel_pass_over_its_ground(lap_and_a_half):
    """Every wheel pass over a window's dug ground is simulated by it: ground driven again
    belongs to its last wheel pass, a rear wheel's, whose front wheel went over it a
    wheelbase of travel earlier (1 m on the paper's platform, more than the window's reach
    ahead of its start): those poses must be among the window's own, or among its earlier
    visits' (a first view). Checked against every wheel centre of the drive within half a
    wheel width of a dug cell of each window."""
    first, _, robot = lap_and_a_half
    idx = path_index(first.grid, first.poses, robot, 1.6)
    dense = first.poses
    t = dense[:, 0]
    wheels = wheel_positions(dense[:, [0, 1, 2, 6]], robot.wheels[:, :2])      # (K, N, 2)
    tree = cKDTree(wheels.reshape(-1, 2))
    xs, ys = first.grid.centers()
    checked = 0
    for spec in plan_windows(float(idx.arc[-1]), 0.8, 0.4):
        wd = prepare_window(first, idx, spec, EstimatorConfig(), SimConfig(), view="first_view")
        if wd is None:
            continue
        i0, _, j0, _ = wd.crop
        ii, jj = np.nonzero(wd.weight.numpy() > 0)
        xy = np.stack([xs[ii + i0], ys[jj + j0]], 1)
        spans = [(float(g.poses[0, 0]), float(g.poses[-1, 0])) for g in (*wd.earlier, wd.geom)]
        for hits in tree.query_ball_point(xy, robot.wheel_width / 2 - first.dx):
            for h in hits:
                when = t[h % len(t)]
                assert any(a <= when <= b for a, b in spans), (spec, when, spans)
                checked += 1
    assert checked > 1000


def test_a_full_window_store_prepares_anew_instead_of_growing():
    """A store of 2 kB that does not spill to disk keeps the first two 1 kB windows (64 float64
    and, nested, 128 int32 each) and no more."""
    store, made = WindowStore(max_bytes=2048, spill=False), []

    def window(key):
        made.append(key)
        return torch.zeros(64, dtype=torch.float64), (torch.zeros(128, dtype=torch.int32),)

    for key in (1, 2, 3, 3, 1):
        store.get(key, lambda k=key: window(k))
    assert made == [1, 2, 3, 3] and len(store) == 2 and store.nbytes == 2048


def test_smoothing_along_a_rut_keeps_its_section_and_averages_the_noise():
    """A rut 7 cells wide and 30 mm deep (a cosine section) runs at 30 deg across the grid,
    with 3 mm of Gaussian noise. Smoothed along its own direction over sigma = 3.5 cells, the
    noise-free rut moves by less than 1 mm anywhere (bilinear samples between cells; not at
    all along a grid axis), its noisy cross-section stays within 1.5 mm of the noise-free
    one, and the noise falls to about a third (1 / sqrt(2 sqrt(pi) 3.5) = 0.32). The same
    smoothing across the rut fills it."""
    from scipy import ndimage

    from torchsoil.estimate.windows import smooth_along

    ii, jj = np.indices((120, 120), dtype=float)
    inner = (slice(20, 100), slice(20, 100))
    for deg in (0.0, 30.0):
        yaw = np.radians(deg)
        off = -(ii - 60) * np.sin(yaw) + (jj - 60) * np.cos(yaw)          # cells across the rut
        rut = np.where(np.abs(off) < 3.5, -0.015 * (1 + np.cos(np.pi * off / 3.5)), 0.0)
        moved = np.abs(smooth_along(rut, np.full(rut.shape, yaw), 3.5) - rut)[inner]
        assert moved.max() < (1e-12 if deg == 0 else 0.001)
    noisy = rut + np.random.default_rng(0).normal(0, 0.003, rut.shape)
    err = (smooth_along(noisy, np.full(rut.shape, yaw), 3.5) - rut)[inner]
    bins = np.round(off[inner]).astype(int) + 10
    section = ndimage.mean(err, labels=bins, index=np.arange(6, 15))        # offsets -4..4 cells
    assert np.abs(section).max() < 0.0015
    assert 0.25 < np.std(err) / 0.003 < 0.4
    across = smooth_along(noisy, np.full(rut.shape, yaw + np.pi / 2), 3.5) - rut
    assert across[inner][np.abs(off[inner]) < 0.5].mean() > 0.008
    assert np.array_equal(smooth_along(noisy, np.full(rut.shape, np.nan), 3.5), noisy)


def test_points_near_ground_as_by_brute_force():
    """windows._within searches only the ground's edge cells: the same answer as every cell."""
    from torchsoil.estimate.windows import _within

    rng = np.random.default_rng(3)
    grid = Grid(0.02, (-1.0, -0.5), (100, 60))
    xs, ys = grid.centers()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    blob = (np.hypot(X - 0.1, Y) < 0.3) & ~(np.hypot(X - 0.15, Y + 0.05) < 0.08)   # a disc with a hole
    blob |= rng.random(blob.shape) < 0.01                                          # and specks
    cells = np.argwhere(blob)
    ground = np.stack([xs[cells[:, 0]], ys[cells[:, 1]]], 1)
    pts = rng.uniform((-1.3, -0.8), (1.3, 0.8), (3000, 2))
    for reach in (0.02, 0.05, 0.35):
        brute = (np.hypot(*(pts[:, None] - ground[None]).transpose(2, 0, 1)) <= reach).any(1)
        got = _within(pts, ground, grid, reach)
        assert np.array_equal(got, brute), reach
        assert 0 < got.sum() < len(pts)

"""Ground driven more than once (FORMATS.md visits v1.1): wheel passes counted by hand, the
poses of a visit, the multi-pass table, and the estimator fitting each visit of a window on
its own maps, checked on an out-and-back made by the independent reference model
(tests/reference_model.py) with a different sinkage on each visit."""

import csv
import math

import numpy as np
import pytest
from scipy import ndimage

from tests.reference_model import simulate as reference_simulate
from torchsoil.estimate.estimator import Estimator
from torchsoil.estimate.visits import (
    multipass_table,
    passes_before,
    rut_depth,
    visit_poses,
    visit_stretches,
    wheel_passes,
)
from torchsoil.grid import Grid
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.jobs.estimate import estimate
from torchsoil.settings import load_settings

# --------------------------------------------------------------------------- hand-counted passes
WHEELS = np.array([[0.3, 0.0, 0], [-0.3, 0.0, 0]])      # one track, a front and a rear wheel 0.6 m apart
WIDTH = 0.1


def line_grid():
    return Grid(0.02, (-1.0, -0.2), (201, 21))           # x from -1 to 3 m, y from -0.2 to 0.2 m


def out_and_back(length=2.0, dt=0.01):
    """Out along +x from x = 0 to `length` at 1 m/s, then back in reverse: (N, 7) poses."""
    t = np.arange(0.0, 2 * length + 1e-9, dt)
    x = np.where(t <= length, t, 2 * length - t)
    poses = np.zeros((len(t), 7))
    poses[:, 0], poses[:, 1] = t, x
    return poses


def cell(grid, x, y=0.0):
    return int(round((x - grid.origin[0]) / grid.dx)), int(round((y - grid.origin[1]) / grid.dx))


def test_each_wheel_passes_a_cell_once_per_visit():
    grid = line_grid()
    xs, _ = grid.centers()
    poses = out_and_back(length=2.0)[:201]                              # out only: t = x
    vt = np.broadcast_to(np.clip(xs, 0, 2)[:, None], grid.shape)[None].astype(np.float32)
    p = wheel_passes(poses, WHEELS, WIDTH, grid, vt)[0]
    assert p[cell(grid, 1.0)] == 2                         # under both wheels
    assert p[cell(grid, -0.2)] == 1                        # behind the start: the rear wheel only
    assert p[cell(grid, 2.2)] == 1                         # beyond the end: the front wheel only
    assert p[cell(grid, 1.0, 0.1)] == 0                    # beside the track (> half a wheel width)
    assert p[cell(grid, 2.6)] == 0                         # beyond every wheel


def test_passes_go_to_the_visit_nearest_in_time():
    grid = line_grid()
    xs, _ = grid.centers()
    poses = out_and_back(length=2.0)
    x = np.broadcast_to(xs[:, None], grid.shape)
    vt = np.stack([x, 4.0 - x]).astype(np.float32)         # base_link over x at t = x, and again at 4 - x
    vt[1][x > 1.0] = np.nan                                # beyond 1 m: one visit (out and back merge)
    p = wheel_passes(poses, WHEELS, WIDTH, grid, vt)
    assert p[:, cell(grid, 0.5)[0], cell(grid, 0.5)[1]].tolist() == [2, 2]
    assert p[:, cell(grid, 1.5)[0], cell(grid, 1.5)[1]].tolist() == [4, 0]
    np.testing.assert_array_equal(passes_before(p)[:, cell(grid, 0.5)[0], cell(grid, 0.5)[1]], [0, 2])
    np.testing.assert_array_equal(passes_before(np.array([1, 2, 3]).reshape(3, 1, 1)).ravel(), [0, 1, 3])


def test_visit_poses_span_the_visit_and_its_reach():
    poses = out_and_back(length=2.0, dt=0.1)
    arc = np.arange(len(poses)) * 0.1                      # 1 m/s, never standing still
    got = visit_poses(poses, arc, np.array([2.6, 3.0, 2.8]), reach=0.5)
    assert got[0, 0] == pytest.approx(2.0) and got[-1, 0] == pytest.approx(3.6)   # [2.1, 3.5] and one more each side


def test_a_visit_is_the_stretch_of_the_drive_that_passed_most_of_its_ground():
    nan = np.nan
    arc = np.array([[1.0, 1.3, 1.1, 12.0, 12.2, nan],      # three cells on one pass, two a turn later
                    [20.0, 20.5, 21.0, 21.4, 29.0, 30.0]])  # a run of four, then two single cells
    np.testing.assert_allclose(visit_stretches(arc, gap=0.9), [[1.0, 1.3], [20.0, 21.4]])
    np.testing.assert_allclose(visit_stretches(np.array([[5.0, 1.0]]), gap=0.9), [[1.0, 1.0]])   # a tie: the earliest
    assert visit_stretches(np.full((1, 3), nan), gap=0.9).tolist() == [[math.inf, -math.inf]]


def test_rut_depth_is_the_mean_drop_on_measured_rut_cells():
    before = np.zeros((2, 3))
    after = np.array([[-0.01, -0.03, np.nan], [0.02, 0.0, -0.05]])
    ruts = np.array([[True, True, True], [False, False, False]])
    assert rut_depth(before, after, ruts) == pytest.approx(0.02)
    assert math.isnan(rut_depth(before, after, np.zeros((2, 3), bool)))


def test_multipass_table_groups_windows_driven_again_by_pass_count():
    def row(s, visit, pb, d1, d2, rut, residual=0.003):
        return {"s": s, "visit": visit, "passes_before": pb, "d1": d1, "d2": d2, "rut_depth": rut,
                "residual": residual}

    rows = [row(1.0, 0, 0, 0.030, 0.034, 0.028), row(1.0, 1, 2, 0.010, 0.012, 0.008),
            row(1.4, 0, 0, 0.026, 0.030, 0.024), row(1.4, 1, 2, 0.014, 0.016, 0.012),
            row(1.8, 1, 2, 0.5, 0.5, 0.5, residual=math.nan),                    # not fitted: left out
            row(3.0, 0, 0, 0.9, 0.9, 0.9)]                                      # driven once: left out
    for r, pred in zip(rows, (3.0, 2.0, 5.0, 4.0, 1.0, 1.0), strict=True):
        r["prediction"] = pred
    reference = [{"floor": f} for f in (2.0, 4.0, 2.0, 4.0, 1.0, 1.0)]
    table = multipass_table(rows, ["d1", "d2", "chi", "beta"], reference)
    assert [(e["visit"], e["passes_before"], e["windows"]) for e in table] == [(0, 0, 2), (1, 2, 2)]
    assert table[0]["prediction_floor"] == pytest.approx(2.0) and table[1]["prediction_floor"] == pytest.approx(0.75)
    assert table[0]["d"] == pytest.approx(0.030) and table[0]["d_sd"] == pytest.approx(0.002)
    assert table[1]["d"] == pytest.approx(0.013) and table[1]["d_sd"] == pytest.approx(0.002)
    assert table[0]["rut"] == pytest.approx(0.026) and table[1]["rut_sd"] == pytest.approx(0.002)


# ----------------------------------------------------------------- an out-and-back by hand
PLATFORM = np.array([[0.69, 0.5, 0], [0.69, -0.5, 1], [-0.69, 0.5, 0], [-0.69, -0.5, 1]])
D0, D1 = 0.03, 0.015          # sinkage of the first visit, and of the second in the first's ruts
LENGTH, ONCE = 4.0, 2.5       # the drive goes out 4 m and back; beyond x = 2.5 m one visit per cell


def two_visit_pair(seed=0, noise=0.0015, dx=0.02, d1=D1, length=LENGTH, once=ONCE, per_pass_g=None):
    """Out along +x for `length` m at 1 m/s and back in reverse on the same ruts, made by the
    reference model visit by visit: the first with d = D0 from the untouched ground, the
    second with d = d1 from the ground the first left, its reference over the whole footprint
    on the first's ruts (a wheel spans a rut of its own width). With per_pass_g the axles dig in
    turn instead, each from the rut the ones before it left (resting on it as on the first
    visit's ruts), the n-th wheel pass over a cell
    sinking D0 per_pass_g^n (d1 unused). Visit layers as FORMATS.md v1.1: cells
    with x < `once` have two visits (out at t = x, back at t = 2 length - x); the others one
    (from the untouched ground to the end). Returns (pair dict, truth dict)."""
    rng = np.random.default_rng(seed)
    origin = np.array([-1.2, -1.6])
    X, Y = int(round((length + 2.4) / dx)) + 1, int(round(3.2 / dx)) + 1
    smooth = ndimage.gaussian_filter(rng.normal(size=(X, Y)), 3.0)
    h0 = 0.004 * smooth / smooth.std() + 0.001 * rng.normal(size=(X, Y))
    poses = out_and_back(length, dt=0.05)
    out, back = poses[poses[:, 0] <= length], poses[poses[:, 0] >= length]
    beta = math.radians(30.0)
    ys = origin[1] + dx * np.arange(Y)
    xx = origin[0] + dx * np.arange(X)
    ruts = (np.abs(np.abs(ys) - 0.5) <= 0.07)[None] & ((xx >= -0.76) & (xx <= length + 0.76))[:, None]
    if per_pass_g is not None:
        g = per_pass_g
        h1, _ = reference_simulate(h0, dx, origin, out, PLATFORM, 0.14, (D0, D0), 0.5, beta, dig="wheel",
                                   axle_scale=(1.0, g))
        h2, _ = reference_simulate(h1, dx, origin, back, PLATFORM, 0.14, (D0, D0), 0.5, beta, dig="wheel",
                                   axle_scale=(g**2, g**3), dug=ruts)
    else:
        h1, _ = reference_simulate(h0, dx, origin, out, PLATFORM, 0.14, (D0, D0), 0.5, beta)
        h2, _ = reference_simulate(h1, dx, origin, back, PLATFORM, 0.14, (d1, d1), 0.5, beta, dug=ruts)

    def measured(h):
        return (h + rng.normal(0, noise, h.shape)).astype(np.float32)

    x = np.broadcast_to((origin[0] + dx * np.arange(X))[:, None], (X, Y))
    twice = x < once
    nan = np.full((X, Y), np.nan, np.float32)
    f0, b0, f1, b1, once_back = measured(h0), measured(h1), measured(h1), measured(h2), measured(h2)
    visit_front = np.stack([f0, np.where(twice, f1, nan)])
    visit_back = np.stack([np.where(twice, b0, once_back), np.where(twice, b1, nan)])
    visit_time = np.stack([np.clip(x, 0, length), np.where(twice, 2 * length - np.clip(x, 0, length), np.nan)])
    pair = {"dx": np.float64(dx), "origin": origin, "h_front": f0, "h_back": np.where(twice, b1, once_back),
            "poses": poses, "wheels": PLATFORM.astype(np.float64), "wheel_width": np.float64(0.14),
            "visit_front": visit_front, "visit_back": visit_back, "visit_time": visit_time.astype(np.float32)}
    return pair, {"h0": h0, "h1": h1, "h2": h2}


@pytest.fixture(scope="module")
def visits_pair():
    return TerrainPair.from_mapping(two_visit_pair()[0])


def settings():
    return load_settings(overrides=["estimator.init.d=0.02"])


def return_windows(est, x0=0.75, x1=2.45):
    """Indices of the windows on the way back whose ground lies at x0 < x < x1 (two visits)."""
    return [k for k, w in enumerate(est.windows) if 2 * LENGTH - x1 < w.s0 and w.s1 < 2 * LENGTH - x0]


def test_each_visit_is_fitted_on_its_own_maps(visits_pair):
    s = settings()
    est = Estimator(visits_pair, s.estimator, s.sim, per_visit=True)
    ks = return_windows(est)
    assert len(ks) >= 2
    rows = [o.row for o in est.run(start=ks[0], stop=ks[-1] + 1)]
    assert [r["visit"] for r in rows] == [0, 1] * len(ks)
    for v, d, pb in ((0, D0, 0), (1, D1, 2)):           # a rut had two wheel passes (front, rear) before the way back
        mine = [r for r in rows if r["visit"] == v]
        assert all(r["passes_before"] == pb and not r["flags"] for r in mine)
        for r in mine:
            assert r["d1"] == pytest.approx(d, abs=0.003) and r["d2"] == pytest.approx(d, abs=0.003), (v, r)
    first, second = ([r["t"] for r in rows if r["visit"] == v] for v in (0, 1))
    assert max(first) < LENGTH < min(second)              # each visit at its own time


def test_one_fit_over_both_visits_takes_them_for_one_soil(visits_pair):
    """Without per-visit fitting the same windows mix the visits: d lies between D1 and D0 or
    beyond, not at either (what the per-visit fit is for)."""
    s = settings()
    est = Estimator(visits_pair, s.estimator, s.sim)
    ks = return_windows(est)
    rows = [o.row for o in est.run(start=ks[0], stop=ks[-1] + 1)]
    assert len(rows) == len(ks) and {r["visit"] for r in rows} == {0}
    assert all(abs(r["d1"] - D1) > 0.004 for r in rows)


def test_windows_whose_ground_a_later_stretch_drove_again_say_so(visits_pair):
    """On the way out the ground belongs to the way back (its windows fit both visits): those
    windows are flagged driven_again, not empty; a drive that never comes back has none."""
    s = settings()
    est = Estimator(visits_pair, s.estimator, s.sim, per_visit=True)
    out = [k for k, w in enumerate(est.windows) if w.s1 < LENGTH - 1.0]      # clear of the turn
    rows = [o.row for o in est.run(start=out[0], stop=out[-1] + 1)]
    other = [(r["s"], r["flags"]) for r in rows if r["flags"] != "driven_again"]
    assert rows and not other, other
    data, _ = two_visit_pair(seed=2)
    keep = data["poses"][:, 0] <= LENGTH                     # the way out alone, no visit layers
    once = {k: v for k, v in data.items() if not k.startswith("visit_")} | {"poses": data["poses"][keep]}
    est = Estimator(TerrainPair.from_mapping(once), s.estimator, s.sim)
    assert all("driven_again" not in est._no_ground(w) for w in est.windows)


def test_a_single_visit_layer_gives_the_rows_of_a_pair_without_layers():
    data, _ = two_visit_pair(seed=1)
    plain = {k: v for k, v in data.items() if not k.startswith("visit_")}
    one = {**plain, "visit_front": plain["h_front"][None], "visit_back": plain["h_back"][None],
           "visit_time": np.zeros((1, *plain["h_front"].shape), np.float32)}
    s = settings()
    rows = []
    for pair, per_visit in ((plain, False), (plain, True), (one, True)):
        est = Estimator(TerrainPair.from_mapping(pair), s.estimator, s.sim, per_visit=per_visit)
        rows.append([o.row for o in est.run(stop=6)])
    for other in rows[1:]:
        assert len(other) == len(rows[0]) == 6
        for a, b in zip(rows[0], other, strict=True):
            assert a.keys() == b.keys()
            for k in a.keys() - {"seconds"}:
                same = a[k] == b[k] or (isinstance(a[k], float) and math.isnan(a[k]) and math.isnan(b[k]))
                assert same, (k, a[k], b[k])


def test_estimate_writes_the_multipass_outputs_and_resumes_by_visit(tmp_path):
    data, _ = two_visit_pair(seed=2)
    src = tmp_path / "pair.npz"
    np.savez(src, **data)
    s = load_settings(overrides=["estimator.init.d=0.02", "estimator.max_iter=30"])
    out = estimate(src, tmp_path / "run", s, tensorboard=False, progress=False)
    with (out / "params.csv").open() as f:
        full = list(csv.DictReader(f))
    again = [r for r in full if r["visit"] == "1"]
    assert again and all(r["s"] in {q["s"] for q in full if q["visit"] == "0"} for r in again)
    with np.load(out / "passes.npz") as f:
        i, j = cell(TerrainPair.from_mapping(data).grid, 1.0, 0.5)
        assert f["visits"][i, j] == 2 and f["passes"][i, j] == 4 and f["passes_visit"][:, i, j].tolist() == [2, 2]
        assert f["rut_depth"][i, j] == pytest.approx(np.nansum(f["rut_depth_visit"][:, i, j]))
    for name in ("multipass.png", "passes.png"):
        assert (out / name).stat().st_size > 0
    summary = (out / "summary.md").read_text()
    assert "| 1 | 2 |" in summary and "Ground driven more than once" in summary and "noise floor |" in summary
    # interrupted between the two visits of a window: resumed, no row is lost or written twice
    cut = next(n for n, r in enumerate(full) if r["visit"] == "1")
    lines = (out / "params.csv").read_text().splitlines()
    (out / "params.csv").write_text("\n".join(lines[:cut + 1]) + "\n")
    ref = (out / "reference.csv").read_text().splitlines()
    (out / "reference.csv").write_text("\n".join(ref[:cut + 1]) + "\n")
    estimate(src, out, s, resume=True, tensorboard=False, progress=False)
    with (out / "params.csv").open() as f:
        resumed = list(csv.DictReader(f))
    assert [(r["s"], r["visit"]) for r in resumed] == [(r["s"], r["visit"]) for r in full]
    for a, b in zip(full, resumed, strict=True):
        assert float(a["d1"]) == pytest.approx(float(b["d1"]), abs=1e-3, nan_ok=True)


def test_cells_with_another_visit_count_stay_out_of_a_windows_costs(visits_pair):
    s = settings()
    est = Estimator(visits_pair, s.estimator, s.sim, per_visit=True)
    # the window on the way back (s = 2 LENGTH - x) that straddles x = ONCE, where the visit count changes
    k = min(range(len(est.windows)), key=lambda k: abs(2 * LENGTH - est.windows[k].centre - ONCE))
    visits = est.visit_data(k)
    counts = {}
    for v, wd in visits.items():
        i0, i1, j0, j1 = wd.crop
        n = est.visits_per_cell[i0:i1, j0:j1]
        counted = wd.weight.cpu().numpy() > 0
        counts[v] = np.unique(n[counted]).tolist()
    assert len(visits) in (1, 2) and all(len(c) == 1 for c in counts.values())          # one history per window
    assert all(c == [len(visits)] for c in counts.values())


def test_ground_whose_visits_were_other_stretches_of_the_drive_stays_out_of_a_windows_fit():
    """Beside the ruts, a band of the twice-driven ground is labelled as a neighbouring row's
    reach leaves it in a field: its first visit the way back, its second a later pass (past the
    end of the drive). It has two visits as the rest, but its first is another stretch of the
    drive: counted with the rest, the first visit's poses would run from the way out to the way
    back and dig both passes into the first visit's maps."""
    raw, _ = two_visit_pair()
    ys = raw["origin"][1] + raw["dx"] * np.arange(raw["h_front"].shape[1])
    band = np.broadcast_to((np.abs(ys) > 0.72) & (np.abs(ys) < 0.84), raw["h_front"].shape) & np.isfinite(
        raw["visit_time"][1])
    vt = raw["visit_time"].copy()
    vt[0][band], vt[1][band] = vt[1][band], 2 * LENGTH + 5.0
    vf, vb = raw["visit_front"].copy(), raw["visit_back"].copy()
    vf[0][band], vb[0][band], vf[1][band] = vf[1][band], vb[1][band], vb[1][band]
    pair = TerrainPair.from_mapping({**raw, "visit_time": vt, "visit_front": vf, "visit_back": vb})
    s = settings()
    est = Estimator(pair, s.estimator, s.sim, per_visit=True)
    ks = return_windows(est)
    for k in ks:
        for v, wd in est.visit_data(k).items():
            i0, i1, j0, j1 = wd.crop
            assert not (wd.weight.cpu().numpy() > 0)[band[i0:i1, j0:j1]].any(), (k, v)
            if v == 0:                                     # the way out alone, not on to the way back
                assert float(wd.geom.poses[:, 0].max()) < LENGTH, k
    rows = [o.row for o in est.run(start=ks[0], stop=ks[-1] + 1)]
    assert [r["visit"] for r in rows] == [0, 1] * len(ks)
    for v, d in ((0, D0), (1, D1)):
        for r in (r for r in rows if r["visit"] == v):
            assert r["d1"] == pytest.approx(d, abs=0.003) and r["d2"] == pytest.approx(d, abs=0.003), (v, r)
    assert max(r["t"] for r in rows if r["visit"] == 0) < LENGTH


def test_ground_offset_finds_ruts_moved_sideways():
    """Two views of the same ruts, the second moved 3 cells (6 cm) along y, with independent
    noise and a 5 mm vertical offset: the shift comes out at 6 cm, the RMS at the noise level
    (sqrt(2) x 3 mm); unmoved, zero."""
    from torchsoil.pipeline.checks import ground_offset

    rng = np.random.default_rng(0)
    x, y = np.arange(200)[:, None] * 0.02, np.arange(150)[None, :] * 0.02
    h = 0.01 * np.sin(3 * x) - 0.03 * (np.exp(-((y - 1.0) / 0.05) ** 2) + np.exp(-((y - 2.0) / 0.05) ** 2))
    before = h + rng.normal(0, 0.003, h.shape)
    moved = np.full_like(h, np.nan)
    moved[:, 3:] = h[:, :-3]
    shift, rms, n = ground_offset(before, moved + rng.normal(0, 0.003, h.shape) + 0.005, 0.02)
    assert shift == pytest.approx([0.0, 0.06]) and rms == pytest.approx(0.003 * np.sqrt(2), rel=0.1) and n > 20000
    shift, _, _ = ground_offset(before, h + rng.normal(0, 0.003, h.shape), 0.02)
    assert shift == pytest.approx([0.0, 0.0])


def test_visit_offsets_on_a_pair_made_elsewhere():
    """The foreign out-and-back pair (another simulator, its own visit layers): the ground
    between the visits lies on the same cells as seen on the way out and on the way back
    (shift 0). Moving the way back's view by 4 cells across the drive, as a map broken in the
    turn would, is found as an 8 cm shift, at the residual of the unmoved pair."""
    from pathlib import Path

    from torchsoil.pipeline.checks import visit_offsets

    pair = TerrainPair.load(Path(__file__).resolve().parents[3] / "shared/foreign/multi_pass_hardening.npz")
    (off,) = visit_offsets(pair)
    assert off["visit"] == 1 and off["distance_m"] == 0.0 and off["cells"] > 10000
    along_y = abs(np.cos(np.median(pair.poses[:, 6]))) < 0.3     # this drive runs along the grid's y axis
    moved = np.full_like(pair.visit_front, np.nan)
    moved[0] = pair.visit_front[0]
    if along_y:
        moved[1][4:] = pair.visit_front[1][:-4]
    else:
        moved[1][:, 4:] = pair.visit_front[1][:, :-4]
    pair.visit_front = moved
    (bad,) = visit_offsets(pair)
    assert bad["shift_m"] == pytest.approx([0.08, 0.0] if along_y else [0.0, 0.08])
    assert bad["rms_m"] < 1.2 * off["rms_m"]


def test_a_rut_driven_again_by_a_soil_that_does_not_harden_fits_the_same_d():
    """The second visit of a soil that does not harden (the same d, each visit digging from
    the surface it finds, its reference over the whole footprint on the first's ruts) fits
    the first visit's d; with the paper's small reference disc on the ruts (the reference on
    the rut floor) the wheel would dig d below the floor, and the fit reads the same soil as
    one that hardened. The first visit's rows do not depend on it."""
    pair = TerrainPair.from_mapping(two_visit_pair(seed=3, d1=D0)[0])
    fits = {}
    for how in ("footprint", "disc"):
        s = load_settings(overrides=["estimator.init.d=0.02", f"sim.revisit_ref={how}"])
        est = Estimator(pair, s.estimator, s.sim, per_visit=True)
        ks = return_windows(est)
        fits[how] = [o.row for o in est.run(start=ks[0], stop=ks[-1] + 1)]
    ratio = {}
    for how, rows in fits.items():
        d = {v: np.mean([(r["d1"] + r["d2"]) / 2 for r in rows if r["visit"] == v]) for v in (0, 1)}
        assert d[0] == pytest.approx(D0, abs=0.003)
        ratio[how] = d[1] / d[0]
    print(ratio)
    assert ratio["footprint"] == pytest.approx(1.0, abs=0.05)
    assert ratio["disc"] < ratio["footprint"] - 0.05
    first = [[r[k] for k in ("d1", "d2", "chi", "beta", "residual")] for r in fits["footprint"] if r["visit"] == 0]
    assert first == [[r[k] for k in ("d1", "d2", "chi", "beta", "residual")] for r in fits["disc"] if r["visit"] == 0]


def test_track_heading_is_that_of_the_last_pass_over_the_cell():
    """Out along +x (yaw 0) until t = 10 s, back along -x (yaw pi) from t = 20 s: a cell the
    way back passed takes pi, one only the way out passed takes 0, one neither passed the
    heading of the nearest cell that was passed."""
    from torchsoil.estimate.visits import track_heading

    t = np.array([0.0, 10.0, 20.0, 30.0])
    yaw = np.array([0.0, 0.0, np.pi, np.pi])
    times = np.full((2, 3, 4), np.nan)
    times[0, :, :2] = 5.0               # the way out, columns 0-1
    times[1, :, 0] = 25.0               # the way back, column 0
    got = track_heading(times, t, yaw)
    assert got[:, 0] == pytest.approx(np.pi)
    assert got[:, 1] == pytest.approx(0.0)
    assert got[:, 2] == pytest.approx(0.0) and got[:, 3] == pytest.approx(0.0)
    assert np.isnan(track_heading(times[:0], t, yaw)).all()

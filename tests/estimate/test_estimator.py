import csv
import math

import numpy as np
import pytest

from tests.synthetic_pair import sim_pair
from torchsoil.estimate.estimator import Estimator
from torchsoil.estimate.outputs import simulated_error
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.jobs.estimate import estimate
from torchsoil.settings import EstimatorConfig, load_settings

TRUE = dict(d1=0.03, d2=0.025, chi=0.8, beta_deg=35.0)


@pytest.fixture(scope="module")
def pair_truth():
    return sim_pair(length=3.2, **TRUE)


def make(pair, *overrides):
    settings = load_settings(overrides=overrides)
    return Estimator(pair, settings.estimator, settings.sim)


def _rows(est, limit=None):
    rows = []
    for k, out in enumerate(est.run()):
        rows.append(out.row)
        if limit and k + 1 >= limit:
            break
    return rows


@pytest.mark.parametrize("grad", ["autograd", "fd"])
def test_recovers_known_parameters(pair_truth, grad):
    pair, _ = pair_truth
    rows = _rows(make(pair, f"estimator.grad={grad}"), limit=None if grad == "autograd" else 3)
    assert rows
    for r in rows:
        assert r["d1"] == pytest.approx(TRUE["d1"], abs=0.002)
        assert r["d2"] == pytest.approx(TRUE["d2"], abs=0.002)
        assert r["chi"] == pytest.approx(TRUE["chi"], abs=0.15)
        assert r["beta"] == pytest.approx(TRUE["beta_deg"], abs=5.0)
        assert r["flags"] == ""
    # the model explains the measurement down to the noise: residual below the noise floor
    assert np.mean([r["residual"] for r in rows]) < 3.5e-3


def test_prediction_uses_ground_ahead(pair_truth):
    pair, _ = pair_truth
    est = make(pair)
    outs = list(est.run())
    assert all(math.isnan(o.row["prediction"]) for o in outs[-est.ahead:])
    assert all(not math.isnan(o.row["prediction"]) for o in outs[:-est.ahead])
    floor = np.mean([o.reference["floor"] for o in outs])
    pred = np.nanmean([o.row["prediction"] for o in outs])
    signal = np.mean([o.reference["signal"] for o in outs])
    assert pred < floor < signal


def test_merged_sinkage_ties_tracks(pair_truth):
    pair, _ = pair_truth
    rows = _rows(make(pair, "estimator.merged_sinkage=true"), limit=2)
    assert all(r["d1"] == r["d2"] for r in rows)
    assert TRUE["d2"] - 0.003 < rows[0]["d1"] < TRUE["d1"] + 0.003


def test_stopped_robot_flagged():
    pair, _ = sim_pair(length=3.2, stop=(1.5, 3.5), **TRUE)
    rows = _rows(make(pair))
    flagged = [r for r in rows if "stopped" in r["flags"]]
    assert flagged and all(0.7 < r["s"] < 2.3 for r in flagged)


def test_run_writes_outputs_and_resumes(tmp_path, pair_truth):
    pair, truth_hb = pair_truth
    src = tmp_path / "pair.npz"
    pair.save(src)
    cfg = load_settings()
    out = estimate(src, tmp_path / "run", cfg, tensorboard=True, progress=False)
    names = ["s", "visit", "passes_before", "t", "x", "y", "d1", "d2", "chi", "beta", "map_offset", "rut_depth",
             "residual", "prediction", "iterations", "seconds", "latency", "flags"]
    with (out / "params.csv").open() as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == names
        full = list(reader)
    assert {(r["visit"], r["passes_before"]) for r in full} == {("0", "0")}     # a pair without visit layers
    for name in ("summary.md", "fig4_parameters.png", "fig6_difference_maps.png", "simulated.npz"):
        assert (out / name).stat().st_size > 0
    assert any((out / "tensorboard").iterdir())
    assert "noise floor" in (out / "summary.md").read_text()
    assert "Removed from H_b before estimation: offset" in (out / "summary.md").read_text()
    # the stitched simulation is close to the noise-free truth near the wheel paths
    assert simulated_error(out, truth_hb, pair) < 1.5e-3
    # interrupt after 3 windows, killed between the third's two rows (its reference row never
    # written), then resume: the same windows once each, the same parameters
    lines = (out / "params.csv").read_text().splitlines()
    (out / "params.csv").write_text("\n".join(lines[:4]) + "\n")
    ref = (out / "reference.csv").read_text().splitlines()
    (out / "reference.csv").write_text("\n".join(ref[:3]) + "\n")
    estimate(src, out, cfg, resume=True, tensorboard=False, progress=False)
    with (out / "params.csv").open() as f:
        resumed = list(csv.DictReader(f))
    assert [r["s"] for r in resumed] == [r["s"] for r in full]
    with (out / "reference.csv").open() as f:
        assert [r["s"] for r in csv.DictReader(f)] == [r["s"] for r in full]
    for a, b in zip(full, resumed, strict=True):
        assert float(a["d1"]) == pytest.approx(float(b["d1"]), abs=3e-4)
    with pytest.raises(ValueError, match=r"settings differ \(estimator.window\)"):
        estimate(src, out, load_settings(overrides=["estimator.window=1.0"]), resume=True, progress=False)


def test_a_first_view_of_revisited_ground_drives_every_visit():
    """Out and back on the same ruts (a light-bulb turn), recorded by the synth world with H_f
    the first view of every cell (a pipeline keeping the oldest height): the return leg's
    ground shows two visits. Told from the maps, both are simulated and the return leg's d is
    the soil's; simulating the last visit alone takes both ruts for one (about twice as deep)."""
    from torchsoil.synth.scenario import make_terrain_pair

    def seg(**k):
        return {**k, "speed": 1.0}

    sc = {"name": "out_and_back", "world": {"chunk": 0.1}, "measurement": {"first_view": 1.0},
          "soil": {"base": {"d": 0.025, "chi": 0.2, "beta_deg": 30.0}},
          "trajectory": {"accel_limit": 0.5, "segments": [
              seg(straight=5.0), seg(arc=1.6, angle_deg=-60), seg(arc=1.6, angle_deg=300),
              seg(arc=1.6, angle_deg=-60), seg(straight=5.0)]}}
    pair = TerrainPair.from_mapping(make_terrain_pair(sc, seed=0))
    returned = {}
    for view in ("auto", "last_visit"):
        e = Estimator(pair, EstimatorConfig(front_view=view))
        rows = [o.row for o in e.run()]
        s = np.array([r["s"] for r in rows])
        d = np.array([(r["d1"] + r["d2"]) / 2 for r in rows])
        returned[e.view] = float(np.nanmedian(d[s > e.index.arc[-1] - 4.0]))
        assert abs(np.nanmedian(d[(s > 6.5) & (s < e.index.arc[-1] - 6.5)]) - 0.025) < 0.003   # the loop: once
    assert set(returned) == {"first_view", "last_visit"}
    assert abs(returned["first_view"] - 0.025) < 0.3 * 0.025
    assert returned["last_visit"] > 1.6 * 0.025


def test_ground_seen_anew_beside_a_later_pass_is_left_to_that_pass():
    """A racetrack whose last leg runs back over the first 0.2 m to the left of it: its wheels
    pass 0.2 m beside the first leg's ruts, beyond a wheel width (0.14 m) but within the
    simulator's reach (half a wheel width plus the relaxation margin), so a front lidar that
    keeps its newest view shows those ruts in H_f already dug (Gaussian troughs drawn by
    hand). The last pass, not the first, must own them: the first leg's windows fitted 6 mm
    (the reference 24 mm) to ruts H_f already holds. Left with no rut of their own there,
    they are not fitted (NaN); the last leg's windows fit about the reference, taken where
    no pass came back."""
    from scipy.spatial import cKDTree

    from tests.drive_by_hand import poses_from
    from torchsoil.grid import Grid
    from torchsoil.robot import paper_platform
    from torchsoil.sim.geometry import wheel_positions

    robot, dx, R, L, off = paper_platform(), 0.02, 1.5, 5.0, 0.2
    r2 = (2 * R - off) / 2                                       # the last half circle ends at y = off
    legs = [(L, lambda u: (u, 0.0, 0.0)),
            (math.pi * R, lambda u: (L + R * math.sin(u / R), R - R * math.cos(u / R), u / R)),
            (L, lambda u: (L - u, 2 * R, math.pi)),
            (math.pi * r2, lambda u: (-r2 * math.sin(u / r2), 2 * R - r2 + r2 * math.cos(u / r2), math.pi + u / r2)),
            (L / 2, lambda u: (u, off, 2 * math.pi))]
    pts, t0 = [], 0.0
    for length, at in legs:
        u = np.arange(0.0, length, 0.05)
        pts += [(t0 + ui, *at(ui)) for ui in u]
        t0 += length
    p = np.array(pts)
    poses = poses_from(p[:, 0], p[:, 1], p[:, 2], p[:, 3])
    grid = Grid.covering(-R - 1.2, -1.2, L + R + 1.2, 2 * R + 1.2, dx)
    xs, ys = grid.centers()
    cells = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)

    def ruts(sel, depth=0.025, sigma=0.03):
        w = wheel_positions(poses[sel][:, [0, 1, 2, 6]], robot.wheels[:, :2]).reshape(-1, 2)
        return -depth * np.exp(-0.5 * (cKDTree(w).query(cells)[0].reshape(grid.shape) / sigma) ** 2)

    last = p[:, 0] >= t0 - L / 2
    seen = cKDTree(wheel_positions(poses[last][:, [0, 1, 2, 6]], robot.wheels[:, :2]).reshape(-1, 2)).query(
        cells)[0].reshape(grid.shape) <= 0.6                      # what the last leg's front lidar saw anew
    rng = np.random.default_rng(5)
    h_back = np.minimum(ruts(~last), ruts(last))
    h_front = np.where(seen, ruts(~last), 0.0)
    def measured(h):
        return (h + 0.002 * rng.standard_normal(grid.shape)).astype(np.float32)

    pair = TerrainPair(dx, np.array(grid.origin), measured(h_front), measured(h_back), poses, robot.wheels,
                       robot.wheel_width)
    e = Estimator(pair, EstimatorConfig(front_view="last_visit"))
    rows = [o.row for o in e.run()]
    s = np.array([r["s"] for r in rows])
    d = np.array([(r["d1"] + r["d2"]) / 2 for r in rows])
    ref = np.nanmedian(d[(s > L / 2 + 1.0) & (s < L - 0.5)])      # the first leg where nothing came back
    assert ref > 0.01
    first_leg = (s > 0.5) & (s < L / 2 - 0.5)
    assert np.isnan(d[first_leg]).sum() + (d[first_leg] > 0.6 * ref).sum() == first_leg.sum()
    back_again = s > e.index.arc[-1] - L / 2 + 0.5
    assert (d[back_again] > 0.6 * ref).all()


def test_runs_sharing_a_window_store_prepare_each_window_once_and_agree(pair_truth, monkeypatch):
    """A second run over the same pair with the store of the first prepares no window and gives
    the same rows (a diagnosis's passes share one); another tyre section or setting gets its own."""
    import dataclasses

    import torchsoil.estimate.estimator as estimator_module
    from torchsoil.estimate.windows import WindowStore

    pair, _ = pair_truth
    settings = load_settings()
    calls = []
    real = estimator_module.prepare_window
    monkeypatch.setattr(estimator_module, "prepare_window", lambda *a, **k: calls.append(a[2]) or real(*a, **k))

    def rows(p, store, sim=settings.sim):
        est = Estimator(p, settings.estimator, sim, store=store, nuisance=first.nuisance, index=first.index)
        return [{k: v for k, v in o.row.items() if k != "seconds"} for o in est.run()]

    first = Estimator(pair, settings.estimator, settings.sim)
    alone = rows(pair, None)
    n_windows = len(calls)
    store = WindowStore()
    calls.clear()
    assert rows(pair, store) == alone and len(calls) == n_windows
    calls.clear()
    assert rows(pair, store) == alone and calls == []                      # all from the store
    rows(dataclasses.replace(pair, wheel_flat_fraction=0.5), store)
    rows(pair, store, settings.sim.replace(pose_spacing=settings.sim.pose_spacing * 2))
    assert len(calls) == 2 * n_windows                                     # neither shares the first's windows
    assert len(store) == 3 * n_windows


def test_a_blurred_raster_is_fitted_through_the_blur():
    """H_b measured through a Gaussian blur of 1.5 cells (the ruts' walls spread): fitted through
    the same blur (estimator.after_blur) the parameters come back and the residual is lower
    than without it, whose spread walls read as a far lower angle of repose."""
    pair, _ = sim_pair(length=2.4, noise=0.001, blur=1.5, **TRUE)
    plain, blurred = _rows(make(pair)), _rows(make(pair, "estimator.after_blur=1.5"))
    assert np.mean([r["residual"] for r in blurred]) < 0.8 * np.mean([r["residual"] for r in plain])
    assert np.mean([r["beta"] for r in plain]) < TRUE["beta_deg"] - 10.0
    for r in blurred:
        assert r["d1"] == pytest.approx(TRUE["d1"], abs=0.003)
        assert r["d2"] == pytest.approx(TRUE["d2"], abs=0.003)
        assert r["chi"] == pytest.approx(TRUE["chi"], abs=0.15)
        assert r["beta"] == pytest.approx(TRUE["beta_deg"], abs=5.0)

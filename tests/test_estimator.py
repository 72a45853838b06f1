import csv
import math

import numpy as np
import pytest

from tests.synthetic_pair import sim_pair
from torchsoil.estimator import Estimator
from torchsoil.runner import estimate, simulated_error
from torchsoil.settings import EstimatorConfig, load_settings
from torchsoil.terrain import TerrainPair

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
    names = ["s", "t", "x", "y", "d1", "d2", "chi", "beta", "map_offset", "residual", "prediction", "iterations",
             "seconds", "latency", "flags"]
    with (out / "params.csv").open() as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == names
        full = list(reader)
    for name in ("summary.md", "fig4_parameters.png", "fig6_difference_maps.png", "simulated.npz"):
        assert (out / name).stat().st_size > 0
    assert any((out / "tensorboard").iterdir())
    assert "noise floor" in (out / "summary.md").read_text()
    assert "Removed from H_b before estimation: offset" in (out / "summary.md").read_text()
    # the stitched simulation is close to the noise-free truth near the wheel paths
    assert simulated_error(out, truth_hb, pair) < 1.5e-3
    # interrupt after 3 windows, then resume: the same windows, the same parameters
    lines = (out / "params.csv").read_text().splitlines()
    (out / "params.csv").write_text("\n".join(lines[:4]) + "\n")
    ref = (out / "reference.csv").read_text().splitlines()
    (out / "reference.csv").write_text("\n".join(ref[:4]) + "\n")
    estimate(src, out, cfg, resume=True, tensorboard=False, progress=False)
    with (out / "params.csv").open() as f:
        resumed = list(csv.DictReader(f))
    assert len(resumed) == len(full)
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

import csv
import math

import numpy as np
import pytest

from tests.synthetic_pair import sim_pair
from torchsoil.estimator import Estimator
from torchsoil.runner import estimate, simulated_error
from torchsoil.settings import load_settings

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

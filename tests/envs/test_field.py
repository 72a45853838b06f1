"""Fields from their settings (torchsoil.settings.FieldConfig) and from an estimator run's params.csv."""

import csv
import math

import numpy as np
import pytest
import torch

from envs.field import field_config, field_from_params_csv, make_field, read_params_csv
from torchsoil.settings import FieldConfig, Patch


def _cfg(**kw):
    base = {"size": [6.0, 4.0], "dx": 0.05, "roughness": 0.004, "seed": 1,
            "soil": {"d": 0.02, "chi": 0.6, "beta_deg": 30.0},
            "patches": [{"center": [3.0, 2.0], "radius": 0.8, "d": [0.08, 0.06], "beta_deg": 20.0}],
            "lanes": [{"y": [3.5, 3.9], "d": 0.005, "chi": 0.9}], "edge": 0.2}
    return {**base, **kw}


def _at(field, x, y):
    i, j = field.grid.index(np.array([x, y]))
    return field.soil[:, i, j]


def test_make_field_layers_and_patches():
    f = make_field(_cfg())
    assert f.names == ("d1", "d2", "chi", "beta")
    assert f.grid.shape == (121, 81)
    centre = _at(f, 3.0, 2.0)
    assert torch.allclose(centre, torch.tensor([0.08, 0.06, 0.6, math.radians(20.0)]), atol=1e-6)
    far = _at(f, 0.5, 0.5)
    assert torch.allclose(far, torch.tensor([0.02, 0.02, 0.6, math.radians(30.0)]), atol=1e-6)
    lane = _at(f, 0.5, 3.7)
    assert torch.allclose(lane, torch.tensor([0.005, 0.005, 0.9, math.radians(30.0)]), atol=1e-6)
    assert float(f.h0.std()) == pytest.approx(0.004, rel=1e-3)


def test_make_field_is_deterministic_per_seed():
    a, b, c = make_field(_cfg()), make_field(_cfg()), make_field(_cfg(seed=2))
    assert torch.equal(a.h0, b.h0) and torch.equal(a.soil, b.soil)
    assert not torch.equal(a.h0, c.h0)


@pytest.mark.parametrize("bad, match", [
    ({"colour": 1}, r"unknown setting `field.colour`"),
    ({"patches": [{"center": [1, 1], "radius": 1, "d": 0.5}]}, "soil layer d"),
    ({"patches": [{"center": [1, 1], "radius": 1, "wetness": 2}]}, r"unknown setting `field.patches.0.wetness`"),
    ({"patches": [{"center": [1, 1], "radius": -1}]}, r"`field.patches.0.radius` = -1"),
    ({"soil": {"d": [0.1, 0.1, 0.1], "chi": 0.5, "beta_deg": 30}}, "d needs 1 or 2 values"),
    ({"size": [0.1, 4.0]}, "must span several cells"),
])
def test_bad_field_config_names_the_problem(bad, match):
    with pytest.raises(ValueError, match=match):
        make_field(_cfg(**bad))


def test_field_config_merges_onto_the_defaults_and_settings_models_work():
    cfg = field_config({"soil": {"d": 0.03}, "size": [6.0, 4.0]})
    assert cfg.soil.d == 0.03 and cfg.soil.chi == FieldConfig().soil.chi      # merged key by key
    assert cfg.patches == FieldConfig().patches                                 # default patch kept
    assert field_config(cfg) is cfg and field_config(None) == FieldConfig()
    model = FieldConfig(size=(6.0, 4.0), roughness=0.0, patches=(Patch(center=(3.0, 2.0), radius=0.8, d=0.07),),
                        lanes=())
    f = make_field(model, n_tracks=3)
    assert f.names == ("d1", "d2", "d3", "chi", "beta")
    assert torch.allclose(_at(f, 3.0, 2.0)[:3], torch.full((3,), 0.07))
    assert float(f.h0.abs().max()) == 0.0


def _write_csv(path, rows, header=None):
    header = header or ["s", "t", "x", "y", "d1", "d2", "chi", "beta[deg]", "residual", "prediction",
                        "iterations", "seconds", "flags"]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def test_params_csv_replays_estimates_along_the_path(tmp_path):
    rows = [[x - 1, x, x, 2.0, 0.01 * x, 0.005 * x, 0.5, 25.0 + x, 0.001, 0.001, 30, 0.1, ""]
            for x in (1.0, 2.0, 3.0, 4.0, 5.0)]
    rows.append([9, 9, 5.5, 2.0, "nan", 0.01, 0.5, 25.0, 0, 0, 0, 0, "failed"])   # dropped
    p = tmp_path / "params.csv"
    _write_csv(p, rows)
    xy, vals, names = read_params_csv(p)
    assert names == ("d1", "d2", "chi", "beta") and len(xy) == 5
    f = field_from_params_csv(p, field_config(_cfg(patches=[])), reach=0.6)
    near = _at(f, 3.1, 2.2)                   # nearest estimate: x = 3
    assert torch.allclose(near, torch.tensor([0.03, 0.015, 0.5, math.radians(28.0)]), atol=1e-6)
    near5 = _at(f, 5.45, 2.0)                 # the nan row at 5.5 was dropped: x = 5 wins
    assert near5[0].item() == pytest.approx(0.05, abs=1e-6)
    far = _at(f, 3.0, 3.0)                    # beyond reach: the config's soil
    assert far[0].item() == pytest.approx(0.02, abs=1e-6)


def test_params_csv_keeps_the_first_visit_of_ground_driven_again(tmp_path):
    header = ["s", "visit", "passes_before", "t", "x", "y", "d1", "d2", "chi", "beta", "flags"]
    rows = [[1.0, 0, 0, 1.0, 1.0, 2.0, 0.03, 0.03, 0.5, 30.0, ""],
            [1.0, 1, 2, 9.0, 1.0, 2.0, 0.01, 0.01, 0.9, 34.0, ""],     # the same ground, driven again
            [1.4, 0, 0, 1.4, 1.4, 2.0, 0.02, 0.02, 0.5, 30.0, ""]]
    p = tmp_path / "params.csv"
    _write_csv(p, rows, header=header)
    xy, vals, _ = read_params_csv(p)
    np.testing.assert_allclose(xy, [[1.0, 2.0], [1.4, 2.0]])
    np.testing.assert_allclose(vals[:, 0], [0.03, 0.02])


def test_params_csv_missing_column_is_named(tmp_path):
    p = tmp_path / "params.csv"
    _write_csv(p, [[0, 0, 1.0, 2.0, 0.01, 0.5]], header=["s", "t", "x", "y", "d1", "chi"])
    with pytest.raises(ValueError, match=r"missing columns \['beta\[deg\]'\]"):
        read_params_csv(p)
    with pytest.raises(FileNotFoundError, match="params.csv not found"):
        read_params_csv(tmp_path / "nope.csv")


def test_soil_field_rejects_bad_layers():
    from envs.field import SoilField

    f = make_field(_cfg())
    h0 = f.h0.clone()
    h0[3, 4] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        SoilField(f.grid, h0, f.soil, f.names)
    with pytest.raises(ValueError, match=r"h0 must be \(X, Y\)"):
        SoilField(f.grid, f.h0[:-1], f.soil, f.names)
    with pytest.raises(ValueError, match="layer names"):
        SoilField(f.grid, f.h0, f.soil, f.names[:-1])

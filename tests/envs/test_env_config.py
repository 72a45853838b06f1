"""The env's settings (torchsoil.settings.EnvConfig): the forms config takes, errors that
name the key, and the settings derived from them (relaxation margin in cells)."""

import math

import pytest
import torch
import yaml
from env_configs import small_config

from envs.params import env_config, make_params, relax_margin_cells
from envs.soil_traverse import SoilTraverseEnv
from envs.vector import SoilTraverseVectorEnv
from torchsoil.settings import EnvConfig, SettingsError


@pytest.mark.parametrize("doc, key", [
    ({"dt": 0.2, "bogus": 1}, "env.bogus"),
    ({"field": {"sise": [1, 2]}}, "env.field.sise"),
    ({"sim": {"relaxation": "capped"}}, "env.sim.relaxation"),
    ({"weights": {"speed": 1.0}}, "env.weights.speed"),
])
def test_unknown_env_key_is_refused_by_name(doc, key):
    with pytest.raises(SettingsError, match=rf"unknown setting `{key}`"):
        env_config(doc)
    with pytest.raises(SettingsError, match=rf"unknown setting `{key}`"):
        SoilTraverseEnv(doc)
    with pytest.raises(SettingsError, match=rf"unknown setting `{key}`"):
        SoilTraverseVectorEnv(2, {"env": doc})                # as a full settings document


def test_bad_values_are_refused_by_name():
    with pytest.raises(SettingsError, match=r"`env.dt` = -1"):
        env_config({"dt": -1})
    with pytest.raises(SettingsError, match=r"speed must be \(min, max\)"):
        env_config({"speed": [1.0, -0.5]})
    with pytest.raises(SettingsError, match=r"`env.field.patches.0.radius`"):
        env_config({"field": {"patches": [{"center": [1, 1]}]}})
    with pytest.raises(SettingsError, match=r"sim.dig_order: the environment digs every wheel"):
        env_config({"sim": {"dig_order": "wheel"}})
    with pytest.raises(SettingsError, match="must be None, an EnvConfig, a dict or a YAML path"):
        env_config([("dt", 0.1)])


def test_config_forms_agree(tmp_path):
    """None, EnvConfig, dict of the env section, YAML of it and YAML of the full tree."""
    assert env_config(None) == EnvConfig()
    cfg = EnvConfig(max_steps=7)
    assert env_config(cfg) is cfg
    doc = small_config(sim={"fixed_iter": None, "relax_margin": 1.0}, max_steps=9)
    from_dict = env_config(doc)
    assert from_dict.max_steps == 9 and from_dict.sim.fixed_iter is None and from_dict.sim.relax_margin == 1.0
    assert from_dict.sim.tau == EnvConfig().sim.tau                     # merged onto the env's defaults
    assert from_dict.weights == EnvConfig().weights and from_dict.robot == "paper_platform"
    assert from_dict.field.lanes[0].y == (4.0, 4.6) and from_dict.field.lanes[0].chi is None
    env_yaml = tmp_path / "env.yaml"
    env_yaml.write_text(yaml.safe_dump(doc))
    assert env_config(env_yaml) == from_dict and env_config(str(env_yaml)) == from_dict
    full = tmp_path / "settings.yaml"
    full.write_text(yaml.safe_dump({"env": doc, "sim": {"tau": 0.5}, "estimator": {"window": 1.0}}))
    assert env_config(full) == from_dict                                # the simulator's section is not the env's
    assert env_config({"env": None}) == EnvConfig()
    env = SoilTraverseEnv(full)
    assert env.params.config == from_dict


def test_full_settings_document_errors(tmp_path):
    with pytest.raises(SettingsError, match="unknown settings section.*'field'"):
        env_config({"env": {}, "field": {"size": [8, 5]}})
    with pytest.raises(SettingsError, match="section `env` must be a mapping"):
        env_config({"env": [1, 2]})
    with pytest.raises(FileNotFoundError, match="not found"):
        env_config(tmp_path / "missing.yaml")


@pytest.mark.parametrize("margin, width, dx, cells", [
    (0.7, 0.14, 0.05, 2),       # the default: 1.96 cells -> 2 (the env's margin before it was in wheel widths)
    (1.0, 0.14, 0.05, 3),       # 2.8 -> 3
    (0.2, 0.1, 0.01, 2),        # 2.0000000000000004 in floats: still 2
    (0.0, 0.14, 0.05, 0),
])
def test_relax_margin_wheel_widths_to_cells(margin, width, dx, cells):
    assert relax_margin_cells(margin, width, dx) == cells


def test_relax_margin_sets_the_window():
    """Default field and robot: fastest wheel step 0.2 m * (1 + 0.8 * hypot(0.69, 0.5)) = 0.336 m,
    footprint radius 0.07 m and a 1-cell band each end: ceil(0.576 / 0.05) + 1 = 13 cells, plus
    the margin on both sides."""
    step = 0.2 * (1 + 0.8 * math.hypot(0.69, 0.5))
    core_cells = math.ceil((step + 2 * (0.07 + 0.05)) / 0.05) + 1
    assert core_cells == 13
    p = make_params()
    assert (p.relax_margin, p.window) == (2, core_cells + 2 * 2)
    wide = make_params({"sim": {"relax_margin": 1.0}})
    assert (wide.relax_margin, wide.window) == (3, core_cells + 2 * 3)


def test_params_follow_the_settings():
    p = make_params(small_config(sim={"band_width": 2.0}, speed=[-0.5, 0.5]))
    assert p.grid.shape == (161, 101) and p.grid.dx == 0.05
    assert p.robot.wheel_width == 0.14 and p.radius == pytest.approx(0.07)
    assert p.weights == EnvConfig().weights.model_dump()
    assert torch.equal(p.obs_offsets[0], torch.tensor([-0.7, -0.7]))   # 8 cells at 0.2 m
    assert p.soil_hi.shape == (4,)

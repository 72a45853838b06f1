"""The settings tree: defaults, YAML and --set overrides, refusals naming the key."""

import pytest

from torchsoil.settings import (
    EstimatorConfig,
    PipelineConfig,
    Settings,
    SettingsError,
    SimConfig,
    load_settings,
    parse_override,
)


def test_defaults_are_the_papers_values():
    s = load_settings()
    assert s.sim.tau == 0.01 and s.sim.eps_scale == 4.0 and s.sim.fixed_iter is None
    assert s.estimator.window == 0.8 and s.estimator.stride == 0.4 and s.estimator.corridor == 3.0
    assert s.pipeline.raster.dx == 0.02
    assert s == Settings()


def test_yaml_then_overrides_in_order(tmp_path):
    user = tmp_path / "user.yaml"
    user.write_text("estimator:\n  window: 1.2\n  init: {d: 0.05}\nsim:\n  tau: 0.02\n")
    s = load_settings(user, overrides=["sim.fixed_iter=5", "estimator.grad=fd", "sim.tau=0.005"])
    assert s.estimator.window == 1.2 and s.estimator.init.d == 0.05
    assert s.estimator.init.chi == 0.5 and s.estimator.init.beta_deg == 30.0  # nested defaults kept
    assert s.sim.fixed_iter == 5 and s.estimator.grad == "fd"
    assert s.sim.tau == 0.005  # the override comes last


@pytest.mark.parametrize("override, named", [
    ("estimator.windw=1", "estimator.windw"),
    ("estimator.fd_step.x=1", "estimator.fd_step.x"),
    ("pipeline.mapping.voxels=0.1", "pipeline.mapping.voxels"),
    ("nosection.key=1", "nosection"),
    ("estimator.window=abc", "estimator.window"),
    ("estimator.window=-1", "estimator.window"),
    ("estimator.grad=numeric", "estimator.grad"),
    ("sim.backend=cuda_magic", "sim.backend"),
    ("pipeline.read.extrinsics={lidar: [1, 2]}", "pipeline.read.extrinsics"),
    ("diagnosis.alpha_accept=2", "diagnosis.alpha_accept"),
    ("env.field.sise=[1, 2]", "env.field.sise"),
])
def test_unknown_keys_and_wrong_values_are_refused_by_name(override, named):
    with pytest.raises(SettingsError, match=named.replace(".", r"\.")):
        load_settings(overrides=[override])


def test_bad_override_syntax_and_missing_file(tmp_path):
    with pytest.raises(SettingsError, match="section.key=value"):
        parse_override("estimator.window")
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        load_settings(tmp_path / "nope.yaml")
    bad = tmp_path / "list.yaml"
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(SettingsError, match="mapping"):
        load_settings(bad)


def test_sections_are_frozen_and_replace_validates():
    e = EstimatorConfig()
    with pytest.raises(Exception, match="frozen"):
        e.window = 2.0
    assert e.replace(window=1.0).window == 1.0 and e.window == 0.8
    with pytest.raises(Exception, match="window"):
        e.replace(window="long")
    # a mapping for a nested section changes only what it names
    p = PipelineConfig().replace(reregister={"max_iter": 7})
    assert p.reregister.max_iter == 7 and p.reregister.voxel == PipelineConfig().reregister.voxel


def test_yaml_dump_round_trips_and_carries_units():
    s = load_settings(overrides=["estimator.window=1.1", "sim.fixed_iter=3", "env.field.seed=4"])
    text = s.to_yaml()
    assert "# window length along the path, m" in text
    import yaml

    assert load_settings(yaml.safe_load(text)) == s
    only = s.to_yaml(["sim"])
    assert only.startswith("sim:") and "estimator" not in only
    with pytest.raises(SettingsError, match="no settings section"):
        s.to_yaml(["simulator"])


def test_env_and_simulator_share_one_meaning_of_relax_margin():
    """relax_margin is in wheel widths wherever it appears (the env's physics is a SimConfig)."""
    s = Settings()
    assert isinstance(s.env.sim, SimConfig)
    assert SimConfig.model_fields["relax_margin"].description == \
        type(s.env.sim).model_fields["relax_margin"].description
    assert "wheel widths" in SimConfig.model_fields["relax_margin"].description

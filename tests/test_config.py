import pytest

from torchsoil.config import load_config, parse_override
from torchsoil.sim import SimConfig


def test_defaults_are_the_papers():
    cfg = load_config()
    assert cfg["sim"]["tau"] == 0.01 and cfg["sim"]["eps_scale"] == 4.0
    assert cfg["estimator"]["window"] == 0.8 and cfg["estimator"]["stride"] == 0.4
    assert cfg["estimator"]["corridor"] == 3.0
    SimConfig.from_dict(cfg["sim"])  # every sim key is a SimConfig field


def test_overrides_and_user_file(tmp_path):
    user = tmp_path / "my.yaml"
    user.write_text("estimator:\n  window: 1.2\n  init: {d: 0.05}\n")
    cfg = load_config(user, ["sim.fixed_iter=5", "estimator.grad=fd"])
    assert cfg["estimator"]["window"] == 1.2 and cfg["estimator"]["init"]["d"] == 0.05
    assert cfg["estimator"]["init"]["chi"] == 0.5  # nested defaults kept
    assert cfg["sim"]["fixed_iter"] == 5 and cfg["estimator"]["grad"] == "fd"
    assert parse_override("a.b=[1, 2]") == {"a": {"b": [1, 2]}}


def test_bad_settings_are_named(tmp_path):
    with pytest.raises(KeyError, match="estimator.windw"):
        load_config(overrides=["estimator.windw=1"])
    with pytest.raises(ValueError, match="section.key=value"):
        load_config(overrides=["estimator.window"])
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        load_config(tmp_path / "nope.yaml")
    with pytest.raises(ValueError, match="unknown sim settings"):
        SimConfig.from_dict({"tua": 0.1})

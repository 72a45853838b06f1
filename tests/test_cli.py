"""The `torchsoil` command and what importing the library leaves alone."""

import subprocess
import sys
from importlib.metadata import entry_points

from torchsoil.cli import main

SUBCOMMANDS = ("estimate", "export", "process-bag", "diagnose", "record", "rollout", "bench", "settings")


def run(*args):
    return subprocess.run([sys.executable, *map(str, args)], capture_output=True, text=True, timeout=300)


def test_registered_command_lists_every_job():
    (ep,) = [e for e in entry_points(group="console_scripts") if e.name == "torchsoil"]
    assert ep.value == "torchsoil.cli:main"
    r = run("-m", "torchsoil", "--help")
    assert r.returncode == 0, r.stderr
    for name in SUBCOMMANDS:
        assert name in r.stdout


def test_settings_command_prints_the_effective_tree(tmp_path, capsys):
    user = tmp_path / "u.yaml"
    user.write_text("estimator: {window: 1.2}\n")
    assert main(["settings", "estimator", "sim", "--config", str(user), "--set", "sim.tau=0.003"]) == 0
    text = capsys.readouterr().out
    assert "window: 1.2  # window length along the path, m" in text and "tau: 0.003" in text
    assert "pipeline:" not in text
    assert main(["settings", "--set", "estimator.windw=1"]) == 2
    assert "estimator.windw" in capsys.readouterr().err


def test_robot_by_unknown_name_is_a_clear_error(tmp_path, capsys):
    assert main(["diagnose", str(tmp_path), "--robot", "no_such_robot", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "no_such_robot" in err and "paper_platform" in err


def test_noise_redraws_belong_to_the_foreign_study(tmp_path, capsys):
    for args in (["--quick", "--redraws", "2"], ["--foreign", str(tmp_path), "--redraws", "-1"]):
        assert main(["study", *args, "--out", str(tmp_path / "o")]) == 2
        assert "--redraws" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_importing_any_module_changes_nothing_process_wide():
    code = """
import importlib, os, pkgutil, sys
import numba, torch
env, threads, interop, nb = dict(os.environ), torch.get_num_threads(), torch.get_num_interop_threads(), \\
    numba.get_num_threads()
import torchsoil
names = [m.name for m in pkgutil.walk_packages(torchsoil.__path__, "torchsoil.")]
for name in names:
    if name != "torchsoil.__main__":
        importlib.import_module(name)
assert len(names) > 30, names
assert dict(os.environ) == env, set(os.environ.items()) ^ set(env.items())
assert (torch.get_num_threads(), torch.get_num_interop_threads(), numba.get_num_threads()) == (threads, interop, nb)
assert "gymnasium" not in sys.modules and "matplotlib.pyplot" not in sys.modules
print("ok")
"""
    r = run("-c", code)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr


def test_the_package_data_pattern_ships_every_robot_and_scenario():
    """A wheel carries what pyproject's package-data patterns match: every shipped YAML."""
    import re
    from pathlib import Path

    import torchsoil

    root = Path(torchsoil.__file__).parent
    section = (root.parent / "pyproject.toml").read_text().split("[tool.setuptools.package-data]")[1]
    patterns = re.findall(r'"([^"]+)"', re.search(r"torchsoil = \[(.*?)\]", section).group(1))
    shipped = {p for pat in patterns for p in root.glob(pat)}
    files = {p for p in (root / "configs").rglob("*") if p.is_file()}
    assert files and files == shipped
    assert (root / "configs" / "robot" / "paper_platform.yaml") in shipped


BAG_COMMANDS = ("estimate", "process-bag", "diagnose", "ablation")


def test_every_command_that_takes_a_bag_takes_the_same_recording_options(tmp_path):
    from torchsoil.cli import _bag_settings, parser

    for cmd in BAG_COMMANDS:
        args = parser().parse_args([cmd, "in.bag", "--out", "o", "--robot", "r", "--front-topic", "/os1/points",
                                    "--back-topic", "/vlp/points", "--imu-topic", "none",
                                    "--set", "pipeline.raster.dx=0.05",
                                    "--extrinsic", "/vlp/points", "-1", "0", "1", "0", "0.5", "3.14"])
        settings, given = _bag_settings(args)
        read = settings.pipeline.read
        assert (read.front_topic, read.back_topic, read.imu_topic) == ("/os1/points", "/vlp/points", "none"), cmd
        assert settings.pipeline.raster.dx == 0.05
        assert given == {"/vlp/points": [-1.0, 0.0, 1.0, 0.0, 0.5, 3.14]}


def test_the_recording_options_reach_the_pipeline_of_every_command(tmp_path, capsys):
    """A topic the bag does not hold, given on the command line, stops each command with the
    topic named; a non-number in --extrinsic is named too."""
    from tests.pipeline.toyscene import ToyScene

    bag = tmp_path / "bag"
    ToyScene(columns=64).write(bag, 0.3)
    for cmd in BAG_COMMANDS:
        out = tmp_path / cmd
        assert main([cmd, str(bag), "--robot", "paper_platform", "--out", str(out), "--back-topic", "/rear"]) == 2
        assert "'/rear' not found" in capsys.readouterr().err, cmd
    assert main(["process-bag", str(bag), "--robot", "paper_platform", "--out", str(tmp_path / "x"),
                 "--extrinsic", "lidar_front", "1", "0", "1", "0", "0", "yaw"]) == 2
    assert "--extrinsic lidar_front: X Y Z ROLL PITCH YAW must be numbers" in capsys.readouterr().err


def test_pass_workers_default_to_what_the_cores_and_memory_hold(monkeypatch):
    import torchsoil.engines as engines
    from torchsoil.jobs import diagnose
    from torchsoil.settings import Settings

    s = Settings().fleet
    monkeypatch.setattr(engines.os, "sched_getaffinity", lambda _: set(range(16)), raising=False)
    monkeypatch.setattr(engines, "available_mb", lambda: 64000.0)
    assert diagnose.pass_workers(None, "local", s) == diagnose.MAX_PASS_WORKERS        # 16 cores: capped
    monkeypatch.setattr(engines, "available_mb", lambda: 5000.0)        # 2000 MiB a task: two fit
    assert diagnose.pass_workers(None, "local", s) == 2
    monkeypatch.setattr(engines.os, "sched_getaffinity", lambda _: {0}, raising=False)
    assert diagnose.pass_workers(None, "local", s) == 1                          # one core: all in this process
    assert diagnose.pass_workers(3, "local", s) == 3
    assert diagnose.pass_workers(None, "ray", s) == 1


def test_export_command_anchors_and_refuses_clearly(tmp_path, capsys):
    from tests.geo import handbuilt

    run = handbuilt.write_run(tmp_path / "run")
    assert main(["export", str(run), "--out", str(tmp_path / "out"), "--anchor", "47.4,8.55,90",
                 "--formats", "geotiff"]) == 0
    assert "EPSG:32632" in capsys.readouterr().out
    assert main(["export", str(run), "--out", str(tmp_path / "o2"), "--anchor", "47.4,8.55"]) == 2
    assert "LAT,LON,HEADING_DEG" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "nothing"), "--out", str(tmp_path / "o3")]) == 2
    assert "no such run folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["export", str(tmp_path / "empty"), "--out", str(tmp_path / "o4")]) == 2
    assert "holds none of simulated.npz" in capsys.readouterr().err

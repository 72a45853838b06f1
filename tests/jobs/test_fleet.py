"""Many recordings at once (torchsoil.jobs.fleet): inputs from paths, globs and a manifest; each
recording's outputs equal a single run's; a broken recording or a killed worker is recorded and
the others go on; a rerun skips what is complete and retries the rest; the study on the same
engines. The Ray engine runs on a local instance of 2 CPUs (one per module)."""

import csv
import json
import os
from pathlib import Path

import pytest

from tests.jobs.fleet_tasks import kill_first_time, stamp, value_or_kill, where
from tests.synthetic_pair import sim_pair
from torchsoil import engines
from torchsoil.cli import main
from torchsoil.engines import LocalEngine, make_engine
from torchsoil.jobs import fleet
from torchsoil.jobs.estimate import estimate
from torchsoil.jobs.fleet import FleetInput, FleetLog, Task, complete, recordings, run_fleet
from torchsoil.settings import load_settings

FAST = ["estimator.max_iter=8"]                  # short relaxations: the outputs are compared, not judged
TIMING = ("seconds", "latency")                  # params.csv columns that differ between any two runs


@pytest.fixture(scope="session")  # tests/conftest.py SHARED_FIXTURES: built once per worker
def drives(tmp_path_factory):
    """Two short terrain pairs (2 m), a broken one (not an .npz) and each good one's single run."""
    root = tmp_path_factory.mktemp("drives")
    for name, seed in (("north", 0), ("south", 1)):
        sim_pair(length=2.0, seed=seed)[0].save(root / f"{name}.npz")
    (root / "broken.npz").write_bytes(b"half a recording")
    single = {}
    for name in ("north", "south"):
        single[name] = estimate(root / f"{name}.npz", root / "single" / name, load_settings(overrides=FAST),
                                tensorboard=False, progress=False, threads=1)
    return root, single


@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, object_store_memory=128 * 2 ** 20)
    yield ray
    ray.shutdown()


def rows(path: Path, drop=()) -> list[dict]:
    with path.open(newline="") as f:
        return [{k: v for k, v in r.items() if k not in drop} for r in csv.DictReader(f)]


def fleet_rows(out: Path) -> dict[str, dict]:
    return {r["name"]: r for r in rows(out / "fleet.csv")}


def assert_same_as_single(run_dir: Path, single_dir: Path):
    assert rows(run_dir / "params.csv", TIMING) == rows(single_dir / "params.csv", TIMING)
    assert (run_dir / "reference.csv").read_text() == (single_dir / "reference.csv").read_text()
    assert json.loads((run_dir / "run.json").read_text())["settings"] == \
        json.loads((single_dir / "run.json").read_text())["settings"]


def mtimes(out: Path, names) -> dict[str, int]:
    return {n: (out / n / "params.csv").stat().st_mtime_ns for n in names}


# ---------------------------------------------------------------------------- inputs
def test_inputs_from_paths_globs_and_a_manifest(tmp_path):
    for d in ("robot_a", "robot_b"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "may01.npz").write_bytes(b"")
    (tmp_path / "robot_a" / "may02.npz").write_bytes(b"")
    (tmp_path / "soft.yaml").write_text("estimator: {window: 1.0}\n")
    found = recordings([str(tmp_path / "robot_*" / "*.npz")])
    assert [r.name for r in found] == ["robot_a_may01", "may02", "robot_b_may01"]     # same stems: folder added
    assert [Path(r.input).parent.name for r in found] == ["robot_a", "robot_a", "robot_b"]
    manifest = tmp_path / "season.csv"
    manifest.write_text("input,name,robot,config,set\n"
                        "# a comment line\n"
                        "robot_a/may01.npz,first,paper_platform,soft.yaml,estimator.stride=0.5; sim.tau=0.02\n"
                        "robot_b/*.npz,,robots/b.yaml,,\n")
    first, second = fleet.read_manifest(manifest)
    assert first == FleetInput(str(tmp_path / "robot_a/may01.npz"), "first", "paper_platform",
                              (str(tmp_path / "soft.yaml"),), ("estimator.stride=0.5", "sim.tau=0.02"))
    assert second.name == "may01" and second.robot == str(tmp_path / "robots/b.yaml")
    assert recordings([manifest]) == recordings(manifest=manifest)
    assert [r.name for r in recordings([str(tmp_path / "robot_a/may01.npz")], manifest)] == \
        ["robot_a_may01", "first", "may01"]                                 # the derived name gives way
    (tmp_path / "twice.csv").write_text("input,name\nrobot_a/may01.npz,x\nrobot_a/may02.npz,x\n")
    with pytest.raises(ValueError, match="same folder"):
        recordings(manifest=tmp_path / "twice.csv")
    (tmp_path / "bad.csv").write_text("path,name\nx.npz,x\n")
    with pytest.raises(ValueError, match="input"):
        fleet.read_manifest(tmp_path / "bad.csv")
    (tmp_path / "glob.csv").write_text("input,name\nrobot_a/*.npz,one\n")
    with pytest.raises(ValueError, match="a name for a glob of 2"):
        fleet.read_manifest(tmp_path / "glob.csv")
    with pytest.raises(FileNotFoundError, match="no recording matches"):
        recordings([str(tmp_path / "nothing*.bag")])


def test_fleet_csv_appends_rows_and_widens_for_more_tracks(tmp_path):
    log = FleetLog(tmp_path / "fleet.csv")
    log.start([{"name": "old", "status": "skipped", "d1": 0.02}], running=["a", "b"])
    log.add({"name": "a", "status": "ok", "d1": 0.03, "d2": 0.031})
    first = (tmp_path / "fleet.csv").read_text()
    log.add({"name": "b", "status": "ok", "d1": 0.01, "d2": 0.02, "d3": 0.03, "d4": 0.04})   # four tracks
    got = fleet_rows(tmp_path)
    assert list(got) == ["old", "a", "b"] and got["b"]["d4"] == "0.04" and got["a"]["d4"] == ""
    assert first.splitlines()[0].split(",")[:9] == ["name", "job", "status", "input", "windows", "fitted",
                                                    "flagged", "d1", "d2"]
    again = FleetLog(tmp_path / "fleet.csv")
    again.start([], running=["a"])                                           # a runs again: its old row goes
    assert list(fleet_rows(tmp_path)) == ["old", "b"]


def test_complete_means_same_input_robot_and_settings_and_finished(drives):
    root, single = drives
    out = single["north"]

    def task(overrides=FAST, robot=None):
        return Task("estimate", "north", str(root / "north.npz"), str(out), str(root / "x.log"),
                    load_settings(overrides=overrides), robot)

    assert complete(task())
    assert not complete(task(["estimator.max_iter=9"]))                  # other settings
    assert not complete(task(robot="paper_platform"))                    # another robot
    assert not complete(Task("diagnose", "north", str(root / "north.npz"), str(out), "", load_settings()))
    summary = out / "summary.md"
    stamp = summary.stat().st_mtime_ns
    os.utime(summary, ns=(stamp, (out / "run.json").stat().st_mtime_ns - 1_000_000))
    try:
        assert not complete(task())                                      # run.json newer: an unfinished rerun
    finally:
        os.utime(summary, ns=(stamp, stamp))


def test_a_failed_attempt_is_replaced_but_a_finished_run_is_not(drives, tmp_path):
    """A recording whose last task failed may overwrite its folder (mended since), unless the
    folder holds a finished run of other settings: that stays refused, rerun after rerun."""
    import shutil

    from torchsoil.jobs.fleet import plan

    root, single = drives
    out = tmp_path / "out"
    shutil.copytree(single["north"], out / "north")
    log = FleetLog(out / "fleet.csv")
    log.start([{"name": "north", "status": "error", "error": "OutputMismatch: ..."}], running=[])
    rec = [FleetInput(str(root / "north.npz"), "north")]

    def planned(overrides):
        return plan("estimate", rec, out, log, [], overrides, None, None, False, False)

    (task,), early = planned(["estimator.max_iter=9"])                  # finished with max_iter=8
    assert not early and not task.overwrite
    tasks, (row,) = planned(FAST)
    assert not tasks and row["status"] == "skipped"
    (out / "north" / "summary.md").unlink()                             # an unfinished attempt
    (task,), _ = planned(["estimator.max_iter=9"])
    assert task.overwrite


# ---------------------------------------------------------------------------- the local engine
def test_a_killed_worker_takes_only_its_task_down():
    got = dict(LocalEngine(2).imap(value_or_kill, [(0,), (1,), (2,), (3,)]))
    assert sorted(got) == [0, 1, 2, 3]
    assert [got[k].value for k in (0, 2, 3)] == [0, 20, 30] and all(got[k].ok for k in (0, 2, 3))
    assert not got[1].ok and got[1].error.startswith("WorkerDied")
    assert all(got[k].peak_mb > 10 and got[k].seconds >= 0 for k in (0, 2, 3))


def test_a_call_waits_for_the_calls_it_is_after():
    # two workers: call 2 waits for call 0 (the slow one) though a worker is free after call 1
    calls = [("a", 1.0), ("b", 0.1), ("c", 0.1), ("d", 0.1)]
    got = dict(LocalEngine(2).imap(stamp, calls, after=[(), (), (0,), ()]))
    assert all(o.ok for o in got.values())
    (_, end0), (start2, _), (start3, _) = got[0].value, got[2].value, got[3].value
    assert start2 >= end0 and start3 < end0                 # call 3 went ahead of the waiting call 2


def test_a_killed_worker_is_replaced_and_its_task_retried(tmp_path):
    fleet = load_settings(overrides=["fleet.retries=1"]).fleet
    ((i, out),) = list(LocalEngine(1, fleet).imap(kill_first_time, [(str(tmp_path / "killed_once"),)]))
    assert out.ok and out.value == "second try"


def test_estimate_many_on_the_local_engine_then_rerun(drives, tmp_path, capsys):
    """The command with three recordings, one broken: exit 1, the good ones as single runs, the
    broken one's error in fleet.csv; a rerun runs only the broken one again."""
    root, single = drives
    out = tmp_path / "season"
    cmd = ["estimate", *(str(root / f"{n}.npz") for n in ("north", "south", "broken")), "--out", str(out),
           "--workers", "2", "--no-tensorboard", *(a for s in FAST for a in ("--set", s))]
    assert main(cmd) == 1
    assert "2 done, 0 already complete (skipped), 1 failed" in capsys.readouterr().out
    table = fleet_rows(out)
    assert {n: r["status"] for n, r in table.items()} == {"north": "ok", "south": "ok", "broken": "error"}
    assert "broken.npz: not a readable .npz terrain pair" in table["broken"]["error"]
    assert "Traceback" in (out / "logs" / "broken.log").read_text()
    for name in ("north", "south"):
        assert_same_as_single(out / name, single[name])
        params = rows(out / name / "params.csv")
        r = table[name]
        assert int(r["windows"]) == len(params) and int(r["flagged"]) == sum(bool(p["flags"]) for p in params)
        assert float(r["d1"]) == pytest.approx(sum(float(p["d1"]) for p in params) / len(params), rel=1e-5)
        assert float(r["peak_mb"]) > 50 and float(r["seconds"]) > 0
    before = mtimes(out, ["north", "south"])
    (out / "logs" / "broken.log").unlink()

    assert main(cmd) == 1
    assert "1 recording(s) to run" in capsys.readouterr().out
    table = fleet_rows(out)
    assert {n: r["status"] for n, r in table.items()} == {"north": "skipped", "south": "skipped", "broken": "error"}
    assert mtimes(out, ["north", "south"]) == before
    assert (out / "logs" / "broken.log").exists()                        # the broken one ran again
    assert table["north"]["d1"] and table["north"]["seconds"]            # the earlier run's figures are kept


@pytest.mark.long
def test_diagnose_many_on_the_local_engine(tmp_path):
    from torchsoil.jobs.diagnose import diagnose_input

    pair, _ = sim_pair(length=3.6, seed=2)
    pair.save(tmp_path / "long.npz")
    settings = ["diagnosis.n_fit=0", *FAST]
    base = []
    one = diagnose_input(tmp_path / "long.npz", tmp_path / "single", load_settings(overrides=settings),
                         progress=False, tensorboard=False, threads=1, rows=base)
    recs = [FleetInput(str(tmp_path / "long.npz"), "long"), FleetInput(str(tmp_path / "gone.npz"), "gone")]
    got = {r["name"]: r for r in run_fleet("diagnose", recs, tmp_path / "out", overrides=settings,
                                           tensorboard=False, workers=1, echo=lambda s: None)}
    assert json.loads((tmp_path / "out" / "long" / "diagnosis.json").read_text()) == json.loads(json.dumps(one))
    assert got["long"]["status"] == "ok" and got["long"]["verdict"] == one["verdict"]
    assert got["long"]["windows"] == len(base) and got["long"]["prediction_floor"] == pytest.approx(
        one["cost_before"]["prediction"] / one["noise_floor"])
    assert got["gone"]["status"] == "error" and "gone.npz" in got["gone"]["error"]


# ---------------------------------------------------------------------------- the Ray engine
@pytest.mark.long
def test_estimate_many_on_ray_then_rerun_retries_only_the_broken(drives, tmp_path, ray_instance, capsys):
    """Three recordings (a glob), one broken, on a local Ray instance: outputs as single runs,
    the broken one's error in fleet.csv; a rerun retries only the broken one; once it is
    mended, it alone runs, over what its failed attempt left."""
    root, single = drives
    import torchsoil

    assert ray_instance.get(ray_instance.remote(where).remote()) == torchsoil.__file__   # this checkout's code
    out = tmp_path / "season"
    cmd = ["estimate", str(root / "*.npz"), "--out", str(out), "--engine", "ray", "--no-tensorboard",
           *(a for s in FAST for a in ("--set", s))]
    assert main(cmd) == 1
    table = fleet_rows(out)
    assert {n: r["status"] for n, r in table.items()} == {"north": "ok", "south": "ok", "broken": "error"}
    assert "not a readable .npz terrain pair" in table["broken"]["error"]
    for name in ("north", "south"):
        assert_same_as_single(out / name, single[name])
        assert float(table[name]["chi"]) > 0 and table[name]["host"]
    before = mtimes(out, ["north", "south"])
    capsys.readouterr()

    assert main(cmd) == 1
    assert "1 recording(s) to run" in capsys.readouterr().out
    table = fleet_rows(out)
    assert {n: r["status"] for n, r in table.items()} == {"north": "skipped", "south": "skipped", "broken": "error"}
    assert mtimes(out, ["north", "south"]) == before

    mended = tmp_path / "mended"
    mended.mkdir()
    for name in ("north", "south"):
        (mended / f"{name}.npz").write_bytes((root / f"{name}.npz").read_bytes())
    (mended / "broken.npz").write_bytes((root / "south.npz").read_bytes())      # the recording mended
    cmd[1] = str(mended / "*.npz")
    assert main(cmd) == 0                              # copies of the same recordings: still complete
    table = fleet_rows(out)
    assert {n: r["status"] for n, r in table.items()} == {"north": "skipped", "south": "skipped", "broken": "ok"}
    assert mtimes(out, ["north", "south"]) == before
    assert_same_as_single(out / "broken", single["south"])


@pytest.mark.long
def test_ray_records_a_killed_worker_and_refuses_a_task_no_node_holds(ray_instance):
    with make_engine("ray") as eng:
        got = dict(eng.imap(value_or_kill, [(0,), (1,), (2,)]))
        assert [got[k].value for k in (0, 2)] == [0, 20]
        assert not got[1].ok and "Worker" in got[1].error
    huge = load_settings(overrides=["fleet.memory_mb_per_task=100000000"]).fleet
    with make_engine("ray", fleet=huge) as eng, pytest.raises(Exception, match="fleet.memory_mb_per_task"):
        list(eng.imap(value_or_kill, [(0,)]))
    assert ray_instance.is_initialized()                                   # a session it did not start: left up


def test_ray_engine_without_ray_says_how_to_get_it(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(Exception, match=r"torchsoil\[fleet\]"):
        engines.import_ray()


# ---------------------------------------------------------------------------- the study
TINY = {"trajectory": {"segments": [{"straight": 3.6, "speed": 1.0}]}, "terrain": {"margin": 0.5},
        "landmarks": {"poles": 0, "trunks": 0, "shed": False, "fence": False}}


def _without_time(table: str) -> str:
    return "\n".join(line for line in table.splitlines() if not line.startswith("time per case"))


@pytest.mark.long
def test_study_on_ray_gives_the_serial_table(tmp_path, ray_instance):
    from torchsoil.diagnosis.study import run_study

    cases = [(f"tiny {k}", {**TINY, "name": f"tiny{k}"}, k, "adequate", None) for k in range(3)]
    settings = load_settings(overrides=["diagnosis.n_fit=0", *FAST])
    serial = run_study(cases, tmp_path / "serial", settings)
    (tmp_path / "ray").mkdir()
    (tmp_path / "ray" / "cases.jsonl").write_text((tmp_path / "serial" / "cases.jsonl").read_text().splitlines()[1]
                                                  + "\n")                  # one case done: resumed, not rerun
    with make_engine("ray") as eng:
        on_ray = run_study(cases, tmp_path / "ray", settings, engine=eng)
    assert _without_time(on_ray) == _without_time(serial)
    done = [json.loads(line)["case"] for line in (tmp_path / "ray" / "cases.jsonl").read_text().splitlines()]
    assert done[0] == "tiny 1" and sorted(done[1:]) == ["tiny 0", "tiny 2"]


@pytest.mark.long
def test_foreign_study_command_on_the_local_engine(tmp_path, capsys):
    from torchsoil.diagnosis.study import run_foreign

    pair, _ = sim_pair(length=3.6, seed=3)
    pair.save(tmp_path / "drive.npz")
    (tmp_path / "drive_truth.json").write_text(json.dumps({"expected": {"verdict": "adequate",
                                                                        "missing_physics": None}, "windows": []}))
    sets = ["diagnosis.n_fit=0", *FAST]
    serial = run_foreign(tmp_path, tmp_path / "serial", load_settings(overrides=sets))
    assert main(["study", "--foreign", str(tmp_path), "--out", str(tmp_path / "local"), "--engine", "local",
                 "--workers", "1", *(a for s in sets for a in ("--set", s))]) == 0
    assert "[1/1] drive:" in capsys.readouterr().out
    assert _without_time((tmp_path / "local" / "confusion.md").read_text()) == _without_time(serial)

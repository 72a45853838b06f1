"""A diagnosis keeps its finished passes and, run again, resumes from them: the kept results
read back as written, another run's folder is emptied rather than reused, a damaged file is
recomputed, and an interrupted diagnosis ends with the verdict and costs of one run straight
through, running only the passes it had not finished."""

import json

import numpy as np
import pytest

from torchsoil.diagnosis import DiagnosisConfig, diagnose
from torchsoil.diagnosis import fit as fit_module
from torchsoil.diagnosis.checkpoint import KEY_FILE, PassCache
from torchsoil.diagnosis.study_cases import scenario
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.synth.scenario import make_terrain_pair


def test_kept_values_read_back_under_their_own_name_only(tmp_path):
    cache = PassCache(tmp_path / "p", {"input": "a"})
    value = {"rows": [{"s": 0.4, "d1": 0.03}], "costs": np.arange(5.0)}
    cache.save("base", (0.0, (0.5, 1.0), "robot"), value)
    back = cache.load("base", (0.0, (0.5, 1.0), "robot"))
    assert back["rows"] == value["rows"] and np.array_equal(back["costs"], value["costs"])
    assert cache.load("base", (0.0, (0.5, 1.0), "wheel")) is None           # another dig order
    assert cache.load("speed_dependent_sinkage", (0.0, (0.5, 1.0), "robot")) is None
    assert cache.hits == 1 and len(cache) == 1
    assert not list((tmp_path / "p").glob("*.tmp"))


def test_another_runs_folder_is_emptied_and_the_same_runs_kept(tmp_path):
    PassCache(tmp_path / "p", {"input": "a"}).save("base", (1,), 1.5)
    assert PassCache(tmp_path / "p", {"input": "a"}).load("base", (1,)) == 1.5
    other = PassCache(tmp_path / "p", {"input": "b"})
    assert other.load("base", (1,)) is None and len(other) == 0
    assert json.loads((tmp_path / "p" / KEY_FILE).read_text()) == {"input": "b"}


def test_a_damaged_file_is_recomputed_not_trusted(tmp_path):
    cache = PassCache(tmp_path / "p", {"input": "a"})
    cache.save("base", (1,), list(range(1000)))
    path = next((tmp_path / "p").glob("base-*.pkl"))
    path.write_bytes(path.read_bytes()[:100])                                 # cut off mid-write
    assert cache.load("base", (1,)) is None


class Interrupt(Exception):
    pass


class StopAfter:
    """A progress bar that interrupts the diagnosis after n passes (as a killed job would)."""

    def __init__(self, n):
        self.n = n

    def update(self, k=1):
        self.n -= k
        if self.n <= 0:
            raise Interrupt

    def set_postfix_str(self, text):
        pass


@pytest.fixture(scope="module")
def short_drive():
    sc = scenario("speed_dependent_sinkage")
    sc["trajectory"] = {"segments": [{"straight": 3.0, "speed": 1.3}, {"straight": 3.0, "speed": 0.6}]}
    return TerrainPair.from_mapping(make_terrain_pair(sc, seed=3))


ONE_FIT = DiagnosisConfig(n_fit=1, sections=(), dig_orders=(), refine_steps=1)


@pytest.fixture(scope="module")
def straight(short_drive):
    """The summary of the short drive's diagnosis run straight through (the tests below only read it)."""
    return diagnose(short_drive, ONE_FIT).summary


def test_an_interrupted_diagnosis_resumes_and_ends_as_one_run_straight_through(tmp_path, short_drive, straight,
                                                                                monkeypatch):
    cfg = ONE_FIT

    cache = PassCache(tmp_path / "passes", {"input": "short"})
    with pytest.raises(Interrupt):
        diagnose(short_drive, cfg, progress=StopAfter(3), cache=cache)
    kept = len(cache)
    assert kept >= 2                                          # the base pass and a candidate's

    runs = []
    original = fit_module.Estimator.run
    monkeypatch.setattr(fit_module.Estimator, "run", lambda self, *a, **k: runs.append(1) or original(self, *a, **k))
    again = PassCache(tmp_path / "passes", {"input": "short"})
    resumed = diagnose(short_drive, cfg, cache=again).summary
    # every new entry is a pass the estimator ran, but the learned modifier's folds (their terms and curves)
    learned = len(list(again.dir.glob("learned_choice-*.pkl")) + list(again.dir.glob("learned_model-*.pkl")))
    # every kept entry read back (a score two phases share, the base model's on every third window for
    # the raster's blur and for the shape screen, is read by each)
    assert again.hits >= kept and runs and len(runs) == len(again) - kept - learned
    assert resumed == straight


def test_the_command_run_again_into_its_folder_reads_every_pass_back(tmp_path, short_drive, monkeypatch):
    from torchsoil.jobs.diagnose import diagnose_input
    from torchsoil.settings import load_settings

    short_drive.save(tmp_path / "short.npz")
    settings = load_settings(overrides=["diagnosis.n_fit=1", "diagnosis.sections=[]", "diagnosis.dig_orders=[]",
                                        "diagnosis.refine_steps=0"])
    first = diagnose_input(tmp_path / "short.npz", tmp_path / "out", settings, progress=False, tensorboard=False)
    runs = []
    original = fit_module.Estimator.run
    monkeypatch.setattr(fit_module.Estimator, "run", lambda self, *a, **k: runs.append(1) or original(self, *a, **k))
    again = diagnose_input(tmp_path / "short.npz", tmp_path / "out", settings, progress=False, tensorboard=False)
    assert runs == [] and again == first
    assert json.loads((tmp_path / "out" / "diagnosis.json").read_text()) == json.loads(json.dumps(first))


class StopAtWindow(StopAfter):
    """A progress bar that interrupts the base pass when it reports window `k` (a kill mid-pass)."""

    def __init__(self, k):
        super().__init__(10 ** 6)
        self.k = k

    def set_postfix_str(self, text):
        if text == f"base window {self.k}":
            raise Interrupt


def test_a_pass_killed_midway_resumes_from_its_last_window(tmp_path, short_drive, straight, monkeypatch):
    """Kept after every window (every=0), a base pass stopped as it reports window 10 goes on
    from window 10, not from the start, and the diagnosis ends as one run straight through."""
    cfg = ONE_FIT
    with pytest.raises(Interrupt):
        diagnose(short_drive, cfg, progress=StopAtWindow(10), cache=PassCache(tmp_path / "p", {"i": 1}, every=0))
    assert len(list((tmp_path / "p").glob("base-partial-*.pkl"))) == 1
    starts = []
    original = fit_module.Estimator.run
    monkeypatch.setattr(fit_module.Estimator, "run",
                        lambda self, *a, start=0, **k: starts.append(start) or original(self, *a, start=start, **k))
    resumed = diagnose(short_drive, cfg, cache=PassCache(tmp_path / "p", {"i": 1}, every=0)).summary
    assert starts[0] == 10 and all(s == 0 for s in starts[1:])
    assert resumed == straight
    assert not list((tmp_path / "p").glob("*-partial-*.pkl"))      # dropped once their passes were done


@pytest.mark.long
def test_a_diagnose_killed_with_sigkill_resumes_to_the_straight_run(tmp_path, short_drive):
    """`torchsoil diagnose` killed once a pass in progress has been kept, then `--resume`: the
    diagnosis.json of a run straight through."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    from torchsoil.jobs.diagnose import diagnose_input
    from torchsoil.settings import load_settings

    short_drive.save(tmp_path / "short.npz")
    overrides = ("diagnosis.n_fit=1", "diagnosis.sections=[]", "diagnosis.dig_orders=[]", "diagnosis.refine_steps=1",
                 "diagnosis.checkpoint_s=0")
    sets = [a for kv in overrides for a in ("--set", kv)]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))

    def run(out, *extra):
        return subprocess.Popen([sys.executable, "-m", "torchsoil", "diagnose", str(tmp_path / "short.npz"), "--out",
                                 str(out), "--no-tensorboard", *sets, *extra], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)

    # the run straight through in this process, by the function the command calls (one pass worker: the
    # same results as on a pool, tests/diagnosis/test_parallel.py), the killed run by the command itself
    diagnose_input(tmp_path / "short.npz", tmp_path / "straight", load_settings(overrides=list(overrides)),
                   progress=False, tensorboard=False, threads=1, workers=1)
    killed = run(tmp_path / "killed")
    passes = tmp_path / "killed" / "passes"
    while killed.poll() is None and not (passes.exists() and any(passes.glob("*-partial-*.pkl"))):
        time.sleep(0.01)
    assert killed.poll() is None, "the run ended before it could be killed"
    os.killpg(killed.pid, signal.SIGKILL)       # the command and its pass workers, as a job killed whole
    killed.wait()
    assert not (tmp_path / "killed" / "diagnosis.json").exists()
    again = run(tmp_path / "killed", "--resume")
    said, err = again.communicate(timeout=600)
    assert again.returncode == 0, err.decode()[-2000:]
    assert "resuming:" in said.decode()
    assert (json.loads((tmp_path / "killed" / "diagnosis.json").read_text())
            == json.loads((tmp_path / "straight" / "diagnosis.json").read_text()))


def test_the_per_visit_pass_is_kept_and_read_back(tmp_path, monkeypatch):
    """On a pair with visit layers, the per-visit pass of the hardening test is kept with the
    others: a diagnosis run again does not fit the visits again, and tests the same."""
    from types import SimpleNamespace

    from tests.estimate.test_visits import two_visit_pair
    from torchsoil.diagnosis import phases as run_module
    from torchsoil.settings import Settings

    pair = TerrainPair.from_mapping(two_visit_pair(seed=4, d1=0.02, length=4.0, once=3.0)[0])
    st, calls = Settings(), []
    original = run_module.run_visits
    monkeypatch.setattr(run_module, "run_visits", lambda *a, **k: calls.append(1) or original(*a, **k))
    base = SimpleNamespace(nuisance=None, index=None)
    first = run_module._revisit(pair, st.diagnosis, st.estimator, st.sim, base, 2,
                                cache=PassCache(tmp_path / "p", {"i": 1}))
    again = run_module._revisit(pair, st.diagnosis, st.estimator, st.sim, base, 2,
                                cache=PassCache(tmp_path / "p", {"i": 1}))
    assert len(calls) == 1 and first[1] is not None
    assert json.dumps(again, default=str) == json.dumps(first, default=str)

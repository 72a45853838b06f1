"""A diagnosis's independent passes run as tasks of a process pool (diagnosis.parallel): the
diagnosis then reads them back and ends with the results of one run in one process, having run
only its own first section score and the base pass itself; a task that fails costs only time."""

import pytest

from torchsoil.diagnosis import DiagnosisConfig, diagnose
from torchsoil.diagnosis import fit as fit_module
from torchsoil.diagnosis.checkpoint import PassCache
from torchsoil.diagnosis.parallel import PassPool, pass_pool
from torchsoil.diagnosis.study_cases import scenario
from torchsoil.engines import Outcome
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.synth.scenario import make_terrain_pair

CFG = DiagnosisConfig(n_fit=2, sections=((0.3, 1.0), (0.0, 0.5)), dig_orders=("robot", "wheel"), refine_steps=1,
                      learned=False)


@pytest.fixture(scope="module")
def short_drive():
    sc = scenario("speed_dependent_sinkage")
    sc["trajectory"] = {"segments": [{"straight": 3.0, "speed": 1.3}, {"straight": 3.0, "speed": 0.6}]}
    return TerrainPair.from_mapping(make_terrain_pair(sc, seed=3))


@pytest.fixture(scope="module")
def straight(short_drive):
    return diagnose(short_drive, CFG).summary


def count_runs(monkeypatch) -> list:
    runs = []
    original = fit_module.Estimator.run
    monkeypatch.setattr(fit_module.Estimator, "run", lambda self, *a, **k: runs.append(1) or original(self, *a, **k))
    return runs


def test_passes_on_two_workers_give_the_one_process_results(tmp_path, short_drive, straight, monkeypatch):
    runs = count_runs(monkeypatch)          # in this process only: the workers are spawned afresh
    cache = PassCache(tmp_path / "passes", {"input": "short"})
    with pass_pool(2, "local", cache) as pool:
        got = diagnose(short_drive, CFG, cache=cache, pool=pool).summary
        assert not pool.failed
    assert got == straight
    assert len(straight["candidates"]) == 2
    assert len(runs) == 2                    # the pair's own section score and the base pass
    assert len(cache) >= 2 + 3 + 3 * 2       # base, 3 sections, their 2 dig orders' scores, candidate passes
    assert not list((tmp_path / "passes").glob("pool-*"))      # the shared state is removed after


class FailingEngine:
    """An engine whose every task fails, as a worker killed or out of memory would."""

    def imap(self, fn, calls, requests=None):
        for i, _ in enumerate(calls):
            yield i, Outcome(error="WorkerDied: the worker process died while running this task")


def test_failed_tasks_are_run_here_instead(tmp_path, short_drive, straight, capsys):
    cache = PassCache(tmp_path / "passes", {"input": "short"})
    pool = PassPool(FailingEngine(), cache)
    assert diagnose(short_drive, CFG, cache=cache, pool=pool).summary == straight
    assert pool.failed and "run here instead" in capsys.readouterr().err


def test_a_pool_needs_a_cache_to_keep_its_passes_in():
    with pytest.raises(ValueError, match="PassCache"), pass_pool(2, "local", None):
        pass


@pytest.mark.long
def test_the_per_visit_pass_runs_on_the_pool_beside_the_candidates(tmp_path, monkeypatch):
    """On a pair with visit layers the hardening test's per-visit pass is a task of the pool too:
    the diagnosis reads it back instead of fitting the visits itself, and tests the same."""
    from tests.estimate.test_visits import two_visit_pair
    from torchsoil.diagnosis import phases as run_module

    pair = TerrainPair.from_mapping(two_visit_pair(seed=4, d1=0.02, length=4.0, once=3.0)[0])
    cfg = DiagnosisConfig(n_fit=1, sections=(), dig_orders=(), refine_steps=1, learned=False)
    here = []
    original = run_module.run_visits
    monkeypatch.setattr(run_module, "run_visits", lambda *a, **k: here.append(1) or original(*a, **k))
    cache = PassCache(tmp_path / "passes", {"input": "two visits"})
    with pass_pool(2, "local", cache) as pool:
        pooled = diagnose(pair, cfg, cache=cache, pool=pool)
        assert not pool.failed
    assert not here                                       # read back, not fitted in this process
    assert pooled.revisits is not None and list((tmp_path / "passes").glob("visits-*.pkl"))
    alone = diagnose(pair, cfg)
    assert here and pooled.summary == alone.summary
    assert pooled.revisits["z"] == alone.revisits["z"]

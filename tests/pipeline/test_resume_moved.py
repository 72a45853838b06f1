"""A checkpoint written before a module moved (its pickle names a class at an old import path)
is not resumed from: the run starts afresh, it does not crash. The same for a diagnosis's kept
passes, which are recomputed."""

import pickle

import numpy as np

from torchsoil.diagnosis.checkpoint import PassCache, kept
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.pipeline.resume import FORMAT, Checkpoints


def _pickled_at(value, module: str, moved_to: str) -> bytes:
    """value pickled (protocol 2: class paths as text) as if its class lived in `moved_to`, the
    module it was in before a move."""
    data = pickle.dumps(value, protocol=2)
    assert f"c{module}\n".encode() in data
    return data.replace(f"c{module}\n".encode(), f"c{moved_to}\n".encode())


def _pair() -> TerrainPair:
    h = np.zeros((4, 5), np.float32)
    poses = np.zeros((2, 7))
    return TerrainPair(0.02, np.zeros(2), h, h, poses, np.zeros((2, 3)), 0.1)


def test_the_pickle_helper_really_points_at_a_module_that_is_gone():
    data = _pickled_at(_pair(), "torchsoil.io.terrain_pair", "torchsoil.terrain")
    try:
        pickle.loads(data)
    except ModuleNotFoundError as e:
        assert "torchsoil.terrain" in str(e)
    else:
        raise AssertionError("the old module path should not import")


def test_a_pipeline_checkpoint_of_a_moved_class_starts_afresh(tmp_path):
    key = ("bag", "settings")
    cps = Checkpoints(tmp_path / "checkpoint", None, every=0, key=key)
    step = tmp_path / "checkpoint" / "1"
    step.mkdir(parents=True)
    state = {"format": FORMAT, "key": key, "taken": 3, "online": _pair()}
    (step / "state.pkl").write_bytes(_pickled_at(state, "torchsoil.io.terrain_pair", "torchsoil.terrain"))
    (tmp_path / "checkpoint" / "latest").write_text("1")
    assert cps.load() is None
    assert cps.resumed is None


def test_a_kept_pass_of_a_moved_class_is_recomputed(tmp_path):
    cache = PassCache(tmp_path / "passes", {"k": 1})
    what = ("base", 0.8)
    cache.save(what[0], what, "placeholder")
    path = next((tmp_path / "passes").glob("base-*.pkl"))
    path.write_bytes(_pickled_at((repr(what), _pair()), "torchsoil.io.terrain_pair", "torchsoil.terrain"))
    assert cache.load(what[0], what) is None
    calls = []
    assert kept(cache, what[0], what, lambda: calls.append(1) or "again") == "again"
    assert calls == [1]
    assert cache.load(what[0], what) == "again"

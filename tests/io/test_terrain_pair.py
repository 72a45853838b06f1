"""Terrain pair: round trip and validation errors."""

import numpy as np
import pytest

from torchsoil.io.terrain_pair import TerrainPair


def pair(**over):
    rng = np.random.default_rng(0)
    d = dict(dx=0.02, origin=np.array([1.0, -2.0]),
             h_front=rng.normal(size=(5, 4)).astype(np.float32),
             h_back=rng.normal(size=(5, 4)).astype(np.float32),
             poses=np.column_stack([np.arange(3.0), rng.normal(size=(3, 6))]),
             wheels=np.array([[0.7, 0.5, 0], [0.7, -0.5, 1]]), wheel_width=0.14)
    d.update(over)
    return d


def test_round_trip_keeps_every_key(tmp_path):
    d = pair()
    d["h_front"][1, 2] = np.nan
    tp = TerrainPair.from_mapping(d)
    tp.extras["valid_front"] = np.isfinite(d["h_front"])
    path = tp.save(tmp_path / "sub" / "pair.npz")
    back = TerrainPair.load(path)
    for k in ("origin", "poses", "wheels"):
        np.testing.assert_array_equal(getattr(back, k), d[k])
    np.testing.assert_array_equal(back.h_front, d["h_front"])
    np.testing.assert_array_equal(back.extras["valid_front"], np.isfinite(d["h_front"]))
    assert back.dx == 0.02 and back.wheel_flat_fraction == 0.0
    assert back.grid.shape == (5, 4)
    np.testing.assert_allclose(back.h_delta, d["h_back"] - d["h_front"])
    assert list(tmp_path.joinpath("sub").iterdir()) == [path]  # no temporary left behind


@pytest.mark.parametrize("key, value, words", [
    ("h_back", np.zeros((4, 4), np.float32), "h_back"),
    ("poses", np.zeros((3, 6)), "poses"),
    ("dx", -1.0, "dx"),
    ("origin", np.zeros(3), "origin"),
    ("h_front", np.full((5, 4), np.inf, np.float32), "infinite"),
    ("wheels", np.zeros((2, 2)), "wheels"),
])
def test_bad_values_name_the_key(key, value, words):
    with pytest.raises(ValueError, match=words):
        TerrainPair.from_mapping(pair(**{key: value}), source="x.npz")


def test_time_going_backwards_names_the_row():
    d = pair()
    d["poses"][2, 0] = -1.0
    with pytest.raises(ValueError, match="row 2"):
        TerrainPair.from_mapping(d)


def test_missing_key_is_listed(tmp_path):
    d = pair()
    del d["wheels"]
    np.savez(tmp_path / "p.npz", **d)
    with pytest.raises(ValueError, match=r"p\.npz.*wheels"):
        TerrainPair.load(tmp_path / "p.npz")


def test_corrupt_and_missing_files(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        TerrainPair.load(bad)
    with pytest.raises(FileNotFoundError, match="nope.npz"):
        TerrainPair.load(tmp_path / "nope.npz")


def visits(n=2, shape=(5, 4)):
    rng = np.random.default_rng(1)
    layers = {k: rng.normal(size=(n, *shape)).astype(np.float32) for k in ("visit_front", "visit_back")}
    layers["visit_time"] = np.stack([np.full(shape, 10.0 * v, np.float32) for v in range(n)])
    layers["visit_front"][1, 0, 0] = np.nan                   # a cell with one visit
    return layers


def test_visit_layers_round_trip(tmp_path):
    layers = visits()
    back = TerrainPair.load(TerrainPair.from_mapping(pair(**layers)).save(tmp_path / "pair.npz"))
    assert back.n_visits == 2 and not back.extras
    for k, v in layers.items():
        np.testing.assert_array_equal(getattr(back, k), v)
        assert getattr(back, k).dtype == np.float32


def test_a_pair_without_visit_layers_has_one_visit(tmp_path):
    back = TerrainPair.load(TerrainPair.from_mapping(pair()).save(tmp_path / "pair.npz"))
    assert back.n_visits == 1 and back.visit_front is None and back.visit_time is None
    with np.load(tmp_path / "pair.npz") as f:
        assert "visit_front" not in f.files


@pytest.mark.parametrize("change, words", [
    (dict(visit_back=np.zeros((3, 5, 4), np.float32)), r"visit_back' shape \(3, 5, 4\) differs"),
    (dict(visit_time=np.zeros((2, 4, 4), np.float32)), r"visit_time' must be \(V, X, Y\) with \(X, Y\) = h_front's"),
    (dict(visit_front=np.zeros((5, 4), np.float32)), r"visit_front' must be \(V, X, Y\)"),
    (dict(visit_front=np.zeros((2, 5, 4), np.int32)), "floating-point"),
    (dict(visit_back=np.full((2, 5, 4), np.inf, np.float32)), "infinite"),
    (dict(visit_time=None), "visit_time' is missing"),
])
def test_bad_visit_layers_name_the_key(change, words):
    layers = {**visits(), **change}
    layers = {k: v for k, v in layers.items() if v is not None}
    with pytest.raises(ValueError, match=words):
        TerrainPair.from_mapping(pair(**layers), source="x.npz")

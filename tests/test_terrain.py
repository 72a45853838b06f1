"""Terrain pair: round trip and validation errors."""

import numpy as np
import pytest

from torchsoil.terrain import TerrainPair


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

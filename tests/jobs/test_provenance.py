"""Outputs know what made them: a folder, a resume or a cached terrain of another run is
never silently reused."""

import json
import shutil

import numpy as np
import pytest

from tests.pipeline.toyscene import ToyScene
from tests.synthetic_pair import sim_pair
from torchsoil.jobs import provenance
from torchsoil.jobs.common import load_input
from torchsoil.jobs.estimate import estimate
from torchsoil.jobs.provenance import OutputMismatch, claim, input_identity
from torchsoil.robot import paper_platform
from torchsoil.settings import PipelineConfig, load_settings


def test_identity_follows_content_not_place(tmp_path):
    a = tmp_path / "a.npz"
    a.write_bytes(b"x" * 5000)
    moved = tmp_path / "sub" / "a.npz"
    moved.parent.mkdir()
    shutil.copy(a, moved)
    assert input_identity(a)["key"] == input_identity(moved)["key"]
    assert input_identity(a)["path"] != input_identity(moved)["path"]
    moved.write_bytes(b"x" * 4999 + b"y")
    assert input_identity(a)["key"] != input_identity(moved)["key"]
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("m")
    (bag / "bag_0.mcap").write_bytes(b"\0" * (3 << 20))
    ident = input_identity(bag)
    assert ident["size"] == (3 << 20) + 1
    (bag / "bag_0.mcap").write_bytes(b"\0" * (3 << 20 - 1) + b"\1")  # one byte at the end differs
    assert input_identity(bag)["key"] != ident["key"]
    with pytest.raises(FileNotFoundError):
        input_identity(tmp_path / "missing.bag")


def _record(tmp_path, name, content, window=0.8):
    src = tmp_path / name
    src.write_bytes(content)
    return provenance.run_record(src, {"estimator": {"window": window}}, None, "estimate")


def test_claim_refuses_another_run_and_overwrite_clears_it(tmp_path):
    out = tmp_path / "out"
    first = _record(tmp_path, "a.npz", b"first")
    claim(out, first, outputs=("params.csv",))
    (out / "params.csv").write_text("s\n1\n")
    claim(out, first, outputs=("params.csv",))                     # the same run again: fine
    claim(out, first, resume=True, outputs=("params.csv",))        # and its resume
    other = _record(tmp_path, "b.npz", b"second")
    with pytest.raises(OutputMismatch, match="another recording"):
        claim(out, other, outputs=("params.csv",))
    with pytest.raises(OutputMismatch, match=r"settings differ \(estimator.window\)"):
        claim(out, _record(tmp_path, "a.npz", b"first", window=1.0), resume=True, outputs=("params.csv",))
    assert (out / "params.csv").exists()                           # nothing lost by a refusal
    claim(out, other, overwrite=True, outputs=("params.csv",))
    assert not (out / "params.csv").exists()
    assert json.loads((out / "run.json").read_text())["input"]["key"] == other["input"]["key"]


def test_claim_refuses_outputs_of_unknown_origin(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "params.csv").write_text("s\n")
    rec = _record(tmp_path, "a.npz", b"a")
    with pytest.raises(OutputMismatch, match="without a run.json"):
        claim(out, rec, outputs=("params.csv",))
    with pytest.raises(OutputMismatch, match="no run.json to resume"):
        claim(tmp_path / "fresh", rec, resume=True)


def test_two_pairs_into_one_out_never_mix(tmp_path):
    for seed in (0, 1):
        sim_pair(length=2.0, seed=seed)[0].save(tmp_path / f"p{seed}.npz")
    settings = load_settings(overrides=["estimator.max_iter=3"])
    out = estimate(tmp_path / "p0.npz", tmp_path / "run", settings, tensorboard=False, progress=False)
    before = (out / "params.csv").read_text()
    with pytest.raises(OutputMismatch, match="p0.npz"):
        estimate(tmp_path / "p1.npz", out, settings, tensorboard=False, progress=False)
    assert (out / "params.csv").read_text() == before
    estimate(tmp_path / "p1.npz", out, settings, overwrite=True, tensorboard=False, progress=False)
    meta = json.loads((out / "run.json").read_text())
    assert meta["input"]["key"] == input_identity(tmp_path / "p1.npz")["key"]
    assert (out / "params.csv").read_text() != before


def test_cached_terrain_of_another_bag_is_recomputed(tmp_path):
    """The cached terrain pair of a bag is reused only for that bag and pipeline settings."""
    robot = paper_platform()
    bags = {}
    for name, depth in (("shallow", 0.0), ("deep", 0.04)):
        bags[name] = tmp_path / name
        ToyScene(columns=128, rut_depth=depth, noise=0.002).write(bags[name], 2.5)
    out = tmp_path / "out"
    out.mkdir()
    pipe = PipelineConfig()
    keys = {n: provenance.cache_key(provenance.run_record(b, {"pipeline": pipe.model_dump(mode="json")},
                                                          robot.to_dict(), "estimate"), "pipeline")
            for n, b in bags.items()}
    shallow = load_input(bags["shallow"], out, robot, pipe, keys["shallow"])
    deep = load_input(bags["deep"], out, robot, pipe, keys["deep"])
    assert not np.allclose(np.nan_to_num(shallow.h_back), np.nan_to_num(deep.h_back))
    again = load_input(bags["deep"], out, robot, pipe, keys["deep"])         # now from the cache
    np.testing.assert_array_equal(again.h_back, deep.h_back)
    assert provenance.cache_valid(out / "terrain_pair.npz", keys["deep"])
    assert not provenance.cache_valid(out / "terrain_pair.npz", keys["shallow"])

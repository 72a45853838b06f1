"""The command lines, run as a user would."""

import subprocess
import sys
from pathlib import Path

from tests.synthetic_pair import sim_pair

ROOT = Path(__file__).resolve().parent.parent


def run(*args, cwd=ROOT):
    return subprocess.run([sys.executable, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=600)


def test_estimate_cli_on_a_terrain_pair(tmp_path):
    pair, _ = sim_pair(length=2.0)
    src = tmp_path / "pair.npz"
    pair.save(src)
    out = tmp_path / "run"
    r = run("scripts/estimate.py", src, "--out", out, "--no-tensorboard", "--set", "estimator.max_iter=8")
    assert r.returncode == 0, r.stderr
    assert "noise floor" in r.stdout
    header = (out / "params.csv").read_text().splitlines()[0]
    assert header == ("s,visit,passes_before,t,x,y,d1,d2,chi,beta,map_offset,rut_depth,residual,prediction,"
                      "iterations,seconds,latency,flags")   # the columns docs/formats.md section 5 names


def test_estimate_cli_bad_input(tmp_path):
    r = run("scripts/estimate.py", tmp_path / "missing.npz", "--out", tmp_path / "o")
    assert r.returncode == 2 and "missing.npz" in r.stderr
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    r = run("scripts/estimate.py", bad, "--out", tmp_path / "o")
    assert r.returncode == 2 and "bad.npz" in r.stderr and "Traceback" not in r.stderr
    r = run("scripts/estimate.py", bad, "--out", tmp_path / "o", "--set", "estimator.nope=1")
    assert r.returncode == 2 and "estimator.nope" in r.stderr


def test_bench_cli_writes_json(tmp_path):
    r = run("scripts/bench.py", "--only", "sim", "--quick", "--out", tmp_path)
    assert r.returncode == 0, r.stderr
    import json

    figures = json.loads((tmp_path / "bench.json").read_text())
    assert figures["sim_forward_ms_dx0.02_b5"] > 0

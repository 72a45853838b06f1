"""A `process-bag` killed with SIGKILL mid-run and restarted with `--resume` ends with the
outputs of a run straight through, from its last checkpoint rather than from the start."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "data" / "demo"
SETS = ["--set", "pipeline.raster.max_range=8", "--set", "pipeline.checkpoint_s=1"]   # tiles spill on 21 m


def _process_bag(out: Path, *extra: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "torchsoil", "process-bag", str(DEMO / "demo"), "--robot",
                             str(DEMO / "demo.robot.yaml"), "--out", str(out), *SETS, *extra],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def test_a_killed_process_bag_resumes_to_the_straight_run(tmp_path):
    straight = _process_bag(tmp_path / "straight")
    assert straight.wait(timeout=600) == 0, straight.stderr.read().decode()[-2000:]
    out = tmp_path / "killed"
    run = _process_bag(out)
    latest = out / "checkpoint" / "latest"

    def spilled():                 # the newest checkpoint holds tiles spilled to disk
        try:
            return any((out / "checkpoint" / latest.read_text() / "spill").rglob("*.npy"))
        except OSError:
            return False

    while run.poll() is None and not spilled():
        time.sleep(0.02)
    assert run.poll() is None, "the run ended before a checkpoint with spilled tiles could be resumed from"
    run.send_signal(signal.SIGKILL)
    run.wait()
    again = _process_bag(out, "--resume")
    err = again.communicate(timeout=600)[1].decode()
    assert again.returncode == 0, err[-2000:]
    assert "no checkpoint" not in err and "resumed from the checkpoint taken after" in err
    a, b = np.load(tmp_path / "straight" / "terrain.npz"), np.load(out / "terrain.npz")
    assert sorted(a.files) == sorted(b.files)
    for key in a.files:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert (out / "trajectory.csv").read_text() == (tmp_path / "straight" / "trajectory.csv").read_text()
    assert not (out / "checkpoint").exists() and not (out / "tiles").exists()      # removed once done

"""The bench's peak-memory figures come from a process that forked from something small."""

import os
import subprocess
import sys

import numpy as np
import pytest

from torchsoil.bench._memory import command_peak_mb

SMALL = [sys.executable, "-c", "import numpy as np; a = np.ones(50 * 2**20 // 8); print(a.sum())"]  # ~50 MB


def _hwm_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 1024


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="Linux /proc")
def test_a_big_parent_does_not_pass_its_size_on():
    big = np.ones(1024 * 2**20 // 8)           # 1 GiB, touched
    assert _hwm_mb() > 1024
    proc = subprocess.Popen(SMALL, stdout=subprocess.DEVNULL)
    _, _, usage = os.wait4(proc.pid, 0)
    inherited = usage.ru_maxrss / 1024
    assert inherited > 1000                    # the old measurement: the parent's size
    peak = command_peak_mb(SMALL)
    assert 50 <= peak < 300, peak              # the child's own: ~50 MB of array + the interpreter
    del big


def test_a_failing_command_says_so():
    with pytest.raises(RuntimeError, match="exit 3"):
        command_peak_mb([sys.executable, "-c", "import sys; print('boom', file=sys.stderr); sys.exit(3)"])

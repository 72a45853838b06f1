"""Task functions for the engine tests (tests/jobs/test_fleet.py), in a module that a worker can import
by name (a spawned process pool's or a Ray worker's)."""

import os
import signal
from pathlib import Path


def value_or_kill(k: int) -> int:
    """10 k; task 1 kills its own worker process."""
    if k == 1:
        os.kill(os.getpid(), signal.SIGKILL)
    return 10 * k


def kill_first_time(marker: str) -> str:
    """Kills its worker the first time (leaving `marker`), returns the second time."""
    if not Path(marker).exists():
        Path(marker).touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return "second try"


def where() -> str:
    """The file of the torchsoil package the worker imported."""
    import torchsoil

    return torchsoil.__file__


def stamp(path: str, seconds: float) -> tuple[float, float]:
    """Sleeps `seconds`; returns (start, end) wall clock times [s] (time.time)."""
    import time

    t0 = time.time()
    time.sleep(seconds)
    return t0, time.time()

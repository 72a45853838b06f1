"""Peak resident memory of a command, measured from a small launcher.

On Linux a child's `ru_maxrss` (`os.wait4`, `getrusage`) starts from the resident size of the
process it was forked from: the high-water mark survives fork and exec. A benchmark process that
has just generated a long recording in its own memory would pass its size on to every command it
starts (a 1-minute `torchsoil estimate` measured so came out 1,328 MB, the bench's own size, where
`/usr/bin/time -v` gives 622 MB). The command therefore runs as the child of a launcher that is
itself small (`python -S` running `LAUNCHER`), which reports the command's `ru_maxrss`.
"""

from __future__ import annotations

import subprocess
import sys

# argv: the command. Its stdout goes to /dev/null, its stderr is the launcher's; the launcher
# prints "<ru_maxrss kB> <exit status>" and exits with the command's status.
LAUNCHER = """import os, sys
pid = os.fork()
if pid == 0:
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    try:
        os.execvp(sys.argv[1], sys.argv[1:])
    finally:
        os._exit(127)
_, status, usage = os.wait4(pid, 0)
code = os.waitstatus_to_exitcode(status)
print(usage.ru_maxrss, code, flush=True)
sys.exit(min(abs(code), 255))
"""


def command_peak_mb(argv: list[str]) -> float:
    """Peak resident memory [MB] of the command `argv` (its own process and the largest of the
    children it waited for), started by a small launcher; RuntimeError with the end of its
    stderr when it fails."""
    out = subprocess.run([sys.executable, "-S", "-c", LAUNCHER, *argv], capture_output=True, text=True)
    lines = out.stdout.strip().splitlines()
    if out.returncode != 0 or not lines:
        raise RuntimeError(f"{' '.join(argv)} failed (exit {out.returncode}): {out.stderr[-2000:]}")
    return int(lines[-1].split()[0]) / 1024.0


def peak_rss_mb(args: list[str]) -> float:
    """Peak resident memory [MB] of `python -m torchsoil ARGS` (`command_peak_mb`)."""
    return command_peak_mb([sys.executable, "-m", "torchsoil", *args])

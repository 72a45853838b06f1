"""Resident memory of long runs.

glibc serves large allocations with mmap and returns them to the system when freed, but it
raises its mmap threshold to the size of each mmapped block freed (up to 32 MB): after the
first whole-drive array is freed, arrays of that size come from the heap, where freed blocks
between live ones stay resident. A run that builds whole-drive maps (a diagnosis's estimator
setup, the end of a streamed estimate) then holds about twice what it uses: on a 200 m drive
the path index's 63 MB of arrays kept 129 MB resident, smoothing H_f's 14 MB kept 53 MB.
`release` hands the free pages back (glibc's malloc_trim) after such a step. Fixing the mmap
threshold instead (mallopt) does the same for every allocation but costs a page fault per
4 kB on every sweep's and window's arrays: 2.6 to 10 times the system time of a run.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _libc():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc if hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


def release() -> bool:
    """Give the free pages of the heap back to the system (after whole-drive arrays were freed);
    False where the C library is not glibc (nothing done)."""
    libc = _libc()
    return bool(libc is not None and libc.malloc_trim(0))

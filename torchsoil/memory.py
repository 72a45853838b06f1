"""Resident memory of long runs.

glibc serves large allocations with mmap and returns them to the system when freed, but it
raises its mmap threshold to the size of each mmapped block freed (up to 32 MB): after the
first whole-drive array is freed, arrays of that size come from the heap, where freed blocks
between live ones are not returned. A run that builds whole-drive maps again and again (a
diagnosis's passes, the end of a streamed estimate) then holds about twice what it uses: on a
200 m drive the path index's 63 MB of arrays kept 129 MB resident, smoothing H_f's 14 MB kept
53 MB. `bound_heap` fixes the threshold at 1 MB, so that every block of that size or more is
mmapped and given back when freed, and the heap's trim threshold at 32 MB (fixing one stops
glibc moving the other, and at its 128 kB default the heap grows and shrinks with every
window: 5 times the system time of a diagnosis).
"""

from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3   # glibc's mallopt parameters


def bound_heap(threshold: int = 1 << 20, trim: int = 32 << 20) -> bool:
    """Fix glibc's mmap threshold at `threshold` bytes for this process (allocations from
    then on); False where the C library is not glibc (nothing changed)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        return bool(libc.mallopt(M_MMAP_THRESHOLD, int(threshold)) and libc.mallopt(M_TRIM_THRESHOLD, int(trim)))
    except (OSError, AttributeError):
        return False

"""Bounded memory of the streamed estimate: the simulated change stitched tile by tile (far tiles
on disk) equals the stitching of every window's piece over one array."""

import numpy as np

from torchsoil.estimate.tiles import SimTiles


def _pieces(rng, n=40):
    out = []
    for k in range(n):   # windows along +x, overlapping, with cells off their ground (inf)
        i0, j0 = 37 * k - 50, int(rng.integers(-80, -60))
        shape = (int(rng.integers(60, 140)), int(rng.integers(100, 170)))
        dist = rng.uniform(0, 2, shape).astype(np.float32)
        dist[rng.uniform(size=shape) < 0.2] = np.inf
        out.append((i0, j0, rng.normal(0, 0.01, shape).astype(np.float32), dist))
    return out


def test_stitched_tiles_spilled_to_disk_equal_one_array(tmp_path):
    pieces = _pieces(np.random.default_rng(0))
    i0, i1 = min(p[0] for p in pieces), max(p[0] + p[2].shape[0] for p in pieces)
    j0, j1 = min(p[1] for p in pieces), max(p[1] + p[2].shape[1] for p in pieces)
    h, best = np.full((i1 - i0, j1 - j0), np.nan, np.float32), np.full((i1 - i0, j1 - j0), np.inf, np.float32)
    for a, b, change, dist in pieces:   # nearest window centre wins, the first on a tie
        view = (slice(a - i0, a - i0 + change.shape[0]), slice(b - j0, b - j0 + change.shape[1]))
        take = dist < best[view]
        best[view][take], h[view][take] = dist[take], change[take]
    held, spilled = SimTiles(), SimTiles(tmp_path, size=32, keep=2)
    for p in pieces:
        held.add(*p)
        spilled.add(*p)
    assert spilled.spilled and len(spilled.tiles) < len(held.tiles)   # far tiles left memory
    np.testing.assert_array_equal(held.region(i0, i1, j0, j1), h)
    np.testing.assert_array_equal(spilled.region(i0, i1, j0, j1), h)
    np.testing.assert_array_equal(spilled.region(i0 + 5, i1 - 7, j0 + 3, j1 + 9)[:, :-9], h[5:-7, 3:])


def test_a_full_disk_stops_with_a_clear_error_and_keeps_the_rows(tmp_path, monkeypatch, capsys):
    """ENOSPC while a row is written (os.fsync made to fail as a full disk does): the CLI says so
    in one line, exit status 2, and params.csv holds whole rows only, readable by --resume."""
    import errno
    import os

    from torchsoil import cli
    from torchsoil.estimate.outputs import CsvLog, DiskFull

    log = CsvLog(tmp_path / "p.csv", ["s", "flags"], resume=False)
    log.append({"s": 0.5, "flags": ""})
    real, calls = os.fsync, []

    def full(fd):
        calls.append(fd)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    try:
        log.append({"s": 1.0, "flags": "x"})
    except DiskFull as e:
        assert "no space left" in str(e) and "--resume" in str(e)
    else:
        raise AssertionError("no DiskFull")
    monkeypatch.setattr(os, "fsync", real)
    assert calls and CsvLog(tmp_path / "p.csv", ["s", "flags"], resume=True).rows == [{"s": 0.5, "flags": ""}]

    def estimate(args):
        raise DiskFull(tmp_path / "p.csv")

    monkeypatch.setitem(cli.COMMANDS, "estimate", estimate)
    assert cli.main(["estimate", "x.npz"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no space left on the device writing") and len(err.splitlines()) == 1


def test_a_long_map_is_drawn_from_block_means():
    """figures.coarse on a 5 x 3 map with at most 2 cells a side: 3 x 3 blocks (f 3), NaN cells
    left out, a block of NaN only stays NaN; coarse_extent covers the padded blocks."""
    from torchsoil.plotting import coarse, coarse_extent

    img = np.array([[1, 2, 3], [4, 5, 6], [7, 8, np.nan], [10, 11, 12], [np.nan, np.nan, np.nan]], np.float32)
    out, f = coarse(img, max_cells=2)
    assert f == 3 and out.shape == (2, 1)
    assert out[0, 0] == (1 + 2 + 3 + 4 + 5 + 6 + 7 + 8) / 8 and out[1, 0] == (10 + 11 + 12) / 3
    assert coarse(img, max_cells=5) == (img, 1)
    assert np.isnan(coarse(np.full((4, 4), np.nan), max_cells=2)[0]).all()
    assert coarse_extent((1.0, -2.0), 0.1, (5, 3), 3) == (0.95, 0.95 + 6 * 0.1, -2.05, -2.05 + 3 * 0.1)


def test_a_window_store_over_its_memory_budget_reads_windows_back_from_disk():
    """With room for two 1 kB windows in memory, the third goes to disk: asked again, the same
    tensors come back without preparing it anew, and memory holds the first two only."""
    import torch

    from torchsoil.estimate.windows import WindowStore

    store, made = WindowStore(max_bytes=2048), []

    def window(key):
        made.append(key)
        return torch.full((64,), float(key), dtype=torch.float64), (torch.arange(128, dtype=torch.int32) + key,)

    for key in (1, 2, 3, 3, 1):
        got = store.get(key, lambda k=key: window(k))
        assert torch.equal(got[0], torch.full((64,), float(key), dtype=torch.float64))
        assert torch.equal(got[1][0], torch.arange(128, dtype=torch.int32) + key)
    assert made == [1, 2, 3] and len(store) == 3 and store.nbytes == 2048 and store.spilled_bytes == 1024


_HEAP = """
import sys
import numpy as np
from torchsoil.memory import release
def rss():
    return next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmRSS")) / 1024
np.ones(2 << 20)                                   # a 16 MB block, mmapped and freed
keep, gone = [], []
for k in range(12):                                # 16 MB maps with small live objects between them
    (gone if k % 2 else keep).append(np.ones(2 << 20))
    keep.append(np.ones(100))
before = rss()
gone.clear()
if sys.argv[1] == "release":
    assert release()
print(before - rss())
"""


def test_whole_drive_arrays_are_given_back_once_released(tmp_path):
    """Six of twelve 16 MB arrays freed, after one of that size had been (glibc then serves that
    size from the heap, between live blocks): memory.release gives the 96 MB back; without it
    they stay resident."""
    import subprocess
    import sys

    script = tmp_path / "heap.py"
    script.write_text(_HEAP)
    freed = {mode: float(subprocess.run([sys.executable, str(script), mode], capture_output=True, text=True,
                                        check=True).stdout) for mode in ("release", "default")}
    assert freed["release"] > 80, freed
    assert freed["default"] < 40, freed           # what it is for (glibc's own behaviour)

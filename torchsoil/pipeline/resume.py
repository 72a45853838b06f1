"""Checkpoints of the streaming pipeline, so that a `process-bag` killed midway resumes.

Every `pipeline.checkpoint_s` seconds the pipeline's whole state (`OnlinePipeline`: the map,
trajectory, sweeps in flight, tiles in memory, visit tracker) is pickled together with how
many of the recording's items (sweeps and IMU samples, in bag order) it has taken, and the
tiles spilled to disk so far are kept as hard links (a spilled tile is replaced, never written
in place: `raster.spill_far`), so the checkpoint sees them as they were. A resumed run restores
the spilled tiles, reads the recording again from its start, skips the items already taken
and goes on: its outputs are those of a run straight through, and it loses at most the work
since the last checkpoint.

Layout: DIR/<n>/state.pkl and DIR/<n>/spill/ (the tiles), DIR/latest naming the newest <n>;
`latest` is replaced last, so a kill while a checkpoint is written leaves the one before.
"""

from __future__ import annotations

import os
import pickle
import shutil
import time
from pathlib import Path

FORMAT = 1

# What unpickling a file another version of torchsoil wrote may raise: a class that moved to
# another module (ImportError, ModuleNotFoundError) or was renamed (AttributeError), one whose
# fields changed (TypeError, ValueError), a file cut short (EOFError, UnpicklingError). Such a
# file is not resumed from: its work is done again.
UNREADABLE = (OSError, EOFError, pickle.UnpicklingError, AttributeError, ImportError, TypeError, ValueError)


def _link_tree(src: Path, dst: Path) -> None:
    """Hard-link every file under src into dst (same relative paths; copies across devices)."""
    for root, _, files in os.walk(src):
        target = dst / Path(root).relative_to(src)
        target.mkdir(parents=True, exist_ok=True)
        for name in files:
            if name.endswith(".tmp"):
                continue
            try:
                os.link(Path(root) / name, target / name)
            except OSError:
                shutil.copy2(Path(root) / name, target / name)


class Checkpoints:
    """Pipeline checkpoints in `directory` for a pipeline spilling its tiles to `spill_dir`
    (None: all in memory), taken at most every `every` seconds of wall time. key: what the run
    depends on (recording, robot, settings; any picklable value): a checkpoint taken under
    another key is not resumed from."""

    def __init__(self, directory: str | Path, spill_dir: str | Path | None, every: float = 30.0, key=None):
        self.dir, self.every, self.key = Path(directory), every, key
        self.spill = Path(spill_dir) if spill_dir is not None else None
        self.last = time.monotonic()
        self.n = 0
        self.resumed: int | None = None       # items taken before the checkpoint a run resumed from

    def due(self) -> bool:
        return time.monotonic() - self.last >= self.every

    def save(self, online, taken: int) -> None:
        """Keep `online` (an OnlinePipeline) after it took the recording's first `taken` items."""
        self.n += 1
        step = self.dir / f"{self.n}"
        if step.exists():
            shutil.rmtree(step)
        step.mkdir(parents=True)
        if self.spill is not None and self.spill.exists():
            _link_tree(self.spill, step / "spill")
        with (step / "state.pkl").open("wb") as fh:
            pickle.dump({"format": FORMAT, "key": self.key, "taken": taken, "online": online}, fh,
                        protocol=pickle.HIGHEST_PROTOCOL)
        tmp = self.dir / "latest.tmp"
        tmp.write_text(str(self.n))
        os.replace(tmp, self.dir / "latest")
        for old in self.dir.iterdir():           # the checkpoints before this one
            if old.is_dir() and old.name.isdigit() and int(old.name) != self.n:
                shutil.rmtree(old, ignore_errors=True)
        self.last = time.monotonic()

    def load(self):
        """(OnlinePipeline, items taken) of the newest checkpoint, its spilled tiles put back in
        spill_dir; None when there is none, it is unreadable or was taken under another key
        (start afresh)."""
        latest = self.dir / "latest"
        if not latest.exists():
            return None
        step = self.dir / latest.read_text().strip()
        try:
            with (step / "state.pkl").open("rb") as fh:
                state = pickle.load(fh)
        except UNREADABLE:
            return None
        if state.get("format") != FORMAT or state.get("key") != self.key:
            return None
        if self.spill is not None:
            if self.spill.exists():
                shutil.rmtree(self.spill)
            if (step / "spill").exists():
                _link_tree(step / "spill", self.spill)
        self.n, self.resumed = int(step.name), state["taken"]
        return state["online"], state["taken"]

    def clear(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)

"""Finished work of one diagnosis kept on disk, so that a rerun resumes it.

A diagnosis runs the estimator over the whole drive a score of times (the base model, the tyre
sections and dig orders, every candidate coefficient); over an hour's drive each pass takes
tens of minutes. `PassCache` keeps each finished pass (and each section score) in a folder
of the run's output, under a name that says what it was run with; a diagnosis that finds a
pass there reads it back instead of running it again. The folder carries the key of what
its passes depend on (the input, the robot, the settings, the torchsoil version): under
another key its contents are discarded, not reused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pickle
import shutil
from pathlib import Path

from torchsoil.pipeline.resume import UNREADABLE

KEY_FILE = "key.json"


class PassCache:
    """A folder of finished passes (`fit.Pass`) and other results of one diagnosis.

    directory: where they are kept (created). key: JSON-ready dict of what they depend on
    (`provenance.cache_key` of the run record, with the torchsoil version); a folder holding
    another key is emptied first. every: seconds between two saves of a pass in progress
    (`fit.Partial`; 0: after every window)."""

    def __init__(self, directory: str | Path, key: dict, every: float = 15.0):
        self.dir, self.every = Path(directory), every
        key_text = json.dumps(key, sort_keys=True)
        meta = self.dir / KEY_FILE
        if self.dir.exists() and (not meta.exists() or meta.read_text() != key_text):
            shutil.rmtree(self.dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        meta.write_text(key_text)
        self.hits = 0

    @classmethod
    def open(cls, directory: str | Path, every: float = 15.0) -> PassCache:
        """The cache a diagnosis made in `directory`, as it is (for its parallel passes:
        diagnosis.parallel; its key is neither checked nor written again)."""
        cache = cls.__new__(cls)
        cache.dir, cache.every, cache.hits = Path(directory), every, 0
        if not (cache.dir / KEY_FILE).exists():
            raise FileNotFoundError(f"no diagnosis cache in {directory}")
        return cache

    def _path(self, label: str, what: tuple) -> Path:
        digest = hashlib.sha1(repr(what).encode()).hexdigest()[:16]
        return self.dir / f"{label}-{digest}.pkl"

    def load(self, label: str, what: tuple):
        """What was saved under (label, what), or None. what: a tuple of plain values (numbers,
        strings, tuples) that says what the result was computed with."""
        path = self._path(label, what)
        if not path.exists():
            return None
        try:
            with path.open("rb") as fh:
                stored_what, value = pickle.load(fh)
        except UNREADABLE:
            return None            # unreadable (written by another version, its classes moved): recompute
        if stored_what != repr(what):
            return None
        self.hits += 1
        return value

    def save(self, label: str, what: tuple, value) -> None:
        """Keep value under (label, what); written to a temporary file first, so that an
        interruption leaves the old file or none, never half of one."""
        path = self._path(label, what)
        tmp = path.with_suffix(".tmp")
        with tmp.open("wb") as fh:
            pickle.dump((repr(what), value), fh, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, path)

    def drop(self, label: str, what: tuple) -> None:
        """Forget what was saved under (label, what) (a pass in progress, once it is done)."""
        self._path(label, what).unlink(missing_ok=True)

    def __len__(self) -> int:
        return sum(1 for _ in self.dir.glob("*.pkl"))


def portable(p):
    """A `fit.Pass` without what a later run rebuilds from the pair (its path index, map
    nuisance, window store and surfaces), for `PassCache.save`."""
    return dataclasses.replace(p, index=None, nuisance=None, store=None, surfaces=None)


def kept(cache: PassCache | None, label: str, what: tuple, compute):
    """What `cache` keeps under (label, what), else compute(), then kept there (no cache:
    compute() alone)."""
    value = cache.load(label, what) if cache is not None else None
    if value is None:
        value = compute()
        if cache is not None:
            cache.save(label, what, value)
    return value

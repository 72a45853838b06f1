"""A diagnosis's independent passes on a process pool or a Ray cluster.

Most of a diagnosis is estimator passes that do not depend on each other: the tyre sections and
dig orders scored on the same windows, and every candidate at its first trial coefficients. `PassPool`
runs them ahead of the diagnosis as tasks of a fleet engine (torchsoil.jobs.fleet: `local` process
pools or `ray`), each task keeping its result in the diagnosis's `PassCache`; the diagnosis then
runs as it does in one process and reads them back there. Its results are those of a run in one
process; a task that fails only costs time, as the diagnosis then runs that pass itself.

Each worker loads the pair and the estimator's whole-drive state (path index, map nuisance, view,
smoothed surfaces) once, from files the pool writes beside the cache, and keeps them for its
next tasks.
"""

from __future__ import annotations

import dataclasses
import pickle
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

from torchsoil.diagnosis.checkpoint import PassCache, portable

_LOADED: dict[tuple, tuple] = {}     # in a worker: the files last shared -> their unpickled contents
_WINDOWS: dict[tuple, object] = {}   # in a worker: the files last shared -> the passes' prepared windows


def _load(files: tuple[str, ...]) -> tuple:
    if files not in _LOADED:
        _LOADED.clear()                   # an older state (or another diagnosis's): let it go
        _WINDOWS.clear()
        contents = []
        for path in files:
            with open(path, "rb") as fh:
                contents.append(pickle.load(fh))
        _LOADED[files] = tuple(contents)
    return _LOADED[files]


def _windows(files: tuple[str, ...], shared: dict):
    """In a worker: the prepared windows its passes over the shared state share (a
    windows.WindowStore, as the passes of a diagnosis in one process share the base pass's;
    under every tyre section, `fit.AnySection`), kept for its next tasks on that state."""
    from torchsoil.diagnosis.fit import AnySection
    from torchsoil.estimate.windows import WindowStore

    if files not in _WINDOWS:
        _WINDOWS[files] = AnySection(shared.get("index"), shared.get("surfaces"), WindowStore())
    return _WINDOWS[files]


def _pass_task(files: tuple[str, str], cache_dir: str, every: float, kind: str, args: tuple) -> None:
    """In a worker: one section score (`fit.section_cost`; kind trial_section: under a candidate
    at a trial coefficient, as `fit.candidate_pass` scores it), one candidate pass
    (`fit.candidate_pass`), the rest of one candidate's fit (`fit.fit_extension`), the
    per-visit pass of the hardening test on ground driven again and its pass-by-pass fit
    (`phases.hardening_on_visits`) or one fold of the learned modifier (`learned.fold_task`),
    kept in the cache at cache_dir."""
    from torchsoil.diagnosis import catalogue
    from torchsoil.diagnosis.catalogue import ExtensionModel, PassCounts
    from torchsoil.diagnosis.covariates import DriveSignals
    from torchsoil.diagnosis.fit import candidate_pass, fit_extension, section_cost, with_section

    pair, (shared, base) = _load(tuple(files))
    cache = PassCache.open(cache_dir, every)
    if kind == "section":
        est, sim, sec, every, model = args
        section_cost(pair, est, sim, sec, every, model, shared, cache)
        return
    if kind == "visits":
        from torchsoil.diagnosis.phases import hardening_on_visits

        est, sim, cfg = args
        hardening_on_visits(pair, cfg, est, sim, dataclasses.replace(base, **shared), pair.robot.n_tracks, cache)
        return
    if kind == "trial_section":
        est, sim, section, ext_id, k, sec = args
        pair = with_section(pair, section)
        model = ExtensionModel(catalogue.get(ext_id), k, DriveSignals.from_pair(pair), pair.robot,
                               base.view or "last_visit", sim.dig_order, PassCounts())
        section_cost(pair, est, sim, sec, 3, model, {**shared, "store": None}, cache)
        return
    if kind == "learned":
        from torchsoil.diagnosis.learned import fold_task

        est, sim, section, cfg, fold, stage = args
        base = dataclasses.replace(base, **shared, store=_windows(tuple(files), shared))
        fold_task(with_section(pair, section), est, sim, base, cfg, fold, cache, stage)
        return
    est, sim, section, ext_id, k, offsets, sections, refine_steps, block_m = args
    pair = with_section(pair, section)
    base = dataclasses.replace(base, **shared, store=_windows(tuple(files), shared))
    drive = DriveSignals.from_pair(pair)
    ext = catalogue.get(ext_id)
    if kind == "pass":
        candidate_pass(pair, est, sim, ext, k, drive, base, None, offsets, sections, cache)
    else:
        fit_extension(pair, est, sim, ext, drive, base, block_m, refine_steps, None, None, offsets, sections, cache)


def _warm() -> None:
    """In a worker: import what its tasks need (torch, the simulator's kernels), ahead of them."""
    import torchsoil.diagnosis.phases  # noqa: F401
    import torchsoil.sim.simulate  # noqa: F401


class PassPool:
    """Runs passes of one diagnosis on `engine` (torchsoil.engines.LocalEngine or RayEngine,
    entered), keeping them in `cache` (a PassCache: for a Ray cluster, a folder every node
    reads and writes). progress: optional tqdm-like bar (its postfix tells the tasks done).

    One batch of tasks runs at a time: `run` waits for it, `start` leaves it running in a
    thread of this process (the diagnosis goes on meanwhile; the next `run`, `start` or `wait`
    waits for it first). `warm` starts the workers ahead of the first batch."""

    def __init__(self, engine, cache: PassCache, progress=None):
        self.engine, self.cache, self.progress = engine, cache, progress
        self.files: tuple[str, str] | None = None
        self.shared = 0                   # states shared so far (each in files of its own)
        self.failed: list[str] = []
        self._running: threading.Thread | None = None

    def warm(self, workers: int) -> None:
        """Start `workers` workers now (their imports), in a thread: the diagnosis's first
        passes in this process need not wait for them (local engine only: its workers are kept)."""
        if getattr(self.engine, "name", "") != "local" or workers < 2:
            return
        self.wait()
        self._running = threading.Thread(target=lambda: [None for _ in self.engine.imap(_warm, [()] * workers)],
                                         daemon=True)
        self._running.start()

    def wait(self) -> None:
        """Wait for the batch `start` (or `warm`) left running."""
        if self._running is not None:
            self._running.join()
            self._running = None

    def start(self, kind: str, jobs: list[tuple], others: list[tuple[str, tuple]] = (), after=None) -> None:
        """As `run`, in a thread: returns at once."""
        self.wait()
        self._running = threading.Thread(target=self.run, args=(kind, jobs, others, after), daemon=True)
        self._running.start()

    def share(self, pair, shared: dict, base=None) -> None:
        """The pair and the estimator's whole-drive state the tasks start from (run_pass's
        keywords: index, nuisance, view, surfaces; the store is each worker's own), and the
        base model's pass once it is done (checkpoint.portable, without its stitched map).
        Written to new files each time, so that workers do not keep an older state."""
        self.wait()                       # a batch running reads the files of the last state
        n, self.shared = self.shared, self.shared + 1
        state = ({k: v for k, v in shared.items() if k != "store"},
                 None if base is None else dataclasses.replace(portable(base), h_sim=None))
        files = (str(self.cache.dir / f"pool-pair-{n}.pool"), str(self.cache.dir / f"pool-state-{n}.pool"))
        for path, value in zip(files, (pair, state), strict=True):
            tmp = Path(path).with_suffix(".tmp")
            with tmp.open("wb") as fh:
                pickle.dump(value, fh, protocol=pickle.HIGHEST_PROTOCOL)
            tmp.replace(path)
        if self.files is not None:
            for old in self.files:
                Path(old).unlink(missing_ok=True)
        self.files = files

    def run(self, kind: str, jobs: list[tuple], others: list[tuple[str, tuple]] = (), after=None) -> None:
        """Each job's arguments (`_pass_task`) as a task, and each of `others` ((kind, arguments):
        tasks of other kinds to run beside them, first); failed ones are noted in `failed` (the
        diagnosis runs those passes itself). after: per task (others, then jobs), the indices
        of the tasks it starts after (engines' imap), default none."""
        if threading.current_thread() is not self._running:
            self.wait()
        if not jobs and not others:
            return
        if self.files is None:
            raise RuntimeError("PassPool.share first")
        tasks = [*others, *((kind, a) for a in jobs)]
        calls = [(self.files, str(self.cache.dir), self.cache.every, k, a) for k, a in tasks]
        try:
            runs = self.engine.imap(_pass_task, calls, **({} if after is None else {"after": after}))
        except TypeError:                 # an engine whose calls cannot wait for others: in their order
            runs = self.engine.imap(_pass_task, calls)
        for n, (_, out) in enumerate(runs, start=1):
            if out.error:
                self.failed.append(out.error)
                print(f"a parallel pass failed (run here instead): {out.error}", file=sys.stderr)
            if self.progress is not None:
                self.progress.set_postfix_str(f"{kind} tasks {n}/{len(calls)}")

    def close(self) -> None:
        self.wait()
        for path in self.files or ():
            Path(path).unlink(missing_ok=True)


@contextmanager
def pass_pool(workers: int = 1, engine: str = "local", cache: PassCache | None = None, progress=None):
    """A PassPool on `workers` tasks at once (the local engine; with Ray: at most `workers`
    when above 1, RAY_ADDRESS's cluster or a local Ray instance), or None for workers 1 on
    the local engine (the diagnosis then runs in this process alone)."""
    if workers <= 1 and engine == "local":
        yield None
        return
    if cache is None:
        raise ValueError("passes run in parallel are kept in a PassCache: give diagnose() a cache")
    from torchsoil.engines import make_engine

    with make_engine(engine, workers if workers > 1 else None) as eng:
        pool = PassPool(eng, cache, progress)
        pool.warm(workers)
        try:
            yield pool
        finally:
            pool.close()

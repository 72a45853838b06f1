"""Where independent tasks run: single-worker process pools on this machine (`LocalEngine`) or
Ray tasks on a cluster (`RayEngine`), chosen by `make_engine`.

    with make_engine("local", workers=2) as eng:
        for i, outcome in eng.imap(fn, [(a,), (b,)]):
            ...

Each call runs in a worker with its own torch and numba threads, timed, its peak memory
measured and any exception turned into `Outcome.error`. The engines know nothing of what
their tasks do: the fleet's jobs (`torchsoil.jobs.fleet`), the diagnosis's passes
(`torchsoil.diagnosis.parallel`) and the studies use them alike. Ray is optional
(`pip install torchsoil[fleet]`) and imported only by the Ray engine. The engine owns its
worker processes, so it sets their thread environment (OMP_NUM_THREADS, NUMBA_NUM_THREADS,
OMP_WAIT_POLICY) there, never in the caller's process."""

from __future__ import annotations

import math
import os
import socket
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

ENGINES = ("local", "ray")


class EngineError(RuntimeError):
    """An engine that cannot run here (Ray not installed, no node large enough for a task)."""


# ---------------------------------------------------------------------------- engines
@dataclass
class Outcome:
    """What a task gave back: its value, or its error (one line); wall time [s], the worker's
    peak resident memory during the task [MiB] and the worker's host name."""

    value: Any = None
    error: str = ""
    seconds: float = math.nan
    peak_mb: float = math.nan
    host: str = ""

    @property
    def ok(self) -> bool:
        return not self.error


def one_line(e: BaseException, limit: int = 400) -> str:
    text = " ".join(str(e).split())
    text = f"{type(e).__name__}: {text}" if text else type(e).__name__
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _reset_peak() -> None:
    try:            # Linux: clear the peak resident set size (VmHWM) of this process
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def _proc_mb(path: str, key: str) -> float | None:
    """The `key` line (in kB) of a /proc file, MiB; None where there is no such file or line."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(key):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def _peak_mb() -> float:
    hwm = _proc_mb("/proc/self/status", "VmHWM:")
    if hwm is not None:
        return hwm
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2 ** 20 if sys.platform == "darwin" else peak / 1024


@contextmanager
def _threads(n: int):
    """torch intra-op and numba threads = n within the block (numba: at most its pool's size).
    In a worker that has not started torch or numba yet, their thread counts are set through
    the environment they read when they start (OMP_NUM_THREADS, NUMBA_NUM_THREADS), so a task
    that uses neither does not pay for importing them."""
    torch, numba = sys.modules.get("torch"), sys.modules.get("numba")
    if torch is None:
        os.environ["OMP_NUM_THREADS"] = str(n)
    if numba is None:
        os.environ.setdefault("NUMBA_NUM_THREADS", str(n))
    old = (torch.get_num_threads() if torch else None, numba.get_num_threads() if numba else None)
    if torch:
        torch.set_num_threads(n)
    if numba:
        numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        if torch:
            torch.set_num_threads(old[0])
        if numba:
            numba.set_num_threads(old[1])


def call(fn: Callable, args: tuple, cpus: int = 1) -> Outcome:
    """fn(*args) in a worker with `cpus` torch and numba threads, timed, its peak memory
    measured and any exception turned into Outcome.error."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")   # a worker process: before torch starts OpenMP
    _reset_peak()
    t0 = time.perf_counter()
    try:
        with _threads(cpus):
            value, error = fn(*args), ""
    except Exception as e:
        value, error = None, one_line(e)
    return Outcome(value, error, time.perf_counter() - t0, _peak_mb(), socket.gethostname())


def available_mb() -> float:
    """Memory available for new processes on this machine, MiB (inf when unknown)."""
    found = _proc_mb("/proc/meminfo", "MemAvailable:")
    return math.inf if found is None else found


def default_workers(fleet, n_tasks: int | None = None) -> int:
    """Local workers: as many tasks as the cores (fleet.cpus_per_task each) and the available
    memory (fleet.memory_mb_per_task each) hold, at least 1, at most n_tasks."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    n = max(1, cores // fleet.cpus_per_task)
    if fleet.memory_mb_per_task > 0:
        n = min(n, max(1, int(available_mb() // fleet.memory_mb_per_task)))
    return max(1, min(n, n_tasks)) if n_tasks else n


class LocalEngine:
    """Tasks on this machine: `workers` single-worker process pools (spawn start method, so
    each worker imports torch afresh and a killed worker breaks only its own pool). A worker
    is kept for the next task (within `with`, for the next imap too); one that died is
    replaced, its task recorded as failed (or started again, fleet.retries times)."""

    name = "local"

    def __init__(self, workers: int | None = None, fleet=None):
        from torchsoil.settings import FleetConfig

        self.fleet = fleet or FleetConfig()
        self.workers = workers
        self._kept: list | None = None     # within `with`: idle workers kept for the next imap

    def __enter__(self):
        self._kept = []
        return self

    def __exit__(self, *exc):
        kept, self._kept = self._kept or [], None
        for pool in kept:                 # idle: ended at once (an interpreter's own exit takes seconds)
            for p in list(getattr(pool, "_processes", {}).values()):
                p.terminate()
            pool.shutdown(wait=True)
        return False

    def imap(self, fn: Callable, calls: list[tuple], requests: list | None = None,
             after: list | None = None) -> Iterator[tuple[int, Outcome]]:
        """fn(*calls[i]) for every i, yielding (i, Outcome) as each finishes; requests: one
        FleetConfig per call (its cpus_per_task = the call's threads), default the engine's.
        after: per call, the indices of the calls it waits for (started once they have all
        finished, failed or not; `_next`), default none: calls start in their order."""
        import multiprocessing as mp
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
        from concurrent.futures.process import BrokenProcessPool

        requests = requests or [self.fleet] * len(calls)
        n = min(self.workers or default_workers(self.fleet, len(calls)), max(1, len(calls)))
        ctx = mp.get_context("spawn")
        idle = self._kept if self._kept is not None else []
        todo, running, tries, finished = deque(range(len(calls))), {}, [0] * len(calls), set()
        try:
            while todo or running:
                while todo and len(running) < n and (i := _next(todo, after, finished, not running)) is not None:
                    pool = idle.pop() if idle else ProcessPoolExecutor(1, ctx)
                    tries[i] += 1
                    running[pool.submit(call, fn, calls[i], requests[i].cpus_per_task)] = (i, pool)
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for fut in done:
                    i, pool = running.pop(fut)
                    try:
                        out = fut.result()
                        idle.append(pool)
                    except BrokenProcessPool:
                        pool.shutdown(wait=False)
                        if tries[i] <= requests[i].retries:
                            todo.append(i)
                            continue
                        out = Outcome(error="WorkerDied: the worker process died while running this task "
                                            "(killed, or out of memory)", host=socket.gethostname())
                    except Exception as e:          # the call or its result could not be pickled
                        idle.append(pool)
                        out = Outcome(error=one_line(e))
                    finished.add(i)
                    yield i, out
        finally:
            for _, pool in running.values():
                for p in list(getattr(pool, "_processes", {}).values()):
                    p.terminate()
            for pool in [*(idle if self._kept is None else []), *(p for _, p in running.values())]:
                pool.shutdown(wait=True, cancel_futures=True)


def _next(todo: deque, after: list | None, finished: set, idle: bool = False) -> int | None:
    """The first call in `todo` whose calls to wait for (`after[i]`) have all finished, taken
    out of it; None when every one still waits, but for the first when nothing runs (`idle`:
    what it waits for is not among the calls)."""
    for i in todo:
        if after is None or all(j in finished for j in after[i]):
            todo.remove(i)
            return i
    return todo.popleft() if idle else None


def import_ray():
    try:
        import ray
    except ImportError:
        raise EngineError("--engine ray needs Ray: pip install 'torchsoil[fleet]' (or 'ray>=2.9'); "
                          "--engine local needs nothing more") from None
    return ray


class RayEngine:
    """Tasks on a Ray cluster (`address`, e.g. ray://head:10001 or auto) or, without one, on a
    local Ray instance with `workers` x fleet.cpus_per_task CPUs (default: all cores), shut
    down after. Each task asks for fleet.cpus_per_task CPUs and fleet.memory_mb_per_task MiB
    of Ray's memory resource, so the cluster runs no more at once than its nodes hold; with
    `workers`, at most that many are submitted at once. A task whose worker dies is retried
    fleet.retries times by Ray, then recorded with Ray's error. In an already initialised Ray
    session (ray.is_initialized()), that session is used and left running."""

    name = "ray"

    def __init__(self, address: str | None = None, workers: int | None = None, fleet=None):
        from torchsoil.settings import FleetConfig

        self.address, self.workers, self.fleet = address, workers, fleet or FleetConfig()
        self.started = False

    def __enter__(self):
        ray = import_ray()
        if not ray.is_initialized():
            if self.address:
                ray.init(address=self.address, log_to_driver=False)
            else:
                os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
                cpus = self.workers * self.fleet.cpus_per_task if self.workers else None
                ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False,
                         object_store_memory=256 * 2 ** 20)
            self.started = True
        return self

    def __exit__(self, *exc):
        if self.started:
            import_ray().shutdown()
            self.started = False
        return False

    def check(self, requests: list) -> None:
        """Refuse tasks no alive node can hold (Ray would wait for such a node for ever)."""
        ray = import_ray()
        nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
        cpus = max((r.cpus_per_task for r in requests), default=1)
        mem = max((r.memory_mb_per_task for r in requests), default=0)
        if not any(n.get("CPU", 0) >= cpus and n.get("memory", 0) >= mem * 2 ** 20 for n in nodes):
            most = max(nodes, key=lambda n: n.get("CPU", 0), default={})
            raise EngineError(f"no node of the Ray cluster offers {cpus} CPUs and {mem} MiB for one task (largest: "
                              f"{most.get('CPU', 0):g} CPUs, {most.get('memory', 0) / 2 ** 20:.0f} MiB); lower "
                              "fleet.cpus_per_task or fleet.memory_mb_per_task")

    def imap(self, fn: Callable, calls: list[tuple], requests: list | None = None,
             after: list | None = None) -> Iterator[tuple[int, Outcome]]:
        """As LocalEngine.imap, each call a Ray task with its request's CPUs and memory."""
        ray = import_ray()
        requests = requests or [self.fleet] * len(calls)
        if calls:
            self.check(requests)
        remote = ray.remote(call)
        todo, refs, finished = deque(range(len(calls))), {}, set()
        limit = self.workers or len(calls)
        while todo or refs:
            while todo and len(refs) < limit and (i := _next(todo, after, finished, not refs)) is not None:
                r = requests[i]
                opts = {"num_cpus": r.cpus_per_task, "max_retries": r.retries, "retry_exceptions": False}
                if r.memory_mb_per_task:
                    opts["memory"] = r.memory_mb_per_task * 2 ** 20
                refs[remote.options(**opts).remote(fn, calls[i], r.cpus_per_task)] = i
            done, _ = ray.wait(list(refs), num_returns=1)
            for ref in done:
                i = refs.pop(ref)
                try:
                    out = ray.get(ref)
                except ray.exceptions.RayError as e:
                    first = (str(e).strip().splitlines() or [""])[0]
                    out = Outcome(error=f"{type(e).__name__}: {first}"[:400])
                finished.add(i)
                yield i, out


def make_engine(kind: str = "local", workers: int | None = None, address: str | None = None, fleet=None):
    """An engine (a context manager with imap): `local` or `ray` (address: a running cluster)."""
    if kind == "local":
        if address:
            raise ValueError("--ray-address goes with --engine ray")
        return LocalEngine(workers, fleet)
    if kind == "ray":
        return RayEngine(address, workers, fleet)
    raise ValueError(f"unknown engine {kind!r}; known: {', '.join(ENGINES)}")

"""The job behind `torchsoil study`: the diagnosis's confusion table over drives with known
truth (torchsoil.diagnosis.study), in this process or with one task per drive on an engine."""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path

from torchsoil.diagnosis.study import run_foreign, run_study
from torchsoil.diagnosis.study_cases import STUDY_CASES, randomized_cases, revisit_cases
from torchsoil.engines import make_engine
from torchsoil.jobs.common import torch_threads
from torchsoil.settings import Settings


def study(settings: Settings, out: str | Path | None = None, *, quick: bool = False, randomized: int | None = None,
          null: int = 20, seed: int = 0, revisits: bool = False, learned: int = 0, foreign: str | Path | None = None,
          redraws: int = 0, threads: int | None = None, engine: str | None = None, workers: int | None = None,
          address: str | None = None) -> str:
    """The study's confusion table (Markdown; also OUT/confusion.md, OUT/cases.jsonl one line per
    drive, and a rerun resumes). Default: the fixed synthetic cases (`quick`: one per kind);
    `randomized` N drives with a random effect plus `learned` drives with a random law outside
    the catalogue that a learned modifier names (speed_deposit, turn_scrub, pass_loosening)
    plus `null` null drives (`revisits`: only those over their own ruts); `foreign`: the
    terrain pairs of another simulator in that folder, with `redraws` other draws of each
    pair's noise. With any of engine, workers, address, each drive
    is a task on that engine (settings.fleet's CPUs and memory each); otherwise all run here
    with `threads` torch threads."""
    if (revisits or learned) and randomized is None:
        raise ValueError("--revisits and --learned go with --randomized N")
    if redraws < 0 or (redraws and foreign is None):
        raise ValueError(f"--redraws {redraws}: a count >= 0, and only with --foreign")
    on_engine = any(v is not None for v in (engine, workers, address))
    if on_engine and threads:
        settings = settings.replace(fleet={"cpus_per_task": threads})
    context = make_engine(engine or "local", workers, address, settings.fleet) if on_engine else nullcontext()
    with torch_threads(threads or 1), context as eng:
        if foreign is not None:
            return run_foreign(Path(foreign), Path(out or "out/diagnosis_study_foreign"), settings, engine=eng,
                               redraws=redraws)
        if randomized is not None:
            cases = randomized_cases(randomized, null, seed, learned)
            cases = revisit_cases(cases) if revisits else cases
            return run_study(cases, Path(out or "out/diagnosis_study_randomized"), settings, engine=eng)
        cases = STUDY_CASES[::3] if quick else STUDY_CASES
        return run_study(cases, Path(out or "out/diagnosis_study"), settings, engine=eng)

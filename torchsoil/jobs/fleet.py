"""Many recordings at once: a season of field logs estimated or diagnosed on a process pool or a
Ray cluster.

    recs = recordings(["season/*.bag", "extra.npz"], manifest="season.csv")
    rows = run_fleet("estimate", recs, "out/season", robot="paper_platform", engine="ray")

Each recording is one task that calls the function a single run calls (`jobs.estimate.estimate`,
`jobs.diagnose.diagnose_input`), so OUT/<name>/ holds exactly what `torchsoil estimate INPUT
--out OUT/<name>` writes; the task's printed output goes to OUT/logs/<name>.log. OUT/fleet.csv
gets one row per recording as its task finishes (`FleetLog`). A task that fails is recorded
with its error and the others go on; a rerun skips the recordings whose outputs are complete
and were made from the same input, robot and settings (`complete`) and runs the rest.

Engines (`torchsoil.engines.make_engine`): `local`, single-worker process pools on this machine (spawned, so a
killed worker takes only its own task down), or `ray`, Ray tasks on a running cluster or a
local Ray instance, each asking for the `fleet` settings' CPUs and memory. The same engines run
the diagnosis studies (`diagnosis.study.run_study(..., engine=...)`). Ray is optional
(`pip install torchsoil[fleet]`) and imported only by the Ray engine.
"""

from __future__ import annotations

import csv
import glob
import json
import math
import os
import traceback
from collections.abc import Callable, Iterable
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from torchsoil.engines import make_engine, one_line

SUMMARY = "fleet.csv"
LOGS = "logs"
# the settings sections each job records in run.json (jobs.estimate.estimate, jobs.diagnose.diagnose_input)
SECTIONS = {"estimate": ("sim", "estimator"), "diagnose": ("sim", "estimator", "diagnosis")}
# the output each job writes last: present and newer than run.json = the run completed
LAST = {"estimate": "summary.md", "diagnose": "report.md"}
MANIFEST_COLUMNS = ("input", "name", "robot", "config", "set")
GLOB_CHARS = "*?["


# ---------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class FleetInput:
    """One input of a many-recordings run: its path (bag or terrain pair), the name of its
    output folder, and its own robot (name or YAML path), settings YAMLs and `section.key=value`
    overrides, applied after the command's."""

    input: str
    name: str
    robot: str | None = None
    config: tuple[str, ...] = ()
    overrides: tuple[str, ...] = ()


def _stem(path: Path) -> str:
    return path.name if path.is_dir() else path.stem


def _expand(item: str | Path) -> list[Path]:
    """A path, or the sorted matches of a glob (`**` recursive); a glob matching nothing is an error."""
    text = str(item)
    if not any(c in text for c in GLOB_CHARS):
        return [Path(text)]
    found = sorted(Path(p) for p in glob.glob(text, recursive=True))
    if not found:
        raise FileNotFoundError(f"no recording matches {text}")
    return found


def _split(cell: str | None) -> list[str]:
    return [part.strip() for part in (cell or "").split(";") if part.strip()]


def _beside(value: str, base: Path) -> str:
    p = Path(value).expanduser()
    return str(p if p.is_absolute() else base / p)


def read_manifest(path: str | Path) -> list[FleetInput]:
    """The recordings of a CSV manifest: a header naming some of `input` (required), `name`,
    `robot`, `config`, `set`; one row per recording (an input may be a glob, then without a
    name). `config` and `set` hold several values separated by `;`. Relative paths (input,
    config, a robot ending in .yaml/.yml) are relative to the manifest's folder; a robot
    without such a suffix is a shipped name. Lines starting with `#` are skipped."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"manifest not found: {path}")
    base = path.parent
    with path.open(newline="") as f:
        reader = csv.DictReader(line for line in f if line.strip() and not line.lstrip().startswith("#"))
        columns = [c.strip() for c in reader.fieldnames or []]
        unknown = sorted(set(columns) - set(MANIFEST_COLUMNS))
        if "input" not in columns or unknown:
            raise ValueError(f"{path}: a manifest's header names `input` and any of name, robot, config, set"
                             + (f" (unknown: {', '.join(unknown)})" if unknown else " (no `input` column)"))
        rows = [{k.strip(): (v or "").strip() for k, v in row.items() if k is not None} for row in reader]
    out = []
    for n, row in enumerate(rows, start=2):
        robot = row.get("robot") or None
        if robot and Path(robot).suffix in (".yaml", ".yml"):
            robot = _beside(robot, base)
        extra = {"robot": robot, "config": tuple(_beside(c, base) for c in _split(row.get("config"))),
                 "overrides": tuple(_split(row.get("set")))}
        paths = _expand(_beside(row["input"], base))
        if row.get("name") and len(paths) > 1:
            raise ValueError(f"{path} line {n}: a name for a glob of {len(paths)} recordings")
        out += [FleetInput(str(p), row.get("name") or _stem(p), **extra) for p in paths]
    return out


def recordings(inputs: Iterable[str | Path] = (), manifest: str | Path | None = None) -> list[FleetInput]:
    """The recordings of paths, globs and CSV manifests (`read_manifest`; an input ending in
    .csv is one too), each with a unique output name: the input's stem, prefixed by its
    folder's name where two stems collide, or the manifest's `name`."""
    found: list[tuple[FleetInput, bool]] = []          # (recording, name derived from the path)
    for item in [*inputs, *([manifest] if manifest else [])]:
        if str(item).endswith(".csv"):
            found += [(r, False) for r in read_manifest(item)]
        else:
            found += [(FleetInput(str(p), _stem(p)), True) for p in _expand(item)]
    return _unique(found)


def _unique(found: list[tuple[FleetInput, bool]]) -> list[FleetInput]:
    out = list(dict.fromkeys(found))                   # the same recording twice: once
    names = [r.name for r, _ in out]
    for i, (rec, derived) in enumerate(out):
        if derived and names.count(rec.name) > 1:
            parent = Path(rec.input).resolve().parent.name
            out[i] = (FleetInput(rec.input, f"{parent}_{rec.name}", rec.robot, rec.config, rec.overrides), derived)
    names = [r.name for r, _ in out]
    clash = sorted({n for n in names if names.count(n) > 1})
    if clash:
        raise ValueError(f"two recordings would write to the same folder ({', '.join(clash)}): give them "
                         "names in a manifest (`name` column)")
    bad = [n for n in names if n in ("", ".", "..", LOGS) or "/" in n or "\\" in n]
    if bad:
        raise ValueError(f"recording name(s) {bad} cannot be an output folder name")
    return [r for r, _ in out]


# ---------------------------------------------------------------------------- tasks
@dataclass
class Task:
    """One recording's job: `job` (estimate or diagnose) on `input` into `out`, with its own
    settings (a `settings.Settings`), robot (name or YAML path) and extrinsics ({frame or topic:
    [x, y, z, roll, pitch, yaw]}, m, rad); its printed output goes to `log`."""

    job: str
    name: str
    input: str
    out: str
    log: str
    settings: Any
    robot: str | None = None
    extrinsics: dict = field(default_factory=dict)
    tensorboard: bool = True
    overwrite: bool = False


def expected_record(task: Task) -> dict:
    """The run.json a single run of this task writes (input identity, robot, settings used)."""
    from torchsoil.io.extrinsics import pipeline_settings
    from torchsoil.jobs.common import run_record
    from torchsoil.robot import load_robot, robot_path

    robot = load_robot(task.robot) if task.robot else None
    pipeline = pipeline_settings(task.settings, robot_path(task.robot) if task.robot else None, task.extrinsics)
    record = run_record(task.job, task.input, task.settings, pipeline, robot, SECTIONS[task.job])
    return json.loads(json.dumps(record))


def finished(job: str, out: Path) -> bool:
    """True when `out` holds a run of `job` that finished: its last output (LAST) was written
    after its run.json (whatever input and settings made it)."""
    meta, last = Path(out) / "run.json", Path(out) / LAST[job]
    return meta.is_file() and last.is_file() and last.stat().st_mtime_ns >= meta.stat().st_mtime_ns


def complete(task: Task) -> bool:
    """True when task.out holds a finished run of this very task: its run.json names the same
    job, input (content key), robot and settings, and the job's last output (LAST) was written
    after it (an interrupted or failed run leaves it missing or older)."""
    from torchsoil.jobs import provenance

    if not finished(task.job, Path(task.out)):
        return False
    try:
        old = json.loads((Path(task.out) / provenance.RUN_FILE).read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return not provenance.differences(old, expected_record(task))


def run_task(task: Task) -> dict:
    """Run one task (in a worker): the single-run function with the task's arguments, its
    printed output (and a traceback) in task.log; returns `summarize` of its outputs."""
    from torchsoil.robot import load_robot, robot_path

    Path(task.log).parent.mkdir(parents=True, exist_ok=True)
    threads = task.settings.fleet.cpus_per_task
    rows: list | None = None
    with open(task.log, "w") as log, redirect_stdout(log), redirect_stderr(log):
        try:
            robot = load_robot(task.robot) if task.robot else None
            robot_yaml = robot_path(task.robot) if task.robot else None
            common = {"robot": robot, "overwrite": task.overwrite, "tensorboard": task.tensorboard,
                      "progress": False, "robot_yaml": robot_yaml, "threads": threads,
                      "extrinsics": task.extrinsics}
            if task.job == "estimate":
                from torchsoil.jobs.estimate import estimate

                estimate(task.input, task.out, task.settings, **common)
            else:
                from torchsoil.jobs.diagnose import diagnose_input

                rows = []
                diagnose_input(task.input, task.out, task.settings, rows=rows, **common)
        except Exception:
            traceback.print_exc()
            raise
    return summarize(task.job, Path(task.out), rows)


# ---------------------------------------------------------------------------- summaries
def _read_csv(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _num(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _nanmean(values) -> float:
    vals = [x for x in (_num(v) for v in values) if math.isfinite(x)]
    return sum(vals) / len(vals) if vals else math.nan


def window_stats(rows: list[dict], floor: float = math.nan) -> dict:
    """fleet.csv's window columns from params.csv rows: windows (distinct s), fitted (rows
    with a finite residual), flagged (rows with any flag), the mean of each of d1..dT [m], chi
    [-] and beta [deg] over the rows (one per window, or per visit of a window's ground), and
    mean prediction cost / `floor` (the mean noise floor, m)."""
    windows = len({r.get("s", i) for i, r in enumerate(rows)})
    out: dict = {"windows": windows, "fitted": sum(math.isfinite(_num(r.get("residual"))) for r in rows),
                 "flagged": sum(bool(r.get("flags")) for r in rows)}
    k = 1
    while rows and f"d{k}" in rows[0]:
        out[f"d{k}"] = _nanmean(r[f"d{k}"] for r in rows)
        k += 1
    for name in ("chi", "beta"):
        out[name] = _nanmean(r.get(name) for r in rows)
    if math.isfinite(floor) and floor > 0:
        out["prediction_floor"] = _nanmean(r.get("prediction") for r in rows) / floor
    return out


def summarize(job: str, out: Path, rows: list[dict] | None = None) -> dict:
    """A finished run's fleet.csv columns, from its outputs: for an estimate, params.csv and
    reference.csv (`window_stats`); for a diagnosis, diagnosis.json (verdict, missing physics,
    prediction cost / noise floor of the base and of the extended model) and, when given, the
    base model's window rows."""
    out = Path(out)
    if job == "estimate":
        floor = _nanmean(r.get("floor") for r in _read_csv(out / "reference.csv"))
        return window_stats(_read_csv(out / "params.csv"), floor)
    d = json.loads((out / "diagnosis.json").read_text())
    floor = _num(d.get("noise_floor"))
    res = window_stats(rows) if rows is not None else {}
    res.update({"verdict": d["verdict"], "missing_physics": d.get("missing_physics") or ""})
    if math.isfinite(floor) and floor > 0:
        res["prediction_floor"] = _num(d["cost_before"]["prediction"]) / floor
        res["prediction_floor_after"] = _num(d["cost_after"]["prediction"]) / floor
    return res


HEAD = ["name", "job", "status", "input", "windows", "fitted", "flagged"]
TAIL = ["chi", "beta", "prediction_floor", "verdict", "missing_physics", "prediction_floor_after", "seconds",
        "peak_mb", "host", "finished", "error", "out"]


def _columns(keys: Iterable[str]) -> list[str]:
    keys = set(keys)
    d = sorted((k for k in keys if k[:1] == "d" and k[1:].isdigit()), key=lambda k: int(k[1:]))
    rest = sorted(keys - set(HEAD) - set(TAIL) - set(d))
    return [*HEAD, *d, *TAIL, *rest]


def _fmt(v) -> str:
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    return "" if v is None else str(v)


class FleetLog:
    """OUT/fleet.csv: one row per recording, in the order their tasks finish. Rows of an earlier
    run are kept for recordings not run again; a row with a column the file lacks (a robot with
    more tracks) rewrites the file with it, atomically (write, then rename)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.rows: dict[str, dict] = {}
        if self.path.is_file():
            self.rows = {r["name"]: r for r in _read_csv(self.path) if r.get("name")}
        self.columns = _columns(k for r in self.rows.values() for k in r)

    def previous(self, name: str) -> dict | None:
        return self.rows.get(name)

    def start(self, rows: list[dict], running: list[str]) -> None:
        """Before the tasks: drop the old rows of `running`, set `rows` (skipped, failed to start)."""
        for name in [*running, *(r["name"] for r in rows)]:
            self.rows.pop(name, None)
        for r in rows:
            self.rows[r["name"]] = r
        self._rewrite()

    def add(self, row: dict) -> None:
        """One finished task's row: appended (the file rewritten if it brings a new column)."""
        self.rows.pop(row["name"], None)
        self.rows[row["name"]] = row
        if not set(row) <= set(self.columns):
            self._rewrite()
            return
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, self.columns).writerow({k: _fmt(row.get(k)) for k in self.columns})

    def _rewrite(self) -> None:
        self.columns = _columns(k for r in self.rows.values() for k in r)
        tmp = self.path.with_name(self.path.name + ".tmp")
        with tmp.open("w", newline="") as f:
            w = csv.DictWriter(f, self.columns)
            w.writeheader()
            for r in self.rows.values():
                w.writerow({k: _fmt(r.get(k)) for k in self.columns})
        os.replace(tmp, self.path)


# ---------------------------------------------------------------------------- the run
def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _absolute(path: str | Path | None, existing: bool = False) -> str | None:
    """An absolute path (workers, on this machine or a cluster's, need not share the working
    directory); with `existing`, only a path that exists (otherwise a shipped robot's name)."""
    if path is None or (existing and not Path(path).exists()):
        return None if path is None else str(path)
    return str(Path(path).expanduser().absolute())


def plan(job: str, recs: list[FleetInput], out: Path, log: FleetLog, configs: list[str], overrides: list[str],
         robot: str | None, extrinsics: dict | None, tensorboard: bool,
         overwrite: bool) -> tuple[list[Task], list[dict]]:
    """The tasks to run, and the fleet.csv rows of recordings not to run: skipped (complete,
    `complete`; the row of the earlier run kept, its figures read again from the outputs) or
    failed before starting (settings or robot unusable). A recording whose last task failed
    (its fleet.csv row says error) may replace what that attempt left in its folder, even if
    it was made from another input or settings (the recording mended, a setting corrected),
    unless the folder holds a finished run; other folders of another run are refused unless
    `overwrite` (provenance.claim)."""
    from torchsoil.settings import load_settings

    tasks, early = [], []
    for rec in recs:
        row = {"name": rec.name, "job": job, "input": rec.input, "out": str(out / rec.name)}
        try:
            task = Task(job, rec.name, _absolute(rec.input), _absolute(out / rec.name),
                        _absolute(out / LOGS / f"{rec.name}.log"),
                        load_settings(*configs, *rec.config, overrides=[*overrides, *rec.overrides]),
                        _absolute(rec.robot or robot, existing=True), dict(extrinsics or {}), tensorboard, overwrite)
        except Exception as e:
            early.append({**row, "status": "error", "error": one_line(e), "finished": _now()})
            continue
        try:
            done = complete(task) and summarize(job, Path(task.out))
        except Exception:                       # e.g. a missing input: the task itself reports it
            done = None
        before = log.previous(rec.name) or {}
        if done:
            early.append({**before, **done, **row, "status": "skipped", "error": ""})
        else:
            # what a failed attempt left (e.g. of a recording since mended) is replaced, not refused
            task.overwrite = overwrite or (before.get("status") == "error" and not finished(job, Path(task.out)))
            tasks.append(task)
    return tasks, early


def run_fleet(job: str, recs: list[FleetInput], out: str | Path, *, configs: Iterable[str] = (),
              overrides: Iterable[str] = (), robot: str | None = None, extrinsics: dict | None = None,
              engine: str = "local", workers: int | None = None, address: str | None = None,
              tensorboard: bool = True, overwrite: bool = False, echo: Callable[[str], Any] = print) -> list[dict]:
    """Run `job` (estimate or diagnose) on every recording, each into OUT/<name>/, on `engine`.

    Settings of a recording: defaults, `configs`, its own config YAMLs, `overrides`, its own
    overrides. robot: the robot (name or YAML path) of recordings without their own; extrinsics
    ({frame or topic: [x, y, z, roll, pitch, yaw]}, m, rad) apply to all. Recordings whose
    outputs are complete and match (`complete`) are skipped; the others run, also after a
    failure. Returns the fleet.csv rows of `recs` (status ok, skipped or error)."""
    from torchsoil.settings import load_settings

    if job not in SECTIONS:
        raise ValueError(f"unknown job {job!r}; known: {', '.join(SECTIONS)}")
    configs, overrides = list(configs), list(overrides)
    base = load_settings(*configs, overrides=overrides)       # the command's own settings: refused at once
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log = FleetLog(out / SUMMARY)
    tasks, early = plan(job, recs, out, log, configs, overrides, robot, extrinsics, tensorboard, overwrite)
    log.start(early, [t.name for t in tasks])
    for r in early:
        echo(f"{r['name']}: {r['status']}" + (f" ({r['error']})" if r["error"] else " (complete, same settings)"))
    if tasks:
        echo(f"{len(tasks)} recording(s) to run on the {engine} engine")
        with make_engine(engine, workers, address, base.fleet) as eng:
            for k, (i, o) in enumerate(eng.imap(run_task, [(t,) for t in tasks], [t.settings.fleet for t in tasks])):
                t = tasks[i]
                row = {**(o.value or {}), "name": t.name, "job": job, "input": t.input, "out": t.out,
                       "status": "ok" if o.ok else "error", "error": o.error, "seconds": o.seconds,
                       "peak_mb": o.peak_mb, "host": o.host, "finished": _now()}
                log.add(row)
                echo(f"[{k + 1}/{len(tasks)}] {t.name}: {row['status']} in {o.seconds:.1f} s, peak "
                     f"{o.peak_mb:.0f} MiB" + (f": {o.error}" if o.error else ""))
    return [log.rows[r.name] for r in recs]


def run_many(job: str, inputs: Iterable[str | Path], manifest: str | Path | None, out: str | Path,
             echo: Callable[[str], Any] = print, **options) -> int:
    """`run_fleet` of `job` on the recordings of paths, globs and CSV manifests (`recordings`),
    with run_fleet's keyword options; says how many finished, were skipped and failed, and
    returns the exit status of the command: 1 when some failed (their errors are in
    OUT/fleet.csv), else 0."""
    recs = recordings(inputs, manifest)
    if not recs:
        raise FileNotFoundError("no recordings given (paths, globs, or --manifest CSV)")
    rows = run_fleet(job, recs, out, echo=echo, **options)
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ok", "skipped", "error")}
    echo(f"wrote {Path(out) / SUMMARY}: {counts['ok']} done, {counts['skipped']} already complete (skipped), "
         f"{counts['error']} failed")
    return 1 if counts["error"] else 0

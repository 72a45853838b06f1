"""What made an output folder: the input's identity, the robot and the settings (run.json).

An output folder, a `--resume` or a cached terrain pair is used only when what made it
matches the run asking for it; otherwise the run is refused with a message naming the
difference (or, for a cache, the terrain is recomputed). Never silently reused.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

RUN_FILE = "run.json"
CHUNK = 1 << 20  # bytes hashed at each end of every file


class OutputMismatch(ValueError):
    """An output folder holds results made from another input or with other settings."""


def input_identity(path: str | Path) -> dict:
    """Identity of an input file or bag directory: its path and modification time (for the
    reader) and its content key (total size and a SHA-256 over the size, name and first and
    last MiB of every file), which is what runs are compared by: a copied or moved
    recording keeps its key, another recording gets another one."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"input not found: {path}")
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    h = hashlib.sha256()
    size = 0
    for f in files:
        n = f.stat().st_size
        size += n
        h.update(f"{f.relative_to(path) if path.is_dir() else f.name}:{n}\n".encode())
        with f.open("rb") as fh:
            h.update(fh.read(CHUNK))
            if n > 2 * CHUNK:
                fh.seek(-CHUNK, 2)
                h.update(fh.read(CHUNK))
            elif n > CHUNK:
                h.update(fh.read())
    return {"path": str(path.resolve()), "mtime": max(f.stat().st_mtime for f in files) if files else 0.0,
            "size": size, "key": h.hexdigest()}


def run_record(input_path: str | Path, settings: dict, robot: dict | None, job: str) -> dict:
    """The run.json content of a job on an input with these settings (JSON-ready dicts)."""
    from torchsoil import __version__

    return {"job": job, "input": input_identity(input_path), "robot": robot, "settings": settings,
            "torchsoil": __version__}


def differences(old: dict, new: dict) -> list[str]:
    """What differs between two run records, as short phrases (empty: same run)."""
    out = []
    if old.get("job") != new.get("job"):
        out.append(f"it holds a {old.get('job')!r} run, not {new.get('job')!r}")
    if (old.get("input") or {}).get("key") != new["input"]["key"]:
        out.append(f"its input was {old.get('input', {}).get('path')} (another recording than "
                   f"{new['input']['path']})")
    if old.get("robot") != new.get("robot"):
        out.append("its robot description differs")
    changed = sorted(_changed_keys(old.get("settings") or {}, new.get("settings") or {}))
    if changed:
        shown = ", ".join(changed[:6]) + (f" and {len(changed) - 6} more" if len(changed) > 6 else "")
        out.append(f"its settings differ ({shown})")
    return out


def _changed_keys(a, b, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        keys = []
        for k in set(a) | set(b):
            keys += _changed_keys(a.get(k), b.get(k), f"{prefix}{k}.")
        return keys
    return [] if a == b else [prefix.rstrip(".")]


def claim(out: Path, record: dict, resume: bool = False, overwrite: bool = False,
          outputs: tuple[str, ...] = ()) -> None:
    """Make `out` the folder of this run, writing run.json.

    - no run.json there: fine, unless some of `outputs` exist (unknown origin: refused);
    - run.json of the same job, input, robot and settings: fine (a rerun or a resume);
    - anything else: refused, unless `overwrite`, which deletes `outputs` first;
    - `resume` needs a matching run.json."""
    out.mkdir(parents=True, exist_ok=True)
    meta = out / RUN_FILE
    present = [name for name in outputs if (out / name).exists()]
    problems: list[str] = []
    if meta.exists():
        try:
            problems = differences(json.loads(meta.read_text()), record)
        except (json.JSONDecodeError, AttributeError, KeyError, TypeError):
            problems = [f"its {RUN_FILE} is unreadable"]
    elif present:
        problems = [f"it holds outputs ({', '.join(present[:3])}) without a {RUN_FILE} saying what made them"]
    elif resume:
        problems = [f"there is no {RUN_FILE} to resume from"]
    if problems and (resume or not overwrite):
        hint = "start a new run in another --out" + ("" if resume else ", or pass --overwrite to replace it")
        raise OutputMismatch(f"{out}: {'; '.join(problems)}. Not reusing it: {hint}.")
    if problems:  # overwrite
        for name in present:
            target = out / name
            shutil.rmtree(target) if target.is_dir() else target.unlink()
    meta.write_text(json.dumps(record, indent=1))


def cache_key(record: dict, *sections: str) -> dict:
    """The part of a run record a cached intermediate depends on (input, robot, sections)."""
    return {"input": record["input"]["key"], "robot": record.get("robot"),
            "settings": {s: record["settings"].get(s) for s in sections}}


def cache_valid(path: Path, key: dict) -> bool:
    """True when `path` exists and its sidecar PATH.json holds this key."""
    side = path.with_suffix(".json")
    if not (path.exists() and side.exists()):
        return False
    try:
        return json.loads(side.read_text()) == json.loads(json.dumps(key))
    except json.JSONDecodeError:
        return False


def mark_cache(path: Path, key: dict) -> None:
    path.with_suffix(".json").write_text(json.dumps(key, indent=1))

"""Manual pages made when the manual is built (called from conf.py): the settings reference
from the typed settings tree, and the benchmark figures of the last `torchsoil bench` run kept
in docs/bench/."""

from __future__ import annotations

import ast
import json
import sys
from pathlib import Path

from pydantic import BaseModel

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchsoil.settings import Settings  # noqa: E402


def settings_rows(model: BaseModel, prefix: str = "") -> list[tuple[str, str, str]]:
    """(dotted key, default as YAML-ish text, description) for every leaf of a settings tree."""
    rows = []
    plain = model.model_dump(mode="json")
    for name, info in type(model).model_fields.items():
        value = getattr(model, name)
        key = f"{prefix}{name}"
        if isinstance(value, BaseModel) and len(type(value).model_fields) > 4:
            rows += settings_rows(value, key + ".")
            continue
        rows.append((key, json.dumps(plain[name]), (info.description or "").replace("|", "\\|")))
    return rows


def settings_page(settings: Settings) -> str:
    lines = ["# Settings reference", "",
             "Every setting, its default (the paper's values where the paper gives one) and its unit. "
             "This page is generated from the typed tree (`torchsoil/settings.py`) when the manual is built; "
             "`torchsoil settings [SECTION]` prints the same tree as YAML. Change values with "
             "`--config my.yaml` (any subset of the sections) and `--set section.key=value`, applied in "
             "that order; an unknown key or a value of the wrong type is refused with the key named.", ""]
    for section in type(settings).model_fields:
        doc = (type(getattr(settings, section)).__doc__ or "").strip().split("\n\n")[0]
        lines += [f"## `{section}`", "", " ".join(doc.split()), "",
                  "| key | default | meaning |", "| --- | --- | --- |"]
        for key, default, text in settings_rows(getattr(settings, section), section + "."):
            lines.append(f"| `{key}` | `{default}` | {text} |")
        lines.append("")
    return "\n".join(lines)


def module_docstring(path: Path) -> str:
    return ast.get_docstring(ast.parse(path.read_text())) or ""


def benchmarks_page(bench_dir: Path) -> str:
    figures = json.loads((bench_dir / "bench.json").read_text())
    meta = json.loads((bench_dir / "bench_meta.json").read_text())
    lines = ["# Benchmarks", "",
             "Figures of the last `torchsoil bench` run kept with the manual (`docs/bench/`), "
             f"measured on {meta['machine']}, {meta['date']}, command `{meta['command']}`. "
             "This page is generated from that run's `bench.json` when the manual is built; run "
             "`torchsoil bench` (the benchmarks are `torchsoil.bench`, one module per group) to measure your "
             "machine, `--only online estimator` for some groups, `--quick` for fewer sizes and repeats.", ""]
    for name, keys in meta["modules"].items():
        doc = module_docstring(ROOT / "torchsoil" / "bench" / f"{name}.py")
        lines += [f"## {name}", "", doc, "", "| figure | value |", "| --- | --- |"]
        lines += [f"| `{k}` | {figures[k]:.4g} |" for k in keys if k in figures]
        lines.append("")
    return "\n".join(lines)


def write_pages(out: Path) -> None:
    """Write settings.md and benchmarks.md into `out` (rewritten only when they change)."""
    out.mkdir(parents=True, exist_ok=True)
    for name, text in (("settings.md", settings_page(Settings())),
                       ("benchmarks.md", benchmarks_page(ROOT / "docs" / "bench"))):
        path = out / name
        if not path.exists() or path.read_text() != text:
            path.write_text(text)

"""The manual (docs/): it builds with warnings as errors, every Python example in it runs, and
every command line in it is one the `torchsoil` command accepts (those marked
`<!-- test: run -->` are run too), so that no example can rot."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from torchsoil.cli import parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
FENCE = re.compile(r"^(?P<mark><!-- test: run -->\n)?```(?P<lang>[a-z]*)\n(?P<body>.*?)^```", re.M | re.S)


def pages() -> list[Path]:
    """The manual's hand-written pages (not the reference pages, generated at build time) and
    the README."""
    hand = [p for p in DOCS.rglob("*.md") if not {"_build", "reference"} & set(p.relative_to(DOCS).parts)]
    return sorted(hand) + [ROOT / "README.md"]


def blocks(lang: set[str]) -> list[tuple[str, str, bool]]:
    """(page:block number, code, marked to run) of every fenced block in one of `lang`."""
    out = []
    for page in pages():
        for i, m in enumerate(FENCE.finditer(page.read_text())):
            if m["lang"] in lang:
                out.append((f"{page.relative_to(ROOT)}:{i}", m["body"], bool(m["mark"])))
    return out


def commands(body: str) -> list[list[str]]:
    """The `torchsoil ...` and `python3 scripts/X.py ...` calls of a shell block, as argv for the
    torchsoil parser (comments, continuations and other commands left out)."""
    out = []
    for line in body.replace("\\\n", " ").splitlines():
        for part in line.split("&&"):
            words = shlex.split(part, comments=True)
            if words[:1] == ["torchsoil"]:
                out.append(words[1:])
            elif len(words) >= 2 and words[0].startswith("python") and words[1].startswith("scripts/"):
                name = Path(words[1]).stem.replace("_", "-")
                sub = {"estimate": "estimate", "process-bag": "process-bag", "diagnose": "diagnose",
                       "make-recording": "record", "bench": "bench", "rollout": "rollout",
                       "diagnosis-study": "study", "ablation": "ablation"}[name]
                out.append([sub, *words[2:]])
    return out


def workdir(tmp_path: Path) -> Path:
    """A scratch directory that sees the bundled demo as a checkout does (data/demo)."""
    (tmp_path / "data").symlink_to(ROOT / "data")
    return tmp_path


PYTHON = [(w, c) for w, c, _ in blocks({"python"})]
SHELL = blocks({"bash", "console", "sh"})


@pytest.mark.parametrize("where, code", PYTHON, ids=[w for w, _ in PYTHON])
def test_python_example_runs(where, code, tmp_path, monkeypatch):
    monkeypatch.chdir(workdir(tmp_path))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    exec(compile(code, where, "exec"), {"__name__": "__main__"})  # as `python3 example.py` runs it


@pytest.mark.parametrize("where, code, run", SHELL, ids=[w for w, _, _ in SHELL])
def test_command_lines_are_accepted(where, code, run, tmp_path):
    argvs = commands(code)
    for argv in argvs:
        try:
            parser().parse_args(argv)
        except SystemExit as e:
            pytest.fail(f"{where}: `torchsoil {' '.join(argv)}` is refused by the command line ({e})")
    if run:
        cwd = workdir(tmp_path)
        for argv in argvs:
            res = subprocess.run([sys.executable, "-m", "torchsoil.cli", *argv], cwd=cwd,
                                 capture_output=True, text=True, timeout=300,
                                 env={**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"})
            assert res.returncode == 0, f"{where}: torchsoil {' '.join(argv)}\n{res.stderr[-2000:]}"


def test_a_renamed_option_would_be_caught():
    """The command-line check fails on an option the command does not have."""
    with pytest.raises(SystemExit):
        parser().parse_args(commands("torchsoil estimate x.bag --windw 1.0 # comment")[0])


def test_manual_builds_without_warnings(tmp_path):
    res = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
                          str(DOCS), str(tmp_path / "html")], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-4000:]
    assert (tmp_path / "html" / "reference" / "settings.html").exists()

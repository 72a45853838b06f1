"""The house (docs/architecture.md): the library's import graph, read from the source with `ast`,
has no cycle, no room imports a `_private` name of another room, and each room imports only
the rooms upstream of it in the data flow. Every import counts, also one inside a function;
only imports under `if TYPE_CHECKING:` (never run) do not."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("torchsoil", "envs")

# The rooms in data-flow order: a room may import itself and the rooms before it. `torchsoil`
# is the library's top level (settings, robot, grid, plotting, memory, engines): what every
# room shares.
ORDER = ("torchsoil", "io", "sim", "envs", "pipeline", "estimate", "geo", "field", "synth", "diagnosis", "jobs", "node",
         "bench", "cli")
# gymnasium.make("torchsoil:torchsoil/SoilTraverse-v0") imports torchsoil, which registers the
# environments by their string entry points: envs.registration imports nothing of the library.
UPSTREAM_EXCEPTIONS = {("torchsoil", "envs.registration")}


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def library_modules(root: Path = ROOT) -> dict[str, Path]:
    return {module_name(p, root): p for pkg in PACKAGES if (root / pkg).is_dir()
            for p in sorted((root / pkg).rglob("*.py"))}


def _type_checking(node: ast.AST) -> bool:
    test = getattr(node, "test", None)
    return isinstance(node, ast.If) and (
        (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING")
        or (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"))


def imports(path: Path, name: str, modules: dict[str, Path]) -> list[tuple[str, str]]:
    """(imported module, imported name or '') of every import in the file that reaches the
    library, `from a import b` resolved to module a.b where that is a module."""
    is_package = path.name == "__init__.py"
    out = []

    def visit(node: ast.AST) -> None:
        if _type_checking(node):
            return
        if isinstance(node, ast.Import):
            out.extend((a.name, "") for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = name.split(".") if is_package else name.split(".")[:-1]
                pkg = pkg[:len(pkg) - node.level + 1]
                base = ".".join([*pkg, *([base] if base else [])])
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.append((sub, "") if sub in modules else (base, a.name))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text()))
    return [(m, n) for m, n in out if m.split(".")[0] in PACKAGES and m in modules]


def room(module: str) -> str:
    """`torchsoil.estimate.windows` -> estimate; `torchsoil.cli` -> cli; `torchsoil.settings` ->
    torchsoil (the shared top level); `envs.core` -> envs."""
    parts = module.split(".")
    if module == "torchsoil.__main__":
        return "cli"
    if parts[0] == "envs":
        return "envs"
    if len(parts) > 1 and parts[1] in ORDER:
        return parts[1]
    return "torchsoil"


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def graph() -> dict[str, list[tuple[str, str]]]:
    modules = library_modules()
    return {name: imports(path, name, modules) for name, path in modules.items()}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan), and modules that
    import themselves."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in edges.get(v, ()):
                found.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            strong(v)
    return found


def test_the_cycle_finder_finds_a_hand_made_cycle():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert sorted(cycles(edges)) == [["a", "b", "c"], ["e"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_import_reader_sees_function_level_and_relative_imports_but_not_type_checking(tmp_path):
    pkg = tmp_path / "torchsoil" / "estimate"
    pkg.mkdir(parents=True)
    (tmp_path / "torchsoil" / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "b.py").write_text("")
    (tmp_path / "torchsoil" / "io.py").write_text("")
    (pkg / "a.py").write_text("from typing import TYPE_CHECKING\nfrom . import b\nif TYPE_CHECKING:\n"
                              "    from torchsoil.io import Thing\ndef f():\n    from torchsoil.io import _x\n")
    found = imports(pkg / "a.py", "torchsoil.estimate.a", library_modules(tmp_path))
    assert found == [("torchsoil.estimate.b", ""), ("torchsoil.io", "_x")]


def test_no_import_cycle_among_the_library_modules():
    edges = {m: {t for t, _ in imps if t != m} for m, imps in graph().items()}
    assert cycles(edges) == []


def test_no_private_name_is_imported_from_another_room():
    bad = [f"{m} imports {t}{'.' + n if n else ''}"
           for m, imps in graph().items() for t, n in imps
           if room(t) != room(m) and any(_private(p) for p in [*t.split("."), n])]
    assert bad == []


@pytest.mark.parametrize("name", ORDER)
def test_each_room_imports_only_rooms_upstream_of_it(name):
    rank = {r: i for i, r in enumerate(ORDER)}
    bad = [f"{m} imports {t}" for m, imps in graph().items() if room(m) == name
           for t, _ in imps if rank[room(t)] > rank[name] and (m, t) not in UPSTREAM_EXCEPTIONS]
    assert bad == []

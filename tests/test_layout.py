"""The house's rule, held against the code: each top-level folder is one room of the pipeline, and
imports flow one way (docs/architecture.md).

Every ``import damcap.X`` / ``from damcap.X import ...`` in a room's modules, at module level or
inside a function, must name a room the importing room may use; and the modules' import graph has
no cycle (two modules that need each other belong together, or a third module holds what they
share).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: room -> the rooms it may import (besides itself)
ALLOWED: dict[str, set[str]] = {
    "common": set(),
    "capture": {"common"},
    "reconstruct": {"common", "capture"},
    "synth": {"common"},
    "appearance": {"common"},
    "export": {"common", "appearance"},
    "paper": {"common", "appearance", "synth"},
    "cli": {"common", "capture", "reconstruct", "synth", "appearance", "export", "paper"},
    "bench": {"common", "capture", "reconstruct", "synth", "appearance", "export", "paper"},
}


def module_name(path: Path) -> str:
    """``appearance/segment/train.py`` -> ``damcap.appearance.segment.train`` (bench: ``bench.x``)."""
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts) if parts[0] == "bench" else "damcap." + ".".join(parts)


def imported_modules(path: Path) -> set[str]:
    """Every damcap module a file imports (absolute or relative, anywhere in the file)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    me = module_name(path).split(".")
    package = me if path.name == "__init__.py" else me[:-1]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith(("damcap.", "bench."))}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.startswith(("damcap.", "bench")):
                out.add(mod)
                out |= {f"{mod}.{a.name}" for a in node.names}  # `from pkg import module`
    return out


def room_files() -> list[Path]:
    return sorted(p for room in ALLOWED for p in (REPO / room).rglob("*.py"))


def room_of(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] == "bench":
        return "bench"
    return parts[1] if len(parts) > 1 and parts[0] == "damcap" else None


def test_rooms_exist():
    for room in ALLOWED:
        assert (REPO / room / "__init__.py").is_file(), f"{room}/ is not a package"


def violations(room: str, modules: set[str]) -> list[str]:
    """The imported damcap modules that ``room`` may not import."""
    return sorted(m for m in modules if room_of(m) in ALLOWED and room_of(m) not in {room} | ALLOWED[room])


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of a directed graph (as a path that returns to its start), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state:
                cycle = visit(n)
                if cycle:
                    return cycle
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            cycle = visit(m)
            if cycle:
                return cycle
    return None


@pytest.mark.parametrize("path", room_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_imports_flow_one_way(path):
    room = path.relative_to(REPO).parts[0]
    bad = violations(room, imported_modules(path))
    assert not bad, f"{path.relative_to(REPO)} ({room}/) imports {bad}; {room}/ may import only {sorted(ALLOWED[room])}"


def test_no_import_cycles():
    modules = {module_name(p): p for p in room_files()}
    graph = {m: {i for i in imported_modules(p) if i in modules and i != m} for m, p in modules.items()}
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_checkers_themselves():
    """A back-flow and a cycle are reported; allowed imports are not."""
    assert violations("appearance", {"damcap.reconstruct.normalize", "damcap.common.mesh", "damcap.appearance.dam"}) \
        == ["damcap.reconstruct.normalize"]
    assert violations("export", {"damcap.appearance.dam"}) == []
    assert violations("synth", {"damcap.capture.raw"}) == ["damcap.capture.raw"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None

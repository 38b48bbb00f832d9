"""The import structure of the package (docs/DESIGN.md section 6): no import cycle, also through
imports inside functions, and the reference engine below the entry point and the jobs."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "dampax"


def _module_name(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """dampax modules imported anywhere in the file (module level and inside functions)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.startswith("dampax"):
                out.add(target)
                for alias in node.names:  # "from . import _x" names a module
                    module = SRC.parent / target.replace(".", "/") / (alias.name + ".py")
                    if module.exists():
                        out.add(f"{target}.{alias.name}")
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("dampax"))
    return out


def _graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for p in SRC.rglob("*.py")}
    graph = {}
    for name, path in files.items():
        # an import of a package runs its __init__; edges to the package itself (its own
        # __init__ from a submodule) are how Python loads it, not a dependency
        graph[name] = {t for t in _imports(path) if t in files and not name.startswith(t + ".")
                       and t != name}
    return graph


def test_no_import_cycle():
    graph = _graph()
    state: dict[str, int] = {}

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(graph[node]):
            if nxt == "dampax":  # the public face re-exports; nothing imports it back
                continue
            if state.get(nxt) == 1:
                pytest.fail("import cycle: " + " -> ".join(path + [nxt]))
            if nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])


def test_reference_engine_imports_only_the_ground_layers():
    allowed = {"dampax._oscillator", "dampax._solution", "dampax._atlas", "dampax._trig"}
    for name, targets in _graph().items():
        if name.startswith("dampax._reference"):
            outside = {t for t in targets if not t.startswith("dampax._reference")}
            assert outside <= allowed, f"{name} imports {sorted(outside - allowed)}"

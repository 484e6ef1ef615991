"""The layout of src/meshseq: no import cycle between its modules, no function over 150 lines.

The import graph is read from the source with ``ast`` (nothing is imported). Its edges are every
``import meshseq...`` / ``from meshseq... import ...`` / ``from . import ...`` statement of a
module, at module level AND inside functions and classes (a deferred import is still a
dependency: the cycles this test was written against, api -> train -> api, ran through imports
inside functions). Imports under ``if TYPE_CHECKING:`` are left out (they never run). An edge goes
to the module named, or to the submodule when ``from package import name`` names one; the
implicit import of a module's parent package is not an edge (a package's ``__init__`` re-exporting
its submodules would otherwise always close a cycle).
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
MAX_FUNCTION_LINES = 150


def modules(root: Path = SRC) -> dict[str, tuple[Path, bool]]:
    """``{dotted name: (file, is package)}`` of every module under ``root/meshseq``."""
    out = {}
    for path in sorted((root / "meshseq").rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        package = parts[-1] == "__init__"
        out[".".join(parts[:-1] if package else parts)] = (path, package)
    return out


def _type_checking(node: ast.If) -> bool:
    t = node.test
    return getattr(t, "id", None) == "TYPE_CHECKING" or getattr(t, "attr", None) == "TYPE_CHECKING"


def imported(name: str, path: Path, package: bool, known: dict) -> set[str]:
    """The meshseq modules that module ``name`` imports anywhere in its code."""
    base = name if package else name.rpartition(".")[0]

    def resolve(target: str) -> str | None:
        while target and target not in known:
            target = target.rpartition(".")[0]
        return target or None

    out = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            out.update(resolve(a.name) for a in node.names if a.name.split(".")[0] == "meshseq")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = base.split(".")
                target = ".".join(parts[:len(parts) - node.level + 1] + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "meshseq":
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    out.add(sub if sub in known else resolve(target))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text(), str(path)))
    return {m for m in out if m and m != name}


def import_graph(root: Path = SRC) -> dict[str, set[str]]:
    known = modules(root)
    return {name: imported(name, path, package, known) for name, (path, package) in known.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle ``[a, b, ..., a]`` of ``graph``, or None (depth-first search, white/grey/black)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(v: str) -> list[str] | None:
        state[v] = 1
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if state.get(w) == 1:
                return stack[stack.index(w):] + [w]
            if w not in state and (found := dfs(w)):
                return found
        stack.pop()
        state[v] = 2
        return None

    for v in sorted(graph):
        if v not in state and (found := dfs(v)):
            return found
    return None


def long_functions(root: Path = SRC, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """``path:line name (N lines)`` of every function or method in src/meshseq over ``limit`` lines
    (from its ``def`` to its last line, decorators and docstring included)."""
    out = []
    for path, _ in modules(root).values():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > limit:
                    out.append(f"{path.relative_to(root)}:{node.lineno} {node.name} ({n} lines)")
    return out


def test_src_meshseq_has_no_import_cycle():
    graph = import_graph()
    assert "meshseq.training.loop" in graph and "meshseq.api" in graph["meshseq.training.loop"]
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_function_in_src_meshseq_is_longer_than_150_lines():
    assert long_functions() == []


def test_the_checks_find_what_they_look_for(tmp_path):
    """The graph reader sees deferred and relative imports (and skips TYPE_CHECKING), the cycle
    finder names a cycle, and the length check counts a long function."""
    pkg = tmp_path / "meshseq"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from . import b\n")
    (pkg / "a.py").write_text("def f():\n    from meshseq.sub import b\n")
    (pkg / "sub" / "b.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import meshseq.c\n"
                                      "from .. import a\n")
    (pkg / "c.py").write_text("def g():\n" + "    x = 1\n" * 150)
    graph = import_graph(tmp_path)
    assert graph["meshseq.a"] == {"meshseq.sub.b"}
    assert graph["meshseq.sub.b"] == {"meshseq.a"}  # TYPE_CHECKING left out; `from .. import a` found
    assert graph["meshseq.sub"] == {"meshseq.sub.b"}
    assert find_cycle(graph) in (["meshseq.a", "meshseq.sub.b", "meshseq.a"],
                                 ["meshseq.sub.b", "meshseq.a", "meshseq.sub.b"])
    assert find_cycle({"x": {"y"}, "y": set()}) is None
    assert long_functions(tmp_path) == [f"{Path('meshseq/c.py')}:1 g (151 lines)"]

"""The code's shape, as promised in docs/architecture.md: short functions, a filter update that
reads as its pipeline, and no docstring or comment that points outside the repository (unique
module names: tests/test_module_names.py).

These read the source (``ast``), not the behaviour; the import contracts (layers, no cycles,
the daemon never imports the evaluations) are import-linter's, in pyproject.toml.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("lino_loc", "drivers", "services", "benchmarks")


def _sources(*roots: str) -> list[Path]:
    return sorted(p for r in roots for p in (ROOT / r).rglob("*.py"))


def _functions(path: Path) -> list[tuple[str, int, int]]:
    """(qualified name, first line, number of lines) of every function in a file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out: list[tuple[str, int, int]] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = prefix + child.name
                out.append((name, child.lineno, child.end_lineno - child.lineno + 1))
                visit(child, name + ".")
            elif isinstance(child, ast.ClassDef):
                visit(child, prefix + child.name + ".")

    visit(tree, "")
    return out


def _long_functions(paths: list[Path], limit: int, base: Path = ROOT) -> list[str]:
    return [
        f"{p.relative_to(base)}:{line} {name} ({n} lines)"
        for p in paths
        for name, line, n in _functions(p)
        if n > limit
    ]


def test_the_filter_update_reads_as_its_pipeline() -> None:
    path = ROOT / "lino_loc" / "particle_filter.py"
    (n,) = [n for name, _, n in _functions(path) if name == "AuxiliaryParticleFilter.update"]
    assert n < 25, f"AuxiliaryParticleFilter.update has {n} lines"


@pytest.mark.parametrize("where", ["lino_loc", "services/daemon.py"])
def test_no_function_over_60_lines(where: str) -> None:
    paths = [ROOT / where] if where.endswith(".py") else _sources(where)
    assert _long_functions(paths, 60) == []


_OUTSIDE = re.compile(r"design\.md|\bissues? #?\d+\b|\.\./shared", re.IGNORECASE)


def test_no_docstring_or_comment_points_outside_the_repository() -> None:
    hits = [
        f"{p.relative_to(ROOT)}:{i}: {line.strip()}"
        for p in _sources(*PACKAGES, "tests")
        for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
        if _OUTSIDE.search(line)
    ]
    assert hits == []


def test_the_checks_see_what_they_check(tmp_path: Path) -> None:
    """The counting itself: a 3-line function and a nested method are found with their sizes."""
    f = tmp_path / "m.py"
    f.write_text("def a():\n    x = 1\n    return x\n\nclass C:\n    def b(self):\n        pass\n")
    assert _functions(f) == [("a", 1, 3), ("C.b", 6, 2)]
    assert _long_functions([f], 2, base=tmp_path) == ["m.py:1 a (3 lines)"]
    assert _long_functions([f], 3, base=tmp_path) == []

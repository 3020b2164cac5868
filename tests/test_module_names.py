"""Every Python module of the repository has a file name of its own (packages' __init__.py aside),
so that a name in a traceback, a grep or an import names one file."""

from __future__ import annotations

import collections
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TREES = ("lino_loc", "drivers", "services", "benchmarks", "tests", "scripts")


def test_no_two_modules_share_a_file_name() -> None:
    names: dict[str, list[str]] = collections.defaultdict(list)
    for tree in TREES:
        for path in (ROOT / tree).rglob("*.py"):
            if path.name != "__init__.py" and ".venv" not in path.parts:
                names[path.name].append(str(path.relative_to(ROOT)))
    assert not {n: p for n, p in names.items() if len(p) > 1}

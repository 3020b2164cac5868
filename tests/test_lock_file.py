"""requirements/robot.lock (scripts/lock.sh) pins the whole core install and nothing else.

Every dependency of ``[project] dependencies`` in pyproject.toml is in the lock file with an
exact version that satisfies its range; the extras (``eval``, ``test``) are not; every line is
``name==version``; docs/install.md installs from it.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
LOCK = ROOT / "requirements" / "robot.lock"


def _pins() -> dict[str, Version]:
    pins: dict[str, Version] = {}
    for raw in LOCK.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        m = re.fullmatch(r"([A-Za-z0-9_.-]+)==([0-9][A-Za-z0-9_.+!-]*)", line)
        assert m, f"{LOCK.name}: not an exact pin: {line!r}"
        name = canonicalize_name(m.group(1))
        assert name not in pins, f"{LOCK.name}: {name} twice"
        pins[name] = Version(m.group(2))
    return pins


def _project() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def test_every_core_dependency_is_pinned_within_its_range() -> None:
    pins = _pins()
    for spec in _project()["dependencies"]:
        req = Requirement(spec)
        name = canonicalize_name(req.name)
        assert name in pins, f"{LOCK.name} lacks {req.name} (run scripts/lock.sh)"
        assert req.specifier.contains(pins[name], prereleases=True), f"{name}=={pins[name]} is not {req.specifier}"


def test_no_extra_is_in_the_robot_lock() -> None:
    pins = _pins()
    core = {canonicalize_name(Requirement(s).name) for s in _project()["dependencies"]}
    for extra, specs in _project()["optional-dependencies"].items():
        for spec in specs:
            name = canonicalize_name(Requirement(spec).name)
            if name != "lino-loc" and name not in core:
                assert name not in pins, f"{name} (extra {extra}) is in the robot's lock file"
    assert "lino-loc" not in pins


def test_install_guide_uses_the_lock_file() -> None:
    text = (ROOT / "docs" / "install.md").read_text(encoding="utf-8")
    assert "pip install -r requirements/robot.lock" in text
    assert "pip install --no-deps ." in text

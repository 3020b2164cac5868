"""What `pip install .` installs: every package, and the config folder's files as the data
package ``lino_loc_config``, so that an installed service finds its worlds and the simulated
robot's configuration without a checkout, and without the optional extras."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CODE = ("lino_loc", "drivers", "services")
DATA = {"lino_loc_config", "lino_loc_config.worlds"}


def _listed() -> set[str]:
    with (ROOT / "pyproject.toml").open("rb") as f:
        return set(tomllib.load(f)["tool"]["setuptools"]["packages"])


def test_every_package_is_listed_for_installation() -> None:
    found = {
        ".".join(init.parent.relative_to(ROOT).parts)
        for top in CODE
        for init in (ROOT / top).rglob("__init__.py")
    }
    assert _listed() == found | DATA


def test_an_installed_wheel_finds_its_worlds_and_the_sim_config(tmp_path: Path) -> None:
    src = tmp_path / "src"  # build from a copy: the build leaves build/ and egg-info behind
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "build")
    for name in (*CODE, "config"):
        shutil.copytree(ROOT / name, src / name, ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    out = tmp_path / "wheel"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
         "-w", str(out), "."],
        cwd=src, check=True, capture_output=True, timeout=300,
    )
    (wheel,) = out.glob("lino_loc-*.whl")
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    probe = f"""
import sys
sys.modules["matplotlib"] = None  # the core install has no eval extra
from pathlib import Path
import drivers, services.daemon, services.commands.run
from drivers.sim.config_files import CONFIG_DIR, SIM_TOML
from drivers.sim.world import load_world
from services.config import load_config
site = Path({str(site)!r})
assert Path(drivers.__file__).is_relative_to(site), drivers.__file__
assert CONFIG_DIR == site / "lino_loc_config", CONFIG_DIR
assert load_world("office").name and load_world("lab").name
assert load_config(SIM_TOML).simulated
print("ok")
"""
    env = {**os.environ, "PYTHONPATH": str(site)}
    run = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr

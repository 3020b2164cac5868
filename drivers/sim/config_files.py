"""Where the files of the repository's ``config/`` folder are: the simulated worlds
(``worlds/*.json``) and the simulated robot's configuration (``sim.toml``).

In a checkout, or an editable install, they are the checkout's own ``config/``; in an
installed wheel they are the data package ``lino_loc_config`` that ``pyproject.toml`` builds
from that folder. When neither is there the checkout's path is returned, so that an error
names the place that was looked in.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

__all__ = ["CONFIG_DIR", "SIM_TOML", "WORLDS_DIR", "config_dir"]


def config_dir() -> Path:
    """The folder holding ``sim.toml`` and ``worlds/`` (see the module docstring)."""
    checkout = Path(__file__).resolve().parents[2] / "config"
    if (checkout / "worlds").is_dir():
        return checkout
    spec = importlib.util.find_spec("lino_loc_config")
    if spec is not None and spec.submodule_search_locations:
        installed = Path(next(iter(spec.submodule_search_locations)))
        if (installed / "worlds").is_dir():
            return installed
    return checkout


CONFIG_DIR = config_dir()
WORLDS_DIR = CONFIG_DIR / "worlds"
SIM_TOML = CONFIG_DIR / "sim.toml"

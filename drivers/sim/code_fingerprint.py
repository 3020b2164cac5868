"""Fingerprint of the code that renders a simulated view and builds a map from it.

A cached rendered view or map made by other code is stale: :func:`code_fingerprint` is part
of every such cache key (the evaluations' survey maps and the simulated service's map).
"""

from __future__ import annotations

import hashlib
import importlib
from pathlib import Path

#: Modules whose code decides a rendered view and the map built from it.
CACHE_CODE: tuple[str, ...] = (
    "drivers.sim.renderer", "drivers.sim.lighting", "drivers.sim.textures", "drivers.sim.world",
    "drivers.sim.survey",
    "lino_loc.preprocessing", "lino_loc.disparity", "lino_loc.pca", "lino_loc.pca_missing",
    "lino_loc.virtual_views", "lino_loc.virtual_translations", "lino_loc.appearance_map",
)


def code_fingerprint() -> str:
    """First 8 hex digits of the SHA-256 of the sources of :data:`CACHE_CODE`, in that order."""
    h = hashlib.sha256()
    for name in CACHE_CODE:
        source = importlib.import_module(name).__file__
        if source is not None:
            h.update(Path(source).read_bytes())
    return h.hexdigest()[:8]

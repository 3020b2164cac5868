"""Which lattice positions of the cells a survey could not stand in its neighbours see.

A survey stands at the positions of a regular grid (spacing ``step``) that are free; a cell
whose centre is blocked (a table, a cabinet) holds no survey position, although its free floor
around the obstacle is where a robot may later stand. Virtual translations
(:func:`lino_loc.virtual_translations.translate_survey`) see every surveyed cell's lattice
(``step / m`` apart, :func:`lino_loc.virtual_translations.lattice_offsets`) from its survey
position; :func:`cover_offsets` gives, for one survey position, the lattice positions of its
eight neighbouring cells that hold no survey position and whose nearest survey position it is
(ties to the lexicographically first of the nearest; no farther than ``reach``), so that every
such lattice position is seen from exactly one survey position, with all its headings, and the
map stays a product grid of positions x headings. Whether a covered position is free is the
caller's ``keep`` (a floor plan): without one, an unsurveyed cell may as well lie beyond a wall.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: Neighbouring cells, in cells (x major).
NEIGHBOUR_CELLS = np.array([[i, j] for i in (-1, 0, 1) for j in (-1, 0, 1) if (i, j) != (0, 0)], dtype=np.float64)


def cover_offsets(xy: ArrayLike, survey_xy: ArrayLike, step: float, cell_offsets: ArrayLike,
                  reach: float | None = None, tol: float = 1e-6) -> FloatArray:
    """Offsets (K, 2) from the survey position ``xy`` of the lattice positions it covers in its
    unsurveyed neighbouring cells (module docstring). ``survey_xy`` (N, 2): every survey
    position (``xy`` among them); ``step``: the survey's spacing (m); ``cell_offsets`` (m^2, 2):
    a cell's lattice around its centre; ``reach``: the farthest covered position (m, default
    ``step``). A cell counts as surveyed when a survey position lies within ``step / 2`` of its
    centre."""
    p = np.asarray(xy, dtype=np.float64).reshape(2)
    s = np.asarray(survey_xy, dtype=np.float64).reshape(-1, 2)
    cells = p + step * NEIGHBOUR_CELLS  # (8, 2) neighbouring cell centres
    to_cells = np.hypot(cells[:, None, 0] - s[None, :, 0], cells[:, None, 1] - s[None, :, 1])
    empty = cells[np.min(to_cells, axis=1) >= 0.5 * step - tol]
    if empty.shape[0] == 0:
        return np.zeros((0, 2))
    pts = (empty[:, None, :] + np.asarray(cell_offsets, dtype=np.float64)[None, :, :]).reshape(-1, 2)
    d = np.hypot(pts[:, None, 0] - s[None, :, 0], pts[:, None, 1] - s[None, :, 1])  # (K, N)
    nearest = d <= np.min(d, axis=1, keepdims=True) + tol
    order = np.lexsort((np.round(s[:, 1], 6), np.round(s[:, 0], 6)))  # survey positions, x then y
    first = order[np.argmax(nearest[:, order], axis=1)]  # the first of the nearest, in that order
    mine = np.all(np.abs(s[first] - p) <= tol, axis=1)
    mine &= np.hypot(pts[:, 0] - p[0], pts[:, 1] - p[1]) <= (step if reach is None else reach) + tol
    return pts[mine] - p

"""What one cell of a multi-room world can see of the others: sound culling for renderer and bake.

The cells of a :class:`~drivers.sim.rooms.Layout` are convex and closed by their walls except
at portals (:mod:`drivers.sim.rooms`). A straight sight line that starts inside a cell
therefore either ends at one of that cell's walls or leaves through a portal into the next
cell; the cells it visits are joined by a chain of portals that the line *stabs*, crossing
each in the direction of the chain. Two sets follow (Teller and Sequin, "Visibility
preprocessing for interactive walkthroughs", SIGGRAPH 1991, in 2D):

- :func:`potentially_visible` (region to region, for the light bake): the cells reached from a
  cell by some stabbed chain. A line stabs portals ``(L_i, R_i)`` (left and right end points
  seen along the chain) iff some ``f(p) = a x + b y + c`` has ``f(L_i) >= 0 >= f(R_i)`` for
  every i; with ``f(L_1) - f(R_1) = 1`` fixing the scale, a linear feasibility problem
  (scipy's HiGHS). Touching lines count, so the set errs on the side of seeing more.
- :func:`visible_cells` (point to region, per rendered view): the cells reached from the
  camera's position through chains of portals whose angular wedges, seen from that point,
  still overlap the view's azimuth range; each portal's wedge is widened by
  :data:`ANGLE_MARGIN`.

Geometry of the cells outside these sets cannot change a ray or a shadow ray: every ray that
reaches it first crosses a wall of a cell in the set (which the culled computation keeps).
:class:`CellSets` lists, per cell, the walls on its boundary and the boxes whose footprint
touches it, so that a set of cells gives the walls and boxes to trace.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog

from drivers.sim.rooms import Layout
from drivers.sim.world_parts import Box

#: Widening (rad) of every portal's angular wedge and of the view's azimuth range.
ANGLE_MARGIN = 1e-6
#: A point closer than this (m) to a cell counts as inside it.
CELL_EPS = 1e-6


def cells_at(rects: np.ndarray, x: np.ndarray, y: np.ndarray, eps: float = CELL_EPS) -> np.ndarray:
    """(N, C) bool: point n inside (or within ``eps`` of) cell rectangle c."""
    x = np.asarray(x, np.float64)[:, None]
    y = np.asarray(y, np.float64)[:, None]
    return ((x >= rects[None, :, 0] - eps) & (x <= rects[None, :, 1] + eps)
            & (y >= rects[None, :, 2] - eps) & (y <= rects[None, :, 3] + eps))


def _oriented(layout: Layout) -> dict[int, list[tuple[int, np.ndarray, np.ndarray]]]:
    """Per cell, its portals as (next cell, left end, right end) seen from the cell."""
    rects = layout.rects
    out: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = {i: [] for i in range(len(rects))}
    for p in layout.portals:
        p0, p1 = np.array(p.p0), np.array(p.p1)
        for src, dst in ((p.a, p.b), (p.b, p.a)):
            r = rects[dst]
            into = np.array([(r[0] + r[1]) / 2, (r[2] + r[3]) / 2]) - 0.5 * (p0 + p1)
            e = p1 - p0
            n = np.array([-e[1], e[0]])
            if np.dot(n, into) < 0:
                n = -n
            # looking along n, the left side is n rotated counter-clockwise
            left = np.array([-n[1], n[0]])
            a, b = (p1, p0) if np.dot(left, p1 - p0) > 0 else (p0, p1)
            out[src].append((dst, a, b))
    return out


def _stabbable(chain: list[tuple[np.ndarray, np.ndarray]]) -> bool:
    """Whether a line crosses every portal (L, R) of ``chain`` with L on its left (touching counts)."""
    if len(chain) <= 1:
        return True
    a_ub, b_ub = [], []
    for left, right in chain:
        a_ub.append([-left[0], -left[1], -1.0])
        a_ub.append([right[0], right[1], 1.0])
        b_ub += [0.0, 0.0]
    l1, r1 = chain[0]
    res = linprog(np.zeros(3), A_ub=np.array(a_ub), b_ub=np.array(b_ub),
                  A_eq=np.array([[l1[0] - r1[0], l1[1] - r1[1], 0.0]]), b_eq=np.array([1.0]),
                  bounds=[(None, None)] * 3, method="highs")
    return bool(res.status == 0)


def potentially_visible(layout: Layout) -> list[np.ndarray]:
    """Per cell, the sorted indices of the cells some sight line from it reaches (itself included)."""
    ports = _oriented(layout)
    out = []
    for start in range(len(layout.cells)):
        seen = {start}
        _walk_chains(ports, start, [], {start}, seen)
        out.append(np.array(sorted(seen), np.int64))
    return out


def _walk_chains(ports: dict[int, list[tuple[int, np.ndarray, np.ndarray]]], cell: int,
                 chain: list[tuple[np.ndarray, np.ndarray]], path: set[int], seen: set[int]) -> None:
    """Depth first over the portal chains from ``cell`` that a line can stab; adds their cells to ``seen``."""
    for nxt, left, right in ports[cell]:
        if nxt in path:
            continue
        c2 = [*chain, (left, right)]
        if _stabbable(c2):
            seen.add(nxt)
            _walk_chains(ports, nxt, c2, path | {nxt}, seen)


def _wedge(ox: float, oy: float, a: np.ndarray, b: np.ndarray) -> tuple[float, float] | None:
    """(start angle, width) of the directions from (ox, oy) through segment a-b, widened by
    :data:`ANGLE_MARGIN`; None when the point is on the segment's line (no narrowing)."""
    ta = math.atan2(a[1] - oy, a[0] - ox)
    tb = math.atan2(b[1] - oy, b[0] - ox)
    cross = (a[0] - ox) * (b[1] - oy) - (a[1] - oy) * (b[0] - ox)
    if abs(cross) <= CELL_EPS * max(1.0, math.dist(a, b)):
        return None
    start, end = (ta, tb) if cross > 0 else (tb, ta)
    width = (end - start) % (2 * math.pi)
    return start - ANGLE_MARGIN, width + 2 * ANGLE_MARGIN


def _intersect(w1: tuple[float, float] | None, w2: tuple[float, float] | None) -> tuple[float, float] | None | bool:
    """Intersection of two wedges (start, width), each narrower than pi, or None (every
    direction); False when empty."""
    if w1 is None:
        return w2
    if w2 is None:
        return w1
    s1, d1 = w1
    s2, d2 = w2
    rel = (s2 - s1 + math.pi) % (2 * math.pi) - math.pi  # start of w2 seen from the start of w1
    lo, hi = max(0.0, rel), min(d1, rel + d2)
    if hi < lo:
        return False
    return s1 + lo, hi - lo


Ports = dict[int, list[tuple[int, np.ndarray, np.ndarray]]]


def oriented_portals(layout: Layout) -> Ports:
    """Per cell, its portals as (next cell, left end, right end) seen from the cell."""
    return _oriented(layout)


def visible_cells(layout: Layout, ox: float, oy: float, az0: float, az1: float,
                  ports: Ports | None = None) -> np.ndarray | None:
    """Sorted indices of the cells that rays from (ox, oy) with azimuths in [az0, az1] (radians,
    ``az1 - az0`` may exceed pi) can reach; None when the point is in no cell (trace everything)."""
    rects = layout.rects
    start = np.flatnonzero(cells_at(rects, np.array([ox]), np.array([oy]))[0])
    if start.size == 0:
        return None
    ports = ports if ports is not None else _oriented(layout)
    span = az1 - az0 + 2 * ANGLE_MARGIN
    fov = None if span >= math.pi else (az0 - ANGLE_MARGIN, span)
    seen = set(int(c) for c in start)

    def walk(cell: int, wedge: tuple[float, float] | None, path: frozenset[int]) -> None:
        for nxt, left, right in ports[cell]:
            if nxt in path:
                continue
            w = _intersect(wedge, _wedge(ox, oy, right, left))
            if w is False or w is True:
                continue
            seen.add(nxt)
            walk(nxt, w, path | {nxt})

    for c in start:
        walk(int(c), fov, frozenset({int(c)}))
    return np.array(sorted(seen), np.int64)


@dataclass(frozen=True)
class CellSets:
    """Per cell, the indices of the walls (of a geometry's wall list) on its boundary and of the
    boxes whose footprint's bounding rectangle touches the cell."""

    walls: list[np.ndarray]
    boxes: list[np.ndarray]
    box_free: np.ndarray  # boxes touching no cell (never seen from a cell)

    def union(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sorted wall and box indices of the cells ``cells``."""
        w = np.unique(np.concatenate([self.walls[c] for c in cells])) if len(cells) else np.zeros(0, np.int64)
        b = np.unique(np.concatenate([self.boxes[c] for c in cells])) if len(cells) else np.zeros(0, np.int64)
        return w.astype(np.int64), b.astype(np.int64)


def cell_sets(layout: Layout, n_other_walls: int, boxes: tuple[Box, ...]) -> CellSets:
    """:class:`CellSets` of a geometry whose walls are ``n_other_walls`` free walls (none in a
    world with rooms) followed by ``layout.walls``, and whose boxes are ``boxes``."""
    if n_other_walls:
        raise ValueError("a world with rooms has no free walls")
    nc = len(layout.cells)
    walls = [np.flatnonzero(layout.wall_cell == c) for c in range(nc)]
    rects = layout.rects
    if boxes:
        corners = np.stack([b.corners() for b in boxes])  # (B, 4, 2)
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        touch = ((lo[:, None, 0] <= rects[None, :, 1] + CELL_EPS) & (hi[:, None, 0] >= rects[None, :, 0] - CELL_EPS)
                 & (lo[:, None, 1] <= rects[None, :, 3] + CELL_EPS) & (hi[:, None, 1] >= rects[None, :, 2] - CELL_EPS))
    else:
        touch = np.zeros((0, nc), bool)
    return CellSets(walls=walls, boxes=[np.flatnonzero(touch[:, c]) for c in range(nc)],
                    box_free=np.flatnonzero(~touch.any(axis=1)))

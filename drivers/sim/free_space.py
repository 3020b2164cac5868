"""Free space of a simulated world as a raster, for the simulated base's 50 Hz kinematics.

:class:`FreeSpace` rasterizes :meth:`drivers.sim.world.World.is_free` once on a fine grid
(``cell`` metres) so that the kinematics can ask "is the robot disc free here?" in
microseconds instead of milliseconds. The raster is conservative: it is computed for the
radius ``radius + cell / sqrt(2)``, and a query reads the nearest grid point, which is at most
``cell / sqrt(2)`` away, so a point it calls free is free for ``radius`` (the disc around the
query lies inside the larger disc around the grid point).

:func:`free_loop_box` finds, from a world's free space alone, where a closed test loop fits:
the box of the longest superellipse (:func:`superellipse`) inside the mapped area whose every
point leaves a robot disc of ``radius + margin`` free (walls and furniture footprints). The
search is seeded: the same world and seed give the same box.

Usage::

    free = FreeSpace(world, radius=0.25)
    free.free_point(x, y)
    box = free_loop_box(world, seed=0)      # (xmin, xmax, ymin, ymax)
"""

from __future__ import annotations

import math

import numpy as np

from drivers.sim.world import World
from lino_loc.errors import LinoLocError

Box4 = tuple[float, float, float, float]

#: Loop boxes narrower than this (m) on either axis are not considered: a loop there is a line.
MIN_LOOP_SIDE = 0.3
#: Step (m) by which :func:`free_loop_box` grows a side of the best lattice box.
LOOP_GROW_STEP = 0.05
#: Points at which a candidate loop is checked (every 3.5 cm of a 28 m loop).
LOOP_POINTS = 800
#: Candidate loops checked at once (one vectorized raster look-up).
LOOP_BATCH = 256
#: A lattice axis of :func:`free_loop_box` has at least this many lines across the mapped area.
LATTICE_LINES = 20
#: Cell (m) of the free-space raster of :func:`free_loop_box`.
FREE_LOOP_CELL = 0.02


class FreeSpace:
    """Conservative raster of where a robot disc of ``radius`` fits (see module docstring)."""

    def __init__(
        self,
        world: World,
        radius: float = 0.25,
        scene_changes: tuple[str, ...] | list[str] = (),
        cell: float = 0.02,
    ) -> None:
        self.world = world
        self.radius = float(radius)
        self.cell = float(cell)
        self.scene_changes = world.check_changes(tuple(scene_changes))
        xmin, xmax, ymin, ymax = world.room
        self.x0, self.y0 = xmin, ymin
        self.nx = int(math.ceil((xmax - xmin) / cell)) + 1
        self.ny = int(math.ceil((ymax - ymin) / cell)) + 1
        xs = xmin + cell * np.arange(self.nx)
        ys = ymin + cell * np.arange(self.ny)
        margin = cell * math.sqrt(0.5)
        self.grid = world.is_free(
            xs[:, None], ys[None, :], self.radius + margin, self.scene_changes
        )

    def is_free(self, x: float | np.ndarray, y: float | np.ndarray) -> np.ndarray:
        """True where the disc fits for sure (vectorized; outside the room: False)."""
        ix = np.rint((np.asarray(x, dtype=np.float64) - self.x0) / self.cell).astype(np.int64)
        iy = np.rint((np.asarray(y, dtype=np.float64) - self.y0) / self.cell).astype(np.int64)
        inside = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)
        out = np.zeros(np.broadcast(ix, iy).shape, dtype=bool)
        out[inside] = self.grid[ix[inside], iy[inside]]
        return out

    def free_point(self, x: float, y: float) -> bool:
        """Scalar :meth:`is_free`."""
        ix = int(round((x - self.x0) / self.cell))
        iy = int(round((y - self.y0) / self.cell))
        return 0 <= ix < self.nx and 0 <= iy < self.ny and bool(self.grid[ix, iy])

    def segment_free(
        self, a: tuple[float, float], b: tuple[float, float], clearance: float = 0.0
    ) -> bool:
        """True if the disc of ``radius + clearance`` fits all along the straight segment a-b
        (sampled every cell; with clearance the world is asked directly, vectorized)."""
        length = math.dist(a, b)
        n = max(2, int(math.ceil(length / self.cell)) + 1)
        t = np.linspace(0.0, 1.0, n)
        xs = a[0] + t * (b[0] - a[0])
        ys = a[1] + t * (b[1] - a[1])
        if clearance <= 0.0:
            return bool(np.all(self.is_free(xs, ys)))
        return bool(np.all(self.world.is_free(xs, ys, self.radius + clearance, self.scene_changes)))


def superellipse(box: Box4, exponent: float, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """``samples + 1`` points (x, y) of the closed curve ``|x - cx|^p / a^p + |y - cy|^p / b^p = 1``
    (p = ``exponent``) inscribed in ``box`` = (xmin, xmax, ymin, ymax), counter-clockwise from
    (xmax, cy), the last point equal to the first: ``x = cx + a sgn(cos t) |cos t|^(2/p)``,
    ``y = cy + b sgn(sin t) |sin t|^(2/p)`` at ``samples + 1`` equally spaced t in [0, 2 pi]."""
    xmin, xmax, ymin, ymax = (float(v) for v in box)
    cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
    a, b = 0.5 * (xmax - xmin), 0.5 * (ymax - ymin)
    t = np.linspace(0.0, 2.0 * np.pi, samples + 1)
    c, s = np.cos(t), np.sin(t)
    e = 2.0 / exponent
    return cx + a * np.sign(c) * np.abs(c) ** e, cy + b * np.sign(s) * np.abs(s) ** e


def _unit_loop(exponent: float, samples: int = 0) -> np.ndarray:
    """(2, n) points of the superellipse of the box (-1, 1, -1, 1): scaled by the half sizes
    and shifted by the centre, any box's loop (n = ``samples`` or :data:`LOOP_POINTS`)."""
    x, y = superellipse((-1.0, 1.0, -1.0, 1.0), exponent, samples or LOOP_POINTS)
    return np.stack([x[:-1], y[:-1]])


def _loops_free(free: FreeSpace, boxes: np.ndarray, unit: np.ndarray) -> np.ndarray:
    """(B,) whether the loop of each box (B, 4) is free in the raster ``free``."""
    c = 0.5 * (boxes[:, [0, 2]] + boxes[:, [1, 3]])
    h = 0.5 * (boxes[:, [1, 3]] - boxes[:, [0, 2]])
    x = c[:, :1] + h[:, :1] * unit[0][None, :]
    y = c[:, 1:] + h[:, 1:] * unit[1][None, :]
    return free.is_free(x, y).all(axis=1)


def _off_grid(v: np.ndarray, origin: float, step: float | None) -> np.ndarray:
    """Whether the coordinates ``v`` are at least ``step / 4`` from every line ``origin + k step``
    (all True without a step)."""
    if step is None:
        return np.ones(np.shape(v), bool)
    r = np.mod(np.asarray(v, dtype=np.float64) - origin, step)
    return np.minimum(r, step - r) >= 0.25 * step - 1e-9


def _grow(free: FreeSpace, box: np.ndarray, bounds: Box4, unit: np.ndarray, grid_step: float | None) -> np.ndarray:
    """Move the sides of ``box`` outward by :data:`LOOP_GROW_STEP`, one side at a time (xmin,
    xmax, ymin, ymax in turn), as long as the loop stays free, inside ``bounds`` and each side
    off the survey grid's lines (:func:`_off_grid`)."""
    cur = np.asarray(box, dtype=np.float64).copy()
    grew = True
    while grew:
        grew = False
        for k, sign in ((0, -1.0), (1, 1.0), (2, -1.0), (3, 1.0)):
            cand = cur.copy()
            step = cand[k] + sign * LOOP_GROW_STEP
            cand[k] = max(step, bounds[k]) if sign < 0 else min(step, bounds[k])
            origin = bounds[0] if k < 2 else bounds[2]
            if (cand[k] != cur[k] and _off_grid(cand[k], origin, grid_step)
                    and _loops_free(free, cand[None, :], unit)[0]):
                cur = cand
                grew = True
    return cur


def free_loop_box(
    world: World,
    seed: int = 0,
    radius: float = 0.25,
    margin: float = 0.1,
    exponent: float = 4.0,
    lattice: float = 0.1,
    grid_step: float | None = None,
) -> Box4:
    """The box (xmin, xmax, ymin, ymax) of the longest free test loop (see the module docstring).

    The free space is a :class:`FreeSpace` raster for a disc of ``radius + margin`` in the
    world without scene changes. The candidate boxes have their sides on a lattice of
    ``lattice`` metres inside the mapped area, shifted from its minimum corner by an offset in
    [0, ``lattice``) per axis drawn from ``numpy.random.default_rng(seed)``, both sides at
    least :data:`MIN_LOOP_SIDE`; with ``grid_step`` (the survey grid's step, the grid starting
    at the mapped area's minimum corner) only lattice lines at least ``grid_step / 4`` from the
    grid's lines, so that the loop's straight stretches run between surveyed rows and columns. Their loops (:func:`superellipse` with ``exponent``, checked at
    :data:`LOOP_POINTS` points) are tried longest perimeter first (ties: the order of the
    lattice); the first free one is grown side by side (:func:`_grow`) while it stays free and
    inside the mapped area. Raises :class:`LinoLocError` naming the world when no loop fits."""
    if radius <= 0 or margin < 0 or exponent <= 0 or lattice <= 0:
        raise LinoLocError(f"free loop: bad parameters (radius {radius}, margin {margin}, "
                           f"exponent {exponent}, lattice {lattice})")
    bounds = world.mapped_area
    mx0, mx1, my0, my1 = bounds
    lx = min(lattice, (mx1 - mx0) / LATTICE_LINES)
    ly = min(lattice, (my1 - my0) / LATTICE_LINES)
    off = np.random.default_rng(seed).uniform(0.0, 1.0, 2) * (lx, ly)
    gx = mx0 + off[0] + lx * np.arange(int(math.floor((mx1 - mx0 - off[0]) / lx)) + 1)
    gy = my0 + off[1] + ly * np.arange(int(math.floor((my1 - my0 - off[1]) / ly)) + 1)
    gx = gx[_off_grid(gx, mx0, grid_step)]
    gy = gy[_off_grid(gy, my0, grid_step)]
    ix0, ix1 = np.triu_indices(len(gx), 1)
    iy0, iy1 = np.triu_indices(len(gy), 1)
    sx = gx[ix1] - gx[ix0]
    sy = gy[iy1] - gy[iy0]
    kx = np.flatnonzero(sx >= MIN_LOOP_SIDE)
    ky = np.flatnonzero(sy >= MIN_LOOP_SIDE)
    px, py = np.meshgrid(kx, ky, indexing="ij")
    px, py = px.ravel(), py.ravel()
    order = np.argsort(-(sx[px] + sy[py]), kind="stable")
    free = FreeSpace(world, radius + margin, cell=FREE_LOOP_CELL)
    unit = _unit_loop(exponent)
    for b0 in range(0, order.size, LOOP_BATCH):
        sel = order[b0:b0 + LOOP_BATCH]
        boxes = np.column_stack([gx[ix0[px[sel]]], gx[ix1[px[sel]]], gy[iy0[py[sel]]], gy[iy1[py[sel]]]])
        ok = np.flatnonzero(_loops_free(free, boxes, unit))
        if ok.size:
            b = _grow(free, boxes[ok[0]], bounds, unit, grid_step)
            return float(b[0]), float(b[1]), float(b[2]), float(b[3])
    raise LinoLocError(f"free loop: no closed loop fits the free space of world '{world.name}' "
                       f"(radius {radius} + margin {margin} m, mapped area {bounds})")

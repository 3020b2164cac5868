"""Free space of a simulated world as a raster, for the simulated base's 50 Hz kinematics.

:class:`FreeSpace` rasterizes :meth:`drivers.sim.world.World.is_free` once on a fine grid
(``cell`` metres) so that the kinematics can ask "is the robot disc free here?" in
microseconds instead of milliseconds. The raster is conservative: it is computed for the
radius ``radius + cell / sqrt(2)``, and a query reads the nearest grid point, which is at most
``cell / sqrt(2)`` away, so a point it calls free is free for ``radius`` (the disc around the
query lies inside the larger disc around the grid point).

Usage::

    free = FreeSpace(world, radius=0.25)
    free.free_point(x, y)
"""

from __future__ import annotations

import math

import numpy as np

from drivers.sim.world import World


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

"""Free space of a simulated world and a simple wander plan for the simulated robot's base.

:class:`FreeSpace` rasterizes :meth:`drivers.sim.world.World.is_free` once on a fine grid
(``cell`` metres) so that the 50 Hz kinematics can ask "is the robot disc free here?" in
microseconds instead of milliseconds. The raster is conservative: it is computed for the
radius ``radius + cell / sqrt(2)``, and a query reads the nearest grid point, which is at most
``cell / sqrt(2)`` away, so a point it calls free is free for ``radius`` (the disc around the
query lies inside the larger disc around the grid point).

:class:`WanderPlan` drives a differential-drive base through free space, piecewise smoothly:
it picks a random goal inside ``area`` (the world's mapped area by default) that the robot
can reach in a straight line with ``clearance`` to spare, turns towards it, drives to it
with bounded linear and angular accelerations, sometimes pauses there, and picks the next
goal. Commands are (v, omega) in m/s and rad/s; everything random comes from one generator
seeded by ``seed``, and the plan is a function of the poses it is given, so a base stepped
with a fixed time step follows the same path for the same seed.

(``drivers/sim/drive.py`` generates drive plans for the evaluations; this one is the
small, always-available plan of ``lino-loc sim``.)

Usage::

    free = FreeSpace(world, radius=0.25)
    plan = WanderPlan(world, free, speed=0.3, seed=0)
    v, omega = plan.command(pose, dt)        # then integrate, check free.is_free(...)
"""

from __future__ import annotations

import math

import numpy as np

from drivers.sim.world import World
from lino_loc.poses import wrap_angle


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


class WanderPlan:
    """Goal-to-goal wandering with bounded accelerations (see the module docstring)."""

    def __init__(
        self,
        world: World,
        free: FreeSpace,
        *,
        speed: float = 0.3,
        max_omega: float = 0.8,
        accel: float = 0.5,
        alpha: float = 2.0,
        clearance: float = 0.10,
        area: tuple[float, float, float, float] | None = None,
        min_goal_distance: float = 1.0,
        pause_probability: float = 0.3,
        max_pause_s: float = 2.0,
        seed: int = 0,
    ) -> None:
        if speed < 0 or max_omega <= 0 or accel <= 0 or alpha <= 0:
            raise ValueError("speed must be >= 0 and max_omega, accel, alpha > 0")
        self.world = world
        self.free = free
        self.speed = float(speed)
        self.max_omega = float(max_omega)
        self.accel = float(accel)
        self.alpha = float(alpha)
        self.clearance = float(clearance)
        self.area = area if area is not None else world.mapped_area
        self.min_goal_distance = float(min_goal_distance)
        self.pause_probability = float(pause_probability)
        self.max_pause_s = float(max_pause_s)
        self.rng = np.random.default_rng(seed)
        self.goal: tuple[float, float] | None = None
        self.v = 0.0
        self.omega = 0.0
        self._pause = 0.0
        self._retry = 0.0
        self.goals_reached = 0

    # goals -------------------------------------------------------------------------------------
    def _pick_goal(self, x: float, y: float) -> tuple[float, float] | None:
        xmin, xmax, ymin, ymax = self.area
        cand = self.rng.uniform((xmin, ymin), (xmax, ymax), size=(64, 2))
        ok = self.world.is_free(
            cand[:, 0], cand[:, 1], self.free.radius + self.clearance, self.free.scene_changes
        )
        far = np.hypot(cand[:, 0] - x, cand[:, 1] - y) >= self.min_goal_distance
        order = np.concatenate([np.flatnonzero(ok & far), np.flatnonzero(ok & ~far)])
        for i in order[:16]:
            g = (float(cand[i, 0]), float(cand[i, 1]))
            if self.free.segment_free((x, y), g, self.clearance):
                return g
        return None

    def blocked(self) -> None:
        """The base could not move as commanded: stop and choose another goal."""
        self.v = 0.0
        self.goal = None

    # control -----------------------------------------------------------------------------------
    def command(
        self, pose: np.ndarray | tuple[float, float, float], dt: float
    ) -> tuple[float, float]:
        """(v, omega) for the next ``dt`` seconds from the robot pose (x, y, theta)."""
        x, y, theta = float(pose[0]), float(pose[1]), float(pose[2])
        v_t, w_t = 0.0, 0.0
        if self._pause > 0.0:
            self._pause -= dt
        elif self.goal is None:
            self._retry -= dt
            if self._retry <= 0.0:
                self.goal = self._pick_goal(x, y)
                if self.goal is None:
                    self._retry = 0.5  # nowhere to go from here: turn a little and look again
            if self.goal is None:
                w_t = 0.5 * self.max_omega
        if self.goal is not None and self._pause <= 0.0:
            gx, gy = self.goal
            dist = math.hypot(gx - x, gy - y)
            if dist < 0.1:
                self.goal = None
                self.goals_reached += 1
                if self.rng.random() < self.pause_probability:
                    self._pause = float(self.rng.uniform(0.3, self.max_pause_s))
            else:
                err = float(wrap_angle(math.atan2(gy - y, gx - x) - theta))
                w_t = max(-self.max_omega, min(self.max_omega, 2.0 * err))
                if abs(err) < 0.5:
                    # slow down for the turn and on arrival (stopping distance v^2 / 2a)
                    v_t = (
                        self.speed
                        * math.cos(err) ** 2
                        * min(1.0, math.sqrt(2.0 * self.accel * dist) / max(self.speed, 1e-9))
                    )
        self.v += max(-self.accel * dt, min(self.accel * dt, v_t - self.v))
        self.omega += max(-self.alpha * dt, min(self.alpha * dt, w_t - self.omega))
        return self.v, self.omega

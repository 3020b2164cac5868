"""Send the simulated base to a pose: a path through free space and a controller that follows it.

:func:`plan_path` finds a path for the robot disc from a start position to a goal position
through a :class:`drivers.sim.free_space.FreeSpace` raster: A* over the cells of a wider
raster (the base's radius plus ``PATH_CLEARANCE_M``; every ``stride``-th cell, 8-connected,
Euclidean costs and heuristic), then shortened by dropping every waypoint the straight
segment between its neighbours makes unnecessary (:meth:`FreeSpace.segment_free`). LinoLocError when the goal is not free for the disc or no
path reaches it.

:class:`GotoPlan` follows such a path with the interface the simulated base steps
(``command(pose, dt) -> (v, omega)`` and ``blocked()``, :func:`drivers.sim.robot.base_step`).
For the waypoint ahead at distance d and heading error e::

    omega = clip(k_turn e, -turn_rate, turn_rate)
    v     = 0                                  if |e| > TURN_IN_PLACE_RAD
            min(speed, k_speed d) cos(e)       otherwise

and at the last waypoint, once within ``POSITION_TOLERANCE_M``, it turns on the spot to the
goal heading until within ``HEADING_TOLERANCE_RAD``; then it stands still with
``state == "arrived"``. A step the base refuses (``blocked``) makes the state ``"blocked"``
and the plan stands still (the caller sends another goal).

Usage::

    plan = GotoPlan(plan_path(free, (x0, y0), (x1, y1)), theta1, speed=0.3)
    robot.plan = plan; ...; plan.state   # "driving", "arrived" or "blocked"
"""

from __future__ import annotations

import heapq
import math
import threading

import numpy as np

from drivers.sim.free_space import FreeSpace
from lino_loc.errors import LinoLocError
from lino_loc.poses import wrap_angle

#: The goal position is reached within this distance (m).
POSITION_TOLERANCE_M = 0.01
#: The goal heading is reached within this angle (rad, 0.3 deg).
HEADING_TOLERANCE_RAD = math.radians(0.3)
#: Beyond this heading error (rad) the base turns on the spot before driving on.
TURN_IN_PLACE_RAD = math.radians(5.0)
#: Clearance (m) beyond the base's radius that a path keeps between its ends (``wide``).
PATH_CLEARANCE_M = 0.06
#: Length (m) at each end of a path that needs only the base's own free space.
END_SLACK_M = 0.15
#: Gains of the controller: turn rate per rad of heading error (1/s), speed per metre to go (1/s).
K_TURN = 4.0
K_SPEED = 3.0
#: Intermediate waypoints count as passed within this distance (m).
WAYPOINT_RADIUS_M = 0.05


def plan_path(
    free: FreeSpace,
    start: tuple[float, float],
    goal: tuple[float, float],
    stride: int = 2,
    wide: FreeSpace | None = None,
) -> list[tuple[float, float]]:
    """Waypoints from ``start`` to ``goal`` (both included) for the disc of ``free`` (see the
    module docstring). ``stride``: raster cells per search cell. ``wide``: the free space of a
    larger disc (the base's plus a clearance) that the path keeps to between its first and
    its last segment, so that a base following it with small errors is never blocked (the
    ends, which may be close to furniture, need only ``free``)."""
    if not free.free_point(*goal):
        raise LinoLocError(
            f"goto: ({goal[0]:.3f}, {goal[1]:.3f}) is not free space for the robot "
            f"(radius {free.radius:g} m) in world '{free.world.name}'"
        )
    space = wide if wide is not None else free
    if _clear(free, space, start, goal, True, True):
        return [start, goal]
    grid = space.grid[::stride, ::stride]
    cell = space.cell * stride
    nx, ny = grid.shape

    def index(p: tuple[float, float]) -> tuple[int, int]:
        return (min(nx - 1, max(0, int(round((p[0] - free.x0) / cell)))),
                min(ny - 1, max(0, int(round((p[1] - free.y0) / cell)))))

    def nearest_free(ij: tuple[int, int]) -> tuple[int, int] | None:
        ii, jj = np.nonzero(grid)
        if len(ii) == 0:
            return None
        k = int(np.argmin((ii - ij[0]) ** 2 + (jj - ij[1]) ** 2))
        return int(ii[k]), int(jj[k])

    s, g = nearest_free(index(start)), nearest_free(index(goal))
    if s is None or g is None:
        raise LinoLocError(f"goto: world '{free.world.name}' has no free space for the robot")
    steps = [(di, dj, math.hypot(di, dj)) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
    best = {s: 0.0}
    parent: dict[tuple[int, int], tuple[int, int]] = {}
    heap = [(math.dist(s, g), s)]
    while heap:
        _, cur = heapq.heappop(heap)
        if cur == g:
            break
        c0 = best[cur]
        for di, dj, w in steps:
            nb = (cur[0] + di, cur[1] + dj)
            if not (0 <= nb[0] < nx and 0 <= nb[1] < ny) or not grid[nb]:
                continue
            c = c0 + w
            if c < best.get(nb, math.inf):
                best[nb] = c
                parent[nb] = cur
                heapq.heappush(heap, (c + math.dist(nb, g), nb))
    if g not in best:
        raise LinoLocError(
            f"goto: no path for the robot from ({start[0]:.2f}, {start[1]:.2f}) to ({goal[0]:.2f}, {goal[1]:.2f})"
        )
    cells = [g]
    while cells[-1] != s:
        cells.append(parent[cells[-1]])
    cells.reverse()
    mid = [(space.x0 + i * cell, space.y0 + j * cell) for i, j in cells]
    raw = [start, *mid, goal]
    last = len(raw) - 1

    def clear(k: int, j: int) -> bool:
        return _clear(free, space, raw[k], raw[j], k == 0, j == last)

    path = [raw[0]]
    k = 0
    while k < last:  # the farthest waypoint reachable in a straight line
        j = last
        while j > k + 1 and not clear(k, j):
            j -= 1
        path.append(raw[j])
        k = j
    return path


def _clear(free: FreeSpace, space: FreeSpace, a: tuple[float, float], b: tuple[float, float],
           a_end: bool, b_end: bool) -> bool:
    """The segment a-b is free for the base, and for the wider disc of ``space`` but within
    ``END_SLACK_M`` of an end of the path (``a_end``, ``b_end``), which may lie near furniture
    or a wall: a base driving along the edge of its free space is stopped by the smallest
    heading error."""
    if not free.segment_free(a, b):
        return False
    length = math.dist(a, b)
    if length == 0.0:
        return True
    ta = min(END_SLACK_M, 0.5 * length) / length if a_end else 0.0
    tb = min(END_SLACK_M, 0.5 * length) / length if b_end else 0.0
    if ta + tb >= 1.0:
        return True
    a2 = (a[0] + ta * (b[0] - a[0]), a[1] + ta * (b[1] - a[1]))
    b2 = (b[0] + tb * (a[0] - b[0]), b[1] + tb * (a[1] - b[1]))
    return space.segment_free(a2, b2)


class GotoPlan:
    """Follow waypoints, then turn to the goal heading (see the module docstring)."""

    def __init__(
        self, waypoints: list[tuple[float, float]], theta: float, speed: float = 0.3, turn_rate: float = 0.8
    ) -> None:
        if len(waypoints) < 1:
            raise ValueError("GotoPlan needs at least the goal waypoint")
        self.waypoints = list(waypoints)
        self.theta = float(wrap_angle(theta))
        self.speed = float(speed)
        self.turn_rate = float(turn_rate)
        self._lock = threading.Lock()
        self._next = 1 if len(self.waypoints) > 1 else 0
        self._state = "driving"

    @property
    def goal(self) -> tuple[float, float, float]:
        x, y = self.waypoints[-1]
        return (x, y, self.theta)

    @property
    def state(self) -> str:
        with self._lock:
            return self._state

    def blocked(self) -> None:
        with self._lock:
            if self._state == "driving":
                self._state = "blocked"

    def command(self, pose: tuple[float, float, float] | np.ndarray, dt: float) -> tuple[float, float]:
        """(v, omega) for the next ``dt`` s from the present pose."""
        x, y, th = float(pose[0]), float(pose[1]), float(pose[2])
        with self._lock:
            if self._state != "driving":
                return 0.0, 0.0
            last = len(self.waypoints) - 1
            while self._next < last and math.dist((x, y), self.waypoints[self._next]) < WAYPOINT_RADIUS_M:
                self._next += 1
            wx, wy = self.waypoints[self._next]
            d = math.hypot(wx - x, wy - y)
            final = self._next == last
            if final and d < POSITION_TOLERANCE_M:
                err = float(wrap_angle(self.theta - th))
                if abs(err) < HEADING_TOLERANCE_RAD:
                    self._state = "arrived"
                    return 0.0, 0.0
                return 0.0, self._turn(err, dt)
            err = float(wrap_angle(math.atan2(wy - y, wx - x) - th))
            omega = self._turn(err, dt)
            if abs(err) > TURN_IN_PLACE_RAD:
                return 0.0, omega
            to_go = d if final else d + WAYPOINT_RADIUS_M
            v = min(self.speed, K_SPEED * to_go, to_go / dt) * math.cos(err)
            return v, omega

    def _turn(self, err: float, dt: float) -> float:
        """The turn rate toward a heading error, bounded and never overshooting in one step."""
        w = max(-self.turn_rate, min(self.turn_rate, K_TURN * err))
        return w if abs(w * dt) <= abs(err) else err / dt

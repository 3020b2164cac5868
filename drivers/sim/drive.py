"""The simulated base's drive planner, and drive plans: smooth trajectories with wheel odometry.

:class:`DrivePlanner` drives a differential-drive base through the free space of a world
(:meth:`drivers.sim.world.World.is_free`) inside the mapped area (shrunk by ``margin``). It
heads for random goals that it can reach along a straight segment with ``clearance`` to walls
and furniture (segment sampled every 5 cm); a goal at least ``min_goal_distance`` away is
preferred, else the farthest reachable one of the candidates drawn. The controller, for the
heading error e to the goal and the distance d to it:

    omega = clip(2 e, -turn_rate, turn_rate)
    v     = 0                                             if |e| > turn_in_place_deg
            speed cos(e) min(1, d / 0.3 m + 0.3)          otherwise

so the base turns on the spot toward a goal far off its heading and slows down near it.
Within ``arrival_radius`` of the goal it takes the next one (after a pause of
U(0.3 s, ``max_pause_s``) with probability ``pause_probability``). With ``accel`` /
``angular_accel`` set, v and omega follow those targets with bounded accelerations; unset,
they are the targets. :meth:`DrivePlanner.command` gives (v, omega) for the next ``dt``
seconds from the present pose; everything random comes from the generator it is given, so a
base stepped with a fixed time step follows the same path for the same seed. The simulator's
base (:mod:`drivers.sim.robot`) steps it at its kinematics rate; :func:`plan_drive` steps it
offline for the evaluations.

:func:`plan_drive` integrates the true motion at the odometry rate (``odom_rate`` Hz) along
exact arcs, with the wheel-odometry errors of :mod:`drivers.sim.wheel_noise` (true wheel
travels ``d_l, d_r = ds -/+ wheel_base dtheta / 2`` per tick), and samples it at the camera
rate: :class:`DrivePlan` holds the frames' stamps, the true robot poses, the odometry poses
and the odometry increments between consecutive frames (``lino_loc.poses.between(odom[k-1],
odom[k])``, the action ``u_t`` of eq. 3 and 5). Its random stream, from ``seed``: the start
pose (unless given), the run's wheel scale errors, then per tick the goals drawn and the two
wheels' slip.

Usage::

    plan = plan_drive(load_world("lab"), DriveConfig(duration=240.0), seed=1)
    for k in range(1, len(plan)):
        loc.update(plan.increments[k], pan=0.0, image=render(plan.truth[k]))
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from drivers.sim.wheel_noise import WheelOdometryNoise
from drivers.sim.world import World
from lino_loc.errors import LinoLocError
from lino_loc.poses import between, wrap_angle

FloatArray = NDArray[np.float64]

#: Distance (m) over which the controller slows down toward a goal (v factor d / 0.3 + 0.3).
SLOW_DOWN_DISTANCE = 0.3
#: A goal candidate nearer than this (m) is never taken.
MIN_GOAL_STEP = 0.3
#: Seconds before a planner that found no reachable goal (turning on the spot) looks again.
RETRY_S = 0.5


class PlannerConfig(BaseModel):
    """The drive planner: goal choice and controller (see module docstring). m, m/s, rad/s."""

    model_config = ConfigDict(extra="forbid")

    speed: float = Field(0.3, ge=0.0, description="top linear speed, m/s")
    turn_rate: float = Field(0.6, gt=0.0, description="top turn rate, rad/s")
    turn_in_place_deg: float = Field(25.0, gt=0.0, le=180.0, description="turn on the spot beyond this error")
    arrival_radius: float = Field(0.15, gt=0.0, description="a goal this near is reached, m")
    clearance: float = Field(0.35, gt=0.0, description="free disc radius along the goal segments, m")
    margin: float = Field(0.2, ge=0.0, description="goals stay this far inside the mapped area, m")
    min_goal_distance: float = Field(1.0, gt=0.0, description="preferred least distance to a new goal, m")
    accel: float | None = Field(None, gt=0.0, description="linear acceleration bound, m/s^2; None: none")
    angular_accel: float | None = Field(None, gt=0.0, description="angular acceleration bound, rad/s^2; None: none")
    pause_probability: float = Field(0.0, ge=0.0, le=1.0, description="chance of a pause at a reached goal")
    max_pause_s: float = Field(2.0, ge=0.3, description="longest pause, s")


class DriveConfig(BaseModel):
    """An offline drive (:func:`plan_drive`): duration, rates, base, world condition, planner
    and wheel-odometry errors. Units: s, Hz, m."""

    model_config = ConfigDict(extra="forbid")

    duration: float = Field(240.0, gt=0.0)
    camera_rate: float = Field(5.0, gt=0.0)
    odom_rate: float = Field(50.0, gt=0.0)
    radius: float = Field(0.25, gt=0.0, description="robot disc that must stay free")
    wheel_base: float = Field(0.4, gt=0.0)
    scene_changes: tuple[str, ...] = ()
    planner: PlannerConfig = Field(default_factory=PlannerConfig)
    noise: WheelOdometryNoise = Field(default_factory=WheelOdometryNoise)


@dataclass
class DrivePlan:
    """A drive at the camera rate: K frames."""

    stamps: FloatArray  # (K,) seconds from the start
    truth: FloatArray  # (K, 3) true robot poses
    odometry: FloatArray  # (K, 3) odometry poses (start = truth[0])
    fine_truth: FloatArray = field(repr=False)  # (M, 3) true poses at the odometry rate
    wheel_bias: tuple[float, float] = (0.0, 0.0)

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    @property
    def increments(self) -> FloatArray:
        """(K, 3) odometry increment into each frame from the previous one (row 0 is zero)."""
        inc = np.zeros_like(self.odometry)
        inc[1:] = between(self.odometry[:-1], self.odometry[1:])
        return inc

    @property
    def true_increments(self) -> FloatArray:
        inc = np.zeros_like(self.truth)
        inc[1:] = between(self.truth[:-1], self.truth[1:])
        return inc

    @property
    def length_m(self) -> float:
        d = np.diff(self.fine_truth[:, :2], axis=0)
        return float(np.hypot(d[:, 0], d[:, 1]).sum())


def _segment_free(world: World, a: FloatArray, b: FloatArray, clearance: float, changes: tuple[str, ...]) -> bool:
    n = max(2, int(math.ceil(float(np.hypot(*(b - a))) / 0.05)) + 1)
    t = np.linspace(0.0, 1.0, n)
    pts = a[None, :] + t[:, None] * (b - a)[None, :]
    return bool(np.all(world.is_free(pts[:, 0], pts[:, 1], clearance, changes)))


def goal_box(world: World, cfg: PlannerConfig) -> tuple[float, float, float, float]:
    """The mapped area shrunk by ``cfg.margin`` (xmin, xmax, ymin, ymax); LinoLocError if empty."""
    xmin, xmax, ymin, ymax = world.mapped_area
    m = cfg.margin
    if xmax - xmin <= 2 * m or ymax - ymin <= 2 * m:
        raise LinoLocError(f"drive: mapped area of world '{world.name}' is smaller than twice the margin {m}")
    return xmin + m, xmax - m, ymin + m, ymax - m


def random_free_pose(world: World, cfg: PlannerConfig, rng: np.random.Generator,
                     scene_changes: tuple[str, ...] = ()) -> FloatArray:
    """A pose uniform over the free space (clearance ``cfg.clearance``) of the goal box."""
    x0, x1, y0, y1 = goal_box(world, cfg)
    for _ in range(200):
        c = np.column_stack([rng.uniform(x0, x1, 64), rng.uniform(y0, y1, 64)])
        ok = world.is_free(c[:, 0], c[:, 1], cfg.clearance, scene_changes)
        if ok.any():
            p = c[int(np.flatnonzero(ok)[0])]
            return np.array([p[0], p[1], rng.uniform(-math.pi, math.pi)])
    raise LinoLocError(f"drive: no free pose found in world '{world.name}'")


class DrivePlanner:
    """Goal-to-goal driving through free space (see the module docstring)."""

    def __init__(self, world: World, cfg: PlannerConfig, rng: np.random.Generator,
                 scene_changes: tuple[str, ...] = ()) -> None:
        self.world = world
        self.cfg = cfg
        self.rng = rng
        self.scene_changes = world.check_changes(tuple(scene_changes))
        self.box = goal_box(world, cfg)
        self.goal: FloatArray | None = None
        self.stuck = False  # the last goal search found nothing reachable
        self.v = 0.0
        self.omega = 0.0
        self.goals_reached = 0
        self._turn_lim = math.radians(cfg.turn_in_place_deg)
        self._pause = 0.0
        self._retry = 0.0

    def next_goal(self, pos: FloatArray) -> FloatArray | None:
        """A reachable goal from ``pos`` (x, y), or None: up to 60 rounds of 16 candidates."""
        cfg, world, changes = self.cfg, self.world, self.scene_changes
        x0, x1, y0, y1 = self.box
        best, best_d = None, 0.0
        for _ in range(60):
            c = np.column_stack([self.rng.uniform(x0, x1, 16), self.rng.uniform(y0, y1, 16)])
            ok = world.is_free(c[:, 0], c[:, 1], cfg.clearance, changes)
            for g in c[ok]:
                d = float(np.hypot(*(g - pos)))
                if d < MIN_GOAL_STEP or not _segment_free(world, pos, g, cfg.clearance, changes):
                    continue
                if d >= cfg.min_goal_distance:
                    return g
                if d > best_d:
                    best, best_d = g, d
        return best

    def blocked(self) -> None:
        """The base could not move as commanded: stop and choose another goal."""
        self.v = 0.0
        self.goal = None

    def _update_goal(self, x: float, y: float, dt: float) -> None:
        if self.goal is not None and float(np.hypot(*(self.goal - (x, y)))) < self.cfg.arrival_radius:
            self.goal = None
            self.goals_reached += 1
            p = self.cfg.pause_probability
            if p > 0.0 and self.rng.random() < p:
                self._pause = float(self.rng.uniform(0.3, self.cfg.max_pause_s))
                return
        if self.goal is None:
            self._retry -= dt
            if self._retry <= 0.0:
                self.goal = self.next_goal(np.array([x, y]))
                self.stuck = self.goal is None
                if self.stuck:
                    self._retry = RETRY_S

    def command(self, pose: FloatArray | tuple[float, float, float], dt: float) -> tuple[float, float]:
        """(v, omega) for the next ``dt`` seconds from the robot pose (x, y, theta)."""
        cfg = self.cfg
        x, y, th = pose[0], pose[1], pose[2]
        v_t, w_t = 0.0, 0.0
        if self._pause > 0.0:
            self._pause -= dt
        else:
            self._update_goal(x, y, dt)
            if self.goal is not None:
                to_goal = self.goal - (x, y)
                err = float(wrap_angle(math.atan2(to_goal[1], to_goal[0]) - th))
                w_t = float(np.clip(2.0 * err, -cfg.turn_rate, cfg.turn_rate))
                v_t = 0.0 if abs(err) > self._turn_lim else cfg.speed * math.cos(err) * min(
                    1.0, float(np.hypot(*to_goal)) / SLOW_DOWN_DISTANCE + 0.3)
            elif self._pause <= 0.0:
                w_t = 0.5 * cfg.turn_rate  # nowhere to go from here: turn and look again
        self.v = v_t if cfg.accel is None else self.v + max(-cfg.accel * dt, min(cfg.accel * dt, v_t - self.v))
        a = cfg.angular_accel
        self.omega = w_t if a is None else self.omega + max(-a * dt, min(a * dt, w_t - self.omega))
        return self.v, self.omega


def plan_drive(
    world: World,
    cfg: DriveConfig | None = None,
    seed: int = 0,
    start: FloatArray | None = None,
) -> DrivePlan:
    """Simulate one drive (see module docstring). ``start`` (x, y, theta) must be free."""
    cfg = cfg or DriveConfig()
    rng = np.random.default_rng(seed)
    changes = world.check_changes(cfg.scene_changes)
    if start is None:
        pose = random_free_pose(world, cfg.planner, rng, changes)
    else:
        pose = np.asarray(start, dtype=np.float64).copy()
    if not bool(world.is_free(pose[0], pose[1], cfg.radius, changes)):
        raise LinoLocError(f"drive: start ({pose[0]:.2f}, {pose[1]:.2f}) is not in the free space")
    dt = 1.0 / cfg.odom_rate
    n_fine = int(round(cfg.duration * cfg.odom_rate)) + 1
    fine = np.empty((n_fine, 3))
    odo = np.empty((n_fine, 3))
    fine[0] = pose
    odo[0] = pose
    encoders = cfg.noise.start(rng)
    b_true = cfg.wheel_base
    b_odo = cfg.noise.odometry_wheel_base(cfg.wheel_base)
    planner = DrivePlanner(world, cfg.planner, rng, changes)
    for i in range(1, n_fine):
        v, w = planner.command(fine[i - 1], dt)
        if planner.stuck:
            x, y = fine[i - 1, 0], fine[i - 1, 1]
            raise LinoLocError(f"drive: stuck at ({x:.2f}, {y:.2f}) in world '{world.name}': no reachable goal")
        # true wheel travels of this tick and the exact differential-drive motion
        ds, dth = v * dt, w * dt
        d_l, d_r = ds - 0.5 * b_true * dth, ds + 0.5 * b_true * dth
        fine[i] = _arc(fine[i - 1], ds, dth)
        # measured wheel travels -> odometry pose
        ml, mr = encoders.measure(d_l, d_r)
        odo[i] = _arc(odo[i - 1], 0.5 * (ml + mr), (mr - ml) / b_odo)
    step = max(1, int(round(cfg.odom_rate / cfg.camera_rate)))
    idx = np.arange(0, n_fine, step)
    return DrivePlan(
        stamps=idx * dt,
        truth=fine[idx].copy(),
        odometry=odo[idx].copy(),
        fine_truth=fine,
        wheel_bias=(encoders.bias_l, encoders.bias_r),
    )


def _arc(p: FloatArray, ds: float, dth: float) -> FloatArray:
    """Pose after driving ``ds`` along an arc turning by ``dth`` (exact for constant v, w)."""
    x, y, th = p
    if abs(dth) < 1e-9:
        return np.array([x + ds * math.cos(th), y + ds * math.sin(th), th])
    r = ds / dth
    return np.array(
        [
            x + r * (math.sin(th + dth) - math.sin(th)),
            y - r * (math.cos(th + dth) - math.cos(th)),
            float(wrap_angle(th + dth)),
        ]
    )


def integrate(start: FloatArray, increments: FloatArray) -> FloatArray:
    """Poses obtained by composing ``increments`` (K, 3) (row 0 ignored) onto ``start``."""
    from lino_loc.poses import compose

    out = np.empty_like(np.asarray(increments, dtype=np.float64))
    out[0] = start
    for k in range(1, out.shape[0]):
        out[k] = compose(out[k - 1], increments[k])
    return out

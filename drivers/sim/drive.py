"""Drive plans: a smooth simulated trajectory through a world's free space, with wheel odometry.

:func:`plan_drive` drives a differential-drive robot through the free space of a world
(:meth:`drivers.sim.world.World.is_free`, robot disc of ``radius``), inside the mapped area
(shrunk by ``margin``), for ``duration`` seconds. The robot heads for random goals in the free
space that it can reach along a straight segment with ``clearance`` > ``radius`` to walls and
furniture; a simple controller turns it toward the goal with a bounded rate and slows it
down (turning on the spot when the goal is more than ``turn_in_place_deg`` off), so the path
is smooth and stays within a few centimetres of collision-free segments. The true motion is
integrated at the odometry rate (``odom_rate`` Hz, 50 Hz like the odometry board).

Wheel odometry (what the robot's encoders report): per odometry tick the true left / right
wheel travels ``d_l, d_r`` (wheel base ``wheel_base``) become

    d_l' = d_l (1 + bias_l) + N(0, k^2 |d_l|),   d_r' = d_r (1 + bias_r) + N(0, k^2 |d_r|)

(a systematic scale error per wheel plus random slip growing with the distance rolled, the
classic model of Borenstein and Feng, "Measurement and correction of systematic odometry
errors", IEEE T-RA 1996), and the odometry pose integrates ``d_l', d_r'`` with a wheel base
that is off by ``wheel_base_error`` (relative). The biases of a run are drawn once, from
N(0, ``scale_bias_std``^2) per wheel, so every run has its own drift.

The camera frames come at ``camera_rate`` Hz: :class:`DrivePlan` holds their stamps, the true
robot poses, the odometry poses and the odometry increments between consecutive frames
(``lino_loc.poses.between(odom[k-1], odom[k])``, the action ``u_t`` of eq. 3 and 5).

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

from drivers.sim.world import World
from lino_loc.errors import LinoLocError
from lino_loc.poses import between, wrap_angle

FloatArray = NDArray[np.float64]


class OdometryNoise(BaseModel):
    """Wheel odometry errors (see module docstring). Zeros give exact odometry."""

    model_config = ConfigDict(extra="forbid")

    slip_k: float = Field(0.005, ge=0.0, description="random slip, m^(1/2): std = k sqrt(|d|)")
    scale_bias_std: float = Field(0.003, ge=0.0, description="std of each wheel's scale error")
    wheel_base_error: float = Field(0.005, description="relative error of the assumed wheel base")

    @classmethod
    def exact(cls) -> OdometryNoise:
        return cls(slip_k=0.0, scale_bias_std=0.0, wheel_base_error=0.0)


class DriveConfig(BaseModel):
    """The drive: duration, rates, speeds, clearance. Units: s, Hz, m, m/s, rad/s."""

    model_config = ConfigDict(extra="forbid")

    duration: float = Field(240.0, gt=0.0)
    camera_rate: float = Field(5.0, gt=0.0)
    odom_rate: float = Field(50.0, gt=0.0)
    speed: float = Field(0.3, gt=0.0)
    turn_rate: float = Field(0.6, gt=0.0)
    turn_in_place_deg: float = Field(25.0, gt=0.0, le=180.0)
    radius: float = Field(0.25, gt=0.0, description="robot disc that must stay free")
    clearance: float = Field(0.35, gt=0.0, description="clearance of the goal segments")
    margin: float = Field(0.2, ge=0.0, description="goals stay this far inside the mapped area")
    min_goal_distance: float = Field(1.0, gt=0.0)
    wheel_base: float = Field(0.4, gt=0.0)
    scene_changes: tuple[str, ...] = ()
    noise: OdometryNoise = Field(default_factory=OdometryNoise)


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


def _goal_box(world: World, cfg: DriveConfig) -> tuple[float, float, float, float]:
    xmin, xmax, ymin, ymax = world.mapped_area
    m = cfg.margin
    if xmax - xmin <= 2 * m or ymax - ymin <= 2 * m:
        raise LinoLocError(f"drive: mapped area of world '{world.name}' is smaller than twice the margin {m}")
    return xmin + m, xmax - m, ymin + m, ymax - m


def random_free_pose(world: World, cfg: DriveConfig, rng: np.random.Generator) -> FloatArray:
    """A pose uniform over the free space (clearance ``cfg.clearance``) of the goal box."""
    x0, x1, y0, y1 = _goal_box(world, cfg)
    for _ in range(200):
        c = np.column_stack([rng.uniform(x0, x1, 64), rng.uniform(y0, y1, 64)])
        ok = world.is_free(c[:, 0], c[:, 1], cfg.clearance, cfg.scene_changes)
        if ok.any():
            p = c[int(np.flatnonzero(ok)[0])]
            return np.array([p[0], p[1], rng.uniform(-math.pi, math.pi)])
    raise LinoLocError(f"drive: no free pose found in world '{world.name}'")


def _next_goal(world: World, cfg: DriveConfig, pos: FloatArray, rng: np.random.Generator) -> FloatArray:
    x0, x1, y0, y1 = _goal_box(world, cfg)
    best, best_d = None, 0.0
    for _ in range(60):
        c = np.column_stack([rng.uniform(x0, x1, 16), rng.uniform(y0, y1, 16)])
        ok = world.is_free(c[:, 0], c[:, 1], cfg.clearance, cfg.scene_changes)
        for g in c[ok]:
            d = float(np.hypot(*(g - pos)))
            if d < 0.3 or not _segment_free(world, pos, g, cfg.clearance, cfg.scene_changes):
                continue
            if d >= cfg.min_goal_distance:
                return g
            if d > best_d:
                best, best_d = g, d
    if best is not None:
        return best
    raise LinoLocError(f"drive: stuck at ({pos[0]:.2f}, {pos[1]:.2f}) in world '{world.name}': no reachable goal")


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
    pose = random_free_pose(world, cfg, rng) if start is None else np.asarray(start, dtype=np.float64).copy()
    if not bool(world.is_free(pose[0], pose[1], cfg.radius, changes)):
        raise LinoLocError(f"drive: start ({pose[0]:.2f}, {pose[1]:.2f}) is not in the free space")
    dt = 1.0 / cfg.odom_rate
    n_fine = int(round(cfg.duration * cfg.odom_rate)) + 1
    fine = np.empty((n_fine, 3))
    odo = np.empty((n_fine, 3))
    fine[0] = pose
    odo[0] = pose
    nz = cfg.noise
    bias_l, bias_r = (float(v) for v in rng.normal(0.0, nz.scale_bias_std, 2)) if nz.scale_bias_std > 0 else (0.0, 0.0)
    b_true = cfg.wheel_base
    b_odo = cfg.wheel_base * (1.0 + nz.wheel_base_error)
    goal = _next_goal(world, cfg, pose[:2], rng)
    turn_lim = math.radians(cfg.turn_in_place_deg)
    for i in range(1, n_fine):
        x, y, th = fine[i - 1]
        to_goal = goal - (x, y)
        if float(np.hypot(*to_goal)) < 0.15:
            goal = _next_goal(world, cfg, np.array([x, y]), rng)
            to_goal = goal - (x, y)
        err = float(wrap_angle(math.atan2(to_goal[1], to_goal[0]) - th))
        w = float(np.clip(2.0 * err, -cfg.turn_rate, cfg.turn_rate))
        v = 0.0 if abs(err) > turn_lim else cfg.speed * math.cos(err) * min(1.0, float(np.hypot(*to_goal)) / 0.3 + 0.3)
        # true wheel travels of this tick and the exact differential-drive motion
        ds, dth = v * dt, w * dt
        d_l, d_r = ds - 0.5 * b_true * dth, ds + 0.5 * b_true * dth
        fine[i] = _arc(fine[i - 1], ds, dth)
        # measured wheel travels -> odometry pose
        ml = d_l * (1.0 + bias_l) + (nz.slip_k * math.sqrt(abs(d_l)) * rng.standard_normal() if nz.slip_k else 0.0)
        mr = d_r * (1.0 + bias_r) + (nz.slip_k * math.sqrt(abs(d_r)) * rng.standard_normal() if nz.slip_k else 0.0)
        odo[i] = _arc(odo[i - 1], 0.5 * (ml + mr), (mr - ml) / b_odo)
    step = max(1, int(round(cfg.odom_rate / cfg.camera_rate)))
    idx = np.arange(0, n_fine, step)
    return DrivePlan(
        stamps=idx * dt,
        truth=fine[idx].copy(),
        odometry=odo[idx].copy(),
        fine_truth=fine,
        wheel_bias=(bias_l, bias_r),
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

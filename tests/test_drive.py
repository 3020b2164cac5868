"""The drive planner and drive plans: free space, smoothness, camera-rate stamps, odometry that
integrates back; the wheel-odometry noise model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.drive import (
    DriveConfig,
    DrivePlanner,
    PlannerConfig,
    integrate,
    plan_drive,
    random_free_pose,
)
from drivers.sim.wheel_noise import WheelOdometryNoise
from drivers.sim.world import load_world
from lino_loc.errors import LinoLocError
from lino_loc.poses import between, pose_distance, wrap_angle

CHANGES = ("boxes", "people")


@pytest.fixture(scope="module")
def lab():
    return load_world("lab")


def test_path_stays_in_free_space_and_mapped_area(lab) -> None:
    cfg = DriveConfig(duration=60.0, scene_changes=CHANGES)
    plan = plan_drive(lab, cfg, seed=2)
    f = plan.fine_truth
    assert np.all(lab.is_free(f[:, 0], f[:, 1], cfg.radius, CHANGES))
    xmin, xmax, ymin, ymax = lab.mapped_area
    assert f[:, 0].min() >= xmin and f[:, 0].max() <= xmax
    assert f[:, 1].min() >= ymin and f[:, 1].max() <= ymax
    assert plan.length_m > 5.0  # it does drive


def test_stamps_are_at_the_camera_rate_and_motion_is_smooth(lab) -> None:
    cfg = DriveConfig(duration=20.0, camera_rate=5.0)
    plan = plan_drive(lab, cfg, seed=4)
    assert len(plan) == 101
    np.testing.assert_allclose(np.diff(plan.stamps), 0.2, atol=1e-9)
    inc = plan.true_increments[1:]
    # never faster than the speed limit, never turning faster than the turn-rate limit
    assert np.all(np.hypot(inc[:, 0], inc[:, 1]) <= cfg.planner.speed / cfg.camera_rate + 1e-6)
    assert np.all(np.abs(inc[:, 2]) <= cfg.planner.turn_rate / cfg.camera_rate + 1e-6)
    # differential drive: no sideways motion beyond the arc's chord offset
    assert np.all(np.abs(inc[:, 1]) <= np.abs(inc[:, 0]) * math.tan(cfg.planner.turn_rate / cfg.camera_rate) + 1e-6)


def test_exact_odometry_integrates_back_to_the_path(lab) -> None:
    plan = plan_drive(lab, DriveConfig(duration=30.0, noise=WheelOdometryNoise.exact()), seed=5)
    np.testing.assert_allclose(plan.odometry, plan.truth, atol=1e-9)
    back = integrate(plan.truth[0], plan.increments)
    np.testing.assert_allclose(back[:, :2], plan.truth[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(back[:, 2] - plan.truth[:, 2]), 0.0, atol=1e-9)


def test_noisy_odometry_drifts_within_the_noise(lab) -> None:
    noise = WheelOdometryNoise(slip_k=0.005, scale_bias_std=0.003, wheel_base_error=0.005)
    plan = plan_drive(lab, DriveConfig(duration=60.0, noise=noise), seed=6)
    back = integrate(plan.truth[0], plan.increments)
    np.testing.assert_allclose(back, plan.odometry, atol=1e-9)  # increments are the odometry's
    drift = pose_distance(plan.odometry, plan.truth)
    assert drift[-1] > 1e-4  # there is noise ...
    assert drift.max() < 0.15 * plan.length_m  # ... of the size of a few percent of the distance
    # per-frame increments agree with the true ones to within a few mm / mrad
    d = plan.increments[1:] - plan.true_increments[1:]
    assert np.abs(d[:, :2]).max() < 0.01
    assert np.abs(wrap_angle(d[:, 2])).max() < 0.02


def test_same_seed_same_plan_other_seed_other_plan(lab) -> None:
    a = plan_drive(lab, DriveConfig(duration=10.0), seed=1)
    b = plan_drive(lab, DriveConfig(duration=10.0), seed=1)
    c = plan_drive(lab, DriveConfig(duration=10.0), seed=2)
    np.testing.assert_array_equal(a.truth, b.truth)
    np.testing.assert_array_equal(a.odometry, b.odometry)
    assert not np.allclose(a.truth[0], c.truth[0])


def test_blocked_start_is_a_user_error(lab) -> None:
    with pytest.raises(LinoLocError, match="free space"):
        plan_drive(lab, DriveConfig(duration=1.0), start=np.array([-10.0, -10.0, 0.0]))


def test_increment_of_first_frame_is_zero(lab) -> None:
    plan = plan_drive(lab, DriveConfig(duration=2.0), seed=0)
    np.testing.assert_array_equal(plan.increments[0], 0.0)
    np.testing.assert_allclose(plan.increments[1:], between(plan.odometry[:-1], plan.odometry[1:]))


# -- the planner on its own ---------------------------------------------------------------------


def _step(planner: DrivePlanner, pose: np.ndarray, steps: int, dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Drive ``steps`` ticks along exact arcs; poses (steps, 3) and commands (steps, 2)."""
    poses, cmds = np.empty((steps, 3)), np.empty((steps, 2))
    for k in range(steps):
        v, w = planner.command(pose, dt)
        pose = pose_after(pose, v, w, dt)
        poses[k], cmds[k] = pose, (v, w)
    return poses, cmds


def pose_after(pose: np.ndarray, v: float, w: float, dt: float) -> np.ndarray:
    if abs(w) < 1e-12:
        return np.array([pose[0] + v * dt * math.cos(pose[2]), pose[1] + v * dt * math.sin(pose[2]), pose[2]])
    r = v / w
    th = pose[2] + w * dt
    return np.array([pose[0] + r * (math.sin(th) - math.sin(pose[2])),
                     pose[1] - r * (math.cos(th) - math.cos(pose[2])), float(wrap_angle(th))])


def test_planner_controller_is_the_closed_form(lab) -> None:
    cfg = PlannerConfig()
    planner = DrivePlanner(lab, cfg, np.random.default_rng(0))
    planner.goal = np.array([3.0, 2.0])
    # goal 1 m straight ahead: full speed, no turn
    v, w = planner.command(np.array([2.0, 2.0, 0.0]), 0.02)
    assert v == pytest.approx(cfg.speed) and w == 0.0
    # 0.2 m ahead at 10 deg off: omega = 2 e, v = speed cos(e) (0.2 / 0.3 + 0.3)
    e = math.radians(10.0)
    v, w = planner.command(np.array([3.0 - 0.2 * math.cos(e), 2.0 - 0.2 * math.sin(e), 0.0]), 0.02)
    assert w == pytest.approx(2 * e) and v == pytest.approx(cfg.speed * math.cos(e) * (0.2 / 0.3 + 0.3))
    # behind: turn on the spot at the turn-rate limit
    v, w = planner.command(np.array([4.0, 2.0, 0.0]), 0.02)
    assert v == 0.0 and abs(w) == pytest.approx(cfg.turn_rate)


def test_planner_bounded_accelerations_and_pauses(lab) -> None:
    cfg = PlannerConfig(speed=0.4, turn_rate=0.8, accel=0.5, angular_accel=2.0, pause_probability=1.0,
                        max_pause_s=0.5)
    planner = DrivePlanner(lab, cfg, np.random.default_rng(3))
    start = random_free_pose(lab, cfg, np.random.default_rng(1))
    _, cmds = _step(planner, start, 3000)
    dt = 0.02
    assert np.all(np.abs(np.diff(cmds[:, 0])) <= 0.5 * dt + 1e-12)
    assert np.all(np.abs(np.diff(cmds[:, 1])) <= 2.0 * dt + 1e-12)
    assert np.all(cmds[:, 0] <= 0.4 + 1e-12) and np.all(np.abs(cmds[:, 1]) <= 0.8 + 1e-12)
    assert planner.goals_reached >= 2  # it reaches goals and, pausing at each, goes on


def test_planner_without_a_reachable_goal_turns_and_retries(lab) -> None:
    planner = DrivePlanner(lab, PlannerConfig(), np.random.default_rng(0))
    planner.next_goal = lambda pos: None  # type: ignore[method-assign]
    v, w = planner.command(np.array([3.0, 2.0, 0.0]), 0.02)
    assert planner.stuck and planner.goal is None and v == 0.0 and w == pytest.approx(0.3)


def test_planner_same_generator_same_path(lab) -> None:
    start = random_free_pose(lab, PlannerConfig(), np.random.default_rng(2))
    a, _ = _step(DrivePlanner(lab, PlannerConfig(), np.random.default_rng(5)), start, 500)
    b, _ = _step(DrivePlanner(lab, PlannerConfig(), np.random.default_rng(5)), start, 500)
    np.testing.assert_array_equal(a, b)


# -- the wheel-odometry noise model -------------------------------------------------------------


def test_wheel_noise_closed_form_and_stream_order() -> None:
    noise = WheelOdometryNoise(slip_k=0.01, scale_bias_std=0.02, wheel_base_error=0.1)
    enc = noise.start(np.random.default_rng(4))
    ref = np.random.default_rng(4)
    bias = ref.normal(0.0, 0.02, 2)
    assert (enc.bias_l, enc.bias_r) == (bias[0], bias[1])
    ml, mr = enc.measure(0.04, 0.01)
    n_l, n_r = ref.standard_normal(), ref.standard_normal()
    assert ml == pytest.approx(0.04 * (1 + bias[0]) + 0.01 * math.sqrt(0.04) * n_l, abs=1e-15)
    assert mr == pytest.approx(0.01 * (1 + bias[1]) + 0.01 * math.sqrt(0.01) * n_r, abs=1e-15)
    assert noise.odometry_wheel_base(0.4) == pytest.approx(0.44)


def test_exact_wheel_noise_draws_nothing() -> None:
    rng = np.random.default_rng(9)
    enc = WheelOdometryNoise.exact().start(rng)
    assert enc.measure(0.03, -0.02) == (0.03, -0.02)
    assert rng.random() == np.random.default_rng(9).random()  # the generator was not used


def test_wheel_slip_variance_grows_with_distance() -> None:
    noise = WheelOdometryNoise(slip_k=0.005, scale_bias_std=0.0)
    enc = noise.start(np.random.default_rng(0))
    err = np.array([enc.measure(0.04, 0.0)[0] - 0.04 for _ in range(20000)])
    assert err.std() == pytest.approx(0.005 * math.sqrt(0.04), rel=0.03)
    assert abs(err.mean()) < 3 * 0.005 * math.sqrt(0.04) / math.sqrt(20000)

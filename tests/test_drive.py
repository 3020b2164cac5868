"""Drive plans: free space, smoothness, camera-rate stamps, odometry that integrates back."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.drive import DriveConfig, OdometryNoise, integrate, plan_drive
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
    assert np.all(np.hypot(inc[:, 0], inc[:, 1]) <= cfg.speed / cfg.camera_rate + 1e-6)
    assert np.all(np.abs(inc[:, 2]) <= cfg.turn_rate / cfg.camera_rate + 1e-6)
    # differential drive: no sideways motion beyond the arc's chord offset
    assert np.all(np.abs(inc[:, 1]) <= np.abs(inc[:, 0]) * math.tan(cfg.turn_rate / cfg.camera_rate) + 1e-6)


def test_exact_odometry_integrates_back_to_the_path(lab) -> None:
    plan = plan_drive(lab, DriveConfig(duration=30.0, noise=OdometryNoise.exact()), seed=5)
    np.testing.assert_allclose(plan.odometry, plan.truth, atol=1e-9)
    back = integrate(plan.truth[0], plan.increments)
    np.testing.assert_allclose(back[:, :2], plan.truth[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(back[:, 2] - plan.truth[:, 2]), 0.0, atol=1e-9)


def test_noisy_odometry_drifts_within_the_noise(lab) -> None:
    noise = OdometryNoise(slip_k=0.005, scale_bias_std=0.003, wheel_base_error=0.005)
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

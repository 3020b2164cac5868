"""Pose algebra: closed forms and invariants."""

import numpy as np
import pytest

from lino_loc.poses import between, camera_pose, circular_mean, compose, pose_distance, wrap_angle


def test_wrap_angle_range_and_identity():
    a = np.linspace(-10, 10, 1001)
    w = wrap_angle(a)
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    assert np.allclose(np.sin(w), np.sin(a)) and np.allclose(np.cos(w), np.cos(a))
    assert wrap_angle(np.pi) == pytest.approx(-np.pi)


def test_compose_closed_form_quarter_turn():
    # Facing +y, moving 1 m forward and 0.5 m left lands at (-0.5, 1).
    p = compose([0.0, 0.0, np.pi / 2], [1.0, 0.5, 0.1])
    assert np.allclose(p, [-0.5, 1.0, np.pi / 2 + 0.1])


def test_between_inverts_compose_vectorized():
    rng = np.random.default_rng(0)
    a = rng.uniform(-5, 5, (100, 3))
    d = rng.uniform(-2, 2, (100, 3))
    b = compose(a, d)
    d2 = between(a, b)
    assert np.allclose(d2[:, :2], d[:, :2])
    assert np.allclose(wrap_angle(d2[:, 2] - d[:, 2]), 0.0)


def test_camera_pose_adds_pan_and_wraps():
    p = camera_pose([1.0, 2.0, 3.0], 0.5)
    assert np.allclose(p[:2], [1.0, 2.0])
    assert p[2] == pytest.approx(3.5 - 2 * np.pi)


def test_circular_mean_across_the_cut():
    m = circular_mean([np.pi - 0.1, -np.pi + 0.1])
    assert abs(wrap_angle(m - np.pi)) < 1e-9
    assert circular_mean([0.0, 1.0], [1.0, 0.0]) == pytest.approx(0.0)


def test_pose_distance():
    assert pose_distance([0, 0, 1], [3, 4, -2]) == pytest.approx(5.0)

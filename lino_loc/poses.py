"""Planar poses (x, y, theta) in metres and radians, REP-103 (x forward, y left, theta CCW).

Arrays of poses have shape (..., 3). All functions are vectorized over leading axes.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def wrap_angle(angle: ArrayLike) -> FloatArray:
    """Wrap angles to [-pi, pi): ``(a + pi) mod 2 pi - pi`` (pi maps to -pi)."""
    a = np.asarray(angle, dtype=np.float64)
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def compose(pose: ArrayLike, delta: ArrayLike) -> FloatArray:
    """pose (+) delta: apply an increment expressed in the frame of ``pose``.

    ``(x + cos t dx - sin t dy, y + sin t dx + cos t dy, wrap(t + dt))``; broadcasts over
    leading axes.
    """
    p = np.asarray(pose, dtype=np.float64)
    d = np.asarray(delta, dtype=np.float64)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    x = p[..., 0] + c * d[..., 0] - s * d[..., 1]
    y = p[..., 1] + s * d[..., 0] + c * d[..., 1]
    th = wrap_angle(p[..., 2] + d[..., 2])
    return np.stack(np.broadcast_arrays(x, y, th), axis=-1)


def between(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """The increment d with a (+) d = b, expressed in the frame of ``a``: the position
    difference rotated by -theta_a, and wrap(theta_b - theta_a)."""
    pa = np.asarray(a, dtype=np.float64)
    pb = np.asarray(b, dtype=np.float64)
    dx = pb[..., 0] - pa[..., 0]
    dy = pb[..., 1] - pa[..., 1]
    c, s = np.cos(pa[..., 2]), np.sin(pa[..., 2])
    return np.stack(
        np.broadcast_arrays(c * dx + s * dy, -s * dx + c * dy, wrap_angle(pb[..., 2] - pa[..., 2])),
        axis=-1,
    )


def camera_pose(robot_pose: ArrayLike, pan: ArrayLike) -> FloatArray:
    """Camera pose from the robot pose and the head's pan angle.

    The pan-tilt head sits on the robot's vertical axis, so the camera shares the robot's
    position and its heading is the robot heading plus the pan angle (paper, section 3).
    """
    p = np.array(robot_pose, dtype=np.float64, copy=True)
    p[..., 2] = wrap_angle(p[..., 2] + np.asarray(pan, dtype=np.float64))
    return p


def circular_mean(angles: ArrayLike, weights: ArrayLike | None = None) -> float:
    """Weighted circular mean of angles (radians), in [-pi, pi): atan2(sum w sin a, sum w cos a)
    (arbitrary when the weighted unit vectors cancel)."""
    a = np.asarray(angles, dtype=np.float64)
    w = np.ones_like(a) if weights is None else np.asarray(weights, dtype=np.float64)
    return float(wrap_angle(np.arctan2(np.sum(w * np.sin(a)), np.sum(w * np.cos(a)))))


def pose_distance(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Euclidean distance between the positions of two (arrays of) poses, metres."""
    pa = np.asarray(a, dtype=np.float64)
    pb = np.asarray(b, dtype=np.float64)
    return np.hypot(pa[..., 0] - pb[..., 0], pa[..., 1] - pb[..., 1])

"""Odometry action model p(x_t | u_t, x_t-1) of the robot pose (paper, eq. 3 and 5).

The action ``u_t`` is the odometry increment between two odometry readings, given as a
relative pose ``delta = (dx, dy, dtheta)`` in the robot frame of the earlier reading
(``lino_loc.poses.between(odom_prev, odom_now)``). It is decomposed as in Thrun, Burgard and
Fox, *Probabilistic Robotics* (2005), table 5.6 (``sample_motion_model_odometry``):

    rot1  = atan2(dy, dx)            (initial turn towards the direction of travel)
    trans = sqrt(dx^2 + dy^2)
    rot2  = dtheta - rot1

each part is perturbed by zero-mean Gaussian noise with variance

    var(rot1)  = alpha1 * rot1^2 + alpha2 * trans^2
    var(trans) = alpha3 * trans^2 + alpha4 * (rot1^2 + rot2^2)
    var(rot2)  = alpha1 * rot2^2 + alpha2 * trans^2

and the perturbed motion is applied to every particle. A process-noise FLOOR is then added
in pose space, independently of the odometry: x, y += N(0, min_sigma_xy^2) each and
theta += N(0, min_sigma_theta^2) per update. Without it a robot standing still (increment
exactly zero) gets no action noise at all, so after resampling the particle set degenerates
into copies of a few poses (sample impoverishment) and a hypothesis that is 20 cm off can
never move onto the truth. The floor is the process-noise form of the regularised particle
filter's jitter (roughening, Gordon, Salmond, Smith 1993; Musso, Oudjane, Le Gland 2001),
kept in the action model so that the APF's two stages stay exact: the first stage still
uses the noise-free mean, the second divides by it. Its cost: a still robot's belief
diffuses by sqrt(k) * min_sigma_xy after k updates unless images pin it (1 cm: 10 cm after
100 updates), which the sensor model's 35 cm kernels do not notice. Two cases the textbook leaves open:

* pure rotation (``trans < min_trans``): the direction of travel is undefined, so
  ``rot1 = 0`` and ``rot2 = dtheta`` (otherwise atan2 of noise would inject a spurious turn);
* backward motion (``dx < 0``): the robot drives backwards rather than turning round, so the
  direction is reversed: ``rot1 = atan2(dy, dx) - pi`` wrapped, ``trans`` negative. rot1 then
  stays within [-pi/2, pi/2] and its noise does not explode (nav2's AMCL does the same by
  taking the smaller of the forward and backward turn for the noise).

Usage::

    model = OdometryMotionModel(MotionModelConfig(alpha1=0.05))
    particles = model.sample(particles, between(odom_prev, odom_now), rng)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.poses import compose, wrap_angle

FloatArray = NDArray[np.float64]


class MotionModelConfig(BaseModel):
    """Noise parameters of the odometry model (Probabilistic Robotics, table 5.6) and the
    process-noise floor (``min_sigma_xy``, ``min_sigma_theta``; 0 disables it).

    alpha1: rotation variance per squared rotation (rad^2/rad^2);
    alpha2: rotation variance per squared translation (rad^2/m^2);
    alpha3: translation variance per squared translation (m^2/m^2);
    alpha4: translation variance per squared rotation (m^2/rad^2).
    """

    model_config = ConfigDict(extra="forbid")

    alpha1: float = Field(0.05, ge=0.0)
    alpha2: float = Field(0.02, ge=0.0)
    alpha3: float = Field(0.05, ge=0.0)
    alpha4: float = Field(0.005, ge=0.0)
    min_trans: float = Field(1e-4, ge=0.0, description="below this (m) a motion is a pure rotation")
    min_sigma_xy: float = Field(
        0.01, ge=0.0, description="process-noise floor per update, m (std of x and of y), "
        "added even when the odometry increment is zero (a still robot)"
    )
    min_sigma_theta: float = Field(
        0.0087, ge=0.0, description="process-noise floor per update, rad (0.5 deg)"
    )


def decompose(
    delta: ArrayLike, min_trans: float = 1e-4
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(rot1, trans, rot2) of relative poses ``delta`` (..., 3); trans is signed (negative = backwards)."""
    d = np.asarray(delta, dtype=np.float64)
    dx, dy, dth = d[..., 0], d[..., 1], d[..., 2]
    trans = np.hypot(dx, dy)
    heading = np.arctan2(dy, dx)
    backward = dx < 0.0
    rot1 = np.where(backward, wrap_angle(heading - np.pi), heading)
    trans = np.where(backward, -trans, trans)
    still = np.abs(trans) < min_trans
    rot1 = np.where(still, 0.0, rot1)
    trans = np.where(still, 0.0, trans)
    rot2 = wrap_angle(dth - rot1)
    return rot1, trans, rot2


def recompose(rot1: ArrayLike, trans: ArrayLike, rot2: ArrayLike) -> FloatArray:
    """The relative pose (dx, dy, dtheta) of a (rot1, trans, rot2) motion."""
    r1 = np.asarray(rot1, dtype=np.float64)
    t = np.asarray(trans, dtype=np.float64)
    r2 = np.asarray(rot2, dtype=np.float64)
    return np.stack(
        np.broadcast_arrays(t * np.cos(r1), t * np.sin(r1), wrap_angle(r1 + r2)), axis=-1
    )


class OdometryMotionModel:
    """Sampling odometry model (Probabilistic Robotics, table 5.6), vectorized over particles."""

    def __init__(self, config: MotionModelConfig | None = None) -> None:
        self.config = config or MotionModelConfig()

    def _parts(
        self, delta: ArrayLike
    ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        c = self.config
        r1, t, r2 = (float(v) for v in decompose(delta, c.min_trans))
        v1 = c.alpha1 * r1**2 + c.alpha2 * t**2
        vt = c.alpha3 * t**2 + c.alpha4 * (r1**2 + r2**2)
        v2 = c.alpha1 * r2**2 + c.alpha2 * t**2
        return (r1, t, r2), (v1, vt, v2)

    def variances(self, delta: ArrayLike) -> tuple[float, float, float]:
        """Noise variances (var rot1, var trans, var rot2) of one odometry increment."""
        return self._parts(delta)[1]

    def predict_mean(self, particles: ArrayLike, delta: ArrayLike) -> FloatArray:
        """Noise-free propagation: every particle composed with the odometry increment."""
        return compose(particles, np.asarray(delta, dtype=np.float64))

    def sample(
        self, particles: ArrayLike, delta: ArrayLike, rng: np.random.Generator
    ) -> FloatArray:
        """One draw of x_t ~ p(x_t | u_t, x_t-1) per particle; particles (N, 3), delta (3,)."""
        p = np.asarray(particles, dtype=np.float64)
        n = p.shape[0]
        (r1, t, r2), var = self._parts(delta)
        noise = rng.standard_normal((n, 3))
        noise *= np.sqrt(var)
        noise += (r1, t, r2)
        # compose(p, recompose(rot1, trans, rot2)) with two trigonometric calls instead of four
        heading = p[:, 2] + noise[:, 0]
        out = np.empty_like(p)
        out[:, 0] = p[:, 0] + noise[:, 1] * np.cos(heading)
        out[:, 1] = p[:, 1] + noise[:, 1] * np.sin(heading)
        out[:, 2] = heading + noise[:, 2]
        c = self.config
        if c.min_sigma_xy > 0.0 or c.min_sigma_theta > 0.0:
            floor = rng.standard_normal((n, 3))
            floor *= (c.min_sigma_xy, c.min_sigma_xy, c.min_sigma_theta)
            out += floor
        out[:, 2] = wrap_angle(out[:, 2])
        return out

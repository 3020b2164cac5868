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
100 updates), which the sensor model's 35 cm kernels do not notice. Two cases the textbook
leaves open:

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

import math

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
        """(rot1, trans, rot2) of one increment (3,) and their noise variances: :func:`decompose`
        in scalar arithmetic (numpy's per-call overhead dominates on three scalars)."""
        c = self.config
        dx, dy, dth = (float(v) for v in np.asarray(delta, dtype=np.float64).reshape(3))
        t = math.hypot(dx, dy)
        r1 = math.atan2(dy, dx)
        if dx < 0.0:  # backwards: reverse the direction, negative translation
            r1 = _wrap(r1 - math.pi)
            t = -t
        if abs(t) < c.min_trans:  # pure rotation
            r1, t = 0.0, 0.0
        r2 = _wrap(dth - r1)
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

    def predict_mean_trig(
        self, particles: ArrayLike, delta: ArrayLike, turn: float = 0.0
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """:meth:`predict_mean` as (x, y, cos(theta + turn), sin(theta + turn)), each (N,).

        For a sensor model that needs the heading only through its cosine and sine (the
        filter's first stage, with ``turn`` = the pan angle): the predicted heading is the
        particle's turned by the constant dtheta + turn, so its cosine and sine follow from the
        particle's by one rotation, and the two trigonometric passes of the composition serve
        both the position and the heading."""
        p = np.asarray(particles, dtype=np.float64)
        dx, dy, dth = (float(v) for v in np.asarray(delta, dtype=np.float64).reshape(3))
        c = np.cos(p[:, 2])
        s = np.sin(p[:, 2])
        x = c * dx
        x -= s * dy
        x += p[:, 0]
        y = s * dx
        y += c * dy
        y += p[:, 1]
        ca, sa = math.cos(dth + turn), math.sin(dth + turn)
        ct = c * ca
        ct -= s * sa
        s *= ca
        c *= sa
        s += c
        return x, y, ct, s

    def sample(
        self, particles: ArrayLike, delta: ArrayLike, rng: np.random.Generator
    ) -> FloatArray:
        """One draw of x_t ~ p(x_t | u_t, x_t-1) per particle; particles (N, 3), delta (3,).

        The same distribution as perturbing (rot1, trans, rot2) and adding the floor, drawn with
        four normals per particle instead of six, in one generator call (only for the parts
        whose spread is not zero; drawing normals is a large share of an update's cost):

        * the rot2 noise and the heading floor both act on the final heading only: one normal
          of variance var(rot2) + min_sigma_theta^2;
        * given the noisy heading h, the translation noise (along h) plus the isotropic floor in
          x, y is a Gaussian of covariance var(trans) h h^T + s^2 I = (var(trans) + s^2) h h^T +
          s^2 h_perp h_perp^T: one normal along h and one across it.
        """
        p = np.asarray(particles, dtype=np.float64)
        n = p.shape[0]
        c = self.config
        (r1, t, r2), (v1, vt, v2) = self._parts(delta)
        sxy = c.min_sigma_xy
        sds = (math.sqrt(v1), math.sqrt(vt + sxy**2), sxy, math.sqrt(v2 + c.min_sigma_theta**2))
        rows = [i for i, sd in enumerate(sds) if sd > 0.0]
        z = rng.standard_normal((len(rows), n)) if rows else np.zeros((0, n))
        noise: dict[int, FloatArray] = {}
        for r, i in enumerate(rows):
            z[r] *= sds[i]
            noise[i] = z[r]
        # compose(p, recompose(rot1, trans, rot2)) with two trigonometric calls instead of four
        heading = p[:, 2] + r1
        if 0 in noise:
            heading += noise[0]
        along: FloatArray | float = t
        if 1 in noise:
            along = noise[1]
            along += t
        ch = np.cos(heading)
        sh = np.sin(heading)
        out = np.empty_like(p)
        v = ch * along
        v += p[:, 0]
        if 2 in noise:
            v -= sh * noise[2]
        out[:, 0] = v
        v = np.multiply(sh, along, out=v)
        v += p[:, 1]
        if 2 in noise:
            v += ch * noise[2]
        out[:, 1] = v
        heading += r2
        if 3 in noise:
            heading += noise[3]
        _wrap_in_place(heading)
        out[:, 2] = heading
        return out


def _wrap_in_place(a: FloatArray) -> None:
    """wrap_angle in place; values already in [-pi, pi) are left unchanged, one turn off (the
    usual case after a motion) is one conditional shift, anything else the general wrap."""
    np.subtract(a, 2.0 * np.pi, out=a, where=a >= np.pi)
    np.add(a, 2.0 * np.pi, out=a, where=a < -np.pi)
    if a.size and not (float(a.min()) >= -np.pi and float(a.max()) < np.pi):
        a[:] = wrap_angle(a)


def _wrap(a: float) -> float:
    """wrap_angle of one float (the same arithmetic)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi

"""Wheel-odometry errors of the simulated base: what its encoders report of the true motion.

One model for every simulated drive (the simulator's base, :mod:`drivers.sim.robot`, and the
evaluations' drive plans, :mod:`drivers.sim.drive`). Per step the true travels ``d_l, d_r``
of the left and right wheel become the measured

    d_l' = d_l (1 + b_l) + k sqrt(|d_l|) n_l,    d_r' = d_r (1 + b_r) + k sqrt(|d_r|) n_r

with n ~ N(0, 1) per wheel and step: a systematic scale error per wheel plus random slip whose
variance grows with the distance rolled (Borenstein and Feng, "Measurement and correction of
systematic odometry errors in mobile robots", IEEE T-RA 1996). The scale errors b_l, b_r of a
run are drawn once from N(0, ``scale_bias_std``^2), so every run has its own drift. The
odometry integrates the measured travels with a wheel base that is off by
``wheel_base_error`` (relative): b_odo = b (1 + e).

Random numbers come from the generator the caller passes, in this order: the two scale
errors (only when ``scale_bias_std`` > 0) when a run starts, then per step n_l, n_r (only
when ``slip_k`` > 0, also for a wheel at rest).

This is the simulated world's truth; the estimator's own motion model
(:mod:`lino_loc.motion_model`) is separate and knows nothing of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class WheelOdometryNoise(BaseModel):
    """Wheel-odometry error model (see module docstring). :meth:`exact` gives exact odometry."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    slip_k: float = Field(0.005, ge=0.0, description="random slip, m^(1/2): std = k sqrt(|d|)")
    scale_bias_std: float = Field(0.003, ge=0.0, description="std of each wheel's scale error, per run")
    wheel_base_error: float = Field(0.005, gt=-1.0, description="relative error of the odometry's wheel base")

    @classmethod
    def exact(cls) -> WheelOdometryNoise:
        return cls(slip_k=0.0, scale_bias_std=0.0, wheel_base_error=0.0)

    def start(self, rng: np.random.Generator) -> WheelEncoders:
        """The encoders of one run: draws the run's two scale errors from ``rng``."""
        if self.scale_bias_std > 0:
            bias_l, bias_r = (float(v) for v in rng.normal(0.0, self.scale_bias_std, 2))
        else:
            bias_l, bias_r = 0.0, 0.0
        return WheelEncoders(self, rng, bias_l, bias_r)

    def odometry_wheel_base(self, wheel_base: float) -> float:
        """The wheel base the odometry integrates with, b (1 + e), for the true base b."""
        return wheel_base * (1.0 + self.wheel_base_error)


@dataclass
class WheelEncoders:
    """One run's encoders: the model, its generator and the run's scale errors."""

    noise: WheelOdometryNoise
    rng: np.random.Generator
    bias_l: float
    bias_r: float

    def measure(self, d_l: float, d_r: float) -> tuple[float, float]:
        """Measured wheel travels (m) of one step for the true travels ``d_l``, ``d_r`` (m)."""
        k = self.noise.slip_k
        ml = d_l * (1.0 + self.bias_l) + (k * math.sqrt(abs(d_l)) * self.rng.standard_normal() if k else 0.0)
        mr = d_r * (1.0 + self.bias_r) + (k * math.sqrt(abs(d_r)) * self.rng.standard_normal() if k else 0.0)
        return ml, mr

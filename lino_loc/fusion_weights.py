"""Adaptive weights for the disjunctive fusion (eq. 8): each channel's recent predictive
likelihood.

Eq. 8 mixes the intensity and disparity sensor models with fixed weights (the paper:
w_d = w_i = 1/2). The adaptive rule treats the two channels as competing models of the
views and weighs them by how well each one predicted the recent views, as Bayesian model
averaging with exponential forgetting does (dynamic model averaging, Raftery, Karny & Ettler,
Technometrics 2010). At a frame with both channels, for channel c with mixture p_c over
camera poses (a normalized density, section 3, so the channels are comparable), and the
belief's particles x_k (robot poses, moved by the frame's mean odometry increment) with
normalized weights w_k:

    l_c = log sum_k w_k p_c(camera_pose(x_k, pan))        (the predictive likelihood)
    s_c <- lambda s_c + l_c                                 (``forgetting`` = lambda)
    r_c = exp(s_c) / sum_c' exp(s_c')                        (the models' posterior)
    w_c = m + (1 - C m) r_c                                  (``min_weight`` = m, C channels)

A channel whose views stop fitting the belief (the light changed its intensity images, or
a scene change its depth) loses weight within about 1 / (1 - lambda) frames; the floor keeps
it in the mixture, so that it earns its weight back when it recovers. Under a uniform belief
every normalized mixture has about the same predictive likelihood, so the weights stay near
1/2 until the belief has a shape; :meth:`AdaptiveFusionWeights.reset` (a new belief) starts
them at 1/2 again.

Usage::

    weights = AdaptiveFusionWeights(AdaptiveWeightsConfig())
    w = weights.update(mixtures, particles, log_weights, delta, pan)   # {"intensity": .., "disparity": ..}
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.poses import camera_pose, compose
from lino_loc.resampling import logsumexp
from lino_loc.sensor_model import PoseMixture

FloatArray = NDArray[np.float64]


class AdaptiveWeightsConfig(BaseModel):
    """``[localizer.fusion.adaptive]``: the adaptive rule's memory and floor (module docstring)."""

    model_config = ConfigDict(extra="forbid")

    forgetting: float = Field(0.9, ge=0.0, lt=1.0, description="lambda: the scores' memory, per frame")
    min_weight: float = Field(0.1, ge=0.0, le=0.5, description="no channel's weight goes below this")


class AdaptiveFusionWeights:
    """The channels' forgetful log predictive likelihoods and the weights they give."""

    def __init__(self, config: AdaptiveWeightsConfig | None = None) -> None:
        self.config = config or AdaptiveWeightsConfig()
        self.scores: dict[str, float] = {}
        self.last_log_likelihood: dict[str, float] = {}

    def reset(self) -> None:
        """Forget the scores (a new belief): equal weights."""
        self.scores = {}
        self.last_log_likelihood = {}

    def weights(self, names: list[str]) -> dict[str, float]:
        """The normalized weights of ``names`` from the scores (equal for unscored names)."""
        s = np.array([self.scores.get(n, 0.0) for n in names], dtype=np.float64)
        r = np.exp(s - s.max())
        r /= r.sum()
        m = self.config.min_weight
        w = m + (1.0 - len(names) * m) * r
        return {n: float(v) for n, v in zip(names, w, strict=True)}

    def update(
        self,
        mixtures: Mapping[str, PoseMixture],
        particles: FloatArray,
        log_weights: FloatArray,
        delta: ArrayLike,
        pan: float,
    ) -> dict[str, float]:
        """Score each channel's mixture against the belief moved by ``delta`` and return the
        weights; with fewer than two channels nothing is scored and the weights are equal."""
        names = list(mixtures)
        if len(names) < 2:
            return {n: 1.0 / len(names) for n in names} if names else {}
        lw = np.asarray(log_weights, dtype=np.float64)
        lw = lw - float(logsumexp(lw))
        cams = camera_pose(compose(np.asarray(particles, dtype=np.float64), delta), pan)
        lam = self.config.forgetting
        for n in names:
            ll = float(logsumexp(lw + mixtures[n].log_pdf(cams)))
            if not math.isfinite(ll):
                ll = -1e6  # the belief gave this channel's poses no probability at all
            self.last_log_likelihood[n] = ll
            self.scores[n] = lam * self.scores.get(n, 0.0) + ll
        return self.weights(names)

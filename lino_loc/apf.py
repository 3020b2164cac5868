"""One step of the auxiliary particle filter (paper, eq. 5-6; Pitt and Shephard 1999), generic.

Pitt and Shephard, "Filtering via simulation: auxiliary particle filters", JASA 94 (1999).
Particles ``x^i`` with normalized log-weights ``log pi^i`` (eq. 4); one step with action u_t and
observation y_t:

1. first stage: predict each particle's mean ``mu^i = E[x_t | u_t, x^i]`` (noise-free
   propagation) and weigh it by how well it explains the new observation,
   ``log lambda^i = log pi^i + beta log p(y_t | mu^i)``; draw ancestors ``k_j`` by these
   weights (systematic resampling by default);
2. propagate: ``x_t^j ~ p(x_t | u_t, x^{k_j})`` (the action model, eq. 5);
3. second stage: ``log pi_t^j = log p(y_t | x_t^j) - beta log p(y_t | mu^{k_j})`` (the
   correction that makes the pair of stages target eq. 6 exactly), normalized.

``beta`` (``first_stage_exponent``) tempers the first stage; beta = 1 is the classic APF,
beta = 0 the bootstrap filter; the second stage divides by the same factor, so the target is
exact for every beta. The first-stage likelihood of every particle is computed once and
reused, indexed by ancestor, in the second stage.

The product of the two stages also estimates the predictive likelihood of the observation,
``p(y_t | y_1..t-1) ~ (sum_i pi^i p(y | mu^i)^beta) * mean_j(second-stage weights)``.

The propagation and the likelihoods are callables, so any state space can be filtered (the
tests run it on a linear-Gaussian model against the Kalman filter); the pose filter
(``lino_loc.particle_filter``) passes a ``first_stage`` that computes ``log p(y | mu(x))``
without forming mu.

Usage::

    res = apf_step(x, log_w, rng, predict_mean=f, propagate=g, log_likelihood=loglik)
    x, log_w, log_py = res.particles, res.log_weights, res.log_likelihood
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lino_loc.resampling import SCHEMES, Resampler, logsumexp, systematic

FloatArray = NDArray[np.float64]


@dataclass
class StepResult:
    """Outcome of one :func:`apf_step`."""

    particles: FloatArray
    log_weights: FloatArray  # normalized
    log_likelihood: float  # estimate of log p(y_t | y_1..t-1), -inf if nothing explains y
    ancestors: NDArray[np.int64]
    weights: FloatArray | None = None  # exp(log_weights) when the step computed it, else None


def normalize(log_weights: ArrayLike) -> FloatArray:
    """Log-weights shifted to sum to one in linear space."""
    lw = np.asarray(log_weights, dtype=np.float64)
    return lw - logsumexp(lw)


def _log_normalize(lw: FloatArray) -> tuple[float, FloatArray]:
    """(log sum exp(lw), normalized linear weights); lw is left unchanged. -inf, empty if none
    is finite. One exp pass serves both the normalizer and the weights."""
    top = float(lw.max())
    if not math.isfinite(top):
        return -math.inf, np.empty(0)
    w = lw - top
    np.exp(w, out=w)
    total = float(w.sum())
    w /= total
    return top + math.log(total), w


def _takes_weights(resample: Resampler) -> bool:
    return any(resample is scheme for scheme in SCHEMES.values())


def apf_step(
    particles: FloatArray,
    log_weights: FloatArray,
    rng: np.random.Generator,
    *,
    predict_mean: Callable[[FloatArray], FloatArray],
    propagate: Callable[[FloatArray, np.random.Generator], FloatArray],
    log_likelihood: Callable[[FloatArray], FloatArray] | None,
    resample: Resampler = systematic,
    first_stage_exponent: float = 1.0,
    first_stage: Callable[[FloatArray], FloatArray] | None = None,
) -> StepResult:
    """One auxiliary-particle-filter step (Pitt and Shephard 1999; paper eq. 5-6).

    ``log_weights`` must be normalized. ``log_likelihood=None`` means no observation: the
    particles are propagated and keep their weights. ``first_stage_exponent`` (beta) tempers
    the first-stage weights, ``p(y | mu)^beta`` (see the module docstring). ``first_stage``,
    if given, maps the particles to ``log p(y | predict_mean(x))`` directly (a faster
    equivalent of ``log_likelihood(predict_mean(x))``).
    """
    n = particles.shape[0]
    if log_likelihood is None:
        return StepResult(propagate(particles, rng), log_weights.copy(), 0.0, np.arange(n))
    beta = first_stage_exponent
    l1: FloatArray | None = None
    w1: FloatArray | None = None
    if beta:
        l1 = first_stage(particles) if first_stage is not None else log_likelihood(
            predict_mean(particles)
        )
        if beta != 1.0:
            l1 = beta * l1
        lw1 = log_weights + l1
        log_c1, w1 = _log_normalize(lw1)
        if not math.isfinite(log_c1):  # no predicted mean explains y: the bootstrap filter
            l1, lw1, log_c1, w1 = None, log_weights, 0.0, None
    else:
        lw1, log_c1 = log_weights, 0.0
    # the built-in schemes take the first-stage weights already computed (one exp pass less)
    anc = resample(lw1, rng, weights=w1) if w1 is not None and _takes_weights(resample) else (
        resample(lw1, rng)
    )
    x = propagate(particles[anc], rng)
    lw2 = log_likelihood(x) if l1 is None else log_likelihood(x) - l1[anc]
    log_c2, w = _log_normalize(lw2)
    if not math.isfinite(log_c2):  # nothing explains y: keep the prediction, uniform weights
        return StepResult(x, np.full(n, -math.log(n)), -math.inf, anc)
    lw2 = lw2 - log_c2
    return StepResult(x, lw2, log_c1 + log_c2 - math.log(n), anc, w)

"""One step of the auxiliary particle filter (paper, eq. 5-6; Pitt and Shephard 1999), generic.

Pitt and Shephard, "Filtering via simulation: auxiliary particle filters", JASA 94 (1999).
Particles ``x^i`` with normalized weights ``pi^i`` (eq. 4, a :class:`lino_loc.weights.Weights`
value); one step with action u_t and observation y_t:

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
reused, indexed by ancestor, in the second stage. When no predicted mean explains y (every
first-stage weight 0) the step falls back to the bootstrap filter; when no propagated particle
explains it, the step keeps the prediction with equal weights and a likelihood of -inf.

The product of the two stages also estimates the predictive likelihood of the observation,
``p(y_t | y_1..t-1) ~ (sum_i pi^i p(y | mu^i)^beta) * mean_j(second-stage weights)``, i.e.
``log Z_1 + log Z_2 - log N`` with Z_1, Z_2 the normalisers of the two stages' weights.

The propagation and the likelihoods are callables, so any state space can be filtered (the
tests run it on a linear-Gaussian model against the Kalman filter); the pose filter
(``lino_loc.particle_filter``) passes a ``first_stage`` that computes ``log p(y | mu(x))``
without forming mu.

Usage::

    res = apf_step(x, Weights(log_w), rng, predict_mean=f, propagate=g, log_likelihood=loglik)
    x, log_w, log_py = res.particles, res.weights.log, res.log_likelihood
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lino_loc.resampling import Resampler, systematic
from lino_loc.weights import NoFiniteWeightError, Weights

FloatArray = NDArray[np.float64]


@dataclass
class StepResult:
    """Outcome of one :func:`apf_step`."""

    particles: FloatArray
    weights: Weights  # normalized second-stage weights
    log_likelihood: float  # estimate of log p(y_t | y_1..t-1), -inf if nothing explains y
    ancestors: NDArray[np.int64]


def apf_step(
    particles: FloatArray,
    weights: Weights,
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

    ``log_likelihood=None`` means no observation: the particles are propagated and keep their
    weights. ``first_stage_exponent`` (beta) tempers the first-stage weights,
    ``p(y | mu)^beta`` (see the module docstring). ``first_stage``, if given, maps the
    particles to ``log p(y | predict_mean(x))`` directly (a faster equivalent of
    ``log_likelihood(predict_mean(x))``). Random draws, in order: the resampler's, then the
    propagation's.
    """
    n = particles.shape[0]
    if log_likelihood is None:
        return StepResult(propagate(particles, rng), weights, 0.0, np.arange(n))
    beta = first_stage_exponent
    l1: FloatArray | None = None
    log_c1 = 0.0
    if beta:
        l1 = first_stage(particles) if first_stage is not None else log_likelihood(
            predict_mean(particles)
        )
        if beta != 1.0:
            l1 = beta * l1
        try:
            first = Weights.from_log(weights.log + l1)
            log_c1 = first.log_normalizer
        except NoFiniteWeightError:  # no predicted mean explains y: the bootstrap filter
            l1 = None
    # without a first stage the ancestors are drawn by the log-weights (softmax recomputed)
    anc = resample(first if l1 is not None else weights.log, rng)
    x = propagate(particles[anc], rng)
    lw2 = log_likelihood(x) if l1 is None else log_likelihood(x) - l1[anc]
    try:
        second = Weights.from_log(lw2)
    except NoFiniteWeightError:  # nothing explains y: keep the prediction, equal weights
        return StepResult(x, Weights.uniform(n), -math.inf, anc)
    return StepResult(x, second, log_c1 + second.log_normalizer - math.log(n), anc)

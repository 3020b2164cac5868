"""Resampling schemes for particle filters.

Every scheme has the same signature ``scheme(weights, rng, n=None) -> indices``: it takes the
particles' weights, a :class:`lino_loc.weights.Weights` value (its cached linear weights are
used) or (possibly unnormalized) log-weights of shape (N,), a ``numpy.random.Generator`` and
the number of draws ``n`` (default N), and returns ``n`` ancestor indices (int64) whose
expected counts are ``n * w_i`` with ``w = softmax(log_weights)`` (all three are unbiased).
They differ in variance: systematic < stratified < multinomial (Douc, Cappe & Moulines,
"Comparison of resampling schemes for particle filtering", 2005). Systematic is the default
of the filter. Each draws its uniforms from ``rng`` in one call (systematic: one number;
stratified and multinomial: n numbers).

Usage::

    from lino_loc.resampling import systematic
    idx = systematic(Weights.from_log(log_w), rng)
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lino_loc.weights import Weights, logsumexp

__all__ = ["SCHEMES", "Resampler", "get_resampler", "logsumexp", "multinomial", "stratified",
           "systematic"]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

Resampler = Callable[..., IntArray]


def _inverse_cdf(weights: FloatArray, uniforms: FloatArray) -> IntArray:
    """Indices i with cdf[i-1] <= u < cdf[i] for sorted uniforms in [0, 1)."""
    cdf = np.cumsum(weights)
    cdf[-1] = 1.0  # guard against round-off: every u < 1 finds a bin
    idx = np.searchsorted(cdf, uniforms, side="right").astype(np.int64, copy=False)
    return np.minimum(idx, weights.size - 1, out=idx)


def _linear(weights: Weights | ArrayLike) -> FloatArray:
    """The normalized linear weights of a :class:`Weights` value or of log-weights."""
    return (weights if isinstance(weights, Weights) else Weights.from_log(weights)).linear


def systematic(
    weights: Weights | ArrayLike,
    rng: np.random.Generator,
    n: int | None = None,
) -> IntArray:
    """Systematic resampling: one uniform U, points (k + U) / n, k = 0..n-1."""
    w = _linear(weights)
    m = w.size if n is None else int(n)
    u = np.arange(m, dtype=np.float64)
    u += rng.random()
    u /= m
    return _inverse_cdf(w, u)


def stratified(
    weights: Weights | ArrayLike,
    rng: np.random.Generator,
    n: int | None = None,
) -> IntArray:
    """Stratified resampling: one uniform in each stratum [k/n, (k+1)/n)."""
    w = _linear(weights)
    m = w.size if n is None else int(n)
    u = (np.arange(m) + rng.random(m)) / m
    return _inverse_cdf(w, u)


def multinomial(
    weights: Weights | ArrayLike,
    rng: np.random.Generator,
    n: int | None = None,
) -> IntArray:
    """Multinomial resampling: n independent draws from the categorical distribution w."""
    w = _linear(weights)
    m = w.size if n is None else int(n)
    u = np.sort(rng.random(m))
    return _inverse_cdf(w, u)


SCHEMES: dict[str, Resampler] = {
    "systematic": systematic,
    "stratified": stratified,
    "multinomial": multinomial,
}


def get_resampler(name: str) -> Resampler:
    """The resampling function called ``name`` (systematic, stratified, multinomial)."""
    try:
        return SCHEMES[name]
    except KeyError:
        raise ValueError(
            f"unknown resampling scheme {name!r}; choose one of {sorted(SCHEMES)}"
        ) from None

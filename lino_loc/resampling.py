"""Resampling schemes for particle filters, all in log-weights.

Every scheme has the same signature ``scheme(log_weights, rng, n=None) -> indices``: it takes
(possibly unnormalized) log-weights of shape (N,), a ``numpy.random.Generator`` and the number
of draws ``n`` (default N), and returns ``n`` ancestor indices (int64) whose expected counts are
``n * w_i`` with ``w = softmax(log_weights)`` (all three are unbiased). The schemes of
:data:`SCHEMES` also take ``weights=`` (that softmax, when the caller has computed it). They differ in variance:
systematic < stratified < multinomial (Douc, Cappe & Moulines, "Comparison of resampling
schemes for particle filtering", 2005). Systematic is the default of the filter.

Usage::

    from lino_loc.resampling import systematic, effective_sample_size
    idx = systematic(log_w, rng)
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

Resampler = Callable[..., IntArray]


def logsumexp(a: ArrayLike, axis: int | None = None, keepdims: bool = False) -> FloatArray | float:
    """log(sum(exp(a))) along ``axis``, stable; all -inf gives -inf.

    A plain-numpy version: scipy.special.logsumexp costs ~0.5 ms per call in argument handling
    (array-API dispatch), which dominated a 1000-particle filter update.
    """
    x = np.asarray(a, dtype=np.float64)
    m = np.max(x, axis=axis, keepdims=True)
    if not np.isfinite(m).all():
        m = np.where(np.isfinite(m), m, 0.0)
    e = x - m
    np.exp(e, out=e)
    s = np.sum(e, axis=axis, keepdims=True)
    with np.errstate(divide="ignore"):
        np.log(s, out=s)
    s += m
    if not keepdims:
        s = np.squeeze(s, axis=axis) if axis is not None else s.reshape(())
    return float(s) if s.ndim == 0 else s


def normalize_log_weights(log_weights: ArrayLike) -> FloatArray:
    """Log-weights shifted so that ``sum(exp(.)) == 1``. Raises ValueError if all are -inf/nan."""
    lw = np.asarray(log_weights, dtype=np.float64)
    total = logsumexp(lw)
    if not np.isfinite(total):
        raise ValueError("log-weights have no finite entry; cannot normalize")
    return lw - total


def weights_from_log(log_weights: ArrayLike) -> FloatArray:
    """Normalized linear weights ``softmax(log_weights)``."""
    lw = np.asarray(log_weights, dtype=np.float64)
    m = np.max(lw)
    if not np.isfinite(m):
        raise ValueError("log-weights have no finite entry; cannot normalize")
    w = np.exp(lw - m)
    return w / w.sum()


def effective_sample_size(log_weights: ArrayLike) -> float:
    """Kish's effective sample size ``1 / sum(w_i^2)`` of normalized weights, in [1, N]."""
    lw = np.asarray(log_weights, dtype=np.float64)
    m = np.max(lw)
    if not np.isfinite(m):
        raise ValueError("log-weights have no finite entry; cannot normalize")
    w = np.exp(lw - m)
    s = w.sum()
    return float(s * s / np.dot(w, w))


def _inverse_cdf(weights: FloatArray, uniforms: FloatArray) -> IntArray:
    """Indices i with cdf[i-1] <= u < cdf[i] for sorted uniforms in [0, 1)."""
    cdf = np.cumsum(weights)
    cdf[-1] = 1.0  # guard against round-off: every u < 1 finds a bin
    idx = np.searchsorted(cdf, uniforms, side="right").astype(np.int64, copy=False)
    return np.minimum(idx, weights.size - 1, out=idx)


def _weights(log_weights: ArrayLike, weights: FloatArray | None) -> FloatArray:
    return weights_from_log(log_weights) if weights is None else weights


def systematic(
    log_weights: ArrayLike,
    rng: np.random.Generator,
    n: int | None = None,
    *,
    weights: FloatArray | None = None,
) -> IntArray:
    """Systematic resampling: one uniform U, points (k + U) / n, k = 0..n-1.

    ``weights``: softmax(log_weights) when the caller already has it (saves an exp pass)."""
    w = _weights(log_weights, weights)
    m = w.size if n is None else int(n)
    u = np.arange(m, dtype=np.float64)
    u += rng.random()
    u /= m
    return _inverse_cdf(w, u)


def stratified(
    log_weights: ArrayLike,
    rng: np.random.Generator,
    n: int | None = None,
    *,
    weights: FloatArray | None = None,
) -> IntArray:
    """Stratified resampling: one uniform in each stratum [k/n, (k+1)/n)."""
    w = _weights(log_weights, weights)
    m = w.size if n is None else int(n)
    u = (np.arange(m) + rng.random(m)) / m
    return _inverse_cdf(w, u)


def multinomial(
    log_weights: ArrayLike,
    rng: np.random.Generator,
    n: int | None = None,
    *,
    weights: FloatArray | None = None,
) -> IntArray:
    """Multinomial resampling: n independent draws from the categorical distribution w."""
    w = _weights(log_weights, weights)
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

"""The weights of a particle set: normalized log-weights and what is derived from them.

A :class:`Weights` value holds the normalized log-weights ``log pi^i`` of N particles (paper,
eq. 4: ``sum_i pi^i = 1``), the log-normaliser ``log Z`` they were divided by, and, computed
once on demand, the linear weights ``pi^i = softmax(l)_i = exp(l_i - m) / sum_j exp(l_j - m)``
(m = max_j l_j, for stability) and Kish's effective sample size ``ESS = 1 / sum_i (pi^i)^2``,
which lies in [1, N] (N for equal weights, 1 when one particle holds all the weight).

Two recipes normalize unnormalized log-weights l (:meth:`Weights.from_log`); they compute the
same softmax and differ only in rounding:

- one pass (the default): ``w = exp(l - m)``, ``Z = sum(w)``, ``log Z = m + log(Z)`` in scalar
  arithmetic, linear weights ``w / Z`` from that same pass (one exponential per particle);
- ``one_pass=False``: ``log Z = logsumexp(l)`` (vectorised), the linear weights computed later
  from the normalized log-weights.

A caller keeps one recipe, so that a seeded filter reproduces its figures bit for bit. A
value is immutable by contract: its arrays are shared, never written to.

Edge cases: log-weights with no finite maximum (all -inf, or nan) have no softmax, and
:meth:`Weights.from_log` raises :class:`NoFiniteWeightError` (a ``ValueError``).

Usage::

    w = Weights.from_log(log_likelihood + prior.log)
    w.linear, w.ess(), w.log_normalizer
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

__all__ = ["NoFiniteWeightError", "Weights", "logsumexp"]


class NoFiniteWeightError(ValueError):
    """The log-weights have no finite entry: there is nothing to normalize."""


def logsumexp(a: ArrayLike, axis: int | None = None, keepdims: bool = False) -> FloatArray | float:
    """log(sum(exp(a))) along ``axis`` (all axes when None), stable: m + log(sum(exp(a - m)))
    with m the maximum (0 where it is not finite); all -inf gives -inf. Plain numpy."""
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


class Weights:
    """Normalized log-weights with cached linear weights, ESS and log-normaliser (see the
    module docstring). ``Weights(log)`` takes log-weights that are already normalized."""

    __slots__ = ("_linear", "log", "log_normalizer")

    def __init__(
        self,
        log: FloatArray,
        linear: FloatArray | None = None,
        log_normalizer: float = 0.0,
    ) -> None:
        self.log = log
        self._linear = linear
        self.log_normalizer = log_normalizer

    @classmethod
    def uniform(cls, n: int) -> Weights:
        """Equal weights 1 / n (log-weights -log n)."""
        return cls(np.full(n, -math.log(n)))

    @classmethod
    def from_log(cls, log_weights: ArrayLike, *, one_pass: bool = True) -> Weights:
        """Normalize unnormalized log-weights (either recipe of the module docstring); the
        input is not modified. Raises :class:`NoFiniteWeightError` when no entry is finite."""
        lw = np.asarray(log_weights, dtype=np.float64)
        if lw.size == 0:
            raise NoFiniteWeightError("log-weights have no finite entry; cannot normalize")
        if not one_pass:
            log_z = float(logsumexp(lw))
            if not math.isfinite(log_z):
                raise NoFiniteWeightError("log-weights have no finite entry; cannot normalize")
            return cls(lw - log_z, None, log_z)
        top = float(lw.max())
        if not math.isfinite(top):
            raise NoFiniteWeightError("log-weights have no finite entry; cannot normalize")
        w = lw - top
        np.exp(w, out=w)
        total = float(w.sum())
        w /= total
        log_z = top + math.log(total)
        return cls(lw - log_z, w, log_z)

    @property
    def linear(self) -> FloatArray:
        """softmax of the log-weights, sums to one (computed once; do not modify)."""
        if self._linear is None:
            w = self.log - self.log.max()
            np.exp(w, out=w)
            w /= w.sum()
            self._linear = w
        return self._linear

    def ess(self) -> float:
        """Kish's effective sample size 1 / sum(w_i^2), in [1, N]."""
        w = self.linear
        return float(1.0 / np.dot(w, w))

    def __len__(self) -> int:
        return int(self.log.shape[0])

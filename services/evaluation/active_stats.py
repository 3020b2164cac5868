"""Intervals and paired differences of the active-localization success figures.

The experiment (:mod:`services.evaluation.active`) scores 0/1 outcomes ``x[p, r, k]`` (test
position p of P, run r of R, after k movements); a success figure is their mean over
positions and runs. Its uncertainty is estimated by a two-stage bootstrap (Davison and
Hinkley, *Bootstrap Methods and their Application*, 1997, section 3.8, resampling at both
stages):

1. draw P test positions with replacement;
2. within each drawn position, draw R of its runs with replacement;

the resample's statistic is the mean of the drawn outcomes. :data:`RESAMPLES` resamples,
generator ``numpy.random.default_rng(SEED)`` (a fixed seed: the interval is a deterministic
function of the outcomes). The 95 % interval is the 2.5 and 97.5 percentiles of the
resampled means; the standard error is their standard deviation.

Vectorized: a resample is a vector of counts ``c[p * R + r]`` (how often run r of position p
was drawn, summing to P R), so all resampled means are one product ``C @ x / (P R)`` of the
(B, P R) counts and the (P R, K) outcomes.

Its variance, for B -> infinity, is ``(V_b + W / R) / P`` with ``V_b = mean_p (xbar_p -
xbar)^2`` (between positions) and ``W = mean_p mean_r (x_pr - xbar_p)^2`` (within a
position). The variance of the mean itself is ``sigma_b^2 / P + sigma_w^2 / (P R)``; the
bootstrap's is larger by the within-position term ``W / (P R)`` (it counts the runs' spread
once in the position means and once more by drawing runs): conservative, at most (2R - 1) / R
times the variance (outcomes independent of the position) and close to it when the
positions differ much more than their runs. With ``runs_too=False`` the runs of a drawn
position are kept as they are (the cluster bootstrap): variance ``V_b / P``, which for
independent Bernoulli(q) outcomes is ``q (1 - q) / (P R)`` up to (P - 1) / P, the normal
approximation's.

The strategies of a run start from the same particles and first pan, so their difference is
paired: the same counts applied to ``x_a - x_b`` give the difference's resampled means and
its standard error.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: Bootstrap resamples of every interval and standard error.
RESAMPLES = 2000
#: Seed of the bootstrap's generator (``numpy.random.default_rng(SEED)``).
SEED = 0
#: Two-sided coverage of the intervals.
LEVEL = 0.95
#: How the intervals and standard errors are computed, as the result's JSON states it.
SE_METHOD = "bootstrap over positions then runs"


def resample_counts(positions: int, runs: int, resamples: int = RESAMPLES, seed: int = SEED,
                    runs_too: bool = True) -> np.ndarray:
    """Counts (resamples, positions * runs) of the two-stage bootstrap: row b counts how often
    run r of position p (column p * runs + r) was drawn; every row sums to positions * runs.
    ``runs_too=False``: every drawn position brings all its runs once (the cluster bootstrap)."""
    if positions < 1 or runs < 1 or resamples < 1:
        raise ValueError(f"bootstrap: positions, runs and resamples must be at least 1 "
                         f"(got {positions}, {runs}, {resamples})")
    rng = np.random.default_rng(seed)
    drawn = rng.integers(positions, size=(resamples, positions))  # (B, P) positions
    if runs_too:
        cell = drawn[:, :, None] * runs + rng.integers(runs, size=(resamples, positions, runs))
    else:
        cell = drawn[:, :, None] * runs + np.arange(runs)[None, None, :]
    offset = (np.arange(resamples) * positions * runs)[:, None, None]
    flat = np.bincount((cell + offset).ravel(), minlength=resamples * positions * runs)
    return flat.reshape(resamples, positions * runs).astype(np.float64)


def resampled_means(x: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Resampled means (B, K) of outcomes ``x`` (P, R, K) or (P, R) (then (B,)) under
    :func:`resample_counts`' counts (B, P R)."""
    a = np.asarray(x, dtype=np.float64)
    flat = a.reshape(a.shape[0] * a.shape[1], -1)
    if counts.shape[1] != flat.shape[0]:
        raise ValueError(f"bootstrap: counts for {counts.shape[1]} outcomes, got {flat.shape[0]}")
    means = counts @ flat / flat.shape[0]
    return means if a.ndim > 2 else means[:, 0]


def interval(x: np.ndarray, counts: np.ndarray, level: float = LEVEL) -> np.ndarray:
    """Percentile interval (K, 2) (or (2,) for (P, R) outcomes) of the mean of ``x``."""
    q = 0.5 * (1.0 - level)
    return np.quantile(resampled_means(x, counts), [q, 1.0 - q], axis=0).T


def intervals_json(x: np.ndarray, counts: np.ndarray) -> list[list[float]]:
    """:func:`interval` of (P, R, K) outcomes as the JSON's ``[[lo, hi], ...]`` per k."""
    return [[round(float(lo), 4), round(float(hi), 4)] for lo, hi in interval(x, counts)]


def paired_difference(a: np.ndarray, b: np.ndarray, counts: np.ndarray) -> dict[str, list[Any]]:
    """Mean paired difference ``a - b`` of outcomes (P, R, K) of the same runs, per k: the
    difference, its bootstrap standard error and ``ahead`` = difference > one standard error."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    mean = d.reshape(-1, d.shape[2]).mean(axis=0)
    se = resampled_means(d, counts).std(axis=0)
    return {"difference": [round(float(v), 4) for v in mean], "se": [round(float(v), 4) for v in se],
            "ahead": [bool(m > s) for m, s in zip(mean, se, strict=True)]}


def bootstrap_report() -> dict[str, Any]:
    """The result's description of its intervals and standard errors."""
    return {"method": SE_METHOD, "interval": "percentile", "level": LEVEL, "resamples": RESAMPLES, "seed": SEED}

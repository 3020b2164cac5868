"""The intervals and paired differences of `eval active` (services/evaluation/active_stats.py):
the two-stage bootstrap against its closed forms on constructed 0/1 samples."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from services.evaluation import active_stats as S


def _bernoulli(positions: int, runs: int, q: float, seed: int = 3, k: int = 1) -> np.ndarray:
    """Independent Bernoulli(q) outcomes (P, R, k): no difference between positions."""
    return (np.random.default_rng(seed).random((positions, runs, k)) < q).astype(np.float64)


def _two_stage_variance(x: np.ndarray) -> float:
    """The two-stage bootstrap's variance of the mean of (P, R) outcomes, B -> infinity:
    (V_b + W / R) / P (module docstring)."""
    p, r = x.shape
    xbar_p = x.mean(axis=1)
    v_b = np.mean((xbar_p - x.mean()) ** 2)
    w = np.mean((x - xbar_p[:, None]) ** 2)
    return float((v_b + w / r) / p)


def test_counts_are_a_resample_of_every_run() -> None:
    c = S.resample_counts(7, 4, resamples=300)
    assert c.shape == (300, 28)
    assert np.all(c.sum(axis=1) == 28)
    assert np.array_equal(c, S.resample_counts(7, 4, resamples=300))  # seeded
    # positions only: a drawn position brings each of its runs once
    c1 = S.resample_counts(7, 4, resamples=300, runs_too=False).reshape(300, 7, 4)
    assert np.all(c1 == c1[:, :, :1])
    with pytest.raises(ValueError):
        S.resample_counts(0, 4)


def _half_widths(runs_too: bool, seeds: range = range(10)) -> tuple[float, float]:
    """Mean half-width of the 95 % interval over samples of 50 x 10 Bernoulli(0.7) outcomes,
    and the normal approximation's 1.96 sqrt(q (1 - q) / n)."""
    half = [np.diff(S.interval(_bernoulli(50, 10, 0.7, seed), S.resample_counts(50, 10, runs_too=runs_too)))[0, 0] / 2
            for seed in seeds]
    return float(np.mean(half)), 1.96 * math.sqrt(0.7 * 0.3 / 500)


def test_positions_only_interval_is_the_normal_approximation_of_a_bernoulli_sample() -> None:
    """Independent outcomes: the cluster bootstrap's 95 % interval is mean +- 1.96 sqrt(q (1 - q) / n)
    (on average over samples; on one sample, its closed form 1.96 sqrt(V_b / P))."""
    x = _bernoulli(50, 10, 0.7)
    lo, hi = S.interval(x, S.resample_counts(50, 10, runs_too=False))[0]
    v_b = np.var(x[:, :, 0].mean(axis=1))
    assert (hi - lo) / 2 == pytest.approx(1.96 * math.sqrt(v_b / 50), rel=0.08)
    assert (lo + hi) / 2 == pytest.approx(x.mean(), abs=0.01)
    mean_half, normal = _half_widths(runs_too=False)
    assert mean_half == pytest.approx(normal, rel=0.06)


def test_two_stage_interval_is_its_closed_form() -> None:
    """Resampling runs as well adds the within-position variance once more: the interval is
    mean +- 1.96 sqrt((V_b + W / R) / P), for independent outcomes about sqrt((2R - 1) / R)
    times the normal approximation's half-width."""
    x = _bernoulli(50, 10, 0.7)
    counts = S.resample_counts(50, 10)
    lo, hi = S.interval(x, counts)[0]
    assert (hi - lo) / 2 == pytest.approx(1.96 * math.sqrt(_two_stage_variance(x[:, :, 0])), rel=0.08)
    assert S.resampled_means(x, counts).std() == pytest.approx(math.sqrt(_two_stage_variance(x[:, :, 0])), rel=0.06)
    mean_half, normal = _half_widths(runs_too=True)
    assert mean_half == pytest.approx(normal * math.sqrt(19 / 10), rel=0.06)


@pytest.mark.parametrize("q", [0.05, 0.5, 0.77, 0.96, 1.0])
def test_the_interval_contains_the_mean(q: float) -> None:
    x = _bernoulli(50, 10, q, k=3)
    ci = S.interval(x, S.resample_counts(50, 10))
    mean = x.mean(axis=(0, 1))
    assert ci.shape == (3, 2)
    assert np.all(ci[:, 0] <= mean) and np.all(mean <= ci[:, 1])
    assert np.all((0.0 <= ci) & (ci <= 1.0))


def test_intervals_shrink_with_more_runs() -> None:
    widths = []
    for runs in (2, 10, 40):
        x = _bernoulli(50, runs, 0.7, seed=runs)
        lo, hi = S.interval(x, S.resample_counts(50, runs))[0]
        widths.append(hi - lo)
    assert widths[0] > widths[1] > widths[2]
    assert widths[1] / widths[2] == pytest.approx(2.0, rel=0.25)  # ~ 1 / sqrt(runs)


def test_positions_that_differ_widen_the_interval() -> None:
    """Half the positions always succeed, half never: every run agrees with its position and
    the interval is that of 50 draws, not 500."""
    x = np.zeros((50, 10, 1))
    x[::2] = 1.0
    lo, hi = S.interval(x, S.resample_counts(50, 10))[0]
    assert (hi - lo) / 2 == pytest.approx(1.96 * math.sqrt(0.25 / 50), rel=0.1)


def test_paired_difference_and_its_standard_error() -> None:
    """Entropy wins exactly one run of ten at every position and otherwise agrees with random:
    difference 0.1, no spread between positions (V_b = 0), within W = 0.09, so the two-stage SE
    is sqrt(W / R / P); ahead. Equal strategies: difference and SE 0, not ahead."""
    rng = np.random.default_rng(5)
    b = (rng.random((50, 10, 2)) < 0.6).astype(np.float64)
    b[:, 0, 1] = 0.0
    a = b.copy()
    a[:, 0, 1] = 1.0  # k = 1: run 0 of every position won by a only
    counts = S.resample_counts(50, 10)
    d = S.paired_difference(a, b, counts)
    assert d["difference"] == [0.0, pytest.approx(0.1)]
    assert d["se"][0] == 0.0
    assert d["se"][1] == pytest.approx(math.sqrt(0.09 / 10 / 50), rel=0.07)
    assert d["ahead"] == [False, True]
    same = S.paired_difference(b, b, counts)
    assert same == {"difference": [0.0, 0.0], "se": [0.0, 0.0], "ahead": [False, False]}
    # the SE of a difference is that of its bootstrap means, not of a and b unpaired
    worse = S.paired_difference(b, a, counts)
    assert worse["difference"][1] == pytest.approx(-0.1) and worse["ahead"][1] is False


def test_the_bootstrap_is_cheap_at_the_experiments_scale() -> None:
    """50 positions x 10 runs x 11 movements: counts, the intervals of three strategies and
    two paired differences well under a second (generous bound for a loaded machine)."""
    x = {s: _bernoulli(50, 10, 0.7, seed=i, k=11) for i, s in enumerate(("entropy", "random", "sweep"))}
    t0 = time.perf_counter()
    counts = S.resample_counts(50, 10)
    for v in x.values():
        S.intervals_json(v, counts)
    for s in ("random", "sweep"):
        S.paired_difference(x["entropy"], x[s], counts)
    assert time.perf_counter() - t0 < 1.0

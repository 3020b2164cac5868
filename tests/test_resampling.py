"""Resampling schemes: unbiased counts, variance ordering, ESS and logsumexp."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import logsumexp as scipy_logsumexp

from lino_loc.resampling import (
    SCHEMES,
    get_resampler,
    logsumexp,
    multinomial,
    stratified,
    systematic,
)
from lino_loc.weights import NoFiniteWeightError, Weights


def effective_sample_size(log_weights) -> float:
    return Weights.from_log(log_weights).ess()

W = np.array([0.02, 0.3, 0.05, 0.13, 0.0, 0.2, 0.07, 0.18, 0.04, 0.01])


def _counts(scheme, log_w, seeds: int, n: int) -> np.ndarray:
    out = np.zeros((seeds, log_w.size))
    for s in range(seeds):
        idx = scheme(log_w, np.random.default_rng(s), n)
        out[s] = np.bincount(idx, minlength=log_w.size)
    return out


@pytest.mark.parametrize("name", sorted(SCHEMES))
def test_expected_counts_are_n_times_weights(name: str) -> None:
    with np.errstate(divide="ignore"):
        log_w = np.log(W) + 3.7  # unnormalized on purpose
    n, seeds = 25, 3000
    counts = _counts(get_resampler(name), log_w, seeds, n)
    expected = n * W
    mean = counts.mean(axis=0)
    se = counts.std(axis=0, ddof=1) / np.sqrt(seeds)
    # zero-weight particle is never drawn
    assert counts[:, 4].max() == 0
    ok = W > 0
    z = (mean[ok] - expected[ok]) / np.maximum(se[ok], 1e-12)
    assert np.all(np.abs(z) < 4.5), z
    # chi-square-like aggregate of the z-scores (9 d.o.f.): far below a 1e-4 tail
    assert float(np.sum(z**2)) < 40.0
    assert np.all(counts.sum(axis=1) == n)


def test_systematic_counts_are_floor_or_ceil() -> None:
    log_w = np.log(W + 1e-300)
    n = 100
    for s in range(50):
        c = np.bincount(systematic(log_w, np.random.default_rng(s), n), minlength=W.size)
        assert np.all(c >= np.floor(n * W) - 1e-9) and np.all(c <= np.ceil(n * W) + 1e-9)


def test_variance_ordering() -> None:
    log_w = np.log(W + 1e-300)
    var = {
        name: _counts(fn, log_w, 1500, 50).var(axis=0).sum()
        for name, fn in (
            ("systematic", systematic),
            ("stratified", stratified),
            ("multinomial", multinomial),
        )
    }
    assert var["systematic"] <= var["stratified"] < var["multinomial"]


def test_ess_bounds() -> None:
    assert effective_sample_size(np.zeros(40)) == pytest.approx(40.0)
    one_hot = np.full(40, -np.inf)
    one_hot[3] = 0.0
    assert effective_sample_size(one_hot) == pytest.approx(1.0)
    lw = np.log(np.array([0.5, 0.5, 0.0, 0.0]) + 1e-300)
    assert effective_sample_size(lw) == pytest.approx(2.0)


def test_logsumexp_matches_scipy_and_handles_minus_inf() -> None:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(7, 5)) * 300
    np.testing.assert_allclose(logsumexp(a, axis=1), scipy_logsumexp(a, axis=1))
    np.testing.assert_allclose(
        logsumexp(a, axis=0, keepdims=True), scipy_logsumexp(a, axis=0, keepdims=True)
    )
    assert logsumexp(a) == pytest.approx(float(scipy_logsumexp(a)))
    assert logsumexp(np.array([-np.inf, -np.inf])) == -np.inf
    with pytest.raises(ValueError):
        Weights.from_log([-np.inf, -np.inf])
    with pytest.raises(NoFiniteWeightError):
        Weights.from_log([-np.inf, -np.inf], one_pass=False)


def test_unknown_scheme() -> None:
    with pytest.raises(ValueError, match="unknown resampling"):
        get_resampler("residualz")

"""The Weights value (lino_loc.weights): softmax closed forms, ESS bounds, errors, invariance,
caching."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.weights import NoFiniteWeightError, Weights, logsumexp


@pytest.mark.parametrize("one_pass", [True, False])
def test_softmax_closed_form(one_pass: bool) -> None:
    lw = np.log([1.0, 2.0, 3.0, 4.0]) + 7.5  # unnormalized on purpose
    w = Weights.from_log(lw, one_pass=one_pass)
    np.testing.assert_allclose(w.linear, [0.1, 0.2, 0.3, 0.4], rtol=1e-14)
    np.testing.assert_allclose(np.exp(w.log), [0.1, 0.2, 0.3, 0.4], rtol=1e-14)
    assert w.log_normalizer == pytest.approx(math.log(10.0) + 7.5, rel=1e-15)
    assert w.linear.sum() == pytest.approx(1.0, abs=1e-15)
    # ESS = 1 / sum w^2 = 1 / 0.3
    assert w.ess() == pytest.approx(1.0 / 0.3, rel=1e-13)


def test_the_two_recipes_agree_to_rounding() -> None:
    lw = np.random.default_rng(0).normal(0, 30, 500)
    a, b = Weights.from_log(lw), Weights.from_log(lw, one_pass=False)
    np.testing.assert_allclose(a.linear, b.linear, rtol=1e-12)
    np.testing.assert_allclose(a.log, b.log, rtol=1e-12, atol=1e-12)
    assert a.log_normalizer == pytest.approx(b.log_normalizer, rel=1e-14)
    assert b.log_normalizer == pytest.approx(float(logsumexp(lw)), rel=0)


def test_ess_lies_between_one_and_n() -> None:
    rng = np.random.default_rng(1)
    n = 200
    assert Weights.uniform(n).ess() == pytest.approx(n, rel=1e-12)
    one_hot = np.full(n, -np.inf)
    one_hot[17] = 3.0
    w = Weights.from_log(one_hot)
    assert w.ess() == pytest.approx(1.0) and w.linear[17] == 1.0
    for scale in (0.1, 1.0, 10.0, 100.0):
        ess = Weights.from_log(rng.normal(0, scale, n)).ess()
        assert 1.0 - 1e-12 <= ess <= n + 1e-9


@pytest.mark.parametrize("one_pass", [True, False])
@pytest.mark.parametrize("bad", [[-np.inf, -np.inf, -np.inf], [np.nan, -np.inf], []])
def test_no_finite_weight_is_a_clear_error(one_pass: bool, bad: list[float]) -> None:
    with pytest.raises(NoFiniteWeightError, match="no finite entry"):
        Weights.from_log(np.array(bad, dtype=np.float64), one_pass=one_pass)
    assert issubclass(NoFiniteWeightError, ValueError)


def test_shift_invariance() -> None:
    lw = np.random.default_rng(2).normal(0, 5, 50)
    a = Weights.from_log(lw)
    for shift in (-1e3, -3.0, 250.0):
        b = Weights.from_log(lw + shift)
        np.testing.assert_allclose(b.linear, a.linear, rtol=1e-10)
        np.testing.assert_allclose(b.log, a.log, atol=1e-9)
        assert b.log_normalizer == pytest.approx(a.log_normalizer + shift, abs=1e-9)


def test_linear_weights_are_computed_once_and_the_input_is_kept() -> None:
    lw = np.log([0.5, 0.25, 0.25])
    w = Weights(lw)
    first = w.linear
    assert w.linear is first  # cached
    np.testing.assert_allclose(first, [0.5, 0.25, 0.25], rtol=1e-15)
    src = np.array([1.0, 2.0, 3.0])
    v = Weights.from_log(src)
    np.testing.assert_array_equal(src, [1.0, 2.0, 3.0])  # not modified
    assert v.linear is v.linear and len(v) == 3
    u = Weights.uniform(4)
    np.testing.assert_array_equal(u.log, np.full(4, -math.log(4)))
    np.testing.assert_array_equal(u.linear, np.full(4, 0.25))

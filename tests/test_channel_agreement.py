"""The overlap of two channel mixtures (lino_loc/channel_agreement.py): closed forms and
invariants, against a Monte Carlo integral."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.channel_agreement import log_inner, overlap
from lino_loc.sensor_model import Bounds, PoseMixture

BOUNDS = Bounds(-10.0, 10.0, -10.0, 10.0)


def _one(x: float, y: float = 0.0, th: float = 0.0, s: float = 0.35, st: float = 0.3, **kw) -> PoseMixture:
    return PoseMixture.create([[x, y, th]], [0.0], s, st, **kw)


def test_the_same_mixture_overlaps_fully_and_overlap_is_symmetric() -> None:
    rng = np.random.default_rng(0)
    a = PoseMixture.create(rng.uniform(-2, 2, (5, 3)), rng.normal(0, 1, 5), 0.35, 0.3)
    b = PoseMixture.create(rng.uniform(-2, 2, (5, 3)), rng.normal(0, 1, 5), 0.35, 0.3)
    assert overlap(a, a) == pytest.approx(1.0)
    assert overlap(a, b) == pytest.approx(overlap(b, a))
    assert 0.0 <= overlap(a, b) <= 1.0
    perm = np.array([3, 1, 4, 0, 2])  # a relabelling of the components changes nothing
    a2 = PoseMixture.create(a.poses[perm], a.log_weights[perm], 0.35, 0.3)
    assert overlap(a2, b) == pytest.approx(overlap(a, b))


def test_two_kernels_d_apart_overlap_as_exp_minus_d2_over_4s2() -> None:
    """Equal widths s, same heading: the heading factors cancel, the position factor is
    exp(-d^2 / (4 s^2))."""
    for d in (0.0, 0.35, 1.0, 2.0):
        assert overlap(_one(0.0), _one(d)) == pytest.approx(math.exp(-d * d / (4 * 0.35**2)), rel=1e-9)
    assert overlap(_one(0.0), _one(5.0)) < 1e-15  # disjoint channels: no overlap


def test_opposite_headings_do_not_overlap_and_scale_and_outlier_do_not_matter() -> None:
    assert overlap(_one(0.0, th=0.0), _one(0.0, th=math.pi)) < 0.01
    a = _one(0.0)
    b = _one(0.5)
    scaled = PoseMixture(b.poses, b.log_weights, b.sigma_xy, b.sigma_theta, log_scale=7.0)
    with_outlier = _one(0.5, outlier_weight=0.3, bounds=BOUNDS)
    assert overlap(a, scaled) == pytest.approx(overlap(a, b))
    assert overlap(a, with_outlier) == pytest.approx(overlap(a, b))


def test_the_inner_product_matches_a_monte_carlo_integral() -> None:
    """<p_a, p_b> = E_{x ~ p_a}[p_b(x)], estimated from 200 000 draws of p_a (seeded)."""
    rng = np.random.default_rng(1)
    a = PoseMixture.create([[0.0, 0.0, 0.2], [0.6, 0.3, 1.0]], np.log([0.7, 0.3]), [0.3, 0.4], [0.3, 0.5])
    b = PoseMixture.create([[0.2, -0.1, 0.5], [1.5, 0.0, -2.0]], np.log([0.5, 0.5]), [0.35, 0.3], [0.4, 0.3])
    x = a.sample(200_000, rng)
    mc = float(np.mean(b.pdf(x)))
    assert math.exp(log_inner(a, b)) == pytest.approx(mc, rel=0.02)

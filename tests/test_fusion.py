"""Fusion of channel mixtures: disjunctive (eq. 8) and the exact conjunctive product (eq. 7)."""

from __future__ import annotations

import numpy as np
import pytest

from lino_loc.fusion import FusionConfig, conjunctive, disjunctive, fuse, product
from lino_loc.sensor_model import Bounds, PoseMixture

BOUNDS = Bounds(0.0, 5.0, 0.0, 4.0)


def _a(outlier: float = 0.0) -> PoseMixture:
    return PoseMixture.create(
        [[1.0, 1.0, 0.3], [3.0, 2.0, np.pi - 0.05], [2.0, 3.0, -1.0]],
        np.log([0.6, 0.3, 0.1]),
        [0.4, 0.3, 0.5],
        [0.3, 0.4, 0.6],
        outlier_weight=outlier,
        bounds=BOUNDS,
    )


def _b(outlier: float = 0.0) -> PoseMixture:
    return PoseMixture.create(
        [[1.2, 0.9, 0.5], [3.1, 2.2, -np.pi + 0.05]],
        np.log([0.5, 0.5]),
        [0.3, 0.35],
        [0.25, 0.3],
        outlier_weight=outlier,
        bounds=BOUNDS,
    )


def _points(n=400, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack(
        [rng.uniform(0, 5, n), rng.uniform(0, 4, n), rng.uniform(-np.pi, np.pi, n)]
    )


@pytest.mark.parametrize("outlier", [0.0, 0.05])
def test_disjunctive_is_weighted_sum(outlier: float) -> None:
    a, b = _a(outlier), _b(outlier)
    x = _points()
    d = disjunctive([a, b], [0.3, 0.7])
    np.testing.assert_allclose(d.pdf(x), 0.3 * a.pdf(x) + 0.7 * b.pdf(x), rtol=1e-10)
    assert d.n_components == 5
    assert d.log_scale == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("outlier", [0.0, 0.05])
def test_conjunctive_is_product_inside_the_map(outlier: float) -> None:
    a, b = _a(outlier), _b(outlier)
    x = _points()
    c = product(a, b)
    np.testing.assert_allclose(c.log_pdf(x), a.log_pdf(x) + b.log_pdf(x), rtol=1e-9, atol=1e-9)
    # sampling ignores the scale: the normalized product has unit mass (grid integral)
    xs = (np.arange(60) + 0.5) * 8.0 / 60 - 1.5
    ys = (np.arange(50) + 0.5) * 7.0 / 50 - 1.5
    ts = -np.pi + (np.arange(48) + 0.5) * 2 * np.pi / 48
    X, Y, T = np.meshgrid(xs, ys, ts, indexing="ij")
    g = np.column_stack([X.ravel(), Y.ravel(), T.ravel()])
    cell = (8 / 60) * (7 / 50) * (2 * np.pi / 48)
    mass = np.sum(np.exp(c.log_pdf(g) - c.log_scale)) * cell
    assert mass == pytest.approx(1.0, abs=0.02)


def test_product_samples_follow_the_product() -> None:
    """Importance check: E_q[f] from product samples equals the grid integral of f * a * b."""
    a, b = _a(), _b()
    c = conjunctive([a, b])
    s = c.sample(60_000, np.random.default_rng(3))
    xs = (np.arange(80) + 0.5) * 8.0 / 80 - 1.5
    ys = (np.arange(70) + 0.5) * 7.0 / 70 - 1.5
    ts = -np.pi + (np.arange(72) + 0.5) * 2 * np.pi / 72
    X, Y, T = np.meshgrid(xs, ys, ts, indexing="ij")
    g = np.column_stack([X.ravel(), Y.ravel(), T.ravel()])
    p = np.exp(a.log_pdf(g) + b.log_pdf(g))
    p /= p.sum()
    assert s[:, 0].mean() == pytest.approx(float(p @ g[:, 0]), abs=0.01)
    assert s[:, 1].mean() == pytest.approx(float(p @ g[:, 1]), abs=0.01)
    assert np.cos(s[:, 2]).mean() == pytest.approx(float(p @ np.cos(g[:, 2])), abs=0.01)
    assert np.sin(s[:, 2]).mean() == pytest.approx(float(p @ np.sin(g[:, 2])), abs=0.01)
    assert s[:, 0].std() == pytest.approx(
        float(np.sqrt(p @ (g[:, 0] - p @ g[:, 0]) ** 2)), rel=0.03
    )


def test_product_across_the_angle_cut() -> None:
    a = PoseMixture.create([[0.0, 0.0, np.pi - 0.1]], [0.0], 0.3, 0.3)
    b = PoseMixture.create([[0.0, 0.0, -np.pi + 0.1]], [0.0], 0.3, 0.3)
    c = product(a, b)
    assert abs(np.angle(np.exp(1j * (c.poses[0, 2] - np.pi)))) < 1e-9
    assert c.sigma_theta[0] < 0.3


def test_disagreeing_channels_give_a_tiny_conjunctive_likelihood() -> None:
    a = PoseMixture.create([[1.0, 1.0, 0.0]], [0.0], 0.3, 0.3)
    b = PoseMixture.create([[4.0, 3.0, 2.0]], [0.0], 0.3, 0.3)
    agree = product(a, a).log_scale
    disagree = product(a, b).log_scale
    assert disagree < agree - 30


def test_fuse_dispatch() -> None:
    a, b = _a(0.01), _b(0.01)
    assert fuse({"intensity": a}) is a
    x = _points(50)
    d = fuse({"intensity": a, "disparity": b}, FusionConfig(w_d=0.25, w_i=0.75))
    np.testing.assert_allclose(d.pdf(x), 0.75 * a.pdf(x) + 0.25 * b.pdf(x), rtol=1e-10)
    c = fuse({"intensity": a, "disparity": b}, FusionConfig(mode="conjunctive"))
    np.testing.assert_allclose(c.log_pdf(x), a.log_pdf(x) + b.log_pdf(x), rtol=1e-9)
    only_d = fuse({"intensity": a, "disparity": b}, FusionConfig(w_d=1.0, w_i=0.0))
    np.testing.assert_allclose(only_d.pdf(x), b.pdf(x), rtol=1e-10)
    with pytest.raises(ValueError):
        disjunctive([a, b], [0.0, 0.0])

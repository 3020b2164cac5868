"""Odometry action model against closed forms (Probabilistic Robotics, table 5.6)."""

from __future__ import annotations

import numpy as np
import pytest

from lino_loc.motion_model import MotionModelConfig, OdometryMotionModel, decompose, recompose
from lino_loc.poses import between, compose, wrap_angle

N = 200_000


def _model(**kw: float) -> OdometryMotionModel:
    base = dict(alpha1=0.0, alpha2=0.0, alpha3=0.0, alpha4=0.0, min_sigma_xy=0.0, min_sigma_theta=0.0)
    base.update(kw)
    return OdometryMotionModel(MotionModelConfig(**base))


@pytest.mark.parametrize(
    "delta",
    [(0.3, 0.0, 0.0), (0.2, 0.1, 0.4), (-0.4, 0.05, -0.2), (0.0, 0.0, 1.2), (0.0, -0.3, 3.0)],
)
def test_zero_noise_is_exact_compose(delta) -> None:
    rng = np.random.default_rng(0)
    particles = np.column_stack(
        [rng.uniform(-5, 5, 50), rng.uniform(-5, 5, 50), rng.uniform(-np.pi, np.pi, 50)]
    )
    out = _model().sample(particles, np.array(delta), rng)
    ref = compose(particles, np.array(delta))
    np.testing.assert_allclose(out[:, :2], ref[:, :2], atol=1e-12)
    np.testing.assert_allclose(wrap_angle(out[:, 2] - ref[:, 2]), 0.0, atol=1e-12)


def test_decompose_roundtrip_and_backward_and_rotation() -> None:
    rng = np.random.default_rng(1)
    d = np.column_stack(
        [rng.normal(size=100), rng.normal(size=100), rng.uniform(-np.pi, np.pi, 100)]
    )
    r1, t, r2 = decompose(d)
    np.testing.assert_allclose(recompose(r1, t, r2)[:, :2], d[:, :2], atol=1e-12)
    np.testing.assert_allclose(wrap_angle(recompose(r1, t, r2)[:, 2] - d[:, 2]), 0, atol=1e-12)
    assert np.all(np.abs(r1) <= np.pi / 2 + 1e-12)  # backward motion never turns round
    r1, t, r2 = decompose(np.array([-0.5, 0.0, 0.1]))
    assert (float(r1), float(t), float(r2)) == pytest.approx((0.0, -0.5, 0.1))
    r1, t, r2 = decompose(np.array([1e-7, 0.0, 0.8]))
    assert (float(r1), float(t), float(r2)) == pytest.approx((0.0, 0.0, 0.8))


def test_straight_line_mean_and_spread_closed_form() -> None:
    a1, a2, a3, a4 = 0.1, 0.2, 0.05, 0.3
    m = _model(alpha1=a1, alpha2=a2, alpha3=a3, alpha4=a4)
    trans = 1.0
    out = m.sample(np.zeros((N, 3)), np.array([trans, 0.0, 0.0]), np.random.default_rng(2))
    v1 = a2 * trans**2  # rot1 = rot2 = 0: only the translation term
    vt = a3 * trans**2
    assert m.variances(np.array([trans, 0.0, 0.0])) == pytest.approx((v1, vt, v1))
    # x = t cos r1, y = t sin r1, theta = r1 + r2 with t ~ N(trans, vt), r1, r2 ~ N(0, v1)
    ex = trans * np.exp(-v1 / 2)
    et2 = trans**2 + vt
    var_x = et2 * (1 + np.exp(-2 * v1)) / 2 - ex**2
    var_y = et2 * (1 - np.exp(-2 * v1)) / 2
    se = lambda v: 5 * np.sqrt(v / N)  # noqa: E731
    assert out[:, 0].mean() == pytest.approx(ex, abs=se(var_x))
    assert out[:, 1].mean() == pytest.approx(0.0, abs=se(var_y))
    assert out[:, 0].var() == pytest.approx(var_x, rel=0.02)
    assert out[:, 1].var() == pytest.approx(var_y, rel=0.02)
    assert out[:, 2].var() == pytest.approx(2 * v1, rel=0.02)


def test_pure_rotation_spread_closed_form() -> None:
    a1, a4 = 0.1, 0.02
    m = _model(alpha1=a1, alpha2=0.3, alpha3=0.4, alpha4=a4)
    dth = 1.0
    out = m.sample(np.zeros((N, 3)), np.array([0.0, 0.0, dth]), np.random.default_rng(3))
    # rot1 = 0 exactly (no noise: alpha1*0 + alpha2*0), trans ~ N(0, a4*dth^2), rot2 ~ N(dth, a1*dth^2)
    assert np.all(out[:, 1] == 0.0)
    assert out[:, 0].mean() == pytest.approx(0.0, abs=5 * np.sqrt(a4 / N))
    assert out[:, 0].var() == pytest.approx(a4 * dth**2, rel=0.02)
    assert out[:, 2].mean() == pytest.approx(dth, abs=5 * np.sqrt(a1 / N))
    assert out[:, 2].var() == pytest.approx(a1 * dth**2, rel=0.02)


def test_backward_motion_has_no_half_turn_noise() -> None:
    m = _model(alpha1=0.2, alpha2=0.01, alpha3=0.01, alpha4=0.01)
    out = m.sample(np.zeros((20_000, 3)), np.array([-0.5, 0.0, 0.0]), np.random.default_rng(4))
    assert out[:, 0].mean() == pytest.approx(-0.5, abs=0.01)
    # heading noise from translation only (2 * alpha2 * 0.25), not alpha1 * pi^2
    assert out[:, 2].var() == pytest.approx(2 * 0.01 * 0.25, rel=0.05)


def test_applies_in_the_particle_frame() -> None:
    m = _model(alpha3=0.01)
    start = np.array([[1.0, 2.0, np.pi / 2]])
    odo_a, odo_b = (
        np.array([5.0, 5.0, 0.3]),
        compose(np.array([5.0, 5.0, 0.3]), np.array([0.4, 0.0, 0.0])),
    )
    out = m.sample(
        np.repeat(start, 50_000, axis=0), between(odo_a, odo_b), np.random.default_rng(5)
    )
    assert out[:, 0].mean() == pytest.approx(1.0, abs=0.005)
    assert out[:, 1].mean() == pytest.approx(2.4, abs=0.005)
    np.testing.assert_allclose(
        m.predict_mean(start, between(odo_a, odo_b)), [[1.0, 2.4, np.pi / 2]], atol=1e-12
    )


def test_noise_floor_spreads_a_still_robot() -> None:
    """Zero increment: without the floor every particle stays put (sample impoverishment);
    with it x, y, theta get independent N(0, floor^2) per update, also about a motion."""
    p0 = np.tile([1.0, -2.0, 3.1], (N, 1))
    still = _model(alpha1=0.1, alpha2=0.1, alpha3=0.1, alpha4=0.1)
    np.testing.assert_allclose(still.sample(p0, np.zeros(3), np.random.default_rng(4)), p0, atol=1e-12)
    sxy, sth = 0.02, 0.01
    m = _model(min_sigma_xy=sxy, min_sigma_theta=sth)
    out = m.sample(p0, np.zeros(3), np.random.default_rng(5))
    d = out - p0
    d[:, 2] = wrap_angle(d[:, 2])
    np.testing.assert_allclose(d.mean(axis=0), 0.0, atol=5 * sxy / np.sqrt(N))
    np.testing.assert_allclose(d.var(axis=0), [sxy**2, sxy**2, sth**2], rtol=0.02)
    assert abs(np.corrcoef(d[:, 0], d[:, 2])[0, 1]) < 0.02
    # about a pure rotation the floor's variance adds to the odometry's
    a1 = 0.05
    m2 = _model(alpha1=a1, min_sigma_xy=sxy, min_sigma_theta=sth)
    out2 = m2.sample(np.zeros((N, 3)), np.array([0.0, 0.0, 1.0]), np.random.default_rng(6))
    assert out2[:, 2].var() == pytest.approx(a1 + sth**2, rel=0.02)
    assert out2[:, 0].var() == pytest.approx(sxy**2, rel=0.02)
    # defaults: a floor of 1 cm and 0.5 deg is on
    cfg = MotionModelConfig()
    assert cfg.min_sigma_xy == pytest.approx(0.01) and np.degrees(cfg.min_sigma_theta) == pytest.approx(0.5, abs=0.01)


def _textbook_sample(m: OdometryMotionModel, p: np.ndarray, delta, rng) -> np.ndarray:
    """Table 5.6 literally: perturb rot1, trans, rot2, compose, then add the floor (six normals)."""
    c = m.config
    r1, t, r2 = (float(v) for v in decompose(np.asarray(delta), c.min_trans))
    v1, vt, v2 = m.variances(delta)
    n = p.shape[0]
    rr1 = r1 + np.sqrt(v1) * rng.standard_normal(n)
    tt = t + np.sqrt(vt) * rng.standard_normal(n)
    rr2 = r2 + np.sqrt(v2) * rng.standard_normal(n)
    out = compose(p, recompose(rr1, tt, rr2))
    out += rng.standard_normal((n, 3)) * [c.min_sigma_xy, c.min_sigma_xy, c.min_sigma_theta]
    out[:, 2] = wrap_angle(out[:, 2])
    return out


@pytest.mark.parametrize("delta", [(0.3, 0.05, 0.2), (0.0, 0.0, 0.0), (-0.2, 0.1, -1.0)])
def test_sampler_has_the_textbook_distribution(delta) -> None:
    """The sampler draws four normals per particle (rot2 noise + heading floor as one normal,
    translation noise + position floor as one normal along and one across the heading); the
    mean and covariance of (x, y, theta) must be those of the six-normal textbook sampler."""
    m = OdometryMotionModel(MotionModelConfig(alpha1=0.05, alpha2=0.1, alpha3=0.2, alpha4=0.05,
                                              min_sigma_xy=0.05, min_sigma_theta=0.05))
    p = np.tile([1.0, 2.0, 2.8], (N, 1))
    fast = m.sample(p, delta, np.random.default_rng(8))
    ref = _textbook_sample(m, p, delta, np.random.default_rng(9))
    for a in (fast, ref):
        a[:, 2] = wrap_angle(a[:, 2] - 2.8)  # about the start heading: no cut in the cloud
    cf, cr = np.cov(fast.T), np.cov(ref.T)
    se = np.sqrt((np.diag(cf) + np.diag(cr)) / N)
    np.testing.assert_array_less(np.abs(fast.mean(axis=0) - ref.mean(axis=0)), 5 * se)
    # covariance entries: standard error sqrt((s_ii s_jj + s_ij^2) / N) each, two samples
    s = np.sqrt(np.outer(np.diag(cr), np.diag(cr)) + cr**2)
    np.testing.assert_array_less(np.abs(cf - cr), 5 * np.sqrt(2.0 / N) * s)
    assert np.all((fast[:, 2] >= -np.pi) & (fast[:, 2] < np.pi))


def test_predict_mean_trig_is_predict_mean() -> None:
    rng = np.random.default_rng(3)
    p = np.column_stack([rng.uniform(-5, 5, 50), rng.uniform(-5, 5, 50), rng.uniform(-np.pi, np.pi, 50)])
    m = OdometryMotionModel()
    d = np.array([0.3, -0.1, 2.5])
    x, y, c, s = m.predict_mean_trig(p, d, turn=0.7)
    ref = m.predict_mean(p, d)
    np.testing.assert_allclose(np.column_stack([x, y]), ref[:, :2], atol=1e-12)
    np.testing.assert_allclose(c, np.cos(ref[:, 2] + 0.7), atol=1e-12)
    np.testing.assert_allclose(s, np.sin(ref[:, 2] + 0.7), atol=1e-12)

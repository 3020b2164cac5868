"""The interpolated sensor model (lino_loc/interpolated_appearance.py) and its H(u)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.active_vision import ActiveVisionConfig, InterpolatedActionEvaluator, action_evaluator
from lino_loc.errors import LinoLocError
from lino_loc.fusion import FusionConfig
from lino_loc.interpolated_appearance import (
    InterpolatedAppearance,
    InterpolatedSensorModel,
    InterpolationConfig,
    fuse_likelihoods,
)
from lino_loc.motion_model import OdometryMotionModel
from lino_loc.particle_filter import AuxiliaryParticleFilter, FilterConfig
from lino_loc.sensor_model import SensorModelConfig

STEP = 0.75
NH = 24


def lattice_poses(nx: int = 5, ny: int = 4, nh: int = NH, holes: tuple[tuple[int, int], ...] = ()) -> np.ndarray:
    """Grid poses ordered by x, y, heading (headings from 0, wrapped to (-pi, pi])."""
    out = []
    for i in range(nx):
        for j in range(ny):
            if (i, j) in holes:
                continue
            for k in range(nh):
                h = math.atan2(math.sin(2 * math.pi * k / nh), math.cos(2 * math.pi * k / nh))
                out.append((1.0 + STEP * i, -0.5 + STEP * j, h))
    return np.asarray(out)


def linear_field(p: np.ndarray) -> np.ndarray:
    """A field linear in x and y at each heading (trilinear interpolation reproduces it there)."""
    x, y, t = p[:, 0], p[:, 1], p[:, 2]
    return np.column_stack([x, y, x - 2 * y, x * y, np.cos(t), np.sin(t)])


def smooth_field(p: np.ndarray) -> np.ndarray:
    """A smooth field that tells poses apart (for the likelihood and the filter)."""
    x, y, t = p[:, 0], p[:, 1], p[:, 2]
    return np.column_stack([
        np.sin(1.3 * x) + 0.5 * np.cos(t), np.cos(0.9 * y) + 0.5 * np.sin(t), np.sin(0.8 * x * y),
        np.cos(t + 0.3 * x), np.sin(t - 0.4 * y), 0.3 * x + np.cos(2 * t),
    ])


def test_exact_at_the_lattice_and_linear_between() -> None:
    poses = lattice_poses()
    app = InterpolatedAppearance(poses, linear_field(poses))
    f, ok = app.features_at(poses)
    assert ok.all()
    np.testing.assert_allclose(f, linear_field(poses), atol=1e-12)
    rng = np.random.default_rng(0)
    q = np.column_stack([rng.uniform(1.0, 1.0 + 4 * STEP, 50), rng.uniform(-0.5, -0.5 + 3 * STEP, 50),
                         np.full(50, 2 * math.pi * 3 / NH)])  # on a lattice heading
    f, ok = app.features_at(q)
    np.testing.assert_allclose(f[:, :4], linear_field(q)[:, :4], atol=1e-12)  # bilinear in x, y
    # between two headings: the mean of the two neighbours
    a, b = 2 * math.pi * 3 / NH, 2 * math.pi * 4 / NH
    mid = np.array([[1.0, -0.5, 0.5 * (a + b)]])
    ends = app.features_at(np.array([[1.0, -0.5, a], [1.0, -0.5, b]]))[0]
    np.testing.assert_allclose(app.features_at(mid)[0][0], ends.mean(axis=0), atol=1e-12)


def test_heading_wraps() -> None:
    poses = lattice_poses()
    app = InterpolatedAppearance(poses, smooth_field(poses))
    last = 2 * math.pi * (NH - 1) / NH
    ends = app.features_at(np.array([[1.75, 0.25, last], [1.75, 0.25, 0.0]]))[0]
    for th in (last + math.pi / NH, last + math.pi / NH - 2 * math.pi):  # both spellings of the angle
        f = app.features_at(np.array([[1.75, 0.25, th]]))[0][0]
        np.testing.assert_allclose(f, ends.mean(axis=0), atol=1e-12)


def test_holes_are_left_out() -> None:
    poses = lattice_poses(holes=((1, 1),))
    app = InterpolatedAppearance(poses, linear_field(poses))
    # a pose inside a cell with the hole at one corner: the 3 other corners, renormalized
    p = np.array([[1.0 + 0.5 * STEP, -0.5 + 0.5 * STEP, 0.0]])
    f, ok = app.features_at(p)
    corners = np.array([[1.0, -0.5, 0.0], [1.0 + STEP, -0.5, 0.0], [1.0, -0.5 + STEP, 0.0]])
    assert ok[0]
    np.testing.assert_allclose(f[0], linear_field(corners).mean(axis=0), atol=1e-12)
    # at the hole itself every corner but the missing one has weight 0: no features
    f, ok = app.features_at(np.array([[1.0 + STEP, -0.5 + STEP, 0.0]]))
    assert not ok[0]
    model = InterpolatedSensorModel(poses, linear_field(poses), SensorModelConfig(outlier_weight=0.01))
    obs = model.observe(linear_field(poses[:1])[0])
    lp = obs.log_pdf(np.array([[1.0 + STEP, -0.5 + STEP, 0.0]]))
    assert lp[0] == pytest.approx(model.log_floor)  # the outlier floor alone


def test_not_a_lattice_is_refused() -> None:
    poses = lattice_poses(nx=3, ny=3, nh=8)
    bad = poses.copy()
    bad[0, 0] += 0.2
    with pytest.raises(LinoLocError, match="lattice|evenly"):
        InterpolatedAppearance(bad, linear_field(bad))
    with pytest.raises(LinoLocError, match="share"):
        InterpolatedAppearance(np.vstack([poses, poses[:1]]), linear_field(np.vstack([poses, poses[:1]])))


def test_scale_from_leave_one_out_residuals() -> None:
    poses = lattice_poses()
    feats = smooth_field(poses)
    m1 = InterpolatedSensorModel(poses, feats, SensorModelConfig())
    m2 = InterpolatedSensorModel(poses, feats, SensorModelConfig(), InterpolationConfig(residual_scale=0.5))
    np.testing.assert_allclose(m2.scale, 0.5 * m1.scale)
    r = m1.appearance.leave_one_out_residuals()
    # interior entries along x (3 of 5) and along y (2 of 4), every heading
    assert r.shape == ((3 * 4 + 5 * 2) * NH, feats.shape[1])


def test_likelihood_peaks_at_the_true_off_grid_pose() -> None:
    poses = lattice_poses()
    model = InterpolatedSensorModel(poses, smooth_field(poses), SensorModelConfig(outlier_weight=0.01),
                                    InterpolationConfig(residual_scale=0.2))
    truth = np.array([1.0 + 1.6 * STEP, -0.5 + 1.4 * STEP, 0.4])  # between grid positions and headings
    obs = model.observe(model.appearance.features_at(truth[None, :])[0][0])
    gx, gy, gh = np.meshgrid(np.arange(0.8, 4.2, 0.05), np.arange(-0.7, 2.0, 0.05),
                             np.radians(np.arange(-180, 180, 2.0)), indexing="ij")
    dense = np.column_stack([gx.ravel(), gy.ravel(), gh.ravel()])
    best = dense[np.argmax(obs.log_pdf(dense))]
    assert math.hypot(best[0] - truth[0], best[1] - truth[1]) < 0.06
    assert abs(math.remainder(best[2] - truth[2], 2 * math.pi)) < math.radians(3)
    # log_pdf_trig agrees, and the proposal is a normalized density the sampler draws from
    c, s = np.cos(dense[:, 2]), np.sin(dense[:, 2])
    np.testing.assert_allclose(obs.log_pdf_trig(dense[:, 0], dense[:, 1], c, s), obs.log_pdf(dense))
    assert np.all(np.isfinite(obs.proposal_log_pdf(obs.sample(50, np.random.default_rng(1)))))


def test_filter_localizes_with_it() -> None:
    poses = lattice_poses(nx=6, ny=5)
    model = InterpolatedSensorModel(poses, smooth_field(poses), SensorModelConfig(outlier_weight=0.01))
    truth = np.array([1.0 + 2.45 * STEP, -0.5 + 1.6 * STEP, -1.0])  # robot pose, off the grid
    pf = AuxiliaryParticleFilter(OdometryMotionModel(), model.bounds, FilterConfig(n_particles=600),
                                 rng=np.random.default_rng(3))
    rng = np.random.default_rng(4)
    for pan in (0.0, 1.2, -1.2, 2.4, 0.6, -0.6):
        cam = truth + np.array([0.0, 0.0, pan])
        y = smooth_field(cam[None, :])[0] + 0.005 * rng.standard_normal(6)
        pf.update(np.zeros(3), pan, model.observe(y))
    est = pf.estimate().pose
    assert math.hypot(est[0] - truth[0], est[1] - truth[1]) < 0.3
    assert abs(math.remainder(est[2] - truth[2], 2 * math.pi)) < 0.2


def test_action_values() -> None:
    poses = lattice_poses()
    model = InterpolatedSensorModel(poses, smooth_field(poses), SensorModelConfig(outlier_weight=0.01),
                                    InterpolationConfig(residual_scale=0.3))
    ev = action_evaluator(model, ActiveVisionConfig(n_actions=7, max_particles=60))
    assert isinstance(ev, InterpolatedActionEvaluator)
    rng = np.random.default_rng(5)
    p = np.column_stack([rng.uniform(1.0, 4.0, 80), rng.uniform(-0.5, 1.75, 80), rng.uniform(-3, 3, 80)])
    v = ev.evaluate(p, np.zeros(80), rng=np.random.default_rng(6))
    assert v.expected_entropy.shape == (7,)
    assert np.all(np.isfinite(v.expected_entropy))
    assert np.all(v.expected_entropy <= v.current_entropy + 1e-9)
    assert np.all(v.expected_entropy >= 0.0)
    # the normalizer of a predicted view at a lattice pose is the exact one
    idx = np.array([3, 100, 250])
    np.testing.assert_allclose(model.node_log_normalizer[idx], model.log_normalizer(model._white[idx]))


def test_fused_channels() -> None:
    poses = lattice_poses()
    cfg = SensorModelConfig(outlier_weight=0.01)
    mi = InterpolatedSensorModel(poses, smooth_field(poses), cfg)
    md = InterpolatedSensorModel(poses, linear_field(poses), cfg, bounds=mi.bounds)
    cam = np.array([[2.0, 0.4, 0.3], [3.0, 1.2, -2.0]])
    oi = mi.observe(smooth_field(cam[:1])[0])
    od = md.observe(linear_field(cam[:1])[0])
    dis = fuse_likelihoods({"intensity": oi, "disparity": od}, FusionConfig(w_i=0.5, w_d=0.5))
    np.testing.assert_allclose(dis.log_pdf(cam), np.logaddexp(oi.log_pdf(cam), od.log_pdf(cam)) + math.log(0.5))
    con = fuse_likelihoods({"intensity": oi, "disparity": od}, FusionConfig(mode="conjunctive"))
    np.testing.assert_allclose(con.log_pdf(cam), oi.log_pdf(cam) + od.log_pdf(cam))
    assert dis.novelty == oi.novelty


def test_action_values_equal_the_model_s_own_likelihoods() -> None:
    """H(u) from the evaluator's float32 linear-space sums equals the entropy of the belief
    reweighted by the model's own log_density of each predicted observation."""
    from lino_loc.active_vision import discrete_entropy

    poses = lattice_poses()
    model = InterpolatedSensorModel(poses, smooth_field(poses), SensorModelConfig(outlier_weight=0.05),
                                    InterpolationConfig(residual_scale=0.5))
    ev = InterpolatedActionEvaluator(model, ActiveVisionConfig(n_actions=3, max_particles=40))
    rng = np.random.default_rng(7)
    p = np.column_stack([rng.uniform(0.6, 4.4, 30), rng.uniform(-0.9, 2.2, 30), rng.uniform(-3, 3, 30)])
    lw = rng.normal(size=30)
    lw -= np.log(np.exp(lw).sum())
    u = np.array([-1.0, 0.2, 2.0])
    got = ev.evaluate(p, lw, u).expected_entropy
    want = []
    for a in u:
        th = p[:, 2] + a
        f, ok = model.appearance.features_trig(p[:, 0], p[:, 1], th)
        idx, w = model.appearance.lattice.corners(p[:, 0], p[:, 1], th)
        log_z = np.einsum("mc,mc->m", w, model.node_log_normalizer[np.maximum(idx, 0)])
        h = [float(discrete_entropy(lw + model.log_density(f[i] / model.scale, log_z[i], p[:, 0], p[:, 1], th)))
             for i in range(30)]
        want.append(float(np.dot(np.exp(lw), h)))
    np.testing.assert_allclose(got, want, atol=2e-4)

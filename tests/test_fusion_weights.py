"""Adaptive fusion weights (lino_loc/fusion_weights.py): the scores' closed form, the floor,
forgetting, a uniform belief, and the Localizer using them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.fusion_weights import AdaptiveFusionWeights, AdaptiveWeightsConfig
from lino_loc.sensor_model import Bounds, PoseMixture


def _mixture(x: float, y: float, theta: float = 0.0, bounds: Bounds | None = None) -> PoseMixture:
    return PoseMixture(np.array([[x, y, theta]]), np.array([0.0]), np.array([0.3]), np.array([0.3]),
                       -math.inf, bounds, 0.0)


def _belief(x: float, y: float, n: int = 400, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    p = np.column_stack([rng.normal(x, 0.1, n), rng.normal(y, 0.1, n), rng.normal(0.0, 0.05, n)])
    return p, np.full(n, -math.log(n))


def test_one_update_gives_the_softmax_of_the_log_predictive_likelihoods_with_the_floor() -> None:
    cfg = AdaptiveWeightsConfig(forgetting=0.5, min_weight=0.1)
    aw = AdaptiveFusionWeights(cfg)
    p, lw = _belief(1.0, 1.0)
    mix = {"intensity": _mixture(1.0, 1.0), "disparity": _mixture(1.5, 1.0)}
    w = aw.update(mix, p, lw, (0.0, 0.0, 0.0), 0.0)
    # closed form: l_c = log mean_k p_c(x_k)
    l_i = math.log(np.mean(np.exp(mix["intensity"].log_pdf(p))))
    l_d = math.log(np.mean(np.exp(mix["disparity"].log_pdf(p))))
    assert aw.last_log_likelihood["intensity"] == pytest.approx(l_i, rel=1e-9)
    r_i = 1.0 / (1.0 + math.exp(l_d - l_i))
    assert w["intensity"] == pytest.approx(0.1 + 0.8 * r_i, rel=1e-9)
    assert w["intensity"] + w["disparity"] == pytest.approx(1.0) and w["intensity"] > w["disparity"]


def test_a_channel_that_stops_fitting_falls_to_the_floor_and_earns_its_weight_back() -> None:
    aw = AdaptiveFusionWeights(AdaptiveWeightsConfig(forgetting=0.9, min_weight=0.1))
    p, lw = _belief(2.0, 1.0)
    good, bad = _mixture(2.0, 1.0), _mixture(5.0, 1.0)
    for _ in range(10):
        w = aw.update({"intensity": good, "disparity": bad}, p, lw, (0.0, 0.0, 0.0), 0.0)
    assert w["disparity"] == pytest.approx(0.1, abs=1e-6) and w["intensity"] == pytest.approx(0.9, abs=1e-6)
    k = 0
    while w["disparity"] < 0.45:  # now intensity is the one that is off
        w = aw.update({"intensity": bad, "disparity": good}, p, lw, (0.0, 0.0, 0.0), 0.0)
        k += 1
        assert k < 30
    assert k >= 1
    aw.reset()
    assert aw.weights(["intensity", "disparity"]) == {"intensity": 0.5, "disparity": 0.5}


def test_the_belief_is_moved_by_the_odometry_and_turned_by_the_pan() -> None:
    aw = AdaptiveFusionWeights(AdaptiveWeightsConfig(forgetting=0.0))
    p, lw = _belief(1.0, 1.0)
    # after moving 1 m ahead (heading 0) with the head turned 90 deg, the camera is at (2, 1, pi/2)
    ahead = {"intensity": _mixture(2.0, 1.0, math.pi / 2), "disparity": _mixture(1.0, 1.0, 0.0)}
    w = aw.update(ahead, p, lw, (1.0, 0.0, 0.0), math.pi / 2)
    assert w["intensity"] > 0.85


def test_a_uniform_belief_keeps_the_weights_near_one_half() -> None:
    b = Bounds.from_poses(np.array([[0.0, 0.0, 0.0], [8.0, 3.0, 0.0]]), 0.0)
    rng = np.random.default_rng(1)
    n = 20000
    p = np.column_stack([rng.uniform(0, 8, n), rng.uniform(0, 3, n), rng.uniform(-math.pi, math.pi, n)])
    aw = AdaptiveFusionWeights(AdaptiveWeightsConfig(forgetting=0.0))
    w = aw.update({"intensity": _mixture(2.0, 1.5, bounds=b), "disparity": _mixture(6.0, 1.5, bounds=b)},
                  p, np.full(n, -math.log(n)), (0.0, 0.0, 0.0), 0.0)
    assert abs(w["intensity"] - 0.5) < 0.05


def test_the_localizer_uses_adaptive_weights_only_when_asked() -> None:
    from lino_loc.localizer import Localizer, LocalizerConfig

    class Ch:
        def __init__(self, feats: np.ndarray) -> None:
            self.features = feats

        def project(self, obs: np.ndarray) -> np.ndarray:
            return np.asarray(obs, dtype=np.float64).ravel()[:2]

    class Map:
        poses = np.array([[x, y, 0.0] for x in range(4) for y in range(2)], dtype=np.float64)
        channels = {"intensity": Ch(poses[:, :2].copy()), "disparity": Ch(poses[:, :2].copy())}

    fixed = Localizer(Map(), LocalizerConfig(), rng=np.random.default_rng(0))
    assert fixed.fusion_weights is None
    cfg = LocalizerConfig.model_validate({"fusion": {"weights": "adaptive"}})
    loc = Localizer(Map(), cfg, rng=np.random.default_rng(0))
    loc.set_pose([1.0, 1.0, 0.0], np.diag([0.01, 0.01, 0.01]))
    for _ in range(5):  # intensity says (1, 1), where the belief is; disparity says (3, 0)
        loc.update((0.0, 0.0, 0.0), 0.0, np.array([1.0, 1.0]), np.array([3.0, 0.0]))
    w = loc.fusion_weights
    assert w is not None and w["intensity"] > 0.8
    loc.start_global()
    assert loc.fusion_weights == {"intensity": 0.5, "disparity": 0.5}

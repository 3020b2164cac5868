"""Tests of lino_loc.active_vision: H(u), entropies, the policy's limits and stop rules."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.active_vision import (
    ActionEvaluator,
    ActivePolicy,
    ActiveVisionConfig,
    belief_entropy,
    discrete_entropy,
    subsample,
)
from lino_loc.poses import camera_pose, wrap_angle
from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig

HEADINGS = wrap_angle(np.radians(np.arange(24) * 15.0))


def grid_map(seed: int = 0, headings: np.ndarray = HEADINGS) -> tuple[np.ndarray, np.ndarray]:
    """An office-like product grid (6 x 3 positions x 24 headings) with smooth features."""
    rng = np.random.default_rng(seed)
    gx, gy, gh = np.meshgrid(np.arange(6) * 0.75, np.arange(3) * 0.75, headings, indexing="ij")
    poses = np.column_stack([gx.ravel(), gy.ravel(), gh.ravel()])
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    feats = np.column_stack([3 * c + 0.4 * poses[:, 0], 3 * s + 0.4 * poses[:, 1], np.sin(2 * poses[:, 0]) * c,
                             0.2 * rng.standard_normal(len(poses))])
    return poses, feats


def uniform_particles(rng: np.random.Generator, m: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-0.2, 4.0, m), rng.uniform(-0.2, 1.7, m), rng.uniform(-np.pi, np.pi, m)])


@pytest.fixture(scope="module")
def model() -> NearestNeighbourSensorModel:
    poses, feats = grid_map()
    return NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=10, outlier_weight=0.01))


@pytest.fixture(scope="module")
def dense_heading_model() -> NearestNeighbourSensorModel:
    """Headings every 3 deg, as a map with virtual headings: the gathered-kernel path."""
    poses, feats = grid_map(headings=wrap_angle(np.radians(np.arange(120) * 3.0)))
    return NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=10, outlier_weight=0.01))


@pytest.mark.parametrize(("use_grid", "dense"), [(True, False), (False, False), (True, True)])
def test_likelihoods_match_the_filter_sensor_model(model: NearestNeighbourSensorModel,
                                                   dense_heading_model: NearestNeighbourSensorModel,
                                                   use_grid: bool, dense: bool) -> None:
    model = dense_heading_model if dense else model
    ev = ActionEvaluator(model, ActiveVisionConfig(n_actions=5), use_grid=use_grid)
    assert ev.grid is use_grid
    rng = np.random.default_rng(1)
    p = uniform_particles(rng, 40)
    loglik, pred = ev.likelihoods(p, ev.actions)
    assert loglik.shape == (5, 40, 40) and pred.shape == (5, 40)
    for a, u in enumerate(ev.actions):
        cam = camera_pose(p, u)
        ref = model.log_likelihood_matrix(model.features[pred[a]], cam)
        np.testing.assert_allclose(loglik[a], ref, atol=2e-4)
        # the predicted observation is the map entry nearest in the kernel metric
        d2 = ((cam[:, None, :2] - model.poses[None, :, :2]) ** 2).sum(-1) / model.config.sigma_xy**2 + (
            2.0 - 2.0 * np.cos(cam[:, None, 2] - model.poses[None, :, 2])
        ) / model.config.sigma_theta**2
        np.testing.assert_array_equal(pred[a], np.argmin(d2, axis=1))


def test_expected_entropy_equals_the_log_space_definition(model: NearestNeighbourSensorModel) -> None:
    ev = ActionEvaluator(model, ActiveVisionConfig(n_actions=7))
    rng = np.random.default_rng(2)
    p = uniform_particles(rng, 60)
    lw = rng.normal(size=60)
    lw -= np.log(np.exp(lw).sum())
    values = ev.evaluate(p, lw)
    loglik, _ = ev.likelihoods(p, ev.actions)
    h = discrete_entropy(loglik + lw[None, None, :], axis=-1)  # (A, i)
    np.testing.assert_allclose(values.expected_entropy, h @ np.exp(lw), rtol=1e-5, atol=1e-6)
    assert values.current_entropy == pytest.approx(float(discrete_entropy(lw)))
    assert np.all(values.expected_entropy <= values.current_entropy + 1e-9)


def two_place_map() -> tuple[np.ndarray, np.ndarray]:
    """Two positions that look identical except when looking left (headings 45..135 deg)."""
    rows, feats = [], []
    for k, x in enumerate((0.0, 4.0)):
        for h in HEADINGS:
            rows.append((x, 0.0, h))
            f = [3 * math.cos(h), 3 * math.sin(h), 0.0]
            if abs(wrap_angle(h - math.pi / 2)) <= math.radians(46):
                f[2] = 10.0 * k  # only place B shows this poster on its left
            feats.append(f)
    return np.asarray(rows), np.asarray(feats)


def test_action_that_separates_two_symmetric_hypotheses_wins() -> None:
    poses, feats = two_place_map()
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=6, outlier_weight=0.01))
    ev = ActionEvaluator(model, ActiveVisionConfig(n_actions=3, pan_min=-math.pi / 2, pan_max=math.pi / 2))
    p = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]])  # two hypotheses, robot heading 0
    lw = np.log([0.5, 0.5])
    values = ev.evaluate(p, lw)
    u = values.actions
    np.testing.assert_allclose(u, [-math.pi / 2, 0.0, math.pi / 2])
    # looking ahead or right: both places look the same, the belief stays split
    assert values.expected_entropy[1] == pytest.approx(math.log(2), abs=1e-3)
    assert values.expected_entropy[0] == pytest.approx(math.log(2), abs=1e-3)
    # looking left tells them apart
    assert values.expected_entropy[2] < 0.05
    assert values.best() == 2
    assert values.gain[2] > 0.6


def test_entropies_of_converged_and_uniform_beliefs() -> None:
    n = 200
    assert float(discrete_entropy(np.zeros(n))) == pytest.approx(math.log(n))
    one = np.full(n, -np.inf)
    one[3] = 0.0
    assert float(discrete_entropy(one)) == pytest.approx(0.0, abs=1e-12)
    rng = np.random.default_rng(3)
    # converged: all particles within a few centimetres and degrees
    conv = np.column_stack([1.1 + 0.02 * rng.standard_normal(n), 0.6 + 0.02 * rng.standard_normal(n),
                            0.3 + 0.01 * rng.standard_normal(n)])
    assert belief_entropy(conv, np.zeros(n)) < 0.05
    # uniform: one particle per cell, equal weights -> log N
    cells = np.array([(0.25 + 0.5 * i, 0.25 + 0.5 * j, -math.pi + math.radians(30) * (k + 0.5))
                      for i in range(5) for j in range(4) for k in range(10)])
    assert belief_entropy(cells, np.zeros(len(cells))) == pytest.approx(math.log(len(cells)))
    # the discrete entropy of equal weights cannot tell them apart; the cell entropy can
    assert float(discrete_entropy(np.zeros(n))) == pytest.approx(math.log(n))


def test_subsample_merges_duplicates_and_keeps_the_weights() -> None:
    rng = np.random.default_rng(4)
    base = uniform_particles(rng, 10)
    p = base[rng.integers(0, 10, 1000)]
    lw = np.zeros(1000)
    q, lq = subsample(p, lw, 150)
    assert q.shape[0] <= 10
    counts = np.array([np.sum(np.all(p == row, axis=1)) for row in q])
    np.testing.assert_allclose(np.exp(lq), counts / 1000.0)
    many = uniform_particles(rng, 1000)
    q, lq = subsample(many, rng.normal(size=1000), 150)
    assert q.shape[0] <= 150
    assert np.exp(lq).sum() == pytest.approx(1.0)


def test_policy_never_commands_beyond_the_head_limits(model: NearestNeighbourSensorModel) -> None:
    rng = np.random.default_rng(5)
    ev = ActionEvaluator(model, ActiveVisionConfig(max_particles=30))
    commands = 0
    for _ in range(150):
        lo, hi = np.sort(rng.uniform(-math.pi, math.pi, 2))
        if hi - lo < 0.05:
            continue
        cfg = ActiveVisionConfig(n_actions=int(rng.integers(2, 12)), pan_min=float(lo), pan_max=float(hi),
                                 min_entropy_gain=0.0, settle_s=0.0, min_interval_s=0.0, max_particles=30)
        # the head's own limits overlap the configured range somewhere
        hlo = float(rng.uniform(lo - 1.0, hi - 0.01))
        hhi = float(rng.uniform(max(hlo, lo) + 0.005, hi + 1.0))
        policy = ActivePolicy(ev, cfg, head_limits=(hlo, hhi))
        allowed = (max(lo, hlo), min(hi, hhi))
        p = uniform_particles(rng, int(rng.integers(1, 40)))
        pan = float(rng.choice([rng.uniform(-4, 4), np.nan, allowed[0], allowed[1]]))
        d = policy.decide(p, rng.normal(size=p.shape[0]), state="global", log_likelihood=-5.0, pan=pan,
                          moving=False, now=float(rng.uniform(0, 100)))
        if d.command is not None:
            commands += 1
            assert allowed[0] - 1e-12 <= d.command <= allowed[1] + 1e-12
        assert allowed[0] <= policy.clamp(float(rng.uniform(-10, 10))) <= allowed[1]
    assert commands > 50  # the property was exercised


def test_policy_rejects_a_range_outside_the_head_limits(model: NearestNeighbourSensorModel) -> None:
    cfg = ActiveVisionConfig(pan_min=0.5, pan_max=1.0)
    with pytest.raises(ValueError):
        ActivePolicy(ActionEvaluator(model, cfg), head_limits=(-1.0, 0.2))


def make_policy(model: NearestNeighbourSensorModel, **kw: float | None) -> ActivePolicy:
    cfg = ActiveVisionConfig(n_actions=8, settle_s=0.5, min_interval_s=2.0, **kw)
    return ActivePolicy(ActionEvaluator(model, cfg), head_limits=(-2.6, 2.6))


def test_policy_looks_while_global_and_waits_for_the_head(model: NearestNeighbourSensorModel) -> None:
    rng = np.random.default_rng(6)
    p = uniform_particles(rng, 100)
    lw = np.zeros(100)
    pol = make_policy(model)
    kw = dict(state="global", log_likelihood=-3.0)
    assert pol.decide(p, lw, pan=0.0, moving=True, now=0.0, **kw).reason == "head moving"
    # it stops: wait settle_s, then for a frame taken after that
    assert pol.decide(p, lw, pan=0.0, moving=False, now=0.1, **kw).reason == "settling"
    assert pol.decide(p, lw, pan=0.0, moving=False, now=0.7, frame_stamp=0.3, **kw).reason == "no new frame"
    d = pol.decide(p, lw, pan=0.0, moving=False, now=0.7, frame_stamp=0.65, **kw)
    assert d.reason == "move" and d.command is not None and d.values is not None
    assert d.command == pytest.approx(d.values.actions[d.values.best(0.0, pol.config.move_cost)])
    assert pol.decide(p, lw, pan=0.0, moving=False, now=1.0, **kw).reason == "interval"
    assert pol.decide(p, lw, pan=d.command, moving=True, now=1.2, **kw).reason == "head moving"
    assert pol.decide(p, lw, pan=d.command, moving=False, now=1.5, **kw).reason == "settling"
    assert pol.decide(p, lw, pan=d.command, moving=False, now=2.6, **kw).reason == "interval"
    # same belief, the head already at the best pan: nothing to do
    assert pol.decide(p, lw, pan=d.command, moving=False, now=3.0, **kw).reason == "stay"
    assert make_policy(model, enabled=False).decide(p, lw, pan=0.0, moving=False, now=9.0, **kw).reason == "disabled"


def test_policy_stop_rules(model: NearestNeighbourSensorModel) -> None:
    rng = np.random.default_rng(7)
    conv = np.column_stack([1.6 + 0.02 * rng.standard_normal(50), 0.85 + 0.02 * rng.standard_normal(50),
                            0.1 + 0.01 * rng.standard_normal(50)])
    lw = np.zeros(50)
    # converged and the image fits: stop without evaluating
    d = make_policy(model).decide(conv, lw, state="tracking", log_likelihood=-1.0, pan=0.0, moving=False, now=5.0)
    assert d.reason == "converged" and d.command is None and d.values is None
    assert d.belief_entropy < 0.1
    # converged with the head turned aside: back to looking ahead (home_pan), once
    d = make_policy(model).decide(conv, lw, state="tracking", log_likelihood=-1.0, pan=1.2, moving=False, now=5.0)
    assert d.reason == "home" and d.command == pytest.approx(0.0)
    d = make_policy(model, home_pan=None).decide(conv, lw, state="tracking", log_likelihood=-1.0, pan=1.2,
                                                 moving=False, now=5.0)
    assert d.reason == "converged" and d.command is None
    # a home outside the head's limits is clamped to them
    d = make_policy(model, home_pan=3.0).decide(conv, lw, state="tracking", log_likelihood=-1.0, pan=0.0,
                                                moving=False, now=5.0)
    assert d.reason == "home" and d.command is not None and d.command <= 2.6 + 1e-12
    # tracking, but the views have stopped fitting the belief (lost detector's evidence at 60 %
    # of its threshold): look before it is declared lost; at 20 % not yet
    d = make_policy(model).decide(conv, lw, state="tracking", log_likelihood=-1.0, pan=0.0, moving=False,
                                  now=5.0, doubt=0.6)
    assert d.values is not None and d.reason in ("move", "no gain", "stay")
    d = make_policy(model).decide(conv, lw, state="tracking", log_likelihood=-1.0, pan=0.0, moving=False,
                                  now=5.0, doubt=0.2)
    assert d.reason == "converged"
    d = make_policy(model, trigger_doubt=None).decide(conv, lw, state="tracking", log_likelihood=-1.0, pan=0.0,
                                                      moving=False, now=5.0, doubt=0.9)
    assert d.reason == "converged"
    # tracking but the image fits the map badly: look again
    pol = make_policy(model, min_log_likelihood=-8.0)
    d = pol.decide(conv, lw, state="tracking", log_likelihood=-20.0, pan=0.0, moving=False, now=5.0)
    assert d.reason in ("move", "no gain", "stay") and d.values is not None
    # entropy trigger: a spread belief is not converged even if the filter says tracking
    spread = uniform_particles(rng, 100)
    pol = make_policy(model, trigger_entropy=1.0)
    d = pol.decide(spread, np.zeros(100), state="tracking", log_likelihood=-1.0, pan=0.0, moving=False, now=5.0)
    assert d.values is not None
    # one particle holds all the belief: no action can lower the entropy -> no gain
    one = np.full(50, -np.inf)
    one[0] = 0.0
    d = make_policy(model).decide(conv, one, state="global", log_likelihood=-1.0, pan=0.0, moving=False, now=5.0)
    assert d.reason == "no gain" and d.command is None
    assert d.values is not None and np.all(d.values.gain < 0.05)


def test_policy_stays_when_the_best_action_is_the_present_pan() -> None:
    poses, feats = two_place_map()
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=6, outlier_weight=0.01))
    cfg = ActiveVisionConfig(n_actions=3, pan_min=-math.pi / 2, pan_max=math.pi / 2, settle_s=0.0, min_interval_s=0.0)
    pol = ActivePolicy(ActionEvaluator(model, cfg))
    p = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    d = pol.decide(p, np.log([0.5, 0.5]), state="global", log_likelihood=-1.0, pan=math.pi / 2 - 0.01,
                   moving=False, now=1.0)
    assert d.reason == "stay" and d.command is None
    d = pol.decide(p, np.log([0.5, 0.5]), state="global", log_likelihood=-1.0, pan=0.0, moving=False, now=2.0)
    assert d.reason == "move" and d.command == pytest.approx(math.pi / 2)


def test_bench_reports_the_cost_table() -> None:
    from services.evaluation.action_cost import run_active_bench

    res = run_active_bench(repeats=1, particles=(50,), actions=(11,))
    assert set(res["particles"]) == {"50"} and set(res["actions"]) == {"11"}
    assert res["particles"]["50"]["median_ms"] > 0 and res["generic_path_150x22"]["cpu_median_ms"] >= 0
    assert res["map_entries"] == 1056
    assert res["interpolated_150x22"]["map_entries"] == 5280 and res["interpolated_150x22"]["median_ms"] > 0
    assert res["translated_150x22"]["map_entries"] == 31 * 10 * 120 and res["translated_150x22"]["median_ms"] > 0

"""Per-pan reliability (lino_loc/pan_reliability.py): the spoil probability's ramp, the
reliability's closed form, the discount H' = r H + (1 - r) H_0, the robot frame under odometry,
and the policy and the experiment that use it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from lino_loc.active_vision import ActionValues, ActivePolicy, ActiveVisionConfig
from lino_loc.pan_reliability import PanReliability, PanReliabilityConfig

CFG = PanReliabilityConfig(enabled=True, novelty_clean=0.8, novelty_spoiled=1.6, reach=math.radians(40.0))


def test_spoil_probability_ramps_in_log_novelty() -> None:
    rel = PanReliability(CFG)
    assert rel.spoil_probability(0.5) == 0.0 and rel.spoil_probability(0.8) == 0.0
    assert rel.spoil_probability(1.6) == 1.0 and rel.spoil_probability(5.0) == 1.0
    assert rel.spoil_probability(math.sqrt(0.8 * 1.6)) == pytest.approx(0.5)  # geometric midpoint
    assert rel.spoil_probability(math.nan) == 0.0 and rel.spoil_probability(0.0) == 0.0


def test_reliability_closed_form() -> None:
    rel = PanReliability(CFG)
    u = np.radians([0.0, 20.0, -20.0, 40.0, 90.0])
    assert np.array_equal(rel.reliability(u), np.ones(5))  # nothing seen: every pan as the map says
    rel.observe(0.0, 3.0)  # a spoiled view straight ahead
    np.testing.assert_allclose(rel.reliability(u), [0.0, 0.5, 0.5, 1.0, 1.0], atol=1e-12)
    rel.observe(math.radians(40.0), math.sqrt(0.8 * 1.6))  # half spoiled, 40 deg left
    np.testing.assert_allclose(rel.reliability(u), [0.0, 0.5 * 0.75, 0.5, 0.5, 1.0], atol=1e-12)
    rel.observe(math.radians(-90.0), 0.6)  # a familiar view changes nothing
    np.testing.assert_allclose(rel.reliability(u[:1]), [0.0])
    rel.observe(math.nan, 3.0)
    rel.observe(1.0, math.nan)
    assert rel.views == 3


def test_discount_mixes_the_prediction_with_no_information() -> None:
    rel = PanReliability(CFG)
    u = np.radians([0.0, 20.0, 90.0])
    v = ActionValues(actions=u, expected_entropy=np.array([1.0, 2.0, 2.5]), current_entropy=4.0, n_particles=10)
    assert rel.discount(v).expected_entropy.tolist() == [1.0, 2.0, 2.5]
    rel.observe(0.0, 3.0)
    d = rel.discount(v)
    np.testing.assert_allclose(d.expected_entropy, [4.0, 0.5 * 2.0 + 0.5 * 4.0, 2.5])
    assert d.best() == 2 and v.best() == 0  # the spoiled direction is no longer chosen
    assert d.current_entropy == v.current_entropy


def test_pans_follow_the_robot_frame_and_travel_forgets() -> None:
    rel = PanReliability(CFG)
    rel.observe(0.0, 3.0)
    rel.move([0.0, 0.0, 0.3])  # the base turned left: what was ahead is now at pan -0.3
    assert rel.reliability([-0.3])[0] == pytest.approx(0.0)
    assert rel.reliability([0.0])[0] == pytest.approx(0.3 / math.radians(40.0))
    rel.move([0.2, 0.0, 0.0])
    assert rel.views == 1  # 0.2 m < forget_xy
    rel.move([0.2, 0.0, 0.0])
    assert rel.views == 0 and rel.reliability([-0.3])[0] == 1.0
    rel.move([math.nan, 0.0, 0.0])  # a bad increment is ignored
    rel.move([0.3, 0.0, 0.0])  # travel before the next view does not count against it
    rel.observe(0.0, 3.0)
    rel.move([0.2, 0.0, 0.0])
    assert rel.views == 1


def test_disabled_remembers_nothing_and_discounts_nothing() -> None:
    rel = PanReliability(CFG.model_copy(update={"enabled": False}))
    rel.observe(0.0, 3.0)
    v = ActionValues(actions=np.zeros(1), expected_entropy=np.array([1.0]), current_entropy=4.0, n_particles=1)
    assert rel.views == 0 and rel.discount(v) is v


def test_memory_keeps_the_latest_views() -> None:
    rel = PanReliability(CFG.model_copy(update={"memory": 2}))
    for pan in (0.0, 1.0, 2.0):
        rel.observe(pan, 3.0)
    assert rel.views == 2 and rel.reliability([0.0])[0] == 1.0 and rel.reliability([2.0])[0] == 0.0


def test_off_by_default_in_the_library_and_the_service() -> None:
    from services.config import ServiceConfig

    assert not PanReliabilityConfig().enabled and not ActiveVisionConfig().reliability.enabled
    assert not ServiceConfig().active_vision.method_config().reliability.enabled


def test_config_rejects_an_inverted_ramp() -> None:
    with pytest.raises(ValidationError, match="novelty_clean"):
        PanReliabilityConfig(novelty_clean=2.0, novelty_spoiled=1.0)


class _FixedEvaluator:
    """H(u) fixed: lowest straight ahead."""

    def __init__(self, config: ActiveVisionConfig) -> None:
        self.config = config

    def evaluate(self, p, lw, actions, rng=None):  # noqa: ANN001, ANN201
        u = np.asarray(actions, dtype=np.float64)
        return ActionValues(actions=u, expected_entropy=2.0 + 0.1 * np.abs(u), current_entropy=4.0,
                            n_particles=len(p))


@pytest.mark.parametrize("enabled", [False, True])
def test_policy_turns_away_from_a_spoiled_direction_only_when_enabled(enabled: bool) -> None:
    cfg = ActiveVisionConfig(n_actions=9, pan_min=-2.0, pan_max=2.0, settle_s=0.0, min_interval_s=0.0,
                             move_cost=0.0, reliability={**CFG.model_dump(), "enabled": enabled})
    pol = ActivePolicy(_FixedEvaluator(cfg), cfg)  # type: ignore[arg-type]
    pol.observe(0.0, 3.0)  # straight ahead fits no map entry
    p = np.zeros((5, 3))
    d = pol.decide(p, np.log(np.full(5, 0.2)), state="global", log_likelihood=-1.0, pan=1.5, moving=False, now=10.0)
    assert d.command is not None
    if enabled:
        assert abs(d.command) >= math.radians(40.0) - 1e-9 and pol.reliability.views == 1
    else:
        assert d.command == 0.0 and pol.reliability.views == 0


def test_the_experiment_reports_and_uses_it(capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from services.cli import main

    tiny = ["--step", "2.0", "--heading-step", "45", "--positions", "2", "--runs", "1", "--movements", "2",
            "--actions", "4", "--particles", "60", "--workers", "1"]
    assert main(["eval", "active", "--json", *tiny]) == 0  # on by default
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["setup"]["pan_reliability"]["enabled"] is True
    assert main(["eval", "active", "--json", *tiny, "--pan-reliability", "off"]) == 0
    assert "pan_reliability" not in json.loads(capsys.readouterr().out.strip().splitlines()[-1])["setup"]


def test_chosen_view_change_is_relative_to_the_positions_mean() -> None:
    """services.evaluation.active.chosen_view_change: the spoil of the chosen views (after the
    first) over the mean spoil of the position's candidate pans."""
    from services.evaluation.active import chosen_view_change

    mapped = np.zeros((2, 4, 2))
    changed = np.zeros((2, 4, 2))
    changed[0, :, 0] = [4.0, 0.0, 0.0, 0.0]  # position 0: mean spoil 1, pan 0 spoiled (4)
    changed[1, :, 0] = [1.0, 1.0, 1.0, 1.0]  # position 1: every view alike (ratio 1)
    parts = [{"pos": 0, "strategies": {"a": {"pans": [[1, 0, 2]]}}},
             {"pos": 1, "strategies": {"a": {"pans": [[3, 2]]}}}]
    assert chosen_view_change(parts, ("a",), mapped, changed)["a"] == pytest.approx((4.0 + 0.0 + 1.0) / 3)

"""The spread rule of a standing robot's next view (lino_loc/view_spread.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.active_vision import ActiveVisionConfig
from lino_loc.pan_reliability import PanReliability, PanReliabilityConfig
from lino_loc.view_spread import separation, spread_values


def test_separation_is_the_wrapped_angle_to_the_nearest_view() -> None:
    u = np.array([0.0, 0.5, 3.0, -3.0, -2.6])
    got = separation([0.2, 2.9], u)
    want = [0.2, 0.3, 0.1, 2 * math.pi - 5.9, 2 * math.pi - 5.5]  # -3.0 is 0.38 rad from 2.9 across +-pi
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert np.all(separation([], u) == math.pi)  # nothing taken: every pan is as far as can be


def test_spread_values_choose_the_pan_farthest_from_every_view() -> None:
    """Greedy max-min: after a view ahead, the pan at the range's end (2.6 rad, the nearest
    to behind); then the one between those and the other end's wrap."""
    pans = ActiveVisionConfig().actions()  # 22 over [-2.6, 2.6]
    taken = [0.0]
    v = spread_values(taken, pans)
    assert v.current_entropy == 0.0
    np.testing.assert_allclose(v.gain, separation(taken, pans))  # the gain is the separation, rad
    first = float(pans[v.best()])
    assert abs(first) == pytest.approx(2.6)
    taken.append(first)
    second = float(pans[spread_values(taken, pans).best()])
    s = separation(taken, pans)
    assert separation(taken, [second])[0] == pytest.approx(s.max())
    assert np.sign(second) == -np.sign(first) and 1.0 < abs(second) < 2.6  # the other side, between


def test_a_spoiled_pan_counts_for_its_reliability() -> None:
    """With the per-pan reliability a spoiled pan's separation is discounted, r(u) s(u)
    (the policy's H'(u) = r H(u) + (1 - r) H_0 with H = -s, H_0 = 0)."""
    pans = ActiveVisionConfig().actions()
    rel = PanReliability(PanReliabilityConfig(enabled=True))
    rel.observe(2.6, 10.0)  # a view at 2.6 rad fit no map entry: spoiled
    v = rel.discount(spread_values([0.0], pans))
    r = rel.reliability(pans)
    assert r[-1] < 1.0
    np.testing.assert_allclose(-v.expected_entropy, r * separation([0.0], pans))
    assert abs(float(pans[v.best()])) == pytest.approx(2.6) and float(pans[v.best()]) < 0  # the other end

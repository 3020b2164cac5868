"""The head-settle rule (lino_loc.active_vision.HeadSettle), the one rule the daemon (which
frames the filter sees) and the active policy (when it may look again) share."""

from __future__ import annotations

import math

import pytest

from lino_loc.active_vision import HeadSettle


def test_at_rest_is_not_moving_and_outside_the_settle_window() -> None:
    s = HeadSettle(settle_s=0.2)
    assert s.at_rest(5.0, moving=False, last_motion=None)
    assert not s.at_rest(5.0, moving=True, last_motion=None)
    # the window [last_motion, last_motion + settle_s) is not at rest
    assert not s.at_rest(1.0, moving=False, last_motion=1.0)
    assert not s.at_rest(1.19, moving=False, last_motion=1.0)
    assert s.at_rest(1.25, moving=False, last_motion=1.0)
    # a frame taken before the last motion, while the head was still (history says so)
    assert s.at_rest(0.9, moving=False, last_motion=1.0)
    assert not s.at_rest(0.9, moving=True, last_motion=1.0)


def test_zero_settle_time_only_excludes_moving() -> None:
    s = HeadSettle(settle_s=0.0)
    assert s.at_rest(1.0, moving=False, last_motion=1.0)
    assert not s.at_rest(1.0, moving=True, last_motion=1.0)


def test_observe_tracks_the_stop_from_readings() -> None:
    s = HeadSettle(settle_s=0.5)
    s.observe(False, 0.0)  # first seen at rest: stopped long ago
    assert s.last_motion == -math.inf and s.observed_at_rest(0.0)
    s.observe(True, 1.0)
    assert s.last_motion is None
    s.observe(True, 1.1)
    s.observe(False, 1.3)  # the first reading at rest after motion
    assert s.last_motion == 1.3
    s.observe(False, 1.4)  # later rest readings keep the stop time
    assert s.last_motion == 1.3
    assert not s.observed_at_rest(1.4)
    assert s.observed_at_rest(1.8)
    # a time before the tracked stop counts as moving (the readings say nothing about it)
    assert not s.observed_at_rest(1.0)


@pytest.mark.parametrize("stamp", [0.3, 0.59, 0.6, 0.65])
def test_observed_rule_equals_the_plain_rule_after_the_stop(stamp: float) -> None:
    s = HeadSettle(settle_s=0.5)
    s.observe(True, 0.0)
    s.observe(False, 0.1)
    expected = stamp >= 0.1 and s.at_rest(stamp, moving=False, last_motion=0.1)
    assert s.observed_at_rest(stamp) == expected

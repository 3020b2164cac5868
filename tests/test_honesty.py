"""The honesty metrics of a run's states against its errors, on hand-made sequences."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.evaluation.honesty import (
    confident_wrong_fraction,
    false_lost_fraction,
    honesty_metrics,
    lost_delay_summary,
    lost_delays,
    lost_when_wrong,
    quality_table,
    state_changes_per_min,
    wrong_episodes,
)

T, L, G = "tracking", "lost", "global"


def _stamps(n: int, dt: float = 1.0) -> np.ndarray:
    return np.arange(n) * dt


def test_confident_wrong_counts_tracking_frames_over_one_metre() -> None:
    err = [0.2, 1.5, 1.5, 1.5, 0.9, 2.0]
    states = [T, T, L, T, T, G]
    assert confident_wrong_fraction(err, states) == pytest.approx(2 / 6)
    assert confident_wrong_fraction([1.0], [T]) == 0.0  # exactly 1 m is not wrong
    assert confident_wrong_fraction([], []) == 0.0


def test_false_lost_counts_lost_frames_within_half_a_metre() -> None:
    err = [0.2, 0.5, 0.6, 1.5, 0.1, 0.3]
    states = [L, L, L, L, T, G]
    assert false_lost_fraction(err, states) == pytest.approx(2 / 6)  # exactly 0.5 m is right
    assert false_lost_fraction([], []) == 0.0
    with pytest.raises(ValueError, match="differ in length"):
        false_lost_fraction([0.1], [L, L])
    assert honesty_metrics(_stamps(6), err, states)["false_lost_fraction"] == pytest.approx(2 / 6)


def test_lost_when_wrong_is_the_lost_share_of_the_frames_over_one_metre() -> None:
    err = [0.2, 1.5, 1.5, 2.0, 1.0, 3.0]
    states = [L, L, T, G, L, L]
    assert lost_when_wrong(err, states) == pytest.approx(2 / 4)  # exactly 1 m is not wrong
    assert lost_when_wrong([0.3], [L]) is None
    with pytest.raises(ValueError, match="differ in length"):
        lost_when_wrong([2.0], [])


def test_episodes_are_maximal_runs_and_short_dips_merge() -> None:
    err = [0, 2, 2, 0, 2, 0, 0, 0, 2, 0]
    t = _stamps(len(err))
    # dips of 1 frame (1 s between wrong frames 2 and 4: gap t=4-2=2 s, not < 2) do not merge
    assert wrong_episodes(t, err, merge_s=2.0) == [(1, 2), (4, 4), (8, 8)]
    # with a 2.5 s merge window the one-frame dip joins frames 1-4, the 3-frame dip does not
    assert wrong_episodes(t, err, merge_s=2.5) == [(1, 4), (8, 8)]
    assert wrong_episodes(t, [0.0, 0.5]) == []


def test_delay_is_time_to_leave_tracking_and_zero_when_not_tracking_at_the_start() -> None:
    t = _stamps(12, 0.5)
    err = [0, 0, 3, 3, 3, 3, 0, 0, 0, 0, 3, 3]
    states = [T, T, T, T, T, L, L, T, T, T, G, G]
    assert lost_delays(t, err, states, merge_s=1.0) == [(1.5, True), (0.0, True)]


def test_a_confirmation_while_wrong_counts_from_the_confirmation() -> None:
    """An episode that starts while searching (``global``) and is then confirmed while still
    wrong: its delay runs from the confirmation to the state's leaving ``tracking``; a frame
    count that starts at the episode's first frame would call it caught at 0."""
    t = _stamps(20, 0.5)
    err = [3.0] * 16 + [0.1] * 4
    states = [G] * 4 + [T] * 8 + [L] * 2 + [T] * 6  # wrong 4..11 (4 s), right again from 16
    assert lost_delays(t, err, states) == [(4.0, False)]  # the second stretch lasts to the end
    states = [G] * 4 + [T] * 8 + [L] * 4 + [T] * 4
    assert lost_delays(t, err, states) == [(4.0, True)]
    assert lost_delays(t, err, [G] * 20) == [(0.0, True)]
    assert lost_delays(t, err, [T] * 3 + [G] * 17) == [(1.5, True)]  # a kidnapping, caught
    assert all(type(x) is float and type(ok) is bool for x, ok in lost_delays(t, err, states))
    json.dumps(lost_delay_summary(t, err, states))  # plain Python numbers: the evaluations' JSON


def test_an_episode_that_stays_tracking_is_not_caught_and_counts_its_duration() -> None:
    t = _stamps(20, 0.5)
    err = [0.0] * 5 + [2.0] * 15  # a kidnapping at frame 5, never noticed
    states = [T] * 20
    s = lost_delay_summary(t, err, states)
    assert s["episodes"] == 1 and s["caught"] == 0
    assert s["median_s"] == s["max_s"] == pytest.approx(7.0)
    assert s["caught_within_s_share"] == 0.0


def test_summary_share_within_five_seconds() -> None:
    t = _stamps(60, 1.0)
    err = np.zeros(60)
    states = [T] * 60
    err[5:15] = 2.0  # caught after 3 s
    states[8:15] = [L] * 7
    err[25:40] = 2.0  # caught after 7 s
    states[32:40] = [L] * 8
    err[50:55] = 2.0  # starts while global, then tracking while wrong to its end: not caught
    states[50] = G
    s = lost_delay_summary(t, err, states)
    assert s["episodes"] == 3 and s["caught"] == 2
    assert s["caught_within_s_share"] == pytest.approx(1 / 3)
    assert s["median_s"] == pytest.approx(3.0) and s["max_s"] == pytest.approx(7.0)
    m = honesty_metrics(t, err, states)
    assert m["lost_delay_s"] == s
    assert m["tracking_fraction"] == pytest.approx(44 / 60)
    assert m["confident_wrong_fraction"] == pytest.approx((3 + 7 + 4) / 60)


def test_no_episode_gives_full_share_and_no_delays() -> None:
    s = lost_delay_summary(_stamps(3), [0.1, 0.2, 0.3], [T, T, T])
    assert s == {"episodes": 0, "caught": 0, "caught_within_s": 5.0, "caught_within_s_share": 1.0,
                 "median_s": None, "max_s": None}


def test_lengths_must_agree() -> None:
    with pytest.raises(ValueError, match="differ in length"):
        lost_delays([0, 1], [0, 1, 2], [T, T, T])


def test_quality_table_bands() -> None:
    q = [0.05, 0.1, 0.5, 0.95, 1.0, np.nan]
    err = [3.0, 1.0, 0.5, 0.1, 0.3, 9.0]
    rows = quality_table(q, err, [G, L, T, T, T, T])
    assert [r["frames"] for r in rows] == [2, 0, 1, 0, 2]
    assert rows[0]["band"] == [0.0, 0.2] and rows[0]["mean_error_m"] == pytest.approx(2.0)
    assert rows[0]["wrong_fraction"] == pytest.approx(0.5) and rows[0]["tracking_fraction"] == 0.0
    assert rows[1]["mean_error_m"] is None
    assert rows[4]["median_error_m"] == pytest.approx(0.2) and rows[4]["tracking_fraction"] == 1.0


def test_state_changes_per_min_counts_the_frames_that_change_state() -> None:
    stamps = np.arange(13) * 5.0  # one minute
    states = ["global"] * 3 + ["tracking"] * 4 + ["lost", "tracking"] * 3
    assert state_changes_per_min(stamps, states) == pytest.approx(7.0)  # 1 + 6 changes in 60 s
    assert state_changes_per_min(stamps[:7], states[:7]) == pytest.approx(2.0)  # 1 in 30 s
    assert state_changes_per_min([0.0], ["lost"]) == 0.0
    assert state_changes_per_min([1.0, 1.0], ["lost", "tracking"]) == 0.0  # no span
    with pytest.raises(ValueError, match="differ in length"):
        state_changes_per_min([0.0, 1.0], ["lost"])

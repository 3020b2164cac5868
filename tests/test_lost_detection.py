"""The lost test (lino_loc.lost_detection): evidence calibrated by the learnt hit rate, counted
per independent view."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.lost_detection import (
    CHANCE_HIT_RATE,
    CONFIRM_RADIUS_THETA,
    CONFIRM_RADIUS_XY,
    MIN_PAN_CHANGE,
    VIEW_THETA,
    VIEW_XY,
    LostConfig,
    LostDetector,
    camera_increment,
    independent_views,
    view_share,
)

STEP = np.array([0.35, 0.0, 0.0])  # one independent view per observation


def _learn(det: LostDetector, hit_rate: float, n: int = 200, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(n):
        det.update(3.0 if rng.random() < hit_rate else 0.0, STEP)


def _misses_until_lost(det: LostDetector, limit: int = 200) -> int | None:
    for k in range(limit):
        if det.update(0.0, STEP):
            return k + 1
    return None


def test_misses_weigh_by_how_reliable_the_views_were() -> None:
    """After reliable views (hit rate ~0.95) a few misses mean lost; after unreliable ones
    (~0.3, as under changed light) the same run of misses is not enough."""
    reliable, unreliable = LostDetector(), LostDetector()
    _learn(reliable, 0.95)
    _learn(unreliable, 0.3)
    assert reliable.hit_rate > 0.85 and 0.15 < unreliable.hit_rate < 0.45
    fast = _misses_until_lost(reliable)
    assert fast is not None and fast <= 10, fast  # (8 with the default threshold of 12 nats)
    for _ in range(fast):
        unreliable.update(0.0, STEP)
    assert not unreliable.lost and unreliable.score > 0.0
    slow = _misses_until_lost(unreliable)
    assert slow is not None and slow > 3 * fast, (fast, slow)


def test_hits_clear_the_evidence_and_a_still_robot_adds_none() -> None:
    det = LostDetector()
    _learn(det, 0.95)
    assert _misses_until_lost(det) is not None
    assert det.lost
    score = det.score
    for _ in range(10):
        det.update(0.0, np.zeros(3))  # standing still: the same view again, no new evidence
    assert det.score == score
    for _ in range(5):
        det.update(5.0, STEP)
    assert not det.lost
    det.reset()
    assert det.score == 0.0 and det.hit_rate == 0.5


def test_nothing_is_learnt_from_views_without_information() -> None:
    """A hit rate at chance level (a wrong belief, or views that match nothing) gives no
    evidence either way: misses then add nothing."""
    assert CHANCE_HIT_RATE == 0.05
    det = LostDetector()
    _learn(det, 0.0, n=400)
    assert det.hit_rate < 0.05
    score = det.score  # (the first misses, while rho was still the prior's 1/2, count a little)
    for _ in range(50):
        det.update(0.0, STEP)
    assert det.score == score and not det.lost


def test_a_new_belief_must_be_confirmed_and_keeps_the_learnt_reliability() -> None:
    det = LostDetector(LostConfig(confirm_views=1.0))
    _learn(det, 0.9)
    rho = det.hit_rate
    assert det.confirmed
    det.new_belief()  # converged again: evidence and confirmation restart, rho stays
    assert not det.confirmed and det.score == 0.0 and det.hit_rate == rho
    det.update(0.0, STEP, learn=False)  # a search teaches rho nothing
    assert not det.confirmed and det.hit_rate == rho
    det.update(3.0, STEP, learn=False)  # one view's worth of hits confirms the belief
    assert det.confirmed and det.hit_rate == rho
    det.reset()
    assert not det.confirmed and det.hit_rate == 0.5
    det.confirm()  # a pose given by the user
    assert det.confirmed


def test_view_share_is_the_kernel_weight_near_the_pose() -> None:
    """Closed form: the weights of the kernels within CONFIRM_RADIUS_XY and
    CONFIRM_RADIUS_THETA (heading wrapped) of the pose, over all kernels' weights."""
    poses = np.array([
        [0.0, 0.0, 0.0],  # at the pose
        [CONFIRM_RADIUS_XY * 0.99, 0.0, 0.0],  # just inside in position
        [0.0, 0.0, 2.0 * np.pi - CONFIRM_RADIUS_THETA * 0.99],  # inside once wrapped
        [CONFIRM_RADIUS_XY * 1.01, 0.0, 0.0],  # just outside in position
        [0.0, 0.0, CONFIRM_RADIUS_THETA * 1.01],  # just outside in heading
        [5.0, 5.0, 0.0],  # another place
    ])
    w = np.array([0.1, 0.2, 0.05, 0.15, 0.25, 0.25])
    lw = np.log(w * 0.5)  # an outlier component of weight 1/2 is not counted
    assert view_share(poses, lw, (0.0, 0.0, 0.0)) == pytest.approx(0.35)
    assert view_share(poses, lw, (5.0, 5.0, 0.0)) == pytest.approx(0.25)
    assert view_share(poses, lw, (-3.0, 0.0, 0.0)) == 0.0
    assert np.isnan(view_share(poses, np.full(6, -np.inf), (0.0, 0.0, 0.0)))


def test_only_views_that_single_out_the_belief_confirm_it() -> None:
    """With ``confirm_share``, a hit whose view points elsewhere as much as at the belief
    (share below the setting) does not count towards the confirmation; the lost test's
    evidence is the same with or without it."""
    plain = LostDetector(LostConfig(confirm_views=2.0))
    strict = LostDetector(LostConfig(confirm_views=2.0, confirm_share=0.5))
    for det in (plain, strict):
        _learn(det, 0.9)
        det.new_belief()
    for _ in range(3):  # hits of views shared with four other places
        plain.update(3.0, STEP, learn=False, share=0.2)
        strict.update(3.0, STEP, learn=False, share=0.2)
    assert plain.confirmed and not strict.confirmed
    assert plain.score == strict.score
    strict.update(3.0, STEP, learn=False, share=0.5)
    assert not strict.confirmed  # one view's worth
    strict.update(3.0, STEP, learn=False, share=0.9)
    assert strict.confirmed
    nan_share = LostDetector(LostConfig(confirm_views=1.0, confirm_share=0.5))
    nan_share.update(3.0, STEP, learn=False, share=float("nan"))
    assert not nan_share.confirmed  # a view with no kernel singles out nothing


def test_doubt_grows_with_the_evidence_and_reaches_one_when_lost() -> None:
    det = LostDetector()
    _learn(det, 0.95)
    assert det.doubt == 0.0
    seen = []
    while not det.lost:
        det.update(0.0, STEP)
        seen.append(det.doubt)
    assert all(b > a for a, b in zip(seen, seen[1:], strict=False))  # each miss adds evidence
    assert seen[-2] < 1.0 < seen[-1] and det.doubt == det.score / det.config.threshold


# --------------------------------------------------------------------- the camera's views


def test_a_standing_robot_whose_head_pans_sees_new_views() -> None:
    """Closed form: standing (delta 0) with a pan change dp >= MIN_PAN_CHANGE is
    min(1, |dp| / VIEW_THETA) of a view; standing with the head still (or jittering under
    MIN_PAN_CHANGE) is none; a moving robot counts as before, whatever the head does."""
    zero = np.zeros(3)
    assert independent_views(camera_increment(zero, 0.15)) == pytest.approx(0.15 / VIEW_THETA)
    assert independent_views(camera_increment(zero, -0.25)) == pytest.approx(0.25 / VIEW_THETA)
    assert independent_views(camera_increment(zero, 1.0)) == 1.0
    assert independent_views(camera_increment(zero, 0.0)) == 0.0
    assert independent_views(camera_increment(zero, 0.5 * MIN_PAN_CHANGE)) == 0.0
    assert independent_views(camera_increment(zero, math.nan)) == 0.0  # no pan known yet
    # a turn of 2 pi is no turn
    assert independent_views(camera_increment(zero, 2.0 * math.pi)) == 0.0
    step = np.array([0.1, 0.0, 0.0])
    assert independent_views(camera_increment(step, 0.0)) == pytest.approx(0.1 / VIEW_XY)
    assert independent_views(camera_increment(step, 0.001)) == pytest.approx(0.1 / VIEW_XY)
    assert independent_views(camera_increment(step, 0.06)) == pytest.approx(
        0.1 / VIEW_XY + 0.06 / VIEW_THETA
    )
    # the base turns left, the head pans right as much: the camera looks where it looked
    assert independent_views(camera_increment([0.0, 0.0, 0.2], -0.2)) == 0.0
    np.testing.assert_array_equal(camera_increment(step, 0.3), [0.1, 0.0, 0.3])


def test_the_head_counts_for_a_standing_base_only() -> None:
    """viewed_increment: standing (under STANDING_VIEWS of a view), the camera's increment;
    driving, the odometry's alone, whatever the head does."""
    from lino_loc.lost_detection import STANDING_VIEWS, viewed_increment

    np.testing.assert_array_equal(viewed_increment(np.zeros(3), 0.25), [0.0, 0.0, 0.25])
    creeping = np.array([0.5 * STANDING_VIEWS * VIEW_XY, 0.0, 0.0])  # still "standing"
    np.testing.assert_allclose(viewed_increment(creeping, 0.25), creeping + [0.0, 0.0, 0.25])
    driving = np.array([0.1, 0.0, 0.02])
    np.testing.assert_array_equal(viewed_increment(driving, 0.25), driving)
    np.testing.assert_array_equal(viewed_increment(driving, -0.2), driving)


def test_a_panning_standing_robot_confirms_a_belief_a_still_one_does_not() -> None:
    panning, still = LostDetector(), LostDetector()
    pans = [0.0, 0.25, 0.5, 0.25, 0.0, -0.25]
    for k in range(1, len(pans)):
        panning.update(3.0, camera_increment(np.zeros(3), pans[k] - pans[k - 1]))
        still.update(3.0, camera_increment(np.zeros(3), 0.0))
    assert panning.confirmed and not still.confirmed

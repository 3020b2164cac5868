"""Appearance-change detection (lino_loc/appearance_change.py) and what the filter does with it:
closed-form detection delay, no alarms on stationary novelty, the filter's relearning."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from lino_loc.appearance_change import AppearanceChangeConfig, AppearanceChangeDetector
from lino_loc.kidnap_recovery import RATIO
from lino_loc.poses import camera_pose

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_particle_filter import _drive, _filter, _synthetic_model  # noqa: E402


def test_a_step_in_novelty_is_found_after_the_closed_form_delay() -> None:
    """Novelty 1 then 2, no noise, one independent view per call. The level is learnt only in
    control: the first changed view still teaches it (no evidence stood before it), mu = alpha
    log 2, then it stays while the evidence builds: S_n = (log 2 - log 1.65) + (n - 1)(log 2 -
    mu - log 1.65), which passes 5 at the 32nd view."""
    det = AppearanceChangeDetector(ratio=1.65, evidence=5.0, alpha=0.05)
    assert not any(det.update(1.0) for _ in range(200))
    fired = [k for k in range(200) if det.update(2.0)]
    step, mu = math.log(2.0) - math.log(1.65), 0.05 * math.log(2.0)
    n = 1 + math.floor((5.0 - step) / (step - mu)) + 1  # first n with S_n > 5
    assert n == 32 and fired == [n - 1]
    # then it restarts at the new level: no second alarm on the plateau
    assert det.changes == 1 and det.level == pytest.approx(math.log(2.0))


def test_evidence_counts_independent_views_not_frames() -> None:
    """The same doubling seen in frames of a quarter view each (a robot moving slowly, a fast
    camera) needs about four times as many frames (a little fewer: the first changed frame
    teaches the level a quarter as much); counting frames it would need as many."""
    whole, quarter = AppearanceChangeDetector(), AppearanceChangeDetector()
    for det, v in ((whole, 1.0), (quarter, 0.25)):
        for _ in range(200):
            det.update(1.0, v)
    k_whole = next(k for k in range(1000) if whole.update(2.0, 1.0))
    k_quarter = next(k for k in range(1000) if quarter.update(2.0, 0.25))
    assert 3 * k_whole <= k_quarter <= 4 * k_whole + 4
    still = AppearanceChangeDetector()
    still.update(1.0)
    assert not any(still.update(10.0, 0.0) for _ in range(100))  # a robot standing still: no views


def test_a_strange_first_view_does_not_blind_the_detector() -> None:
    """The level is the running mean of the in-control views until 1 / alpha of them: a first
    view three times as novel as the next eighteen (a place unlike the rest) weighs 1 / 19, mu
    = log 3 / 19, and a rise to 2.5 is then found after the closed-form count of views. Learnt at
    the rate alpha from that first view, mu would still be log 3 x 0.95^18 = 0.44 and the rise
    would never be found (log 2.5 - 0.44 < log 1.65: the service's light-switch test waited 30 s
    in vain on CI)."""
    det = AppearanceChangeDetector(ratio=1.65, evidence=5.0, alpha=0.05)
    assert not det.update(3.0)
    assert not any(det.update(1.0) for _ in range(18))
    assert det.level == pytest.approx(math.log(3.0) / 19)
    fired = [k for k in range(200) if det.update(2.5)]
    # the first changed view is in control and teaches mu at 1/20 = alpha; then S grows by a
    # fixed step
    mu1 = math.log(3.0) / 19
    mu2 = mu1 + (math.log(2.5) - mu1) / 20
    s1, step = math.log(2.5) - mu1 - math.log(1.65), math.log(2.5) - mu2 - math.log(1.65)
    n = 1 + math.floor((5.0 - s1) / step) + 1  # first n with S_n = s1 + (n - 1) step > 5
    assert fired[:1] == [n - 1] and n < 20


def test_less_novel_views_and_missing_novelty_are_not_changes() -> None:
    det = AppearanceChangeDetector()
    for _ in range(100):
        det.update(2.5)
    assert not any(det.update(1.0) for _ in range(500))  # lights back to the mapping light
    assert not any(det.update(v) for v in (math.nan, 0.0, -1.0, math.inf))
    assert det.changes == 0


def test_stationary_novelty_raises_no_alarm() -> None:
    """Log-novelty spread like the lab's (sd 0.38 per view, here independent): none in 5000."""
    rng = np.random.default_rng(0)
    det = AppearanceChangeDetector()
    assert not any(det.update(float(v)) for v in np.exp(0.25 + 0.38 * rng.standard_normal(5000)))


def _switch_run(pf, model, f, *, horizon=150, switch=60, offset=0.8, seed=2):
    """Drive as the kidnap tests do; from ``switch`` on every view is changed the same way
    (a fixed shift of the features plus noise: less familiar everywhere, like other light)."""
    rng = np.random.default_rng(seed)
    shift = np.random.default_rng(5).normal(0, 1, 8)
    shift *= offset / np.linalg.norm(shift)
    truth, pan = np.array([1.0, 1.0, 0.3]), 0.4
    errors, states, changes = [], [], []
    for t in range(horizon):
        truth, d = _drive(truth)
        y = f(camera_pose(truth, pan))[0] + rng.normal(0, 0.05, 8)
        if t >= switch:
            y = y + shift + rng.normal(0, offset / 2, 8)
        pf.update(d + rng.normal(0, 0.01, 3), pan, model.observe(y))
        est = pf.estimate()
        errors.append(float(np.hypot(*(est.pose[:2] - truth[:2]))))
        states.append(est.state)
        changes.append(pf.appearance_watch.changes if pf.appearance_watch else 0)
    return np.array(errors), states, np.array(changes)


def test_filter_relearns_after_an_appearance_change_and_keeps_its_belief() -> None:
    model, f = _synthetic_model()
    pf = _filter(n=800, seed=1)
    errors, states, changes = _switch_run(pf, model, f)
    first = int(np.argmax(changes > 0))
    assert changes[59] == 0 and 60 <= first <= 90 and changes[-1] == 1  # found once, after the switch
    assert pf.recovery.candidate_draws == 0 and pf.recovery.recoveries == 0
    assert "lost" not in states[first:]
    assert np.all(errors[30:] < 0.5), errors[30:]
    # what it relearnt: w_slow is the running mean of the likelihoods since the change, so it
    # sits at the new (lower) level, no longer at the one learnt before
    assert pf.recovery.log_w_slow < pf.recovery.log_w_fast + math.log(1.0 / RATIO)


def test_the_detector_can_be_switched_off() -> None:
    pf = _filter(n=100, seed=1, appearance_change=AppearanceChangeConfig(enabled=False))
    assert pf.appearance_watch is None


def test_relearnt_averages_are_running_means() -> None:
    """After relearn_averages(), w_slow and w_fast are the plain means (linear space) of the
    likelihoods seen since, until 1 / n falls below their rates."""
    pf = _filter(n=100, seed=1)
    pf.recovery.relearn_averages()
    lls = [-1.0, -3.0, -2.0, -5.0]
    for ll in lls:
        pf.recovery.track_likelihood(ll)
    mean = math.log(np.mean(np.exp(lls)))
    assert pf.recovery.log_w_slow == pytest.approx(mean)
    assert pf.recovery.log_w_fast == pytest.approx(mean)


# ----------------------------------------------------------------- per channel


def _steady_then(det, intensity_after, disparity_after, n_before=200, n_after=200):
    """Both channels familiar (novelty 1) for ``n_before`` views, then the given novelties;
    returns the indices (after the step) at which update reported a light change."""
    for _ in range(n_before):
        assert not det.update({"intensity": 1.0, "disparity": 1.0})
    return [k for k in range(n_after) if det.update({"intensity": intensity_after, "disparity": disparity_after})]


def test_per_channel_light_change_is_found_when_disparity_stays_steady() -> None:
    """Intensity doubles, disparity stays: the same delay as with intensity alone (the step
    test above: the 32nd view), reported as a light change."""
    det = AppearanceChangeDetector()
    fired = _steady_then(det, 2.0, 1.0)
    alone = AppearanceChangeDetector()
    for _ in range(200):
        alone.update(1.0)
    fired_alone = [k for k in range(200) if alone.update(2.0)]
    assert fired == fired_alone == [31]
    assert det.changes == 1 and det.scene_changes == 0 and det.last_change == "light"


def test_both_channels_rising_is_the_place_not_the_light() -> None:
    """Intensity and disparity both double (an unmapped place): the evidence passes at the
    same view, classified as a scene change, not reported (no relearning)."""
    det = AppearanceChangeDetector()
    assert _steady_then(det, 2.0, 2.0) == []
    assert det.changes == 0 and det.scene_changes == 1 and det.last_change == "scene"


def test_the_steady_bound_is_half_the_ratio_in_log() -> None:
    """Disparity rising by a factor just under / over sqrt(RATIO) on average: light / scene."""
    from lino_loc.appearance_change import STEADY_RATIO

    assert math.log(STEADY_RATIO) == pytest.approx(0.5 * math.log(1.65))
    under, over = AppearanceChangeDetector(), AppearanceChangeDetector()
    _steady_then(under, 2.0, STEADY_RATIO * 0.97)
    _steady_then(over, 2.0, STEADY_RATIO * 1.03)
    assert (under.changes, under.scene_changes) == (1, 0)
    assert (over.changes, over.scene_changes) == (0, 1)


def test_a_kidnapping_keeps_both_familiar_and_raises_nothing() -> None:
    rng = np.random.default_rng(3)
    det = AppearanceChangeDetector()
    for _ in range(3000):
        n = np.exp(0.25 + 0.38 * rng.standard_normal(2))
        assert not det.update({"intensity": float(n[0]), "disparity": float(n[1])})
    assert det.changes == det.scene_changes == 0


def test_per_channel_evidence_is_frame_rate_independent_and_missing_disparity_is_light() -> None:
    """Quarter views need about four times the frames, as with one channel; a view without
    a finite disparity novelty adds nothing to its rise (all missing: a light change)."""
    whole, quarter = AppearanceChangeDetector(), AppearanceChangeDetector()
    for det, v in ((whole, 1.0), (quarter, 0.25)):
        for _ in range(200):
            det.update({"intensity": 1.0, "disparity": 1.0}, v)
    k_whole = next(k for k in range(1000) if whole.update({"intensity": 2.0, "disparity": 2.0 ** 0.1}, 1.0))
    k_quarter = next(k for k in range(1000) if quarter.update({"intensity": 2.0, "disparity": 2.0 ** 0.1}, 0.25))
    assert 3 * k_whole <= k_quarter <= 4 * k_whole + 4
    gone = AppearanceChangeDetector()
    _steady_then(gone, 2.0, 1.0, n_after=0)
    fired = [k for k in range(200) if gone.update({"intensity": 2.0, "disparity": math.nan})]
    assert fired == [31] and gone.last_change == "light"


def test_the_filter_watches_each_channel_when_asked() -> None:
    """A fused mixture whose channels' novelties both rise: per channel, no light change (and
    no relearning); with per_channel off the fused (intensity) novelty alone: a change."""
    from dataclasses import replace

    model, f = _synthetic_model()
    out = {}
    for per_channel in (True, False):
        pf = _filter(n=200, seed=1, appearance_change=AppearanceChangeConfig(per_channel=per_channel))
        truth = np.array([1.0, 1.0, 0.3])
        pf.set_pose(truth, np.diag([0.01, 0.01, 0.01]))
        for t in range(150):
            truth, d = _drive(truth)
            m = model.observe(f(camera_pose(truth, 0.0))[0])
            nov = 1.0 if t < 60 else 3.0
            mi, md = replace(m, novelty=nov), replace(m, novelty=nov)
            pf.update(d, 0.0, replace(m, novelty=nov, channels={"intensity": mi, "disparity": md}))
        out[per_channel] = (pf.appearance_watch.changes, pf.appearance_watch.scene_changes)
    assert out[True] == (0, 1) and out[False][0] == 1

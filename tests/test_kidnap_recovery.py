"""Kidnap recovery as a component (lino_loc.kidnap_recovery), without a filter: AMCL's averages
against the closed form of the EMA, the lost-evidence count, the familiarity ramp, and the
candidate set's life (drawn, adopted, dropped, forgotten on an appearance change), and the
channels' agreement a jump needs (each channel's evidence, counted after one view)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.kidnap_recovery import (
    ALPHA_FAST,
    ALPHA_SLOW,
    CANDIDATE_MAX_UPDATES,
    CANDIDATE_MIN_UPDATES,
    MIN_UPDATES,
    ChannelView,
    KidnapRecovery,
    RecoveryConfig,
    Verdict,
)
from lino_loc.lost_detection import independent_views
from lino_loc.motion_model import MotionModelConfig, OdometryMotionModel

N = 100
STEP = np.array([0.1, 0.0, 0.02])


def _recovery(**kw) -> KidnapRecovery:
    return KidnapRecovery(RecoveryConfig(**kw), OdometryMotionModel(MotionModelConfig()))


def _observe(rec, rng, ll, *, novelty=1.0, floor=-math.inf, loglik=None, converged=True):
    def draw(m: int) -> np.ndarray:
        return np.column_stack([rng.uniform(0, 8, m), rng.uniform(0, 4, m), rng.uniform(-3, 3, m)])

    return rec.observe(
        ll, novelty, floor, delta=STEP,
        loglik=loglik if loglik is not None else (lambda x: np.zeros(x.shape[0])),
        converged=converged, n=N, draw=draw, rng=rng,
    )


def _draw_candidates(rec, rng) -> list[Verdict]:
    """Averages at ll = 0 with the outlier floor at 0: every update is lost evidence."""
    return [_observe(rec, rng, 0.0, floor=0.0) for _ in range(MIN_UPDATES + 1)]


def test_averages_are_the_ema_of_the_likelihoods() -> None:
    rec = _recovery()
    lls = np.random.default_rng(0).normal(-5.0, 2.0, 30)
    for ll in lls:
        rec.track_likelihood(float(ll))
    # the first likelihood starts both; then w_k = (1 - a) w_k-1 + a p_k, in linear space
    for alpha, got in ((ALPHA_SLOW, rec.log_w_slow), (ALPHA_FAST, rec.log_w_fast)):
        k = np.arange(1, lls.size)
        w = (1 - alpha) ** (lls.size - 1) * math.exp(lls[0]) + np.sum(
            alpha * (1 - alpha) ** (lls.size - 1 - k) * np.exp(lls[1:])
        )
        assert got == pytest.approx(math.log(w), rel=1e-12)
    # AMCL's injection share, 1 - w_fast / w_slow capped at max_inject_fraction
    frac = 1.0 - math.exp(min(0.0, rec.log_w_fast - rec.log_w_slow))
    assert rec.inject_fraction() == pytest.approx(min(frac, 0.5))


def test_restart_and_relearn() -> None:
    rec = _recovery()
    for ll in (-1.0, -2.0):
        rec.track_likelihood(ll)
    rec.restart_averages()
    rec.track_likelihood(-7.0)
    assert rec.log_w_slow == rec.log_w_fast == -7.0
    rec.relearn_averages()  # after an appearance change: running means until 1 / n < alpha
    lls = [-1.0, -3.0, -2.0, -5.0]
    for ll in lls:
        rec.track_likelihood(ll)
    mean = math.log(np.mean(np.exp(lls)))
    assert rec.log_w_slow == pytest.approx(mean) and rec.log_w_fast == pytest.approx(mean)
    rec.track_likelihood(-math.inf)  # not explained at all: counts as UNEXPLAINED
    assert math.isfinite(rec.log_w_fast)


def test_lost_evidence_count() -> None:
    rec = _recovery()
    rec.track_likelihood(0.0)  # starts the averages, counts nothing
    assert rec.lost_updates == 0
    for k in range(1, 4):  # w_fast below FLOOR_FACTOR x the outlier floor (1): evidence
        rec.track_likelihood(0.0, 1.0, floor=0.0)
        assert rec.lost_updates == k
    rec.track_likelihood(0.0, 0.5, floor=0.0)  # half-familiar still counts
    assert rec.lost_updates == 4
    rec.track_likelihood(0.0, 0.2, floor=0.0)  # a novel view neither adds nor clears
    assert rec.lost_updates == 4
    rec.track_likelihood(0.0, 1.0)  # explained: cleared
    assert rec.lost_updates == 0
    # w_fast far below RATIO x w_slow is evidence too (no floor)
    for _ in range(40):
        rec.track_likelihood(-30.0)
    assert rec.lost_updates > 0


def test_familiarity_ramp() -> None:
    rec = _recovery(familiar_novelty=1.5, novel_novelty=2.0)
    assert rec.familiarity(1.0) == rec.familiarity(1.5) == 1.0
    assert rec.familiarity(1.75) == pytest.approx(0.5)
    assert rec.familiarity(1.9) == pytest.approx(0.2)
    assert rec.familiarity(2.0) == rec.familiarity(3.0) == 0.0
    assert rec.familiarity(math.nan) == 1.0
    with pytest.raises(ValueError):
        RecoveryConfig(familiar_novelty=2.0, novel_novelty=1.5)


def test_candidates_are_drawn_after_min_updates_of_familiar_evidence() -> None:
    rng = np.random.default_rng(1)
    rec = _recovery()
    verdicts = _draw_candidates(rec, rng)
    assert [v.action for v in verdicts] == ["none"] * MIN_UPDATES + ["draw"]
    assert verdicts[-1].count == 32  # max(32, round(CANDIDATE_FRACTION * N))
    assert rec.candidates is not None and rec.candidates.particles.shape == (32, 3)
    assert rec.candidate_draws == 1 and rec.lost_updates == 0
    # half-familiar views count as evidence but draw nothing
    other = _recovery()
    acts = [_observe(other, rng, 0.0, floor=0.0, novelty=1.75).action for _ in range(20)]
    assert set(acts) == {"none"} and other.lost_updates == 19 and other.candidates is None


def test_before_convergence_and_in_amcl_mode_it_injects() -> None:
    rng = np.random.default_rng(2)
    for rec, converged in ((_recovery(), False), (_recovery(mode="amcl"), True)):
        _observe(rec, rng, 0.0, converged=converged)
        v = _observe(rec, rng, -10.0, converged=converged)
        assert v.action == "inject"
        assert v.count == math.floor(rec.inject_fraction() * N) > 0
    off = _recovery(max_inject_fraction=0.0)
    assert {_observe(off, rng, ll, converged=False).action for ll in (0.0, -10.0)} == {"none"}


def test_a_better_candidate_set_is_adopted_after_the_margin_and_min_updates() -> None:
    rng = np.random.default_rng(3)
    rec = _recovery()
    _draw_candidates(rec, rng)
    # the candidates explain each view 50 nats better than the belief
    acts = [_observe(rec, rng, -50.0, floor=0.0).action for _ in range(CANDIDATE_MIN_UPDATES)]
    assert acts == ["none"] * (CANDIDATE_MIN_UPDATES - 1) + ["adopt"]
    assert rec.recoveries == 1 and rec.candidates is None and rec.lost_updates == 0
    rec.track_likelihood(-3.0)  # the averages restart with the new belief
    assert rec.log_w_slow == rec.log_w_fast == -3.0


def test_adopted_particles() -> None:
    rng = np.random.default_rng(4)
    rec = _recovery()
    _draw_candidates(rec, rng)
    v = Verdict()
    while v.action != "adopt":
        v = _observe(rec, rng, -50.0, floor=0.0)
    assert v.particles is not None and v.particles.shape == (N, 3) and v.count == 0


def test_a_worse_candidate_set_is_dropped_at_the_negative_margin() -> None:
    rng = np.random.default_rng(5)
    rec = _recovery()
    _draw_candidates(rec, rng)
    v = _observe(rec, rng, -50.0, floor=0.0, loglik=lambda x: np.full(x.shape[0], -100.0))
    assert v.action == "drop" and rec.candidates is None and rec.recoveries == 0


@pytest.mark.parametrize("novelty", [1.0, 3.0])  # an undecided test, and only novel views
def test_an_undecided_candidate_set_is_dropped_after_max_updates(novelty: float) -> None:
    rng = np.random.default_rng(6)
    rec = _recovery()
    _draw_candidates(rec, rng)
    acts = [
        _observe(rec, rng, -50.0, floor=0.0, novelty=novelty,
                 loglik=lambda x: np.full(x.shape[0], -50.0)).action
        for _ in range(CANDIDATE_MAX_UPDATES)
    ]
    assert acts == ["none"] * (CANDIDATE_MAX_UPDATES - 1) + ["drop"]
    assert rec.candidates is None and rec.recoveries == 0


def test_an_appearance_change_forgets_the_candidates_and_the_evidence() -> None:
    rng = np.random.default_rng(7)
    rec = _recovery()
    _draw_candidates(rec, rng)
    before = rec.candidates.particles.copy()
    rec.predict(STEP, rng)  # a frame without image: the candidates move with the odometry
    assert not np.allclose(rec.candidates.particles, before)
    rec.relearn_averages()
    assert rec.candidates is None and rec.lost_updates == 0
    rec.reset()
    assert rec.candidate_draws == 0 and rec.log_w_slow == -math.inf


def _channels(cand: dict[str, float], belief: dict[str, float]) -> dict[str, ChannelView]:
    """Two channels whose log-likelihood is ``cand[name]`` at every pose, and whose belief's
    log-likelihood of the view is ``belief[name]``."""
    return {
        name: ChannelView(lambda x, v=v: np.full(x.shape[0], v), belief[name])
        for name, v in cand.items()
    }


def _observe_channels(rec, rng, channels, views=None):
    """The fused view: the candidates 50 nats better than the belief (the fused test alone
    adopts after CANDIDATE_MIN_UPDATES)."""
    return rec.observe(
        -50.0, 1.0, 0.0, delta=STEP, loglik=lambda x: np.zeros(x.shape[0]), converged=True,
        n=N, draw=lambda m: np.zeros((m, 3)), rng=rng, channels=channels, views=views,
    )


def test_a_candidate_set_only_one_channel_prefers_is_not_adopted() -> None:
    """A changed light: intensity prefers the candidates by 50 nats a view, disparity not at all;
    the fused evidence clears the margin, the channels disagree: no adoption, dropped at the
    end. With the channel test off (margin 0) the same views adopt at CANDIDATE_MIN_UPDATES."""
    split = _channels({"intensity": 0.0, "disparity": -4.0}, {"intensity": -50.0, "disparity": -4.0})
    rng = np.random.default_rng(8)
    rec = _recovery()
    _draw_candidates(rec, rng)
    acts = [_observe_channels(rec, rng, split).action for _ in range(CANDIDATE_MAX_UPDATES)]
    assert acts == ["none"] * (CANDIDATE_MAX_UPDATES - 1) + ["drop"] and rec.recoveries == 0
    off = _recovery(channel_margin=0.0)
    _draw_candidates(off, rng)
    acts = [_observe_channels(off, rng, split).action for _ in range(CANDIDATE_MIN_UPDATES)]
    assert acts[-1] == "adopt"


def test_channel_evidence_counts_from_one_independent_view_after_the_draw() -> None:
    """Both channels prefer the candidates, by 3 and 2 nats a view. STEP is 0.1 m + 0.02 rad
    of the lost test's view scales (VIEW_XY, VIEW_THETA), so the first updates are the draw's
    own view; from the first update with one view seen, each adds 3 and 2 nats exactly, and
    the set is adopted at the first update where both exceed channel_margin (5 nats)."""
    both = _channels({"intensity": -1.0, "disparity": -2.0}, {"intensity": -4.0, "disparity": -4.0})
    per_frame = independent_views(STEP)
    probation = math.ceil(1.0 / per_frame - 1e-12)  # updates until one view is seen
    rng = np.random.default_rng(9)
    rec = _recovery()
    _draw_candidates(rec, rng)
    acts, evidence = [], []
    while not acts or acts[-1] == "none":
        cs = rec.candidates
        acts.append(_observe_channels(rec, rng, both).action)
        evidence.append(dict(cs.channel_evidence))
    counted = [e for e in evidence if e]
    assert len(evidence) - len(counted) == probation
    k = np.arange(1, len(counted) + 1)
    assert [e["intensity"] for e in counted] == pytest.approx(3.0 * k)
    assert [e["disparity"] for e in counted] == pytest.approx(2.0 * k)
    assert acts[-1] == "adopt" and len(counted) == max(3, CANDIDATE_MIN_UPDATES - probation)


def test_the_filters_views_replace_the_odometrys() -> None:
    """A standing robot whose head turns: the frame's views come from the filter (pan changes),
    not from the zero odometry increment."""
    both = _channels({"intensity": 0.0, "disparity": 0.0}, {"intensity": -10.0, "disparity": -10.0})
    rng = np.random.default_rng(10)
    rec = _recovery()
    _draw_candidates(rec, rng)
    _observe_channels(rec, rng, both, views=1.0)
    assert rec.candidates.seen == 1.0 and rec.candidates.channel_evidence == {}
    _observe_channels(rec, rng, both, views=1.0)
    assert rec.candidates.channel_evidence == pytest.approx({"intensity": 10.0, "disparity": 10.0})

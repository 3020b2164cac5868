"""The challenge of a new belief by its rivals (lino_loc.belief_challenge), without a filter: the
SPRT's arithmetic (views, clipping, the lower bound), who passes and who wins, adoption,
refutation, the rivals kept away from the belief; in the filter, the state waiting for the pass
and a wrong belief refuted."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.belief_challenge import MIN_RIVALS, BeliefChallenge, ChallengeConfig
from lino_loc.lost_detection import CONFIRM_RADIUS_XY, near_pose
from lino_loc.motion_model import MotionModelConfig, OdometryMotionModel

N = 200
STILL = np.zeros(3)
BELIEF = np.array([1.0, 1.0, 0.0])
RIVAL_PLACE = np.array([6.0, 1.0, 0.0])


def _challenge(**kw) -> BeliefChallenge:
    ch = BeliefChallenge(ChallengeConfig(**kw), OdometryMotionModel(MotionModelConfig()))
    ch.start(BELIEF)
    return ch


def _place_loglik(centre: np.ndarray, peak: float, sigma: float = 0.3):
    """log p(y | x): a Gaussian bump of height ``peak`` (nats above 0) around ``centre``."""
    def loglik(x: np.ndarray) -> np.ndarray:
        d2 = np.sum((x[:, :2] - centre[:2]) ** 2, axis=1)
        return peak - 0.5 * d2 / sigma**2
    return loglik


def _observe(ch, rng, ll, loglik, *, views=1.0, floor=-10.0, rivals_at=RIVAL_PLACE):
    def draw(m: int) -> np.ndarray:
        return rivals_at + rng.normal(0.0, [0.1, 0.1, 0.05], size=(m, 3))

    return ch.observe(ll, floor, views, delta=STILL, loglik=loglik, near=lambda x: near_pose(x, BELIEF),
                      draw=draw, n=N, rng=rng)


def test_a_belief_that_explains_the_views_better_passes_after_margin_over_cap_views() -> None:
    rng = np.random.default_rng(0)
    ch = _challenge(margin=8.0, max_view_nats=4.0)
    bad_rivals = _place_loglik(RIVAL_PLACE, peak=-20.0)  # the rivals' place does not fit the views
    assert ch.active and not ch.passed
    _observe(ch, rng, 0.0, bad_rivals)  # the first view draws the rivals (scored against the floor)
    assert ch.rivals is not None and ch.rivals.particles.shape[0] == max(MIN_RIVALS, round(0.1 * N))
    assert ch.evidence == pytest.approx(4.0)  # clipped at max_view_nats
    _observe(ch, rng, 0.0, bad_rivals)
    assert ch.passed and not ch.active and ch.evidence == pytest.approx(8.0)


def test_evidence_counts_independent_views_only() -> None:
    rng = np.random.default_rng(1)
    ch = _challenge(margin=8.0, max_view_nats=4.0)
    loglik = _place_loglik(RIVAL_PLACE, peak=-20.0)
    _observe(ch, rng, 0.0, loglik, views=0.0)  # a camera that did not move: no evidence
    assert ch.evidence == 0.0
    _observe(ch, rng, -1.0, loglik, views=0.25)
    assert ch.evidence == pytest.approx(0.25 * 4.0)


def test_rivals_that_fit_better_hold_the_belief_unconfirmed_at_the_lower_bound() -> None:
    rng = np.random.default_rng(2)
    ch = _challenge(margin=8.0, max_view_nats=4.0, adopt=False, refute_views=0.0)
    good_rivals = _place_loglik(RIVAL_PLACE, peak=0.0)
    for _ in range(20):
        assert _observe(ch, rng, -30.0, good_rivals) is None
    assert ch.evidence == -8.0 and not ch.passed and ch.active and ch.rival_wins == 1
    # the belief must climb the whole width back: 4 views at +4 nats
    poor_rivals = _place_loglik(RIVAL_PLACE, peak=-30.0)
    for k in range(4):
        _observe(ch, rng, 0.0, poor_rivals)
        assert ch.passed == (k == 3)


def test_with_adopt_the_winning_rivals_replace_the_belief() -> None:
    rng = np.random.default_rng(3)
    ch = _challenge(margin=8.0, max_view_nats=4.0, adopt=True)
    good_rivals = _place_loglik(RIVAL_PLACE, peak=0.0)
    outs = [_observe(ch, rng, -30.0, good_rivals) for _ in range(2)]  # the first view draws them
    out = outs[1]
    assert outs[0] is None and out is not None and out.action == "adopt"
    assert out.particles is not None and out.particles.shape == (N, 3)
    assert np.linalg.norm(out.particles[:, :2].mean(axis=0) - RIVAL_PLACE[:2]) < 0.2
    assert not ch.active and not ch.passed  # a new belief: its own challenge at its convergence


def test_rivals_that_win_refute_views_in_a_row_join_the_belief() -> None:
    """E pinned at -margin for ``refute_views`` independent views: a ``join`` verdict with
    ``refute_share`` of n rivals; the streak restarts; views that do not pin E break it."""
    rng = np.random.default_rng(10)
    ch = _challenge(margin=8.0, max_view_nats=4.0, refute_views=5.0, refute_share=0.25)
    good_rivals = _place_loglik(RIVAL_PLACE, peak=0.0)
    out = [_observe(ch, rng, -30.0, good_rivals, views=0.5) for _ in range(14)]
    # view 0 draws the rivals (the floor stands in: E 0 -> -2), then -2 a frame: E reaches -8 at
    # frame 3, pinned from there; 10 frames of 0.5 views pinned = frames 3..12
    joined = [k for k, v in enumerate(out) if v is not None]
    assert joined == [12]
    v = out[12]
    assert v.action == "join" and v.count == round(0.25 * N) and v.particles.shape == (v.count, 3)
    assert np.linalg.norm(v.particles[:, :2].mean(axis=0) - RIVAL_PLACE[:2]) < 0.3
    assert ch.refutations == 1 and ch.active and not ch.passed and ch.evidence == -8.0
    # one view that lifts E off the bound breaks the streak
    _observe(ch, rng, 0.0, _place_loglik(RIVAL_PLACE, peak=-30.0), views=0.5)
    assert ch.evidence > -8.0 and ch._pinned == 0.0
    off = _challenge(refute_views=0.0)
    assert all(_observe(off, rng, -30.0, good_rivals) is None for _ in range(30)) and off.refutations == 0


def test_rivals_near_the_belief_are_not_rivals() -> None:
    rng = np.random.default_rng(4)
    ch = _challenge(margin=8.0, max_view_nats=4.0)
    # every draw of the view lies within the belief's neighbourhood: no rival, the floor stands in
    _observe(ch, rng, -5.0, _place_loglik(BELIEF, 0.0), floor=-7.0, rivals_at=BELIEF)
    assert ch.rivals is None and ch.evidence == pytest.approx(2.0)
    far = BELIEF + np.array([CONFIRM_RADIUS_XY + 0.5, 0.0, 0.0])
    _observe(ch, rng, -5.0, _place_loglik(BELIEF, 0.0), floor=-7.0, rivals_at=far)
    assert ch.rivals is not None and not near_pose(ch.rivals.particles, BELIEF).any()


def test_identical_places_never_pass() -> None:
    """Rivals exactly as good as the belief (identical doors): the ratio is 0 view after view."""
    rng = np.random.default_rng(5)
    ch = _challenge(margin=8.0, max_view_nats=4.0)
    same = _place_loglik(RIVAL_PLACE, peak=-2.0, sigma=100.0)  # flat: every rival fits as the belief
    for _ in range(50):
        _observe(ch, rng, -2.0, same, floor=-2.0)
    assert not ch.passed and abs(ch.evidence) < 1e-3


def test_a_belief_that_spreads_and_gathers_again_at_the_same_place_resumes_its_challenge() -> None:
    rng = np.random.default_rng(9)
    ch = _challenge(margin=8.0, max_view_nats=4.0)
    good_rivals = _place_loglik(RIVAL_PLACE, peak=0.0)
    for _ in range(3):
        _observe(ch, rng, -30.0, good_rivals)
    assert ch.evidence == -8.0
    ch.stop()  # spread for a moment
    assert not ch.active and not ch.passed
    ch.start(BELIEF + [0.3, 0.0, 0.1])  # the same place: the evidence stands
    assert ch.active and ch.evidence == -8.0 and ch.challenges == 1
    ch.stop()
    ch.start(RIVAL_PLACE)  # another place: a new challenge
    assert ch.active and ch.evidence == 0.0 and ch.challenges == 2
    # a challenge passed stays passed for the same place
    for _ in range(2):
        _observe(ch, rng, 0.0, _place_loglik(BELIEF, peak=-30.0))
    assert ch.passed
    ch.stop()
    ch.start(RIVAL_PLACE + [0.2, 0.0, 0.0])
    assert ch.passed and not ch.active


def test_stop_reset_and_waive() -> None:
    ch = _challenge()
    ch.stop()
    assert not ch.active and not ch.passed
    ch.reset()
    ch.start(BELIEF)  # after a reset the same place starts afresh
    assert ch.active and ch.challenges == 2
    ch.waive()
    assert ch.passed and not ch.active
    off = BeliefChallenge(ChallengeConfig(enabled=False), OdometryMotionModel(MotionModelConfig()))
    off.start(BELIEF)
    assert off.passed and not off.active


def test_config_is_checked() -> None:
    with pytest.raises(ValueError):
        ChallengeConfig(margin=0.0)
    with pytest.raises(ValueError):
        ChallengeConfig(refresh=1.5)
    with pytest.raises(ValueError):
        ChallengeConfig(refute_share=0.0)
    with pytest.raises(ValueError):
        ChallengeConfig(refute_views=-1.0)
    assert math.isfinite(ChallengeConfig().margin)


def test_refreshed_rivals_are_scored_only_after_their_probation() -> None:
    """A rival drawn from a view is not scored on the next frames until the camera has moved
    ``probation_views`` views: it must predict a view it was not drawn from."""
    rng = np.random.default_rng(6)
    ch = _challenge(margin=1000.0, refresh=1.0, probation_views=1.0)
    poor = _place_loglik(RIVAL_PLACE, peak=-30.0)
    _observe(ch, rng, 0.0, poor)  # the first draw: scored from the next view
    _observe(ch, rng, 0.0, poor, views=0.5)  # scored, then every rival is replaced (refresh = 1)
    assert ch._seen is not None and np.all(ch._seen == 0.0)
    before = ch.evidence
    _observe(ch, rng, -1.0, poor, views=0.5, floor=-3.0)  # all on probation: the floor stands in
    assert ch.evidence == pytest.approx(before + 0.5 * 2.0)


def test_a_view_no_rival_explains_does_not_break_the_challenge() -> None:
    rng = np.random.default_rng(7)
    ch = _challenge(margin=8.0)
    nothing = lambda x: np.full(x.shape[0], -np.inf)  # noqa: E731
    for _ in range(4):
        _observe(ch, rng, -5.0, nothing)
    assert ch.passed


# --------------------------------------------------------------------- in the filter

def _filter_run(enabled: bool, twin_until: int, frames: int = 60, seed: int = 0, decoy: float = 0.0,
                refute_views: float = 5.0, errors: list[float] | None = None) -> list[str]:
    """A robot driving east at 0.1 m per frame from (2, 2, 0), its belief gathered at the true
    place; each view's mixture has a kernel at the truth and, for the first ``twin_until``
    frames, an equal one at the place 5 m east (identical places); the states per frame (and
    the position errors into ``errors``). ``decoy`` (m): the belief gathered that far west of
    the truth instead, where every view also has a kernel 2 nats less likely than the truth's
    (a place that looks nearly alike)."""
    from lino_loc.particle_filter import AuxiliaryParticleFilter, FilterConfig
    from lino_loc.sensor_model import Bounds, PoseMixture

    bounds = Bounds(0.0, 12.0, 0.0, 4.0)
    motion = OdometryMotionModel(MotionModelConfig(alpha1=0.02, alpha2=0.02, alpha3=0.02, alpha4=0.005))
    cfg = FilterConfig(n_particles=500, challenge=ChallengeConfig(enabled=enabled, refute_views=refute_views))
    cfg.view_fit.enabled = False  # the state of the lost test and the challenge alone
    pf = AuxiliaryParticleFilter(motion, bounds, cfg, rng=np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 1)
    pf.set_particles(np.array([2.0 - decoy, 2.0, 0.0]) + rng.normal(0.0, [0.1, 0.1, 0.05], (500, 3)))
    step = np.array([0.1, 0.0, 0.0])
    states = []
    for k in range(frames):
        truth = np.array([2.1 + 0.1 * k, 2.0, 0.0])
        kernels = np.vstack([truth, truth + [5.0, 0.0, 0.0]]) if k < twin_until else truth[None, :]
        lw = np.zeros(len(kernels))
        if decoy:
            kernels, lw = np.vstack([kernels, truth - [decoy, 0.0, 0.0]]), np.append(lw, -2.0)
        mix = PoseMixture.create(kernels, lw, np.full(len(kernels), 0.3),
                                 np.full(len(kernels), 0.3), outlier_weight=0.01, bounds=bounds)
        pf.update(step, 0.0, mix)
        states.append(pf.state)
        if errors is not None:
            errors.append(float(np.hypot(*(pf.estimate().pose[:2] - truth[:2]))))
    return states


def test_the_filter_calls_a_belief_tracking_only_once_it_beats_its_identical_twin() -> None:
    # without the challenge two views' worth of hits confirm the belief, twin or not
    off = _filter_run(enabled=False, twin_until=40)
    assert "tracking" in off[:20]
    # with it: unconfirmed while the place 5 m east explains every view as well ...
    on = _filter_run(enabled=True, twin_until=40)
    assert "tracking" not in on[:40]
    # ... and confirmed once the views single out the place (the twin stops fitting)
    assert on[-1] == "tracking"


def test_a_belief_gathered_at_the_wrong_place_is_refuted_and_the_filter_finds_the_right_one() -> None:
    """The belief gathered 3 m west of the truth, at a place that explains every view nearly
    as well (a search that settled wrong): its likelihood never drops, so no recovery moves
    it. Refuted by its rivals, it is joined by them, and the filter ends `tracking` at the
    truth; without refutation it stays at the wrong place, honestly `global`."""
    kept: list[float] = []
    states = _filter_run(enabled=True, twin_until=0, frames=80, decoy=3.0, refute_views=0.0, errors=kept)
    assert "tracking" not in states and min(kept[-10:]) > 2.0
    fixed: list[float] = []
    states = _filter_run(enabled=True, twin_until=0, frames=80, decoy=3.0, refute_views=5.0, errors=fixed)
    assert states[-1] == "tracking" and max(fixed[-10:]) < 0.3


def test_refreshing_rivals_some_of_which_drifted_near_the_belief() -> None:
    """Rivals near the belief have no weight; replacing the others must leave a valid set (a
    filter in the simulated service once died here when every weighted rival was replaced)."""
    rng = np.random.default_rng(8)
    ch = _challenge(margin=1000.0, refresh=1.0, probation_views=0.0)
    fit = _place_loglik(RIVAL_PLACE, peak=-1.0)

    def draw(m: int) -> np.ndarray:
        return RIVAL_PLACE + rng.normal(0.0, [0.1, 0.1, 0.05], size=(m, 3))

    def step(near) -> None:
        ch.observe(-1.0, -10.0, 1.0, delta=STILL, loglik=fit, near=near, draw=draw, n=N, rng=rng)

    step(lambda x: near_pose(x, BELIEF))
    for _ in range(5):  # half of the rivals now lie "near the belief"
        step(lambda x: x[:, 0] < RIVAL_PLACE[0])
        assert ch.rivals is not None and np.isfinite(ch.rivals.weights.log).any()


def _misfit_run(after_misfit: bool, twin: bool, seed: int = 0, views: float = 1.0) -> str:
    """A robot driving east at 0.1 m per frame from (2, 2, 0), its belief gathered at the true
    place, the view fit on. Frames 0-29: each view's mixture has one kernel, at the truth;
    frames 30-39: at a place far from it (the views stop fitting: a misfit, reported
    ``global`` or ``lost``); from frame 40 at the truth again and, with ``twin``, as strongly at a place that
    moves as a robot 5 m away facing west would (a view that fits both). The states' first
    letters, one per frame. ``views``: ``after_misfit_views`` (a frame is 0.29 of a view)."""
    from lino_loc.particle_filter import AuxiliaryParticleFilter, FilterConfig
    from lino_loc.sensor_model import Bounds, PoseMixture

    bounds = Bounds(0.0, 12.0, 0.0, 4.0)
    motion = OdometryMotionModel(MotionModelConfig(alpha1=0.02, alpha2=0.02, alpha3=0.02, alpha4=0.005))
    cfg = FilterConfig(n_particles=500, challenge=ChallengeConfig(after_misfit=after_misfit,
                                                                 after_misfit_views=views))
    pf = AuxiliaryParticleFilter(motion, bounds, cfg, rng=np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 1)
    pf.set_particles(np.array([2.0, 2.0, 0.0]) + rng.normal(0.0, [0.1, 0.1, 0.05], (500, 3)))
    states = ""
    for k in range(90):
        truth = np.array([2.1 + 0.1 * k, 2.0, 0.0])
        if 30 <= k < 40:
            kernels = np.array([[1.0, 0.5, math.pi / 2]])
        elif twin and k >= 40:
            kernels = np.vstack([truth, [11.0 - 0.1 * (k - 40), 3.0, math.pi]])
        else:
            kernels = truth[None, :]
        mix = PoseMixture.create(kernels, np.zeros(len(kernels)), np.full(len(kernels), 0.3),
                                 np.full(len(kernels), 0.3), outlier_weight=0.01, bounds=bounds)
        pf.update(np.array([0.1, 0.0, 0.0]), 0.0, mix)
        states += pf.state[0]
    return states


def test_a_refuted_belief_is_tracking_again_only_once_it_beats_its_rivals() -> None:
    """After a misfit the views fit the belief again, and fit a twin as well. Without
    ``after_misfit`` the belief is ``tracking`` again at once; with it, the twin holds it
    unconfirmed (``global``) to the end. Where no twin fits, the re-challenged belief passes
    and is ``tracking`` again."""
    for after in (False, True):
        for twin in (False, True):
            s = _misfit_run(after, twin)
            # the misfit: not tracking (global: within a right belief's chance of misses,
            # lino_loc.view_fit.misfit_limit; lost beyond it)
            assert "t" in s[:30] and set(s[37:41]) <= {"g", "l"}, (after, twin, s)
    assert _misfit_run(False, twin=True)[50:] == "t" * 40
    rechallenged = _misfit_run(True, twin=True)
    assert "t" not in rechallenged[38:] and rechallenged[-40:] == "g" * 40
    passed = _misfit_run(True, twin=False)
    assert "g" in passed[37:45] and passed[60:] == "t" * 30
    # the first misfit frame suffices with after_misfit_views = 0; a misfit shorter than
    # after_misfit_views (10 frames, 2.9 views) is not a refutation
    assert _misfit_run(True, twin=True, views=0.0)[38:] == "g" * 52
    assert _misfit_run(True, twin=True, views=5.0)[50:] == "t" * 40

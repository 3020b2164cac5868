"""A standing robot's views matched jointly with the map's (lino_loc/standing_match.py): the
views kept, the belief moved by the match, and the Localizer's use of it."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from lino_loc.active_vision import ActionEvaluator, ActionValues, ActivePolicy, ActiveVisionConfig
from lino_loc.localizer import Localizer, LocalizerConfig
from lino_loc.motion_model import MotionModelConfig, OdometryMotionModel
from lino_loc.particle_filter import AuxiliaryParticleFilter, FilterConfig
from lino_loc.sensor_model import Bounds, SensorModelConfig
from lino_loc.standing_match import StandingMatch, StandingMatchConfig, cauchy_weights
from lino_loc.subcell_match import SUBCELL_STEPS, SubcellSearch, _vertex, subcell_fit
from lino_loc.view_spread import separation
from tests.test_localizer import Channel, TinyMap, _feature_fn

HEADINGS = 12  # every 30 deg


def _lattice_map(seed: int = 0, d: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Entries (G * HEADINGS, 3) on a 25 cm lattice of 4 x 4 positions and random features."""
    rng = np.random.default_rng(seed)
    h = np.arange(HEADINGS) * 2.0 * math.pi / HEADINGS
    entries = np.array([[x, y, t] for x in np.arange(4) * 0.25 for y in np.arange(4) * 0.25 for t in h])
    return entries, rng.normal(size=(entries.shape[0], d))


def _stored(entries: np.ndarray, features: np.ndarray, xy: tuple[float, float], camera_heading: float) -> np.ndarray:
    """The map's features at position ``xy`` and camera heading ``camera_heading``."""
    dh = np.abs(np.angle(np.exp(1j * (entries[:, 2] - camera_heading))))
    i = np.flatnonzero(np.isclose(entries[:, 0], xy[0]) & np.isclose(entries[:, 1], xy[1]) & (dh < 1e-6))
    return features[int(i[0])]


def _standing(config: StandingMatchConfig | None = None) -> tuple[StandingMatch, np.ndarray, np.ndarray]:
    """The match on :func:`_lattice_map`, at its lattice points (random features have no
    parabola between them: ``subcell`` off unless ``config`` says otherwise)."""
    entries, features = _lattice_map()
    match = StandingMatch.for_map(entries, features, config or StandingMatchConfig(subcell=False))
    assert isinstance(match, StandingMatch)
    return match, entries, features


def _take_views(match: StandingMatch, entries: np.ndarray, features: np.ndarray, xy: tuple[float, float],
                heading: float, pans: list[float], noise: float = 0.01) -> None:
    rng = np.random.default_rng(5)
    step = 2.0 * math.pi / HEADINGS
    for pan in pans:
        y = _stored(entries, features, xy, round((heading + pan) / step) * step)
        match.observe(np.zeros(3), pan, y + noise * rng.normal(size=y.shape))


def test_a_map_of_poses_taken_on_the_way_is_no_lattice() -> None:
    rng = np.random.default_rng(0)
    poses = np.column_stack([rng.uniform(0, 5, 300), rng.uniform(0, 5, 300), rng.uniform(-3, 3, 300)])
    why = StandingMatch.for_map(poses, rng.normal(size=(300, 4)))
    assert isinstance(why, str) and "no lattice" in why and "1.0 headings each" in why
    assert isinstance(StandingMatch.for_map(*_lattice_map()), StandingMatch)


def test_a_robot_survey_whose_stops_drifted_by_millimetres_is_a_lattice() -> None:
    """Each view's measured pose differs from its stop's by the odometry's drift while the robot
    turned (here up to 5 mm, 1 deg): the views of a stop are one position, at their mean."""
    entries, features = _lattice_map()
    rng = np.random.default_rng(3)
    jittered = entries + np.column_stack([rng.uniform(-0.005, 0.005, (entries.shape[0], 2)),
                                          rng.uniform(-0.017, 0.017, entries.shape[0])])
    match = StandingMatch.for_map(jittered, features, StandingMatchConfig(subcell=False))
    assert isinstance(match, StandingMatch)
    assert match.lattice.xy.shape == (16, 2) and match.lattice.n_headings == HEADINGS
    assert np.isfinite(match.lattice.table).all() and match.spacing == pytest.approx(0.25, abs=0.01)
    _take_views(match, entries, features, (0.5, 0.25), 0.0, [0.0, 1.0])
    pose = match.match(np.array([0.4, 0.3, 0.0]))
    assert pose is not None and np.allclose(pose[:2], [0.5, 0.25], atol=0.005)


def test_views_are_kept_while_standing_and_a_moving_base_starts_again() -> None:
    match, _, _ = _standing(StandingMatchConfig(max_views=3, subcell=False))
    y = np.ones(6)
    for pan in (0.0, 0.6, 1.1, 1.6):  # 30 deg headings: four distinct pans
        match.observe(np.zeros(3), pan, y)
    assert match.n_views == 3 and match._pans == [0.6, 1.1, 1.6]  # the most recent
    match.observe(np.zeros(3), 1.15, 2 * y)  # the same stored views as 1.1: replaces it
    assert match.n_views == 3 and match._pans == [0.6, 1.6, 1.15]
    assert np.array_equal(match._views[-1], 2 * y)
    match.observe(np.zeros(3), 0.2, None)  # no image: nothing kept, nothing forgotten
    match.observe(np.zeros(3), 0.2, np.full(6, np.nan))
    assert match.n_views == 3
    match.observe(np.array([0.0, 0.0, 1e-4]), 0.3, y)  # encoder jitter: still standing
    assert match.n_views == 3
    match.observe(np.array([0.05, 0.0, 0.0]), 0.3, y)  # the base moved: this view starts a new set
    assert match.n_views == 1
    match.reset()
    assert match.n_views == 0 and match.match(np.zeros(3)) is None


def test_the_views_taken_name_their_position_and_heading() -> None:
    match, entries, features = _standing()
    heading = 2 * math.pi / HEADINGS * 3
    _take_views(match, entries, features, (0.5, 0.25), heading, [0.0, math.pi / 2, -math.pi / 3])
    pose = match.match(np.array([0.4, 0.3, 0.0]))  # any heading is a candidate
    assert pose is not None and np.allclose(pose, [0.5, 0.25, heading])
    assert match.match(np.array([9.0, 9.0, 0.0])) is None  # no map position near the estimate


def test_recentre_moves_the_neighbourhood_by_the_match_minus_the_estimate() -> None:
    match, entries, features = _standing()
    _take_views(match, entries, features, (0.5, 0.25), 0.0, [0.0, 1.0])
    rng = np.random.default_rng(2)
    est = np.array([0.42, 0.33, 0.1])
    near = est + rng.normal(scale=[0.05, 0.05, 0.05], size=(80, 3))
    far = np.column_stack([rng.uniform(3, 4, 20), rng.uniform(3, 4, 20), rng.uniform(-3, 3, 20)])
    particles = np.vstack([near, far])
    weights = np.full(100, 0.01)
    moved = match.recentre(particles, weights, est)
    assert moved is not None and match.matches == 1
    assert np.allclose(moved[:80, :2], near[:, :2] + np.array([0.5, 0.25]) - est[:2])
    assert np.array_equal(moved[:80, 2], near[:, 2])  # the heading is the filter's
    assert np.array_equal(moved[80:], far)
    # the filter has not found the neighbourhood: half the weight elsewhere is too much
    weights = np.r_[np.full(80, 0.4 / 80), np.full(20, 0.6 / 20)]
    assert match.recentre(particles, weights, est) is None and match.matches == 1


def _filter(n: int = 200) -> AuxiliaryParticleFilter:
    bounds = Bounds.from_poses(np.array([[-1.0, -1.0, 0.0], [2.0, 2.0, 0.0]]), 0.0)
    return AuxiliaryParticleFilter(OdometryMotionModel(MotionModelConfig()), bounds, FilterConfig(n_particles=n, seed=1),
                                   rng=np.random.default_rng(1))


def test_step_moves_the_filter_s_belief_and_keeps_its_weights() -> None:
    match, entries, features = _standing()
    pf = _filter()
    pf.set_pose([0.4, 0.35, 0.0], np.diag([0.03**2, 0.03**2, 0.02**2]))
    weights = pf.weights
    before = pf.particles.copy()
    y = _stored(entries, features, (0.5, 0.25), 0.0)
    assert not match.step(pf, np.zeros(3), 0.0, y)  # one view: the filter's own judgement stands
    assert np.array_equal(pf.particles, before)
    pan = 2 * 2 * math.pi / HEADINGS
    assert match.step(pf, np.zeros(3), pan, _stored(entries, features, (0.5, 0.25), pan))
    shift = pf.particles[:, :2] - before[:, :2]
    assert np.allclose(shift, shift[0]) and np.array_equal(pf.weights, weights)
    assert np.allclose(pf.estimate().pose[:2], [0.5, 0.25], atol=1e-9)
    with pytest.raises(ValueError, match="poses for 200 particles"):
        pf.move_particles(np.zeros((3, 3)))


def test_a_driving_robot_is_never_moved() -> None:
    """Every frame's view is kept as the first of a new set, but one view taken on the way is
    no standing robot's: the belief stays where the filter put it. Once it stands, the views
    of two pans move it (one pan is a head held still)."""
    match, entries, features = _standing()
    pf = _filter()
    pf.set_pose([0.4, 0.35, 0.0], np.diag([0.03**2, 0.03**2, 0.02**2]))
    before = pf.particles.copy()
    y = _stored(entries, features, (0.5, 0.25), 0.0)
    for _ in range(3):
        assert not match.step(pf, np.array([0.05, 0.0, 0.0]), 0.0, y)
        assert match.n_views == 1
    assert np.array_equal(pf.particles, before) and match.matches == 0
    assert not match.step(pf, np.zeros(3), 0.0, y)  # it stops: the view at that pan, now a standing one's
    assert match.n_views == 1 and match.matches == 0  # one pan: a head held still adds no view
    pan = 2 * math.pi / HEADINGS
    assert match.step(pf, np.zeros(3), pan, _stored(entries, features, (0.5, 0.25), pan))
    assert match.n_views == 2 and match.matches == 1


def test_while_the_match_would_act_it_chooses_the_view_farthest_from_those_kept() -> None:
    """``action_values``: the spread rule over the pans kept while the belief is gathered;
    None without views, for a spread belief, on a driving base (its views are not joined),
    after an operator's pose, or with ``choose_views`` off (the filter's H(u) decides then)."""
    match, entries, features = _standing(StandingMatchConfig(subcell=False))
    pf = _filter()
    pans = np.linspace(-2.6, 2.6, 22)
    pf.set_pose([0.4, 0.35, 0.0], np.diag([0.03**2, 0.03**2, 0.02**2]))
    assert match.action_values(pf.particles, pf.weights, pf.estimate().pose, pans) is None  # no views yet
    _take_views(match, entries, features, (0.5, 0.25), 0.0, [0.0, 2.6])
    v = match.action_values(pf.particles, pf.weights, pf.estimate().pose, pans)
    assert v is not None
    np.testing.assert_allclose(v.gain, separation([0.0, 2.6], pans))
    spread = np.column_stack([np.linspace(0.0, 3.0, 200), np.full(200, 0.35), np.zeros(200)])
    assert match.action_values(spread, np.full(200, 1 / 200), np.array([0.4, 0.35, 0.0]), pans) is None
    driving, _, _ = _standing(StandingMatchConfig(subcell=False))
    driving.observe(np.array([0.05, 0.0, 0.0]), 0.0, features[0])  # a moving base's view: not joined
    assert driving.n_views == 1
    assert driving.action_values(pf.particles, pf.weights, pf.estimate().pose, pans) is None
    match.hold()
    assert match.action_values(pf.particles, pf.weights, pf.estimate().pose, pans) is None
    off, entries, features = _standing(StandingMatchConfig(subcell=False, choose_views=False))
    _take_views(off, entries, features, (0.5, 0.25), 0.0, [0.0, 2.6])
    assert off.action_values(pf.particles, pf.weights, pf.estimate().pose, pans) is None


class _CountingEvaluator(ActionEvaluator):
    """The H(u) evaluator, counting its evaluations."""

    calls = 0

    def evaluate(self, *args: Any, **kwargs: Any) -> ActionValues:
        self.calls += 1
        return super().evaluate(*args, **kwargs)


def test_a_standing_localizer_s_policy_looks_away_from_its_views() -> None:
    """The service's wiring: ``Localizer.view_values`` feeds ``ActivePolicy.decide``, which then
    commands the pan farthest from the views taken; with the match off the filter's H(u)
    decides (the evaluator is called)."""
    m, f_img = _grid_world()
    truth = np.array([1.0, 0.75, 0.0])
    for cfg in (StandingMatchConfig(), StandingMatchConfig(choose_views=False)):
        loc = Localizer(m, LocalizerConfig(filter=FilterConfig(n_particles=300, seed=3),
                                           sensor=SensorModelConfig(j=10), standing_match=cfg))
        loc.set_pose(truth, np.diag([0.03**2, 0.03**2, 0.02**2]), confirmed=False)
        for pan in (0.0, 0.5):
            loc.update(np.zeros(3), pan, f_img(truth + [0.0, 0.0, pan])[0])
        evaluator = _CountingEvaluator(loc.sensor_model("intensity"), ActiveVisionConfig())
        policy = ActivePolicy(evaluator)
        p, lw = loc.belief()
        d = policy.decide(p, lw, state="global", log_likelihood=-1.0, pan=0.5, moving=False, now=10.0,
                          view_values=loc.view_values)
        assert d.values is not None
        if cfg.choose_views:
            assert evaluator.calls == 0 and d.command == pytest.approx(-2.6)  # farthest from 0.0 and 0.5
        else:
            assert evaluator.calls == 1 and d.values.current_entropy > 0.0  # H(u), nats


def test_a_lost_belief_forgets_the_views() -> None:
    match, entries, features = _standing()
    lost = SimpleNamespace(estimate=lambda: SimpleNamespace(state="lost", pose=np.zeros(3)),
                           particles=np.zeros((4, 3)), weights=np.full(4, 0.25),
                           move_particles=lambda p: pytest.fail("a lost belief was moved"))
    assert not match.step(lost, np.zeros(3), 0.0, np.ones(6))
    assert match.n_views == 0


def _grid_world() -> tuple[TinyMap, object]:
    """The Localizer tests' feature world on a 25 cm lattice of 12 headings."""
    xs, ys = np.arange(0, 2.01, 0.25), np.arange(0, 2.01, 0.25)
    ts = -np.pi + np.arange(HEADINGS) * 2 * np.pi / HEADINGS
    X, Y, T = np.meshgrid(xs, ys, ts, indexing="ij")
    poses = np.column_stack([X.ravel(), Y.ravel(), T.ravel()])
    f_img = _feature_fn(16, 0)
    proj = np.random.default_rng(9).normal(size=(10, 16)) / np.sqrt(16)
    return TinyMap(poses, {"intensity": Channel(f_img(poses) @ proj.T, proj)}), f_img


def test_a_standing_localizer_is_placed_by_its_views() -> None:
    """A recalled belief 15 cm off, the robot standing at a map position and the head turning: with the
    match at the lattice's points the estimate is that map position; between them (the
    default) it stays nearer than the filter alone leaves it."""
    m, f_img = _grid_world()
    truth = np.array([1.0, 0.75, 0.0])
    errors = {}
    for name, cfg in {"off": StandingMatchConfig(enabled=False), "points": StandingMatchConfig(subcell=False),
                      "default": StandingMatchConfig()}.items():
        loc = Localizer(m, LocalizerConfig(filter=FilterConfig(n_particles=300, seed=3),
                                           sensor=SensorModelConfig(j=10), standing_match=cfg))
        assert (loc.standing is not None) == cfg.enabled
        loc.set_pose(truth + [0.12, -0.09, 0.02], np.diag([0.03**2, 0.03**2, 0.02**2]), confirmed=False)
        rng = np.random.default_rng(4)
        for pan in (0.0, 0.5, 1.0, -0.5, -1.0):
            est = loc.update(np.zeros(3), pan, f_img(truth + [0.0, 0.0, pan])[0] + rng.normal(0, 0.02, 16))
        errors[name] = float(np.hypot(*(est.pose[:2] - truth[:2])))
        if cfg.enabled:
            assert loc.standing is not None and loc.standing.matches >= 1
    assert errors["points"] < 1e-6
    assert errors["default"] < errors["off"] and errors["off"] > 0.01, errors


def _linear_lattice(missing: tuple[float, float] | None = None) -> tuple[np.ndarray, Any]:
    """Entries on a 5 x 5 lattice every 25 cm (without the position ``missing``) and features
    linear in the position (x, y) and turning with the heading: bilinear interpolation between
    the lattice points is exact."""
    h = np.arange(HEADINGS) * 2.0 * math.pi / HEADINGS
    entries = np.array([[x, y, t] for x in np.arange(5) * 0.25 for y in np.arange(5) * 0.25 for t in h
                        if missing is None or not np.allclose((x, y), missing)])

    def feats(xy: np.ndarray, t: np.ndarray) -> np.ndarray:
        return np.column_stack([xy[:, 0], xy[:, 1], 3 * np.cos(t), 3 * np.sin(t)])

    return entries, feats


@pytest.mark.parametrize("subcell", [False, True])
@pytest.mark.parametrize("truth", [(0.575, 0.45), (0.57, 0.46)])
def test_subcell_places_the_position_where_the_interpolated_views_match(subcell: bool, truth: tuple[float, float]) -> None:
    """With features linear in the position, the interpolated views match exactly at the
    true position: found exactly on the search grid (0.575, 0.45: 0.3 and -0.2 spacings from
    the lattice point) and between its points (0.57, 0.46: the cost along each axis is a
    quadratic that the refinement's parabola meets exactly, the features along x and y
    independent); without ``subcell`` the match is the nearest lattice point."""
    entries, feats = _linear_lattice()
    h = np.arange(HEADINGS) * 2.0 * math.pi / HEADINGS
    match = StandingMatch.for_map(entries, feats(entries[:, :2], entries[:, 2]), StandingMatchConfig(subcell=subcell))
    assert isinstance(match, StandingMatch) and match.spacing == pytest.approx(0.25)
    for pan in (0.0, math.pi / 2, -math.pi / 3):
        match.observe(np.zeros(3), pan, feats(np.array([truth]), np.array([h[2] + pan]))[0])
    pose = match.match(np.array([0.45, 0.5, 0.0]))
    assert pose is not None and pose[2] == pytest.approx(h[2])
    if not subcell:
        assert np.allclose(pose[:2], [0.5, 0.5], atol=1e-9)
    else:
        assert np.allclose(pose[:2], truth, atol=1e-9), pose


def test_subcell_interpolates_each_view_at_its_own_camera_heading() -> None:
    """Pans that are no multiples of the map's heading step: each view's camera heading falls
    at its own fraction between two stored headings. With features linear in the position and
    in the camera heading, interpolating each view there is exact, so the pose is found on
    the search grid exactly; rounding the pans to the heading lattice would misplace it."""
    step = 2.0 * math.pi / HEADINGS
    h = np.arange(HEADINGS) * step
    entries = np.array([[x, y, t] for x in np.arange(5) * 0.25 for y in np.arange(5) * 0.25 for t in h])

    def feats(xy: np.ndarray, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        return np.column_stack([xy[:, 0] + 0.3 * t, xy[:, 1] - 0.2 * t, t])

    match = StandingMatch.for_map(entries, feats(entries[:, :2], entries[:, 2]))
    assert isinstance(match, StandingMatch)
    truth = np.array([0.575, 0.45, h[2]])
    for pan in (0.3 * step, 1.7 * step, -1.3 * step):
        match.observe(np.zeros(3), pan, feats(truth[None, :2], np.array([truth[2] + pan]))[0])
    pose = match.match(np.array([0.5, 0.5, h[2]]))
    assert pose is not None and np.allclose(pose, truth, atol=1e-9), pose


@pytest.mark.parametrize("candidates", [1, 3])
def test_the_best_fit_among_the_candidate_lattice_points_wins(candidates: int) -> None:
    """A lattice point away from the truth whose stored views nearly equal the views taken (a
    distractor) matches best on the lattice; between the lattice points around the truth the
    interpolated views match exactly. With one candidate the match stays at the distractor;
    with three, the truth's neighbourhood is refined too and its exact fit wins."""
    entries, feats = _linear_lattice()
    truth = np.array([0.575, 0.45])
    distractor = np.array([0.0, 0.5])  # within 50 cm of the estimate, outside the truth's 3 x 3

    def with_bump(xy: np.ndarray, t: np.ndarray) -> np.ndarray:
        f = np.column_stack([feats(xy, t), np.zeros(len(xy))])
        at = np.all(np.abs(xy - distractor) < 1e-9, axis=1)
        f[at, :2] = truth
        f[at, 4] = 0.01  # nearly the truth's views, but not quite
        return f

    h = np.arange(HEADINGS) * 2.0 * math.pi / HEADINGS
    match = StandingMatch.for_map(entries, with_bump(entries[:, :2], entries[:, 2]),
                                  # unweighed: the bump's feature barely changes, weighed it would count most
                                  StandingMatchConfig(candidates=candidates, weigh_features=False))
    assert isinstance(match, StandingMatch)
    for pan in (0.0, math.pi / 2, -math.pi / 3):
        match.observe(np.zeros(3), pan, np.append(feats(truth[None], np.array([h[2] + pan]))[0], 0.0))
    pose = match.match(np.array([0.45, 0.5, h[2]]))
    assert pose is not None
    if candidates == 1:
        assert np.hypot(*(pose[:2] - truth)) > 0.25, pose
    else:
        assert np.allclose(pose[:2], truth, atol=1e-9) and pose[2] == pytest.approx(h[2]), pose


def test_the_fit_over_several_candidates_is_the_best_of_their_own_fits() -> None:
    """``subcell_fit`` searches the candidates together: its pose and cost are those of the
    candidate whose own fit costs least (the first of equal ones)."""
    entries, feats = _linear_lattice()
    match = StandingMatch.for_map(entries, feats(entries[:, :2], entries[:, 2]) + 0.05 * np.random.default_rng(2).normal(
        size=(entries.shape[0], 4)))
    assert isinstance(match, StandingMatch)
    step = 2.0 * math.pi / HEADINGS
    pans = np.array([0.3 * step, 2.2 * step, -1.6 * step])
    views = feats(np.array([[0.6, 0.4]] * 3), 0.2 + pans)
    poses = np.array([[0.5, 0.5, step], [0.25, 0.5, 0.0], [0.75, 0.25, 2 * step]])
    one = [subcell_fit(match.lattice, p, pans, views) for p in poses]
    pose, cost, _ = subcell_fit(match.lattice, poses, pans, views)
    best = int(np.argmin([f.cost for f in one]))
    assert cost == pytest.approx(one[best].cost, rel=1e-12) and np.allclose(pose, one[best].pose)
    assert len({round(f.cost, 9) for f in one}) == 3  # the candidates' own fits differ


def _interpolated_cost(lattice: Any, pose: np.ndarray, pans: np.ndarray, views: np.ndarray) -> float:
    """``sum_i |y_i - y(p, o + u_i)|^2`` with ``y`` interpolated directly from the lattice's
    table: bilinear over the lattice positions at unit tents in x and y, linear between the
    two stored headings around each camera heading (inf where a weighted view is missing)."""
    sp = 0.25
    total = 0.0
    for pan, y_i in zip(pans, views, strict=True):
        f = (pose[2] + pan) / lattice.heading_step
        h0 = math.floor(f)
        pred = np.zeros(y_i.shape)
        for g, (gx, gy) in enumerate(lattice.xy):
            w_pos = max(0.0, 1 - abs(pose[0] - gx) / sp) * max(0.0, 1 - abs(pose[1] - gy) / sp)
            for h, w_h in ((h0, 1.0 - (f - h0)), (h0 + 1, f - h0)):
                if w_pos * w_h > 0.0:
                    stored = lattice.table[g, h % lattice.n_headings]
                    if np.isnan(stored).any():
                        return math.inf
                    pred += w_pos * w_h * stored
        total += float(np.sum((lattice.weigh(y_i) - pred) ** 2))
    return total


def _noisy_views_on_a_noisy_lattice(seed: int) -> tuple[StandingMatch, np.ndarray, np.ndarray, float]:
    """A match on :func:`_linear_lattice` with noise on the map's features, three noisy views
    of (0.55, 0.42) at pans off the heading lattice, and the heading step."""
    entries, feats = _linear_lattice()
    rng = np.random.default_rng(seed)
    match = StandingMatch.for_map(entries, feats(entries[:, :2], entries[:, 2]) + 0.1 * rng.normal(
        size=(entries.shape[0], 4)))
    assert isinstance(match, StandingMatch)
    step = 2.0 * math.pi / HEADINGS
    pans = np.array([0.0, 1.3 * step, -2.6 * step])
    views = feats(np.array([[0.55, 0.42]] * 3), 0.2 + pans) + 0.05 * rng.normal(size=(3, 4))
    return match, pans, views, step


def test_the_fit_is_the_least_directly_interpolated_cost_on_the_search_grid() -> None:
    """``subcell_fit``'s pose and cost against a direct computation: its cost is the directly
    interpolated cost at its pose, and no pose of the search grid around the candidate costs
    less (the separable quadratic form and the batched heading interpolation change nothing;
    the refinement between the grid's points only lowers it)."""
    match, pans, views, step = _noisy_views_on_a_noisy_lattice(4)
    start = np.array([0.5, 0.5, 0.0])
    pose, cost, _ = subcell_fit(match.lattice, start, pans, views)
    assert cost == pytest.approx(_interpolated_cost(match.lattice, pose, pans, views), rel=1e-9)
    offsets = np.linspace(-1.0, 1.0, 2 * SUBCELL_STEPS + 1) * 0.25
    grid = [_interpolated_cost(match.lattice, np.array([0.5 + dx, 0.5 + dy, t * step]), pans, views)
            for dx in offsets for dy in offsets for t in np.linspace(-0.5, 0.5, 5)]
    assert cost <= min(grid) * (1 + 1e-12)
    assert not all(np.isclose(delta, offsets, rtol=0.0, atol=1e-12).any() for delta in pose[:2] - start[:2]), pose


def _per_view_residuals(lattice: Any, pose: np.ndarray, pans: np.ndarray, views: np.ndarray) -> np.ndarray:
    """Each view's own :func:`_interpolated_cost` at ``pose``."""
    return np.array([_interpolated_cost(lattice, pose, pans[i:i + 1], views[i:i + 1]) for i in range(len(pans))])


def test_the_weighed_fit_is_the_least_weighed_cost_and_reports_each_view_s_residual() -> None:
    """With view weights w, ``subcell_fit``'s cost is ``sum_i w_i r_i`` at its pose, with r_i
    each view's directly interpolated squared residual (reported unweighted), and no pose of
    the search grid has a lower weighed cost."""
    match, pans, views, step = _noisy_views_on_a_noisy_lattice(6)
    w = np.array([1.0, 0.2, 0.7])
    start = np.array([0.5, 0.5, 0.0])
    pose, cost, residuals = subcell_fit(match.lattice, start, pans, views, w)
    direct = _per_view_residuals(match.lattice, pose, pans, views)
    assert np.allclose(residuals, direct, rtol=1e-9) and cost == pytest.approx(float(w @ direct), rel=1e-9)
    offsets = np.linspace(-1.0, 1.0, 2 * SUBCELL_STEPS + 1) * 0.25
    grid = [float(w @ _per_view_residuals(match.lattice, np.array([0.5 + dx, 0.5 + dy, t * step]), pans, views))
            for dx in offsets[::4] for dy in offsets[::4] for t in np.linspace(-0.5, 0.5, 5)]
    assert cost <= min(grid) * (1 + 1e-9)
    unweighed = subcell_fit(match.lattice, start, pans, views)
    assert unweighed.cost == pytest.approx(float(np.sum(_per_view_residuals(match.lattice, unweighed.pose, pans,
                                                                           views))), rel=1e-9)


def test_the_robust_match_is_two_fits_the_second_weighed_by_the_first() -> None:
    """``match`` with ``robust_scale`` against the two fits made from scratch: the first
    unweighed over the best candidates, the second over the candidates ranked with the
    Cauchy weights of the first's residuals. One search fitted with several weights gives
    what a search made for each gives."""
    entries, feats = _linear_lattice()
    rng = np.random.default_rng(9)
    cfg = StandingMatchConfig(robust_scale=0.5)
    match = StandingMatch.for_map(entries, feats(entries[:, :2], entries[:, 2]) + 0.2 * rng.normal(
        size=(entries.shape[0], 4)), cfg)
    assert isinstance(match, StandingMatch)
    lat = match.lattice
    pans = np.array([0.0, 1.7, -1.1, 2.6])
    views = feats(np.array([[0.52, 0.41]] * 4), 0.1 + pans) + 0.3 * rng.normal(size=(4, 4))
    for pan, y in zip(pans, views, strict=True):
        match.observe(np.zeros(3), float(pan), y)
    est = np.array([0.5, 0.5, 0.1])
    first = subcell_fit(lat, np.stack(lat.best_poses(est, pans, views, cfg.candidates)), pans, views)
    w = cauchy_weights(first.residuals, cfg.robust_scale * lat.s2)
    assert np.ptp(w) > 0.05  # the views are weighed unlike
    second = subcell_fit(lat, np.stack(lat.best_poses(est, pans, views, cfg.candidates, w)), pans, views, w)
    pose = match.match(est)
    assert pose is not None and np.allclose(pose, second.pose, atol=1e-12)
    search = SubcellSearch(lat, np.stack(lat.best_poses(est, pans, views, cfg.candidates)), pans, views)
    for weights in (None, w, np.array([1.0, 0.0, 0.5, 2.0])):
        again = subcell_fit(lat, search.poses, pans, views, weights)
        got = search.fit(weights)
        assert np.allclose(got.pose, again.pose, atol=1e-12) and got.cost == pytest.approx(again.cost, rel=1e-12)
        assert np.allclose(got.residuals, again.residuals, rtol=1e-12)


def test_the_parabola_s_vertex_between_grid_points() -> None:
    """``_vertex``: the vertex of a * (t - t0)^2 + b sampled at -1, 0, 1 is t0 (|t0| <= 1/2),
    clipped to half a step; 0 without a neighbour or without curvature."""
    for t0 in (-0.5, -0.2, 0.0, 0.37, 0.5):
        lo, mid, hi = (2.0 * (t - t0) ** 2 + 1.0 for t in (-1.0, 0.0, 1.0))
        assert _vertex(lo, mid, hi) == pytest.approx(t0, abs=1e-12)
    assert _vertex(3.0, 1.0, 1.0 + 1e-9) == pytest.approx(0.5, abs=1e-6)
    assert _vertex(math.inf, 1.0, 2.0) == 0.0 and _vertex(1.0, 1.0, 1.0) == 0.0


def test_cauchy_weights() -> None:
    """``1 / (1 + r / scale)``: 1 for a perfect fit, 1/2 at the scale, 0 for an infinite residual."""
    assert np.allclose(cauchy_weights([0.0, 2.0, 6.0, math.inf], 2.0), [1.0, 0.5, 0.25, 0.0])


def _views_with_one_spoiled(match: StandingMatch, feats: Any, truth: np.ndarray, heading: float,
                            spoil: float) -> None:
    """Four views at ``truth``; the second's position features moved by ``spoil`` (something
    the map does not hold in view)."""
    for i, pan in enumerate((0.0, math.pi / 2, -math.pi / 3, 0.8 * math.pi)):
        y = feats(truth[None], np.array([heading + pan]))[0]
        match.observe(np.zeros(3), pan, y + (np.array([spoil, spoil, 0.0, 0.0]) if i == 1 else 0.0))


@pytest.mark.parametrize("spoil", [0.0, 0.4])
def test_a_view_that_fits_badly_pulls_the_match_less(spoil: float) -> None:
    """One of four views spoiled: fitted alike, the views are placed 14 cm off the truth;
    weighed by their fit (``robust_scale``), within 5 cm. Unspoiled views fit alike, so their
    weights are equal and both matches are the same."""
    entries, feats = _linear_lattice()
    truth, heading = np.array([0.55, 0.45]), 0.3
    poses = []
    for scale in (0.0, 0.5):
        match = StandingMatch.for_map(entries, feats(entries[:, :2], entries[:, 2]),
                                      StandingMatchConfig(robust_scale=scale))
        assert isinstance(match, StandingMatch)
        _views_with_one_spoiled(match, feats, truth, heading, spoil)
        pose = match.match(np.array([0.5, 0.5, heading]))
        assert pose is not None
        poses.append(pose)
    errors = [float(np.hypot(*(p[:2] - truth))) for p in poses]
    if spoil == 0.0:
        assert np.allclose(poses[0], poses[1], atol=1e-9) and errors[0] < 1e-6
    else:
        assert errors[0] > 0.1 and errors[1] < 0.05, errors


def test_subcell_does_not_interpolate_from_a_missing_lattice_point() -> None:
    """A lattice point missing next to the match (a wall): the positions that would take its
    views are not tried, so the truth beyond the half cell next to it is not reached and the
    match stays where the views it can interpolate fit best."""
    entries, feats = _linear_lattice(missing=(0.75, 0.5))
    h = np.arange(HEADINGS) * 2.0 * math.pi / HEADINGS
    match = StandingMatch.for_map(entries, feats(entries[:, :2], entries[:, 2]))
    assert isinstance(match, StandingMatch)
    truth = (0.6, 0.5)  # towards the missing point (0.75, 0.5)
    for pan in (0.0, math.pi / 2):
        match.observe(np.zeros(3), pan, feats(np.array([truth]), np.array([h[2] + pan]))[0])
    pose = match.match(np.array([0.5, 0.5, 0.0]))
    assert pose is not None and pose[0] == pytest.approx(0.5) and pose[1] == pytest.approx(0.5)
    complete = StandingMatch.for_map(*_lattice_arrays(feats))
    assert isinstance(complete, StandingMatch)
    for pan in (0.0, math.pi / 2):
        complete.observe(np.zeros(3), pan, feats(np.array([truth]), np.array([h[2] + pan]))[0])
    found = complete.match(np.array([0.5, 0.5, 0.0]))
    assert found is not None and np.allclose(found[:2], truth, atol=1e-9)


def _lattice_arrays(feats: Any) -> tuple[np.ndarray, np.ndarray]:
    entries, _ = _linear_lattice()
    return entries, feats(entries[:, :2], entries[:, 2])


def test_an_operator_s_pose_holds_until_the_robot_moves() -> None:
    """A confirmed pose (an operator's) is not moved by the views of the place where it was
    given; once the base has moved and stopped again, the match places the belief."""
    m, f_img = _grid_world()
    loc = Localizer(m, LocalizerConfig(filter=FilterConfig(n_particles=300, seed=3), sensor=SensorModelConfig(j=10),
                                       standing_match=StandingMatchConfig(subcell=False)))
    truth = np.array([1.0, 0.75, 0.0])
    loc.set_pose(truth + [0.12, -0.09, 0.02], np.diag([0.03**2, 0.03**2, 0.02**2]))
    rng = np.random.default_rng(4)
    for pan in (0.0, 0.5, 1.0):
        loc.update(np.zeros(3), pan, f_img(truth + [0.0, 0.0, pan])[0] + rng.normal(0, 0.02, 16))
    assert loc.standing is not None and loc.standing.matches == 0
    truth = np.array([1.25, 0.75, 0.0])  # it drives 25 cm ahead and stops
    est = loc.update(np.array([0.25, 0.0, 0.0]), 0.0, f_img(truth)[0] + rng.normal(0, 0.02, 16))
    for pan in (0.5, 1.0):
        est = loc.update(np.zeros(3), pan, f_img(truth + [0.0, 0.0, pan])[0] + rng.normal(0, 0.02, 16))
    assert loc.standing.matches >= 1 and np.hypot(*(est.pose[:2] - truth[:2])) < 1e-6


def _twin_rooms(differ: float) -> tuple[StandingMatch, np.ndarray, np.ndarray]:
    """Two 3 x 3 blocks of lattice positions 3 m apart whose views are the same but for the
    second's at camera headings 0 and 90 deg, ``differ`` off in every feature (features
    unweighed, on the lattice): places that look alike but for two views."""
    rng = np.random.default_rng(8)
    h = np.arange(HEADINGS) * 2.0 * math.pi / HEADINGS
    block = [(x, y) for x in np.arange(3) * 0.25 for y in np.arange(3) * 0.25]
    feats = {(xy, i): rng.normal(size=4) for xy in block for i in range(HEADINGS)}
    entries, features = [], []
    for dx in (0.0, 3.0):
        for xy in block:
            for i, t in enumerate(h):
                entries.append([xy[0] + dx, xy[1], t])
                features.append(feats[(xy, i)] + (differ if dx and i in (0, HEADINGS // 4) else 0.0))
    match = StandingMatch.for_map(np.array(entries), np.array(features),
                                  StandingMatchConfig(subcell=False, weigh_features=False))
    assert isinstance(match, StandingMatch)
    return match, np.array(entries), np.array(features)


def test_beyond_is_every_heading_of_the_positions_farther_than_the_distance() -> None:
    match, _, _ = _twin_rooms(1.0)
    g, o = match.lattice.beyond(np.array([0.25, 0.25, 1.0]), 1.0)
    far = np.hypot(match.lattice.xy[:, 0] - 0.25, match.lattice.xy[:, 1] - 0.25) > 1.0
    assert np.array_equal(g, np.flatnonzero(far)) and g.size == 9 and np.all(match.lattice.xy[g, 0] >= 3.0)
    assert np.array_equal(o, np.arange(HEADINGS))


def _twin_views(match: StandingMatch, entries: np.ndarray, features: np.ndarray, heading: float) -> None:
    """Views at the second block's (3.25, 0.25) at robot ``heading``, pans 0 and 90 deg and 60 deg
    (camera headings 0, 90 and 60 deg: the two that differ and one that does not)."""
    for pan in (0.0, math.pi / 2, math.pi / 3):
        match.observe(np.zeros(3), pan, _stored(entries, features, (3.25, 0.25), heading + pan))


@pytest.mark.parametrize("rivals", [False, True])
def test_an_unconfirmed_belief_goes_to_the_far_place_whose_views_fit_better(rivals: bool) -> None:
    """The views are the second block's; the belief gathered at the first block's twin of the
    place, at another heading. No match near it fits the views that differ; with rivals
    (an unconfirmed belief), the far place takes the particles near the estimate: their spread
    turned by the far heading minus the estimate's, the others left alone."""
    match, entries, features = _twin_rooms(3.0)
    _twin_views(match, entries, features, 0.0)
    rng = np.random.default_rng(2)
    est = np.array([0.27, 0.22, 0.5])
    near = est + rng.normal(scale=[0.05, 0.05, 0.05], size=(80, 3))
    others = np.column_stack([rng.uniform(1.5, 2.0, 20), rng.uniform(0.0, 0.5, 20), rng.uniform(-3, 3, 20)])
    moved = match.recentre(np.vstack([near, others]), np.full(100, 0.01), est, rivals=rivals)
    assert moved is not None and match.matches == 1 and match.relocations == int(rivals)
    assert np.array_equal(moved[80:], others)
    if not rivals:  # the near match: shifted within the first block, the heading the filter's
        shift = moved[:80, :2] - near[:, :2]
        assert np.allclose(shift, shift[0]) and np.all(moved[:80, 0] < 1.0)
        assert np.array_equal(moved[:80, 2], near[:, 2])
        return
    turn = -0.5
    off = near[:, :2] - est[:2]
    rotated = np.column_stack([math.cos(turn) * off[:, 0] - math.sin(turn) * off[:, 1],
                               math.sin(turn) * off[:, 0] + math.cos(turn) * off[:, 1]])
    assert np.allclose(moved[:80, :2], np.array([3.25, 0.25]) + rotated)
    assert np.allclose(np.angle(np.exp(1j * (moved[:80, 2] - near[:, 2]))), turn)
    assert np.allclose(match.match(est, rivals=True), [3.25, 0.25, 0.0])


def test_the_far_place_must_fit_better_by_the_margin() -> None:
    """Near cost minus far cost is exactly the two differing views' 2 x 4 x differ^2 (the far
    place fits the noiseless views exactly): a margin below its ratio to 2 s^2 relocates, one
    above does not."""
    differ = 0.8
    base, entries, features = _twin_rooms(differ)
    nats = 2 * 4 * differ**2 / (2.0 * base.lattice.s2)
    est = np.array([0.25, 0.25, 0.0])
    for margin, far in ((0.98 * nats, True), (1.02 * nats, False)):
        match = StandingMatch(base.lattice, base.config.model_copy(update={"relocate_margin": margin}))
        _twin_views(match, entries, features, 0.0)
        pose = match.match(est, rivals=True)
        assert pose is not None and (pose[0] > 3.0) == far
    off = StandingMatch(base.lattice, base.config.model_copy(update={"relocate": False}))
    _twin_views(off, entries, features, 0.0)
    assert off.match(est, rivals=True)[0] < 1.0


@pytest.mark.parametrize("state", ["global", "tracking"])
def test_only_an_unconfirmed_belief_is_relocated(state: str) -> None:
    """The filter's confirmed belief (``tracking``) stays near its estimate, where the views
    still place it; an unconfirmed one (``global``) goes to the far place."""
    match, entries, features = _twin_rooms(3.0)
    rng = np.random.default_rng(3)
    pf = SimpleNamespace(particles=np.array([0.25, 0.25, 0.0]) + rng.normal(scale=0.03, size=(50, 3)),
                         weights=np.full(50, 0.02))
    pf.estimate = lambda: SimpleNamespace(state=state, pose=np.mean(pf.particles, axis=0))
    moves: list[bool] = []

    def move(particles: np.ndarray, relocated: bool = False) -> None:
        pf.particles = np.asarray(particles)
        moves.append(relocated)

    pf.move_particles = move
    for pan in (0.0, math.pi / 2, math.pi / 3):
        match.step(pf, np.zeros(3), pan, _stored(entries, features, (3.25, 0.25), pan))
    # the second view relocates (the filter is told: a new belief); the third is matched where the belief now is
    assert match.matches == 2 and match.relocations == (1 if state == "global" else 0)
    assert moves == ([True, False] if state == "global" else [False, False])
    x = float(np.mean(pf.particles[:, 0]))
    assert (x > 3.0) if state == "global" else (x < 1.0)


@pytest.mark.parametrize("relocated", [False, True])
def test_a_relocated_belief_is_a_new_one_for_the_filter(relocated: bool) -> None:
    """Moved within its neighbourhood the belief keeps its challenge; taken to another place it
    is a new belief, whose challenge starts afresh when it converges (there)."""
    pf = _filter()
    pf.set_pose([0.4, 0.35, 0.0], np.diag([0.03**2, 0.03**2, 0.02**2]), confirmed=False)
    pf.challenge.start(pf.estimate().pose)
    assert pf.challenge.active
    pf.move_particles(pf.particles + [1.5, 0.0, 0.0], relocated=relocated)
    assert pf.challenge.active != relocated

"""A standing robot's views matched jointly with the map's own views, to place the belief.

The nearest-neighbour sensor model (section 3) judges each view alone and spreads its
likelihood over kernels ``sigma_xy`` wide, so the filter's estimate lands anywhere in a
neighbourhood of the right place. While the base stands, every view the head has taken since
it stopped was taken at one position, and together they say more: the map position and
heading whose stored views best match all of them at their pans (:class:`ViewLattice`, the
map oracle's rule of the evaluation, here near the filter's estimate) is where the robot
stands, to the map's lattice (25 cm with virtual translations); with
:attr:`StandingMatchConfig.subcell` (the default) it is placed between the lattice points
where the views best match the map's views interpolated between them
(:mod:`lino_loc.subcell_match`: the appearance manifold interpolated between sampled poses,
as the paper's reference [8], Murase & Nayar, does), around each of the
:attr:`StandingMatchConfig.candidates` lattice positions that match best; the best fit wins
(the lattice point nearest the truth need not match best of them: the truth lies between).
A view of something the map does not hold (a moved chair, a person in front of the camera)
fits badly wherever the others fit well; with :attr:`StandingMatchConfig.robust_scale` the
match is fitted a second time with each view weighed by how well it fitted the first time
(the Cauchy M-estimator's weights, one step of iteratively reweighted least squares), so such
a view pulls the pose less.

:class:`StandingMatch` keeps those views (robot pan, intensity features) and, after each
filter update, moves the particles near the estimate by the difference between the matched
position and the estimate (:meth:`StandingMatch.recentre`): the belief keeps its shape and
weights, its place is the views' joint answer. It acts only

* on frames the base stood for (less than :data:`lino_loc.lost_detection.STANDING_VIEWS`
  of an independent view since the last frame); the frame a base moved on starts a new set
  of views;
* once the filter has found the neighbourhood: at least
  :attr:`StandingMatchConfig.gate` of the particles' weight lies within
  :attr:`StandingMatchConfig.radius` of its estimate;
* with at least :attr:`StandingMatchConfig.min_views` views of distinct pans (two: a robot
  whose head holds still adds nothing to what the filter judges of its one view), and on a map
  that is a lattice of positions x headings (:meth:`StandingMatch.for_map` says why not,
  once, otherwise);
* not after an operator's pose (:meth:`StandingMatch.hold`) until the base has moved: the
  operator's word holds where it was given.

The heading is left to the filter: the map's headings are a lattice too, and the filter's
heading is finer than it.

A global search can settle among places that look alike (a corridor's two ends, a row of
desks), and the match near its estimate then refines the wrong one. While the filter has not
confirmed its belief (state ``global``; ``lino_loc.belief_challenge``), the views are matched as
well with the whole map beyond the evaluations' confident-wrong bound
(:data:`lino_loc.lost_detection.CONFIRM_RADIUS_XY`) of the estimate
(:attr:`StandingMatchConfig.relocate`); a far place whose views fit better by
:attr:`StandingMatchConfig.relocate_margin` nats takes the belief, turned to the far match's
heading. Each frame decides again on all the views kept, so a place the first views favoured
by chance gives the belief back when the later ones favour the other. A confirmed belief
(``tracking``) is not moved away: the odometry since it was confirmed is evidence the views
alone do not hold.

Once the belief is gathered, it also says where the head should look next
(:meth:`StandingMatch.action_values`, :attr:`StandingMatchConfig.choose_views`): the pan
farthest from the views kept (:mod:`lino_loc.view_spread`), since what remains uncertain is
the match's own error, which the filter's H(u) cannot see.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.active_vision import ActionValues
from lino_loc.lost_detection import CONFIRM_RADIUS_XY, base_stands
from lino_loc.pose_estimate import Estimate
from lino_loc.poses import wrap_angle
from lino_loc.subcell_match import SubcellSearch
from lino_loc.view_match import ViewLattice, ViewMatchConfig
from lino_loc.view_spread import spread_values

FloatArray = NDArray[np.float64]


class ParticleFilterLike(Protocol):
    """What :meth:`StandingMatch.step` needs of the filter
    (:class:`lino_loc.particle_filter.AuxiliaryParticleFilter`)."""

    @property
    def particles(self) -> FloatArray: ...

    @property
    def weights(self) -> FloatArray: ...

    def estimate(self) -> Estimate: ...

    def move_particles(self, particles: ArrayLike, relocated: bool = False) -> None: ...


class _FirstFit(NamedTuple):
    """A fit with every view alike: its hypotheses' axes and per-view costs
    (:meth:`ViewLattice.view_costs`), the pose, each view's squared residual there and the
    subcell search (None: on the lattice), kept for the weighed second fit."""

    g: NDArray[np.int64]
    o: NDArray[np.int64]
    costs: tuple[FloatArray, FloatArray]
    pose: FloatArray
    residuals: FloatArray
    search: SubcellSearch | None

    @property
    def cost(self) -> float:
        """The fit's cost: its views' squared residuals summed."""
        return float(np.sum(self.residuals))


class StandingMatchConfig(BaseModel):
    """Settings of :class:`StandingMatch` (``localizer.standing_match`` in the service's TOML)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(True, description="match a standing robot's views jointly with the map's")
    radius: float = Field(0.5, gt=0.0, description="m; map positions this close to the estimate are candidates")
    gate: float = Field(
        0.5, ge=0.0, le=1.0, description="share of the particles' weight within radius of the estimate "
        "before the match acts (the filter has found the neighbourhood)"
    )
    min_views: int = Field(
        2, ge=1, description="views of distinct pans taken while standing before the match acts (one "
        "view alone is what the filter's sensor model already judges; a head held still gives one)"
    )
    max_views: int = Field(16, ge=1, description="the most recent views (of distinct pans) kept while standing")
    subcell: bool = Field(
        True, description="place the position between lattice points: where the views match the map's "
        "stored views interpolated between the lattice poses around the match (lino_loc.subcell_match)"
    )
    candidates: int = Field(
        3, ge=1, description="with subcell: the lattice positions that match best (each at its best "
        "heading) placed between the lattice points; the best fit of them wins"
    )
    choose_views: bool = Field(
        True, description="once the belief is gathered and a view is kept, active vision looks at the pan "
        "farthest from the views kept (lino_loc.view_spread) instead of the filter's H(u)"
    )
    weigh_features: bool = Field(
        True, description="weigh each feature by the inverse of its own change over one lattice step "
        "(lino_loc.view_match.feature_weights); off: every feature alike"
    )
    robust_scale: float = Field(
        0.5, ge=0.0, description="views that fit badly count less: after a first fit, view i is "
        "weighed by 1 / (1 + r_i / (c s^2)) (Cauchy) and the match fitted again, with r_i its squared "
        "residual, s^2 the lattice's view noise (ViewLattice.s2) and c this scale; 0: every view alike"
    )
    relocate: bool = Field(
        True, description="while the filter's belief is unconfirmed (state 'global'), also match the views "
        "against the map positions far from the estimate (beyond lino_loc.lost_detection.CONFIRM_RADIUS_XY); "
        "one whose fit beats the fit near the estimate by relocate_margin takes the belief"
    )
    relocate_margin: float = Field(
        1.0, ge=0.0, description="nats: how much better a far place's views must fit than those near the "
        "estimate to take the belief, as (c_near - c_far) / (2 s^2) of the first fits' costs c, s^2 the "
        "lattice's view noise (ViewLattice.s2)"
    )
    min_headings: int = Field(
        8, ge=2, description="a map whose positions hold fewer headings than this on average is no "
        "lattice of positions x headings (e.g. a survey's poses taken on the way): no match"
    )


def cauchy_weights(residuals: ArrayLike, scale: float) -> FloatArray:
    """The Cauchy M-estimator's weights ``1 / (1 + r_i / scale)`` of squared residuals ``r_i``
    (iteratively reweighted least squares: Holland & Welsch, "Robust regression using
    iteratively reweighted least-squares", 1977); 0 for an infinite residual."""
    r = np.asarray(residuals, dtype=np.float64)
    return np.where(np.isfinite(r), 1.0 / (1.0 + np.where(np.isfinite(r), r, 0.0) / scale), 0.0)


def gathered(particles: FloatArray, weights: FloatArray, estimate: ArrayLike, radius: float,
             gate: float) -> NDArray[np.bool_] | None:
    """The particles within ``radius`` (m) of ``estimate``, None while they hold less than
    ``gate`` of the weight (the filter has not found the neighbourhood)."""
    est = np.asarray(estimate, dtype=np.float64)
    near = np.hypot(particles[:, 0] - est[0], particles[:, 1] - est[1]) <= radius
    return near if float(np.sum(weights[near])) >= gate else None


class StandingMatch:
    """The views since the base stopped, and the belief's place from them (module docstring)."""

    def __init__(self, lattice: ViewLattice, config: StandingMatchConfig | None = None) -> None:
        self.config = config or StandingMatchConfig()
        self.lattice = lattice
        self._pans: list[float] = []
        self._views: list[FloatArray] = []
        self._held = False
        self._standing = False  # whether the base stood for the last frame
        self.matches = 0  # times the belief was moved (status and tests)
        self.relocations = 0  # of them, times a far place took it

    @classmethod
    def for_map(cls, poses: ArrayLike, features: ArrayLike,
                config: StandingMatchConfig | None = None) -> StandingMatch | str:
        """The match on a map's intensity features (N, d) at its camera poses (N, 3), or why
        the map cannot serve it (one line): not a lattice of positions x headings."""
        cfg = config or StandingMatchConfig()
        lattice = ViewLattice(poses, features, ViewMatchConfig(radius=cfg.radius, heading_span=math.pi,
                                                               weigh_features=cfg.weigh_features))
        per_position = float(np.mean(np.sum(np.isfinite(lattice.table[:, :, 0]), axis=1)))
        if per_position < cfg.min_headings:
            return (f"the map is no lattice of positions x headings ({lattice.xy.shape[0]} positions, "
                    f"{per_position:.1f} headings each on average; needs {cfg.min_headings})")
        return cls(lattice, cfg)

    @property
    def spacing(self) -> float:
        """The lattice's spacing (m; 0 for one position)."""
        return self.lattice.spacing

    @property
    def n_views(self) -> int:
        return len(self._views)

    def reset(self) -> None:
        """Forget the views (the base moved, or the belief was replaced)."""
        self._pans.clear()
        self._views.clear()

    def hold(self) -> None:
        """Do not move the belief until the base has moved: an operator's pose is not
        overridden by the views of the place where it was given."""
        self._held = True

    def observe(self, delta: ArrayLike, pan: float, features: ArrayLike | None) -> bool:
        """A frame: odometry increment ``delta`` (robot frame) since the previous one, the head's
        pan (rad) and the image's intensity features (None: no image). A moving base starts a
        new set of views. One view is kept per pan: a frame at a pan that rounds to a kept
        view's on the map's heading lattice (the same stored views match both) replaces it, so
        a head holding still for many frames weighs as one view. Returns whether the base
        stood for this frame."""
        standing = base_stands(delta)
        self._standing = standing
        if not standing:
            self.reset()
            self._held = False
        if features is None or not math.isfinite(float(pan)):
            return standing
        y = np.asarray(features, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(y)):
            return standing
        step = self.lattice.heading_step
        same = [i for i, u in enumerate(self._pans) if round(u / step) == round(float(pan) / step)]
        for i in reversed(same):
            del self._pans[i], self._views[i]
        self._pans.append(float(pan))
        self._views.append(y)
        if len(self._views) > self.config.max_views:
            del self._pans[0], self._views[0]
        return standing

    def match(self, estimate: ArrayLike, rivals: bool = False) -> FloatArray | None:
        """The matched robot pose (x, y, theta) near ``estimate``, None without enough views
        or candidates (:meth:`_match`); with ``rivals`` and ``relocate``, a far place's pose
        where its views fit better by ``relocate_margin``."""
        m = self._match(np.asarray(estimate, dtype=np.float64), rivals)
        return None if m is None else m[0]

    def _match(self, estimate: FloatArray, rivals: bool) -> tuple[FloatArray, bool] | None:
        """The matched pose and whether it is a far place's (module docstring), None without
        enough views or candidates near ``estimate``. With ``rivals`` and ``relocate``, the views
        are matched as well with the map positions beyond
        :data:`lino_loc.lost_detection.CONFIRM_RADIUS_XY` of the estimate, at every heading;
        the far match wins when its first fit's cost is below the near one's by ``2 s^2``
        ``relocate_margin`` (a likelihood ratio of ``exp(relocate_margin)`` under the lattice's
        Gaussian view noise ``s^2``)."""
        if len(self._views) < self.config.min_views:
            return None
        pans, views = np.asarray(self._pans), np.stack(self._views)
        near = self._first_fit(*self.lattice.near(estimate), pans, views)
        if near is None:
            return None
        if rivals and self.config.relocate:
            far = self._first_fit(*self.lattice.beyond(estimate, CONFIRM_RADIUS_XY), pans, views)
            if far is not None and near.cost - far.cost > 2.0 * self.lattice.s2 * self.config.relocate_margin:
                return self._refit(far, pans, views), True
        return self._refit(near, pans, views), False

    def _first_fit(self, g: NDArray[np.int64], o: NDArray[np.int64], pans: FloatArray,
                   views: FloatArray) -> _FirstFit | None:
        """The first fit (every view alike) among the hypotheses ``g`` x ``o``, None without
        candidates."""
        costs = self.lattice.view_costs(g, o, pans, views)
        first = self._fit(g, o, costs, pans, views, None, None)
        return None if first is None else _FirstFit(g, o, costs, *first)

    def _refit(self, first: _FirstFit, pans: FloatArray, views: FloatArray) -> FloatArray:
        """The matched pose from a first fit. With ``robust_scale``, fitted a second time with
        each view weighed by its fit in the first (:func:`cauchy_weights`), so that a view of
        something the map does not hold (a moved chair, a person) pulls the pose less. The
        second fit reuses the first's per-view costs, and its search where the candidates are
        the same."""
        if self.config.robust_scale <= 0.0:
            return first.pose
        weights = cauchy_weights(first.residuals, self.config.robust_scale * self.lattice.s2)
        if not np.any(weights > 0.0):
            return first.pose
        second = self._fit(first.g, first.o, first.costs, pans, views, weights, first.search)
        return first.pose if second is None else second[0]

    def _fit(self, g: NDArray[np.int64], o: NDArray[np.int64], costs: tuple[FloatArray, FloatArray],
             pans: FloatArray, views: FloatArray, weights: FloatArray | None,
             search: SubcellSearch | None) -> tuple[FloatArray, FloatArray, SubcellSearch | None] | None:
        """The matched pose, each view's squared residual there and the subcell search (None:
        on the lattice), from the hypotheses' per-view ``costs`` (:meth:`ViewLattice.view_costs`)
        weighed by ``weights``; ``search`` is reused when its candidates are this fit's."""
        candidates = self.lattice.ranked(g, o, self.lattice.weighed(*costs, weights), self.config.candidates)
        if not candidates:
            return None
        if not self.config.subcell or self.spacing <= 0.0:
            return candidates[0], self.lattice.residuals(candidates[0], pans, views), None
        poses = np.stack(candidates)
        if search is None or not np.array_equal(search.poses, poses):
            search = SubcellSearch(self.lattice, poses, pans, views)
        fit = search.fit(weights)
        return fit.pose, fit.residuals, search

    def step(self, pf: ParticleFilterLike, delta: ArrayLike, pan: float, features: ArrayLike | None) -> bool:
        """After a filter update with the frame (``delta``, ``pan``, intensity ``features``):
        keep the view (:meth:`observe`) and move the filter's belief to the views' match
        (:meth:`recentre`); a lost belief forgets the views (they may come from two places).
        Nothing moves on the frame the base moved on: its view starts the next set, and one
        view taken on the way is no standing robot's. While the filter has not confirmed its
        belief (state ``global``) the views' far rivals are matched too (``relocate``).
        Returns whether the belief moved."""
        if not self.observe(delta, pan, features) or self._held:
            return False
        est = pf.estimate()
        if est.state == "lost":
            self.reset()
            return False
        before = self.relocations
        moved = self.recentre(pf.particles, pf.weights, est.pose, rivals=est.state == "global")
        if moved is None:
            return False
        pf.move_particles(moved, relocated=self.relocations > before)
        return True

    def _near(self, particles: FloatArray, weights: FloatArray, estimate: FloatArray) -> NDArray[np.bool_] | None:
        return gathered(particles, weights, estimate, self.config.radius, self.config.gate)

    def recentre(self, particles: FloatArray, weights: FloatArray, estimate: ArrayLike,
                 rivals: bool = False) -> FloatArray | None:
        """The particles (N, 3) with those within ``radius`` of ``estimate`` moved by the matched
        position minus the estimate; None when the match does not act (module docstring). With
        ``rivals`` (an unconfirmed belief), a far place that fits better takes them: they keep
        their spread about the estimate, turned by the far match's heading minus the estimate's."""
        est = np.asarray(estimate, dtype=np.float64)
        near = self._near(particles, weights, est)
        m = None if near is None else self._match(est, rivals)
        if m is None or near is None:
            return None
        pose, far = m
        moved = np.array(particles, dtype=np.float64, copy=True)
        turn = float(wrap_angle(pose[2] - est[2])) if far else 0.0
        c, s = math.cos(turn), math.sin(turn)
        off = moved[near, :2] - est[:2]
        moved[near, 0] = pose[0] + c * off[:, 0] - s * off[:, 1]
        moved[near, 1] = pose[1] + s * off[:, 0] + c * off[:, 1]
        if far:
            moved[near, 2] = wrap_angle(moved[near, 2] + turn)
        self.matches += 1
        self.relocations += int(far)
        return moved

    def action_values(self, particles: FloatArray, weights: FloatArray, estimate: ArrayLike,
                      actions: ArrayLike) -> ActionValues | None:
        """With ``choose_views``, on a standing base (the last frame's) once the belief is
        gathered (``gate``) and a view is kept, no operator's pose held: the spread rule's
        values of ``actions`` (:func:`lino_loc.view_spread.spread_values`, the pan farthest from
        the views kept, which the match will join); None otherwise (the filter's H(u) decides:
        a driving base's views are not joined)."""
        if not self.config.choose_views or self._held or not self._views or not self._standing:
            return None
        if self._near(particles, weights, np.asarray(estimate, dtype=np.float64)) is None:
            return None
        return spread_values(self._pans, actions, int(particles.shape[0]))

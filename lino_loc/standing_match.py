"""A standing robot's views matched jointly with the map's own views, to place the belief.

The nearest-neighbour sensor model (section 3) judges each view alone and spreads its
likelihood over kernels ``sigma_xy`` wide, so the filter's estimate lands anywhere in a
neighbourhood of the right place. While the base stands, every view the head has taken since
it stopped was taken at one position, and together they say more: the map position and
heading whose stored views best match all of them at their pans (:class:`ViewLattice`, the
map oracle's rule of the evaluation, here near the filter's estimate) is where the robot
stands, to the map's lattice (25 cm with virtual translations); with
:attr:`StandingMatchConfig.subcell` (the default) it is placed between the lattice points at
the vertex of the parabola through the joint cost of the match and of its two neighbours,
along x and along y (the sub-pixel rule of stereo matching, here on the position lattice).

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
* with at least :attr:`StandingMatchConfig.min_views` views, and on a map that is a lattice
  of positions x headings (:meth:`StandingMatch.for_map` says why not, once, otherwise);
* not after an operator's pose (:meth:`StandingMatch.hold`) until the base has moved: the
  operator's word holds where it was given.

The heading is left to the filter: the map's headings are a lattice too, and the filter's
heading is finer than it.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from lino_loc.lost_detection import STANDING_VIEWS, independent_views
from lino_loc.pose_estimate import Estimate
from lino_loc.view_match import ViewLattice, ViewMatchConfig

FloatArray = NDArray[np.float64]


class ParticleFilterLike(Protocol):
    """What :meth:`StandingMatch.step` needs of the filter
    (:class:`lino_loc.particle_filter.AuxiliaryParticleFilter`)."""

    @property
    def particles(self) -> FloatArray: ...

    @property
    def weights(self) -> FloatArray: ...

    def estimate(self) -> Estimate: ...

    def move_particles(self, particles: ArrayLike) -> None: ...


class StandingMatchConfig(BaseModel):
    """Settings of :class:`StandingMatch` (``localizer.standing_match`` in the service's TOML)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(True, description="match a standing robot's views jointly with the map's")
    radius: float = Field(0.5, gt=0.0, description="m; map positions this close to the estimate are candidates")
    gate: float = Field(
        0.5, ge=0.0, le=1.0, description="share of the particles' weight within radius of the estimate "
        "before the match acts (the filter has found the neighbourhood)"
    )
    min_views: int = Field(1, ge=1, description="views taken while standing before the match acts")
    max_views: int = Field(16, ge=1, description="the most recent views (of distinct pans) kept while standing")
    subcell: bool = Field(
        True, description="place the position between lattice points: a parabola through the "
        "match's cost and its two neighbours' along x and along y (at the matched heading)"
    )
    min_headings: int = Field(
        8, ge=2, description="a map whose positions hold fewer headings than this on average is no "
        "lattice of positions x headings (e.g. a survey's poses taken on the way): no match"
    )


class StandingMatch:
    """The views since the base stopped, and the belief's place from them (module docstring)."""

    def __init__(self, lattice: ViewLattice, config: StandingMatchConfig | None = None) -> None:
        self.config = config or StandingMatchConfig()
        self.lattice = lattice
        self._tree = cKDTree(lattice.xy)
        #: the lattice's spacing (m): the median distance of a position to its nearest other
        self.spacing = float(np.median(self._tree.query(lattice.xy, k=2)[0][:, 1])) if lattice.xy.shape[0] > 1 else 0.0
        self._pans: list[float] = []
        self._views: list[FloatArray] = []
        self._held = False
        self.matches = 0  # times the belief was moved (status and tests)

    @classmethod
    def for_map(cls, poses: ArrayLike, features: ArrayLike,
                config: StandingMatchConfig | None = None) -> StandingMatch | str:
        """The match on a map's intensity features (N, d) at its camera poses (N, 3), or why
        the map cannot serve it (one line): not a lattice of positions x headings."""
        cfg = config or StandingMatchConfig()
        lattice = ViewLattice(poses, features, ViewMatchConfig(radius=cfg.radius, heading_span=math.pi))
        per_position = float(np.mean(np.sum(np.isfinite(lattice.table[:, :, 0]), axis=1)))
        if per_position < cfg.min_headings:
            return (f"the map is no lattice of positions x headings ({lattice.xy.shape[0]} positions, "
                    f"{per_position:.1f} headings each on average; needs {cfg.min_headings})")
        return cls(lattice, cfg)

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
        standing = independent_views(np.asarray(delta, dtype=np.float64)) < STANDING_VIEWS
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

    def match(self, estimate: ArrayLike) -> FloatArray | None:
        """The matched robot pose (x, y, theta) near ``estimate``, None without enough views
        or candidates."""
        if len(self._views) < self.config.min_views:
            return None
        pans, views = np.asarray(self._pans), np.stack(self._views)
        pose = self.lattice.match(np.asarray(estimate, dtype=np.float64), pans, views)
        if pose is None or not self.config.subcell or self.spacing <= 0.0:
            return pose
        return self._subcell(pose, pans, views)

    def _subcell(self, pose: FloatArray, pans: FloatArray, views: FloatArray) -> FloatArray:
        """``pose`` moved along x and along y to the vertex of the parabola through the costs
        at the lattice points one spacing either side and at ``pose`` (same heading), by at most
        half a spacing; an axis lacking a neighbour, or whose costs are not convex, stays."""
        lat, h = self.lattice, self.spacing
        # the match, then its neighbours -x, +x, -y, +y
        pts = pose[:2] + h * np.array([[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])
        dist, g = self._tree.query(pts)
        o = np.full(5, int(round(pose[2] / lat.heading_step)) % lat.n_headings)
        c = lat.costs(g, o, pans, views)
        out = pose.copy()
        for axis, (lo, hi) in enumerate(((1, 2), (3, 4))):
            curvature = c[lo] - 2.0 * c[0] + c[hi]
            if dist[lo] > 0.25 * h or dist[hi] > 0.25 * h or not (np.isfinite(c[[0, lo, hi]]).all() and curvature > 0.0):
                continue
            out[axis] += h * float(np.clip(0.5 * (c[lo] - c[hi]) / curvature, -0.5, 0.5))
        return out

    def step(self, pf: ParticleFilterLike, delta: ArrayLike, pan: float, features: ArrayLike | None) -> bool:
        """After a filter update with the frame (``delta``, ``pan``, intensity ``features``):
        keep the view (:meth:`observe`) and move the filter's belief to the views' match
        (:meth:`recentre`); a lost belief forgets the views (they may come from two places).
        Nothing moves on the frame the base moved on: its view starts the next set, and one
        view taken on the way is no standing robot's. Returns whether the belief moved."""
        if not self.observe(delta, pan, features) or self._held:
            return False
        est = pf.estimate()
        if est.state == "lost":
            self.reset()
            return False
        moved = self.recentre(pf.particles, pf.weights, est.pose)
        if moved is None:
            return False
        pf.move_particles(moved)
        return True

    def recentre(self, particles: FloatArray, weights: FloatArray, estimate: ArrayLike) -> FloatArray | None:
        """The particles (N, 3) with those within ``radius`` of ``estimate`` moved by the matched
        position minus the estimate; None when the match does not act (module docstring)."""
        est = np.asarray(estimate, dtype=np.float64)
        near = np.hypot(particles[:, 0] - est[0], particles[:, 1] - est[1]) <= self.config.radius
        if float(np.sum(weights[near])) < self.config.gate:
            return None
        m = self.match(est)
        if m is None:
            return None
        moved = np.array(particles, dtype=np.float64, copy=True)
        moved[near, :2] += m[:2] - est[:2]
        self.matches += 1
        return moved

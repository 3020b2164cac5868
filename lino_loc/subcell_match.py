"""Where between the map's lattice points a standing robot's views match best.

The map stores views at lattice poses: positions every ``h`` (25 cm with virtual translations)
and headings every ``dtheta`` (3 deg with virtual headings). Given the lattice pose that
matches a set of views best (:meth:`lino_loc.view_match.ViewLattice.match`), the robot's pose
lies near it, and the appearance between lattice poses is interpolated from theirs, as the
paper's reference [8] (Murase & Nayar, parametric eigenspace) interpolates the appearance
manifold between sampled poses: trilinearly, over the 3 x 3 lattice positions around the
match and, for each view, the two stored headings its camera heading falls between. With
``y(p, t)`` that interpolation at position p and camera heading t, the views ``y_i`` taken
at pans ``u_i`` are placed at

    argmin over (p, o) of  sum_i w_i |y_i - y(p, o + u_i)|^2

with view weights ``w_i`` (1 unless the caller weighs the views by their fit,
:meth:`lino_loc.standing_match.StandingMatch.match`), searched on a grid: positions within
one spacing of the match every ``h / SUBCELL_STEPS``, robot headings within half a heading
step of it every ``dtheta / (2 HEADING_STEPS)``, and the position then refined between the
grid's points: along each axis, the vertex of the parabola through the best point and its two
neighbours (within a lattice cell the cost along one axis is a quadratic), where that costs
less. A fit held to the grid would put the pose exactly on the grid's points, among them the
midpoints between lattice points.

Bilinear interpolation in (x, y) is the product of the tent functions
``max(0, 1 - |s - i|)`` along each axis (s in spacings, i in {-1, 0, 1}), and linear
interpolation in heading the tent along it, at each view's own camera heading ``o + u_i``:
the pans need not be multiples of the heading step, and rounding them to it would turn each
view by up to half a step, which the position would absorb. A lattice point missing around
the match (a wall, the map's edge, a heading the survey lacks) excludes the poses that would
interpolate from it.

For each heading the cost is a quadratic form in the interpolation weights ``w`` (S, 9):
``w G w^T - 2 w b + sum_i w_i |v_i|^2`` with ``G = sum_i w_i Y_i Y_i^T`` and
``b = sum_i w_i Y_i v_i`` over the 9 lattice views ``Y_i`` (9, d) of view i at that heading
(:class:`SubcellSearch` keeps each view's products, so a fit with other view weights costs
their sums only), so the search costs (9 x 9) products, not one fit per pose; the bilinear
weights are products of tents along x and y, so the form over the whole position grid
separates into products along each axis.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from lino_loc.poses import wrap_angle
from lino_loc.view_match import ViewLattice

FloatArray = NDArray[np.float64]

#: Positions tried per spacing between the lattice points.
SUBCELL_STEPS = 10
#: Headings tried per half heading step either side of the match's.
HEADING_STEPS = 2
#: The 3 x 3 lattice points around a match, in spacings (x major).
NEIGHBOURS = np.array([[i, j] for i in (-1.0, 0.0, 1.0) for j in (-1.0, 0.0, 1.0)])


def _tent(s: FloatArray, nodes: FloatArray) -> FloatArray:
    """Linear-interpolation weights (len(s), len(nodes)) of unit-spaced ``nodes`` at ``s``."""
    return np.maximum(0.0, 1.0 - np.abs(s[:, None] - nodes[None, :]))


#: The offsets tried along one axis, in spacings.
AXIS_OFFSETS = np.linspace(-1.0, 1.0, 2 * SUBCELL_STEPS + 1)
#: Their tent weights on the lattice points -1, 0, 1 of that axis (21, 3).
AXIS_WEIGHTS = _tent(AXIS_OFFSETS, np.array([-1.0, 0.0, 1.0]))
#: ``t_a t_a'`` of every offset tried along one axis (21, 9): the quadratic form's weights.
AXIS_PAIRS = (AXIS_WEIGHTS[:, :, None] * AXIS_WEIGHTS[:, None, :]).reshape(AXIS_OFFSETS.size, -1)


def _grid() -> tuple[FloatArray, FloatArray, FloatArray]:
    """Position offsets (S, 2) in spacings (x major) and their bilinear weights (S, 9); robot
    heading offsets (T,) in heading steps."""
    sx, sy = (a.ravel() for a in np.meshgrid(AXIS_OFFSETS, AXIS_OFFSETS, indexing="ij"))
    w_pos = _tent(sx, NEIGHBOURS[:, 0]) * _tent(sy, NEIGHBOURS[:, 1])
    t = np.linspace(-0.5, 0.5, 2 * HEADING_STEPS + 1)
    return np.stack([sx, sy], axis=1), w_pos, t


POSITION_OFFSETS, POSITION_WEIGHTS, HEADING_OFFSETS = _grid()
#: Which lattice points each position tried interpolates from (S, 9), as 0 / 1.
SUPPORT = (POSITION_WEIGHTS > 0.0).astype(np.float64)


def _heading_views(lattice: ViewLattice, g: NDArray[np.int64], o: NDArray[np.int64],
                   pans: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The stored views of each candidate's 9 lattice positions ``g`` (C, 9) interpolated in
    camera heading, for every robot heading tried (``o`` (C,) + :data:`HEADING_OFFSETS` steps)
    and every pan: (C, T, 9, k d); and which (C, T, 9) interpolate from a missing view. Each
    view's camera heading ``theta + u_i`` falls between two stored headings, at its own
    fraction of a step: pans need not be multiples of the heading step, so each view is
    interpolated at its own."""
    u = np.asarray(pans, dtype=np.float64) / lattice.heading_step
    r = np.floor(u).astype(np.int64)
    nodes = np.array([-1.0, 0.0, 1.0, 2.0])
    cols = (o[:, None, None] + r[None, None, :] + nodes.astype(np.int64)[None, :, None]) % lattice.n_headings
    at = (g[:, None, :, None], cols[:, :, None, :])  # (C, 4, 9, k): the stored views around each
    nan = np.isnan(lattice.norms[at])  # a missing view's norm is NaN
    y = np.where(nan[..., None], 0.0, lattice.table[at])  # (C, 4, 9, k, d)
    w = _tent((HEADING_OFFSETS[:, None] + (u - r)[None, :]).ravel(), nodes).reshape(-1, u.size, 4)  # (T, k, 4)
    missing = np.einsum("tkc,Ccpk->Ctp", (w > 0.0).astype(np.float64), nan.astype(np.float64)) > 0.0
    n_c, _, n_p, k, d = y.shape
    # interpolate in heading: for each view, (T, 4) weights x (4, C 9 d) views, one batched product
    yt = np.matmul(w.transpose(1, 0, 2), y.transpose(3, 1, 0, 2, 4).reshape(k, 4, -1))  # (k, T, C 9 d)
    yt = yt.reshape(k, -1, n_c, n_p, d).transpose(2, 1, 3, 0, 4)  # (C, T, 9, k, d)
    return yt.reshape(*yt.shape[:3], k * d), missing


def _position_costs(gram: FloatArray, b: FloatArray) -> FloatArray:
    """``w G w^T - 2 w b`` (..., S) at every position tried, of the Gram matrices ``G``
    (..., 9, 9) and ``b`` (..., 9) over the 3 x 3 lattice points (x major). The bilinear
    weight ``w_(a, b)`` is ``t_a(x) t_b(y)``, so the form separates: G contracted with the
    x tents' pairs, then with the y tents' pairs (and b likewise), each a small product."""
    lead = gram.shape[:-2]
    g = gram.reshape(*lead, 3, 3, 3, 3).swapaxes(-3, -2).reshape(*lead, 9, 9)  # [(a, a'), (b, b')]
    quad = AXIS_PAIRS @ g @ AXIS_PAIRS.T  # (..., 21 x, 21 y)
    lin = AXIS_WEIGHTS @ b.reshape(*lead, 3, 3) @ AXIS_WEIGHTS.T
    return (quad - 2.0 * lin).reshape(*lead, -1)


class SubcellFit(NamedTuple):
    """:func:`subcell_fit`'s answer."""

    pose: FloatArray  #: (x, y, theta)
    cost: float  #: ``sum_i w_i |y_i - y(p, o + u_i)|^2`` there (inf: no pose could be interpolated)
    residuals: FloatArray  #: ``|y_i - y(p, o + u_i)|^2`` (k,) of each view there, unweighted (inf: none)


class SubcellSearch:
    """The search of :func:`subcell_fit` prepared once for a set of views around candidate
    lattice poses ``poses`` (C, 3): each view's Gram matrices over the candidates' lattice
    views, so that :meth:`fit` with any view weights costs only their weighted sum and the
    search over the grid (a second fit with the views weighed by their first fit costs a
    fraction of the first)."""

    def __init__(self, lattice: ViewLattice, poses: FloatArray, pans: FloatArray, views: FloatArray) -> None:
        self.lattice = lattice
        self.poses = np.atleast_2d(np.asarray(poses, dtype=np.float64))
        dist, g = lattice.tree.query(self.poses[:, None, :2] + lattice.spacing * NEIGHBOURS[None, :, :])  # (C, 9)
        self.headings = np.round(self.poses[:, 2] / lattice.heading_step).astype(np.int64)
        yt, missing = _heading_views(lattice, g, self.headings, pans)  # (C, T, 9, k d), (C, T, 9)
        self.missing = missing | (dist > 0.25 * lattice.spacing)[:, None, :]
        self.views = lattice.weigh(np.atleast_2d(np.asarray(views, dtype=np.float64)))  # (k, d)
        k, d = self.views.shape
        self.stored = yt.reshape(*yt.shape[:3], k, d).swapaxes(2, 3)  # (C, T, k, 9, d)
        self._gram = self.stored @ self.stored.swapaxes(-1, -2)  # (C, T, k, 9, 9): each view's
        self._b = (self.stored @ self.views[:, :, None])[..., 0]  # (C, T, k, 9)
        self._norms = np.sum(self.views * self.views, axis=1)  # |v_i|^2 (k,)
        self._excluded = self.missing.astype(np.float64) @ SUPPORT.T > 0.0  # (C, T, S)

    def fit(self, view_weights: FloatArray | None = None) -> SubcellFit:
        """The best fit with views weighed by ``view_weights`` (k,) (None: all 1)
        (:func:`subcell_fit`)."""
        k = self.views.shape[0]
        w = np.ones(k) if view_weights is None else np.asarray(view_weights, dtype=np.float64)
        cost = _position_costs(np.einsum("ctkpq,k->ctpq", self._gram, w), np.einsum("ctkp,k->ctp", self._b, w))
        cost[self._excluded] = np.inf
        c, ti, i = np.unravel_index(int(np.argmin(cost)), cost.shape)
        if not np.isfinite(cost[c, ti, i]):
            return SubcellFit(self.poses[0].copy(), math.inf, np.full(k, np.inf))
        offset, weights = _refined(cost[c, ti], int(i), self.missing[c, ti])
        residuals = self._residuals(c, ti, weights)
        if w @ residuals > cost[c, ti, i] + w @ self._norms:  # the grid's point fits better
            offset = POSITION_OFFSETS[i]
            residuals = self._residuals(c, ti, POSITION_WEIGHTS[i])
        out = self.poses[c].copy()
        out[:2] += self.lattice.spacing * offset
        out[2] = wrap_angle((self.headings[c] + HEADING_OFFSETS[int(ti)]) * self.lattice.heading_step)
        return SubcellFit(out, float(w @ residuals), residuals)

    def _residuals(self, c: int, ti: int, weights: FloatArray) -> FloatArray:
        """Each view's squared residual (k,) against candidate c's views at heading ti
        interpolated with the position weights ``weights`` (9,)."""
        return np.sum((self.views - weights @ self.stored[c, ti]) ** 2, axis=1)


def subcell_fit(lattice: ViewLattice, poses: FloatArray, pans: FloatArray, views: FloatArray,
                view_weights: FloatArray | None = None) -> SubcellFit:
    """The pose (x, y, theta) near one of the lattice poses ``poses`` (C, 3) whose interpolated
    stored views match ``views`` (k, d) taken at robot pans ``pans`` (k,) best (module
    docstring), its cost ``sum_i w_i |y_i - y(p, o + u_i)|^2`` in the lattice's weighted
    features (:meth:`ViewLattice.weigh`; ``w`` the ``view_weights`` (k,), None: all 1) and
    each view's own squared residual there. All candidates are searched together and the
    best fit wins (ties: the earlier candidate). The first candidate itself and an infinite
    cost when every pose around every candidate interpolates from a missing point."""
    return SubcellSearch(lattice, poses, pans, views).fit(view_weights)


def _axis_tents(s: float) -> FloatArray:
    """The tents of the lattice points -1, 0, 1 of one axis at ``s`` (spacings)."""
    return np.array([max(0.0, 1.0 - abs(s - node)) for node in (-1.0, 0.0, 1.0)])


def _vertex(lo: float, mid: float, hi: float) -> float:
    """The vertex (in grid steps, within half a step of 0) of the parabola through
    (-1, ``lo``), (0, ``mid``), (1, ``hi``), ``mid`` the least; 0 without both neighbours."""
    curvature = lo - 2.0 * mid + hi
    if not (math.isfinite(lo) and math.isfinite(hi)) or curvature <= 0.0:
        return 0.0
    return min(0.5, max(-0.5, 0.5 * (lo - hi) / curvature))


def _refined(costs: FloatArray, i: int, missing: NDArray[np.bool_]) -> tuple[FloatArray, FloatArray]:
    """The position offset (2,) in spacings and its bilinear weights (9,) refined from the
    search grid's best point ``i`` of ``costs`` (S,) between the grid's points: along each
    axis, the vertex of the parabola through it and its two neighbours (within a lattice cell
    the cost along one axis is a quadratic in the offset, the interpolation being linear in
    it), so that the fit is not held to the grid; the grid's point where the refined offset
    would interpolate from a ``missing`` (9,) lattice point."""
    n = AXIS_OFFSETS.size
    ix, iy = divmod(i, n)
    grid = costs.reshape(n, n)
    along_x = grid[max(ix - 1, 0):ix + 2, iy].tolist()
    along_y = grid[ix, max(iy - 1, 0):iy + 2].tolist()
    dx = _vertex(*along_x) if 0 < ix < n - 1 else 0.0
    dy = _vertex(*along_y) if 0 < iy < n - 1 else 0.0
    if dx == 0.0 and dy == 0.0:
        return POSITION_OFFSETS[i], POSITION_WEIGHTS[i]
    step = float(AXIS_OFFSETS[1] - AXIS_OFFSETS[0])
    offset = POSITION_OFFSETS[i] + step * np.array([dx, dy])
    weights = np.outer(_axis_tents(float(offset[0])), _axis_tents(float(offset[1]))).ravel()  # x major
    if np.any(missing[weights > 0.0]):
        return POSITION_OFFSETS[i], POSITION_WEIGHTS[i]
    return offset, weights

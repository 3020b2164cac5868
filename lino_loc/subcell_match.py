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

    argmin over (p, o) of  sum_i |y_i - y(p, o + u_i)|^2

searched on a grid: positions within one spacing of the match every ``h / SUBCELL_STEPS``,
robot headings within half a heading step of it every ``dtheta / (2 HEADING_STEPS)``.
Bilinear interpolation in (x, y) is the product of the tent functions
``max(0, 1 - |s - i|)`` along each axis (s in spacings, i in {-1, 0, 1}), and linear
interpolation in heading the tent along it, at each view's own camera heading ``o + u_i``:
the pans need not be multiples of the heading step, and rounding them to it would turn each
view by up to half a step, which the position would absorb. A lattice point missing around
the match (a wall, the map's edge, a heading the survey lacks) excludes the poses that would
interpolate from it.

For each heading the cost is a quadratic form in the interpolation weights ``w`` (S, 9):
``w G w^T - 2 w b + |v|^2`` with ``G = Y Y^T`` and ``b = Y v`` over the 9 lattice views ``Y``
(9, k d) at that heading and the views ``v``, so the search costs (9 x 9) products, not one
fit per pose.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

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


def _grid() -> tuple[FloatArray, FloatArray, FloatArray]:
    """Position offsets (S, 2) in spacings and their bilinear weights (S, 9); robot heading
    offsets (T,) in heading steps."""
    s = np.linspace(-1.0, 1.0, 2 * SUBCELL_STEPS + 1)
    sx, sy = (a.ravel() for a in np.meshgrid(s, s, indexing="ij"))
    w_pos = _tent(sx, NEIGHBOURS[:, 0]) * _tent(sy, NEIGHBOURS[:, 1])
    t = np.linspace(-0.5, 0.5, 2 * HEADING_STEPS + 1)
    return np.stack([sx, sy], axis=1), w_pos, t


POSITION_OFFSETS, POSITION_WEIGHTS, HEADING_OFFSETS = _grid()
#: ``w_j w_k`` of every position tried (S, 81): ``w G w^T`` of all of them is one product with G.
WEIGHT_PAIRS = (POSITION_WEIGHTS[:, :, None] * POSITION_WEIGHTS[:, None, :]).reshape(POSITION_WEIGHTS.shape[0], -1)
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
    y = lattice.table[g[:, None, :, None], cols[:, :, None, :]]  # (C, 4, 9, k, d)
    w = _tent((HEADING_OFFSETS[:, None] + (u - r)[None, :]).ravel(), nodes).reshape(-1, u.size, 4)  # (T, k, 4)
    nan = np.isnan(y).any(axis=4)  # (C, 4, 9, k)
    missing = np.einsum("tkc,Ccpk->Ctp", (w > 0.0).astype(np.float64), nan.astype(np.float64)) > 0.0
    yt = np.einsum("tkc,Ccpkd->Ctpkd", w, np.where(nan[..., None], 0.0, y))
    return yt.reshape(*yt.shape[:3], -1), missing


def subcell_fit(lattice: ViewLattice, tree: cKDTree, spacing: float, poses: FloatArray,
                pans: FloatArray, views: FloatArray) -> tuple[FloatArray, float]:
    """The pose (x, y, theta) near one of the lattice poses ``poses`` (C, 3) whose interpolated
    stored views match ``views`` (k, d) taken at robot pans ``pans`` (k,) best (module
    docstring), and its cost ``sum_i |y_i - y(p, o + u_i)|^2``; ``tree`` holds the lattice
    positions, ``spacing`` their spacing (m). All candidates are searched together and the
    best fit wins (ties: the earlier candidate). The first candidate itself and an infinite
    cost when every pose around every candidate interpolates from a missing point."""
    poses = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    dist, g = tree.query(poses[:, None, :2] + spacing * NEIGHBOURS[None, :, :])  # (C, 9)
    o = np.round(poses[:, 2] / lattice.heading_step).astype(np.int64)
    yt, missing = _heading_views(lattice, g, o, pans)  # (C, T, 9, k d), (C, T, 9)
    missing |= (dist > 0.25 * spacing)[:, None, :]
    v = np.asarray(views, dtype=np.float64).reshape(-1)
    gram, b = yt @ yt.swapaxes(-1, -2), yt @ v  # (C, T, 9, 9), (C, T, 9)
    cost = gram.reshape(*gram.shape[:2], -1) @ WEIGHT_PAIRS.T - 2.0 * (b @ POSITION_WEIGHTS.T)  # (C, T, S)
    cost[missing.astype(np.float64) @ SUPPORT.T > 0.0] = np.inf
    c, ti, i = np.unravel_index(int(np.argmin(cost)), cost.shape)
    if not np.isfinite(cost[c, ti, i]):
        return poses[0].copy(), math.inf
    out = poses[c].copy()
    out[:2] += spacing * POSITION_OFFSETS[int(i)]
    out[2] = wrap_angle((o[c] + HEADING_OFFSETS[int(ti)]) * lattice.heading_step)
    return out, float(cost[c, ti, i] + v @ v)

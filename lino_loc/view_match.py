"""Matching the views a standing robot took against the map's stored views near its estimate.

Once the filter has found the neighbourhood, which map position the robot stands nearest to
is a finer question than its sensor model answers: the nearest-neighbour model (section 3)
spreads each view's likelihood over kernels 35 cm wide, while the map holds a view every
25 cm (virtual translations) at every heading (virtual headings). With the robot standing
still, every view taken since it stopped was taken at one pose, so the views can be compared
jointly with the map's own views. Hypotheses are the map's lattice points h = (g, o): a map
position g within :attr:`ViewMatchConfig.radius` of the filter's estimate and a robot heading o
on the map's heading lattice within :attr:`ViewMatchConfig.heading_span` of it. With y(g, t)
the map's stored features at position g and camera heading t, and views y_i taken at pans
u_i:

* cost ``c(h) = sum_i w_i |y_i - y(g, o + u_i)|^2`` (view weights ``w_i``, 1 unless the caller
  weighs the views by their fit) and the decision ``argmin_h c(h)`` (the map
  oracle's rule, here in the filter's neighbourhood), each feature weighed by the inverse of its
  own typical change over one lattice step in position and heading (:func:`feature_weights`, with
  :attr:`ViewMatchConfig.weigh_features`; the table and the views alike);
* a Gaussian posterior over the hypotheses, ``p(h) ∝ exp(-(c(h) - c_min) / (2 s^2))``; one
  view's squared distance to the map's view one lattice step away is the scale,
  ``s^2 = noise * d * m`` with m the median per-feature change between neighbouring lattice
  positions (:attr:`ViewLattice.neighbour_change`) and d the number of features (the features'
  errors are far from independent, so the scale is the whole view's, not one feature's);
* the expected entropy of the POSITION marginal of that posterior after a view at pan u, as
  the paper's H(u) (section 4) with the hypotheses in place of the particles: the predicted view
  of hypothesis h is its stored view ``y(g_h, o_h + u)``, and
  ``H(u) = sum_h p(h) H_pos(p(. | y(g_h, o_h + u)))`` (the heading is not what a position
  criterion judges).

Pans are rounded to the heading lattice (3 deg with the product's virtual headings).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from lino_loc.poses import wrap_angle

#: Positions closer than this (m) are one map position (:func:`views_by_position`).
POSITION_TOLERANCE = 0.02


def views_by_position(entries: np.ndarray, map_features: np.ndarray,
                      tolerance: float = POSITION_TOLERANCE) -> tuple[np.ndarray, np.ndarray, float]:
    """The map's entries as a table: the distinct map positions (G, 2), their features
    (G, H, d) at H headings evenly spaced from 0 (NaN where a position lacks one) and the
    heading spacing (rad). H is the number of distinct headings at the richest position
    (24 for a 15 deg survey, 120 with virtual headings every 3 deg). Positions closer than
    ``tolerance`` (m, linked in chains) are one, at their mean: a robot's survey measures each
    view's pose, and the views of one stop differ by its odometry's drift while it turns. The
    positions are in lexicographic (x, y) order."""
    e = np.asarray(entries, dtype=np.float64)
    points, at = np.unique(np.round(e[:, :2], 6), axis=0, return_inverse=True)
    at = at.reshape(-1)
    tree = cKDTree(points)
    _, cluster = connected_components(tree.sparse_distance_matrix(tree, tolerance, output_type="coo_matrix"),
                                      directed=False)
    n = int(cluster.max()) + 1
    mean = np.zeros((n, 2))
    np.add.at(mean, cluster[at], e[:, :2])
    mean /= np.bincount(cluster[at], minlength=n)[:, None]
    xy, order = np.unique(np.round(mean, 6), axis=0, return_inverse=True)
    pos_idx = order.reshape(-1)[cluster[at]]
    n_head = int(np.bincount(pos_idx).max())
    step = 2.0 * math.pi / n_head
    head_idx = np.round(np.mod(e[:, 2], 2.0 * math.pi) / step).astype(np.int64) % n_head
    f = np.asarray(map_features, dtype=np.float64)
    table = np.full((xy.shape[0], n_head, f.shape[1]), np.nan)
    table[pos_idx, head_idx] = f
    return xy, table, step


def feature_weights(table: np.ndarray, tree: cKDTree, spacing: float) -> np.ndarray:
    """Each feature's weight (d,): the inverse of its typical change over one lattice step,
    ``1 / sqrt(P_f + H_f)``, scaled so that the mean squared weight is 1. ``P_f`` is the mean
    of ``(y_f(g', t) - y_f(g, t))^2`` over neighbouring lattice positions g, g' (``spacing``
    apart; ``tree`` holds the positions of the table (G, H, d)) at every heading t both have,
    ``H_f`` the same over neighbouring headings at each position.

    With these weights the squared distance between views is a Gaussian log-likelihood with a
    diagonal covariance proportional to each feature's own change over one lattice step, in
    place of one variance for all features: a feature that varies fast from place to place
    counts no more than one that varies slowly. A feature that never changes gets weight 0; a
    map without any change weights every feature 1."""
    d = table.shape[2]
    rows = []
    if spacing > 0.0:
        pairs = tree.query_pairs(1.01 * spacing, output_type="ndarray")
        if pairs.size:
            rows.append(table[pairs[:, 1]] - table[pairs[:, 0]])
    rows.append(np.roll(table, -1, axis=1) - table)
    change = np.zeros(d)
    for diff in rows:
        diff = diff.reshape(-1, d)
        diff = diff[np.all(np.isfinite(diff), axis=1)]
        if diff.shape[0]:
            change += np.mean(diff * diff, axis=0)
    w = np.divide(1.0, np.sqrt(change), out=np.zeros(d), where=change > 0.0)
    norm = math.sqrt(float(np.mean(w * w)))
    return w / norm if norm > 0.0 else np.ones(d)


def _pairs(positions: np.ndarray, headings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every (position, heading) pair of the two axes, position major, as two flat arrays."""
    gg, oo = np.meshgrid(positions, headings, indexing="ij")
    return gg.ravel(), oo.ravel()


class ViewMatchConfig(BaseModel):
    """Settings of :class:`ViewLattice`'s decision and action values."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    radius: float = Field(0.5, gt=0.0, description="m; map positions this close to the estimate are hypotheses")
    heading_span: float = Field(
        math.radians(21.0), ge=0.0, le=math.pi, description="radians; robot headings this close to the estimate's"
    )
    max_hypotheses: int = Field(64, ge=2, description="the most probable hypotheses kept for H(u)")
    noise: float = Field(
        1.0, gt=0.0, description="the views' noise variance s^2 as a fraction of the map's own change "
        "between neighbouring lattice positions, summed over the features (module docstring)"
    )
    weigh_features: bool = Field(
        True, description="weigh each feature by the inverse of its own typical change over one "
        "lattice step in position and heading (a diagonal noise model; off: every feature alike)"
    )


class ViewLattice:
    """The map's features as a table of positions x headings, and the matches of
    views against it (module docstring).

    ``entries`` (N, 3) are the map entries' poses, ``features`` (N, d) their features; the
    table has G distinct positions and H headings evenly spaced from 0 (H: the most headings
    any position has), NaN where a position lacks one."""

    def __init__(self, entries: np.ndarray, features: np.ndarray, config: ViewMatchConfig | None = None) -> None:
        e = np.asarray(entries, dtype=np.float64)
        f = np.asarray(features, dtype=np.float64)
        if e.ndim != 2 or e.shape[1] != 3 or f.ndim != 2 or f.shape[0] != e.shape[0]:
            raise ValueError(f"entries (N, 3) and features (N, d) expected, got {e.shape} and {f.shape}")
        self.config = config or ViewMatchConfig()
        self.xy, self.table, self.heading_step = views_by_position(e, f)
        self.n_headings = self.table.shape[1]
        self.tree = cKDTree(self.xy)
        #: the lattice's spacing (m): the median distance of a position to its nearest other (0: one position)
        self.spacing = float(np.median(self.tree.query(self.xy, k=2)[0][:, 1])) if self.xy.shape[0] > 1 else 0.0
        #: the features' weights (d,): the table holds the map's features times them, and
        #: every view is weighed alike (:meth:`weigh`) before it is compared with the table
        self.weights = (feature_weights(self.table, self.tree, self.spacing) if self.config.weigh_features
                        else np.ones(f.shape[1]))
        self.table = self.table * self.weights
        #: |y(g, t)|^2 (G, H), NaN where the view is missing: the stored half of :meth:`costs`
        self.norms = np.einsum("ghd,ghd->gh", self.table, self.table)
        self.neighbour_change = self._neighbour_change()
        self.s2 = self.config.noise * f.shape[1] * self.neighbour_change

    def _neighbour_change(self) -> float:
        """The median over positions and headings of ``|y(g, t) - y(g', t)|^2 / d`` with g' the
        nearest other map position to g: how much a view changes over one lattice step (1 for
        a map of one position)."""
        if self.xy.shape[0] < 2:
            return 1.0
        _, nn = self.tree.query(self.xy, k=2)
        diff = self.table[nn[:, 1]] - self.table
        change = np.mean(diff * diff, axis=2)  # NaN where either position lacks that heading
        change = change[np.isfinite(change)]
        return float(np.median(change)) if change.size else 1.0

    def weigh(self, views: np.ndarray) -> np.ndarray:
        """Views (k, d) or one view (d,) in the table's weighted features."""
        return np.asarray(views, dtype=np.float64) * self.weights

    def near(self, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The hypotheses' axes: the map positions (P,) within ``radius`` of ``estimate``
        (x, y, theta), in ascending order, and the heading indices (O,) within
        ``heading_span`` of its heading; the hypotheses are every pair of them."""
        c = self.config
        g = np.flatnonzero(np.hypot(self.xy[:, 0] - estimate[0], self.xy[:, 1] - estimate[1]) <= c.radius)
        heads = np.arange(self.n_headings)
        o = heads[np.abs(wrap_angle(heads * self.heading_step - estimate[2])) <= c.heading_span + 1e-9]
        return g, o

    def beyond(self, estimate: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
        """The axes of the hypotheses far from ``estimate`` (x, y, theta): the map positions
        (P,) farther than ``distance`` (m) from it, in ascending order, and every heading index."""
        g = np.flatnonzero(np.hypot(self.xy[:, 0] - estimate[0], self.xy[:, 1] - estimate[1]) > distance)
        return g, np.arange(self.n_headings)

    def hypotheses(self, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position and heading indices (P O,) of the lattice points near ``estimate`` (x, y,
        theta): :meth:`near`'s pairs, position major."""
        return _pairs(*self.near(estimate))

    def _shift(self, pans: np.ndarray) -> np.ndarray:
        return np.round(np.asarray(pans, dtype=np.float64) / self.heading_step).astype(np.int64)

    def predicted(self, g: np.ndarray, o: np.ndarray, pans: np.ndarray) -> np.ndarray:
        """The stored views (A, C, d) of hypotheses (g, o) at camera pans ``pans`` (A,)."""
        cols = (o[None, :] + self._shift(pans)[:, None]) % self.n_headings
        return self.table[g[None, :], cols]

    def view_costs(self, g: np.ndarray, o: np.ndarray, pans: np.ndarray, views: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Each view's part of :meth:`costs` for the hypotheses ``g`` (P,) x ``o`` (O,):
        ``|y(g, o + u_i)|^2 - 2 y_i . y(g, o + u_i)`` (P, k, O), NaN where the stored view is
        missing, and ``|y_i|^2`` (k,); :meth:`weighed` sums them with any view weights.

        The dot products of the views with every stored view of the positions are one matrix
        product, so only scalars are gathered per hypothesis and view."""
        v = self.weigh(np.atleast_2d(np.asarray(views, dtype=np.float64)))
        g = np.asarray(g, dtype=np.int64)
        k = v.shape[0]
        # most positions (a search of the whole map): one product over the table, then its rows
        dots = (self.table @ v.T)[g] if 2 * g.size > self.xy.shape[0] else self.table[g] @ v.T
        terms = self.norms[g][:, :, None] - 2.0 * dots  # (P, H, k)
        cols = (np.asarray(o, dtype=np.int64)[None, :] + self._shift(pans)[:, None]) % self.n_headings  # (k, O)
        per_view = np.take(terms.reshape(g.size, self.n_headings * k), cols * k + np.arange(k)[:, None], axis=1)
        return per_view, np.sum(v * v, axis=1)

    @staticmethod
    def weighed(per_view: np.ndarray, norms: np.ndarray, view_weights: np.ndarray | None = None) -> np.ndarray:
        """``c(h)`` (P, O) from :meth:`view_costs`, view i's term counted ``view_weights[i]``
        times (None: once); inf where a stored view is missing."""
        w = np.ones(norms.size) if view_weights is None else np.asarray(view_weights, dtype=np.float64)
        c = np.maximum(np.einsum("pko,k->po", per_view, w) + float(w @ norms), 0.0)
        return np.where(np.isnan(c), np.inf, c)

    def costs(self, g: np.ndarray, o: np.ndarray, pans: np.ndarray, views: np.ndarray,
              view_weights: np.ndarray | None = None) -> np.ndarray:
        """``c(h)`` (P, O) of the views (k, d) taken at ``pans`` (k,), for every hypothesis of
        positions ``g`` (P,) x headings ``o`` (O,) (:meth:`near`); inf where a stored view is missing.
        With ``view_weights`` (k,), view i's term counts ``view_weights[i]`` times (None: once).
        Expanded as ``sum_i |y_i|^2 + |y(g, o + u_i)|^2 - 2 y_i . y(g, o + u_i)``
        (:meth:`view_costs`, :meth:`weighed`)."""
        return self.weighed(*self.view_costs(g, o, pans, views), view_weights)

    def residuals(self, pose: np.ndarray, pans: np.ndarray, views: np.ndarray) -> np.ndarray:
        """``|y_i - y(g, o + u_i)|^2`` (k,) of each view at the lattice point (g, o) nearest to
        ``pose`` (x, y, theta), in the weighted features; inf where the stored view is missing."""
        g = int(self.tree.query(np.asarray(pose, dtype=np.float64)[:2])[1])
        o = int(np.round(pose[2] / self.heading_step)) % self.n_headings
        y = self.predicted(np.array([g]), np.array([o]), np.atleast_1d(pans))[:, 0, :]
        r = np.sum((self.weigh(np.atleast_2d(views)) - y) ** 2, axis=1)
        return np.where(np.isnan(r), np.inf, r)

    def posterior(self, estimate: np.ndarray, pans: np.ndarray, views: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        """The kept hypotheses (g, o), their log posterior (normalized) and s^2; None when no
        hypothesis has every view."""
        pos, heads = self.near(estimate)
        if pos.size == 0 or heads.size == 0:
            return None
        c = self.costs(pos, heads, np.atleast_1d(pans), views).ravel()
        g, o = _pairs(pos, heads)
        if not np.isfinite(c).any():
            return None
        c_min = float(np.min(c))
        s2 = self.s2
        lp = -(c - c_min) / (2.0 * s2)
        keep = np.argsort(-lp, kind="stable")[: self.config.max_hypotheses]
        keep = keep[np.isfinite(lp[keep])]
        lp = lp[keep] - np.logaddexp.reduce(lp[keep])
        return g[keep], o[keep], lp, s2

    def best_poses(self, estimate: np.ndarray, pans: np.ndarray, views: np.ndarray, k: int,
                   view_weights: np.ndarray | None = None) -> list[np.ndarray]:
        """The poses (x, y, theta) of the ``k`` map positions near ``estimate`` whose stored views
        match ``views`` best (each view's term weighed by ``view_weights``, :meth:`costs`), each
        at its best heading, best first (fewer when fewer have every view)."""
        g, o = self.near(estimate)
        return self.ranked(g, o, self.costs(g, o, np.atleast_1d(pans), views, view_weights), k)

    def ranked(self, g: np.ndarray, o: np.ndarray, c: np.ndarray, k: int) -> list[np.ndarray]:
        """The poses of the ``k`` positions of ``g`` (P,) whose cost ``c`` (P, O) is least at
        their best heading of ``o`` (O,) (ties: the first heading, the earlier position), best
        first; those without a finite cost left out."""
        if c.size == 0:
            return []
        head = np.argmin(c, axis=1)
        best = c[np.arange(g.size), head]
        order = np.argsort(best, kind="stable")
        order = order[np.isfinite(best[order])][:k]
        return [np.array([self.xy[g[i], 0], self.xy[g[i], 1], wrap_angle(o[head[i]] * self.heading_step)])
                for i in order]

    def match(self, estimate: np.ndarray, pans: np.ndarray, views: np.ndarray) -> np.ndarray | None:
        """The decision: the pose (x, y, theta) of the best-matching hypothesis, None when there is none."""
        best = self.best_poses(estimate, pans, views, 1)
        return best[0] if best else None

    def expected_entropy(self, estimate: np.ndarray, pans: np.ndarray, views: np.ndarray,
                         actions: np.ndarray) -> np.ndarray | None:
        """H(u) (A,) of the hypotheses' posterior after one more view at each pan of ``actions``
        (module docstring); None when there is no hypothesis."""
        post = self.posterior(estimate, pans, views)
        if post is None:
            return None
        g, o, lp, s2 = post
        y = self.predicted(g, o, np.asarray(actions, dtype=np.float64))  # (A, C, d)
        sq = np.sum(y * y, axis=2)
        d2 = sq[:, :, None] + sq[:, None, :] - 2.0 * np.einsum("aid,ajd->aij", y, y)
        d2 = np.where(np.isnan(d2), np.inf, np.maximum(d2, 0.0))
        idx = np.arange(g.size)
        d2[:, idx, idx] = 0.0
        logp = lp[None, None, :] - d2 / (2.0 * s2)
        logp -= np.logaddexp.reduce(logp, axis=2, keepdims=True)
        _, pos = np.unique(g, return_inverse=True)
        onehot = np.zeros((g.size, int(pos.max()) + 1))
        onehot[np.arange(g.size), pos.reshape(-1)] = 1.0
        q = np.exp(logp) @ onehot  # (A, C, positions): the position marginal
        h = -np.sum(q * np.log(np.where(q > 0.0, q, 1.0)), axis=2)
        return np.sum(np.exp(lp)[None, :] * h, axis=1)

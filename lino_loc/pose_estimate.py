"""The filter's estimate: the dominant mode of a weighted set of robot poses, and its state.

The estimate is the dominant mode of the belief. When every particle lies within
:data:`COMPACT_XY` and :data:`COMPACT_THETA` of the weighted mean, the cloud is one mode and
its weighted mean and covariance are the estimate (the usual case while tracking; the
clustering is skipped). Otherwise particles are binned into cells (:data:`CLUSTER_CELL_XY` x
:data:`CLUSTER_CELL_THETA`), occupied cells that touch (26-neighbourhood, heading cyclic) form
clusters (:func:`cluster_labels`), and the heaviest cluster gives the weighted mean (circular
mean for theta) and the 3 x 3 covariance (heading differences wrapped about the mean).
Only occupied cells are represented, so the clustering costs O(M log M) time and O(M) memory
for M particles however far apart they are; a particle with a non-finite coordinate or
weight belongs to no mode and has no weight in the estimate.

The mode is converged (:meth:`EstimateConfig.converged`) when it holds at least
``converged_mass`` of the weight, the square root of the largest eigenvalue of its position
covariance is at most ``converged_std_xy`` and its heading standard deviation at most
``converged_std_theta``.

Usage::

    mean, cov, mass = dominant_mode(particles, weights)
    labels = cluster_labels(particles)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from lino_loc.poses import wrap_angle

FloatArray = NDArray[np.float64]
State = Literal["global", "tracking", "lost"]

# A cloud within this radius (m) and heading difference (rad) of its weighted mean is one mode
# and is not clustered (docs/results.md, "Notes moved from the code: filter").
COMPACT_XY = 1.0
COMPACT_THETA = math.radians(60.0)
# Cell size of the mode clustering, m and rad (docs/results.md, "Notes moved from the code:
# filter").
CLUSTER_CELL_XY = 0.5
CLUSTER_CELL_THETA = math.radians(30.0)


class EstimateConfig(BaseModel):
    """When the dominant mode counts as converged (the filter then tracks), ``filter.estimate``."""

    model_config = ConfigDict(extra="forbid")

    converged_mass: float = Field(
        0.6, ge=0.0, le=1.0, description="weight share the dominant mode must hold"
    )
    converged_std_xy: float = Field(
        0.5, gt=0.0, description="largest position standard deviation of the mode, m"
    )
    converged_std_theta: float = Field(
        math.radians(25.0), gt=0.0, description="largest heading standard deviation, rad"
    )

    def converged(self, cov: FloatArray, mass: float) -> bool:
        """Whether a mode of covariance ``cov`` (3 x 3) and weight ``mass`` is converged: the
        square root of the largest eigenvalue of the 2 x 2 position block, sqrt((a + d) / 2 +
        hypot((a - d) / 2, b)), and the heading's standard deviation under their limits."""
        a, b, d = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
        std_xy = math.sqrt(max(0.5 * (a + d) + math.hypot(0.5 * (a - d), b), 0.0))
        std_th = math.sqrt(max(float(cov[2, 2]), 0.0))
        return (
            mass >= self.converged_mass
            and std_xy <= self.converged_std_xy
            and std_th <= self.converged_std_theta
        )


def _axis_ranks(cells: FloatArray) -> NDArray[np.int64]:
    """Ranks of integer-valued cell coordinates that keep adjacency: sorted distinct values get
    consecutive ranks when they differ by 1 and ranks two apart otherwise, so two cells touch
    along this axis exactly when their ranks differ by at most 1. Ranks lie in [0, 2 U) for U
    distinct values, whatever the values' spread."""
    values, inverse = np.unique(cells, return_inverse=True)
    step = np.where(np.diff(values) == 1.0, 1, 2)
    rank = np.concatenate([np.zeros(1, dtype=np.int64), np.cumsum(step, dtype=np.int64)])
    return rank[inverse.reshape(-1)]


def _cell_components(
    kx: NDArray[np.int64], ky: NDArray[np.int64], it: NDArray[np.int64], n_th: int
) -> NDArray[np.int64]:
    """Component (0..C-1) of each occupied cell (rank x, rank y, heading bin), numbered in the
    order of each component's first cell in (x, y, theta) order; returns one per input row.

    The occupied cells are hashed to one integer key each (``np.unique``); each cell looks up
    its 13 "forward" neighbours of the 26-neighbourhood (heading bin cyclic) in the sorted key
    table (``np.searchsorted``), and ``scipy.sparse.csgraph.connected_components`` joins the
    cells found. O(M log M) time and O(M) memory for M particles."""
    ny = int(ky.max()) + 3  # y ranks shifted by one, so that neighbours y - 1 and y + 1 fit
    key = ((kx + 1) * ny + (ky + 1)) * n_th + it
    cells, inverse = np.unique(key, return_inverse=True)
    inverse = inverse.reshape(-1)
    u = cells.shape[0]
    if u == 1:
        return np.zeros(kx.shape[0], dtype=np.int64)
    ct = cells % n_th
    cxy = cells - ct
    src, dst = [], []
    for dx, dy, dt in _FORWARD_OFFSETS:
        target = cxy + (dx * ny + dy) * n_th + (ct + dt) % n_th
        pos = np.minimum(np.searchsorted(cells, target), u - 1)
        hit = np.flatnonzero(cells[pos] == target)
        src.append(hit)
        dst.append(pos[hit])
    s, d = np.concatenate(src), np.concatenate(dst)
    graph = coo_matrix((np.ones(s.shape[0], dtype=np.int8), (s, d)), shape=(u, u)).tocsr()
    _, comp = connected_components(graph, directed=True, connection="weak")
    _, first = np.unique(comp, return_index=True)  # first (smallest) cell of each component
    order = np.empty(first.shape[0], dtype=np.int64)
    order[np.argsort(first, kind="stable")] = np.arange(first.shape[0])
    return order[comp][inverse]


# Half of the 26-neighbourhood (dx, dy, dtheta): the offsets after (0, 0, 0) in lexicographic
# order; with each edge found from one side, the other half adds nothing.
_FORWARD_OFFSETS = tuple(
    (dx, dy, dt)
    for dx in (-1, 0, 1)
    for dy in (-1, 0, 1)
    for dt in (-1, 0, 1)
    if (dx, dy, dt) > (0, 0, 0)
)


def cluster_labels(
    poses: FloatArray, cell_xy: float = CLUSTER_CELL_XY, cell_theta: float = CLUSTER_CELL_THETA
) -> NDArray[np.int64]:
    """Connected components of occupied (x, y, theta) cells; heading bins are cyclic.

    Cells are ``floor(x / cell_xy)``, ``floor(y / cell_xy)`` and heading bin ``floor((theta +
    pi) / (2 pi / n))`` mod n, n = round(2 pi / cell_theta) (theta wrapped first). Two
    particles are in the same cluster when a chain of occupied cells, each touching the next
    (26-neighbourhood, bin n - 1 touching bin 0), joins their cells. Returns one label per pose:
    0..C-1, numbered in the order of each cluster's first cell in (x, y, theta) order; -1 for a
    pose with a non-finite coordinate (it belongs to no cluster).

    Only occupied cells are represented (:func:`_cell_components`): time O(M log M) and memory
    O(M) for M poses, whatever their spread.
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    labels = np.full(p.shape[0], -1, dtype=np.int64)
    finite = np.isfinite(p).all(axis=1)
    q = p if bool(finite.all()) else p[finite]
    if q.shape[0] == 0:
        return labels
    n_th = max(1, int(round(2.0 * math.pi / cell_theta)))
    kx = _axis_ranks(np.floor(q[:, 0] / cell_xy))
    ky = _axis_ranks(np.floor(q[:, 1] / cell_xy))
    it = np.floor((wrap_angle(q[:, 2]) + math.pi) / (2.0 * math.pi / n_th)).astype(np.int64) % n_th
    labels[finite] = _cell_components(kx, ky, it, n_th)
    return labels


def pose_stats(
    poses: FloatArray,
    weights: FloatArray,
    trig: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(mean, covariance, deviations from the mean (3, M) with theta wrapped) of weighted poses.

    ``trig`` = (cos theta, sin theta) of the poses when the caller has them (the filter reuses
    those of its likelihood evaluation); ``weights`` need not be normalized.
    """
    w = np.asarray(weights, dtype=np.float64)
    total = float(w.sum())
    if total != 1.0:
        w = w / total
    p = np.asarray(poses, dtype=np.float64)
    if trig is None:
        trig = (np.cos(p[:, 2]), np.sin(p[:, 2]))
    mean = w @ p  # (products of a vector and an (M, 3) array: single-threaded BLAS)
    mean[2] = math.atan2(float(np.dot(w, trig[1])), float(np.dot(w, trig[0])))
    d = p.T - mean[:, None]
    _wrap_deviation(d[2])
    cov = (d * w) @ d.T
    return mean, cov, d


def _wrap_deviation(a: FloatArray) -> None:
    """wrap_angle in place for differences of two wrapped angles (within [-2 pi, 2 pi]): one
    conditional shift, values already in [-pi, pi) unchanged (any others: the general wrap)."""
    np.subtract(a, 2.0 * np.pi, out=a, where=a >= np.pi)
    np.add(a, 2.0 * np.pi, out=a, where=a < -np.pi)
    if a.size and not (float(a.min()) >= -np.pi and float(a.max()) < np.pi):
        a[:] = wrap_angle(a)


def weighted_pose_stats(poses: FloatArray, weights: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Weighted mean (circular mean for theta) and 3 x 3 covariance (theta wrapped about the mean)."""
    mean, cov, _ = pose_stats(poses, weights)
    return mean, cov


def dominant_mode(
    poses: FloatArray,
    weights: FloatArray,
    *,
    compact_xy: float = COMPACT_XY,
    compact_theta: float = COMPACT_THETA,
    cell_xy: float = CLUSTER_CELL_XY,
    cell_theta: float = CLUSTER_CELL_THETA,
    trig: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, FloatArray, float]:
    """(mean, covariance, weight) of the heaviest mode of normalized weighted poses (see the
    module docstring); the clustering runs only when the cloud is not compact.

    A particle with a non-finite coordinate or weight belongs to no mode: it is left out of
    the mean and the covariance, and the returned weight is the mode's share of the whole
    weight. With no finite particle of positive weight: NaN mean and covariance, weight 0.
    Ties between equally heavy clusters go to the one whose first cell comes first in
    (x, y, theta) order."""
    p = np.asarray(poses, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    finite = np.isfinite(p).all(axis=1) & np.isfinite(w)
    if not bool(finite.all()):
        return _dominant_of_finite(p, w, finite, compact_xy, compact_theta, cell_xy, cell_theta)
    mean, cov, d = pose_stats(p, w, trig)
    r2 = d[0] * d[0]
    r2 += d[1] * d[1]
    if float(r2.max()) <= compact_xy**2 and float(np.abs(d[2]).max()) <= compact_theta:
        return mean, cov, 1.0
    labels = cluster_labels(p, cell_xy, cell_theta)
    if labels.max() == 0:  # one cluster
        return mean, cov, 1.0
    mass = np.bincount(labels, weights=w)
    best = int(np.argmax(mass))
    sel = labels == best
    mean, cov = weighted_pose_stats(p[sel], w[sel])
    return mean, cov, float(mass[best])


def _dominant_of_finite(
    p: FloatArray,
    w: FloatArray,
    finite: NDArray[np.bool_],
    compact_xy: float,
    compact_theta: float,
    cell_xy: float,
    cell_theta: float,
) -> tuple[FloatArray, FloatArray, float]:
    """:func:`dominant_mode` of the finite particles only, its weight a share of the whole
    finite weight of all particles (see there)."""
    total = float(np.sum(w[np.isfinite(w)]))
    kept = float(np.sum(w[finite]))
    if not finite.any() or not kept > 0.0 or not math.isfinite(total):
        return np.full(3, np.nan), np.full((3, 3), np.nan), 0.0
    mean, cov, mass = dominant_mode(
        p[finite], w[finite] / kept, compact_xy=compact_xy, compact_theta=compact_theta,
        cell_xy=cell_xy, cell_theta=cell_theta,
    )
    return mean, cov, mass * kept / total


@dataclass(frozen=True)
class Estimate:
    """The robot pose in the map frame and how much to trust it: the one estimate type of the
    filter, the Localizer and the service (``services.messages.PoseMessage.from_estimate``).

    ``pose`` and ``covariance`` are the dominant mode's weighted mean (circular mean for theta)
    and covariance over (x, y, theta); ``cluster_weight`` is that mode's share of the weight
    (1 when the cloud is compact); ``log_likelihood`` the predictive log-likelihood of the last
    observation, log p(y_t | y_1..t-1) (nan before the first one); ``doubt`` the evidence that
    the views no longer fit the belief as a fraction of the lost threshold (0 = they fit,
    1 = lost; ``lino_loc.lost_detection``); ``stamp`` the time of the frame it answers (s, None
    when the caller gave none); ``quality`` in [0, 1], higher meaning a smaller error
    (``lino_loc.quality``; 0 when unknown).
    """

    pose: FloatArray  # (3,) robot pose
    covariance: FloatArray  # (3, 3) over (x, y, theta)
    ess: float
    n_particles: int
    state: State
    cluster_weight: float  # weight of the dominant cluster, in [0, 1]
    log_likelihood: float  # last observation's predictive log-likelihood (nan if none yet)
    doubt: float = 0.0
    stamp: float | None = None
    quality: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (lists instead of arrays; a nan likelihood becomes None)."""
        ll = self.log_likelihood
        return {
            "stamp": self.stamp,
            "pose": [float(v) for v in self.pose],
            "covariance": [[float(v) for v in row] for row in self.covariance],
            "ess": float(self.ess),
            "n_particles": int(self.n_particles),
            "state": self.state,
            "log_likelihood": float(ll) if math.isfinite(ll) else None,
            "cluster_weight": float(self.cluster_weight),
            "doubt": float(self.doubt),
            "quality": float(self.quality),
        }

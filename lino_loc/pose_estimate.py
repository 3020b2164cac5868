"""The filter's estimate: the dominant mode of a weighted set of robot poses, and its state.

The estimate is the dominant mode of the belief. When every particle lies within
:data:`COMPACT_XY` and :data:`COMPACT_THETA` of the weighted mean, the cloud is one mode and
its weighted mean and covariance are the estimate (the usual case while tracking; the
clustering is skipped). Otherwise particles are binned into cells (:data:`CLUSTER_CELL_XY` x
:data:`CLUSTER_CELL_THETA`), occupied cells that touch (26-neighbourhood, heading cyclic) form
clusters (:func:`cluster_labels`), and the heaviest cluster gives the weighted mean (circular
mean for theta) and the 3 x 3 covariance (heading differences wrapped about the mean).

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
from scipy import ndimage

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


def cluster_labels(
    poses: FloatArray, cell_xy: float = CLUSTER_CELL_XY, cell_theta: float = CLUSTER_CELL_THETA
) -> NDArray[np.int64]:
    """Connected components of occupied (x, y, theta) cells; heading bins are cyclic.

    Two particles are in the same cluster when a chain of occupied cells, each touching the
    next (26-neighbourhood), joins their cells. Returns one label (0..C-1) per pose.
    Implementation: ``scipy.ndimage.label`` on the dense occupancy grid of the particles'
    bounding box, then the labels that touch across the heading seam (-pi / pi) are merged.
    """
    p = np.asarray(poses, dtype=np.float64)
    n_th = max(1, int(round(2.0 * math.pi / cell_theta)))
    ix = np.floor(p[:, 0] / cell_xy).astype(np.int64)
    iy = np.floor(p[:, 1] / cell_xy).astype(np.int64)
    it = np.floor((wrap_angle(p[:, 2]) + math.pi) / (2.0 * math.pi / n_th)).astype(np.int64) % n_th
    ix -= ix.min()
    iy -= iy.min()
    shape = (int(ix.max()) + 1, int(iy.max()) + 1, n_th)
    occ = np.zeros(shape, dtype=bool)
    occ[ix, iy, it] = True
    grid, n_lab = ndimage.label(occ, structure=np.ones((3, 3, 3), dtype=bool))
    if n_th >= 3 and n_lab > 1:
        # 26-neighbourhood across the seam: cell (x, y, last) touches (x + a, y + b, 0).
        first, last = grid[:, :, 0], grid[:, :, -1]
        pairs = []
        for a in (-1, 0, 1):
            for b in (-1, 0, 1):
                sa = slice(max(a, 0), shape[0] + min(a, 0))
                sb = slice(max(b, 0), shape[1] + min(b, 0))
                ta = slice(max(-a, 0), shape[0] + min(-a, 0))
                tb = slice(max(-b, 0), shape[1] + min(-b, 0))
                la, lb = last[ta, tb], first[sa, sb]
                both = (la > 0) & (lb > 0) & (la != lb)
                if both.any():
                    pairs.append(np.column_stack([la[both], lb[both]]))
        if pairs:
            parent = np.arange(n_lab + 1)

            def find(u: int) -> int:
                while parent[u] != u:
                    parent[u] = parent[parent[u]]
                    u = int(parent[u])
                return u

            for u, v in np.unique(np.concatenate(pairs), axis=0):
                ru, rv = find(int(u)), find(int(v))
                if ru != rv:
                    parent[max(ru, rv)] = min(ru, rv)
            roots = np.array([find(u) for u in range(n_lab + 1)])
            grid = roots[grid]
    if n_lab <= 1:
        return np.zeros(p.shape[0], dtype=np.int64)
    lab = grid[ix, iy, it]
    present = np.zeros(int(grid.max()) + 1, dtype=bool)  # relabel 0..C-1 without sorting
    present[lab] = True
    return (np.cumsum(present) - 1)[lab].astype(np.int64)



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
    module docstring); the clustering runs only when the cloud is not compact."""
    mean, cov, d = pose_stats(poses, weights, trig)
    r2 = d[0] * d[0]
    r2 += d[1] * d[1]
    if float(r2.max()) <= compact_xy**2 and float(np.abs(d[2]).max()) <= compact_theta:
        return mean, cov, 1.0
    labels = cluster_labels(poses, cell_xy, cell_theta)
    if labels.max() == 0:  # one cluster
        return mean, cov, 1.0
    mass = np.bincount(labels, weights=weights)
    best = int(np.argmax(mass))
    sel = labels == best
    mean, cov = weighted_pose_stats(poses[sel], weights[sel])
    return mean, cov, float(mass[best])


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
    when the caller gave none).
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
        }

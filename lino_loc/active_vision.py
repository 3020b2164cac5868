"""Active vision: the pan angle whose next image is expected to leave the least pose entropy.

Paper, section 4, and its reference [10] (Porta, Terwijn, Kroese, "Efficient entropy-based
action selection for appearance-based robot localization", ICRA 2003). For a candidate pan
angle ``u`` the expected entropy of the pose after turning the camera to ``u`` and taking an
image is approximated with the two parts of the localization system:

* the particle set gives a discrete set of poses where the robot may be: particles ``x_i``
  with weights ``pi_i`` (a weighted subsample of at most ``max_particles``; duplicate
  particles, frequent after resampling, are merged and their weights summed);
* the appearance map gives the observation the camera would get at each of them: the
  predicted observation ``y_i(u)`` is the feature vector of the map entry NEAREST to the
  camera pose ``camera_pose(x_i, u)`` (no interpolation). "Nearest" uses the metric of the
  sensor model's kernel, ``|dp|^2 / sigma_xy^2 + kappa * chord(dtheta)^2`` with
  ``chord = 2 sin(dtheta / 2)`` (the angle wrapped; ``kappa = 1 / sigma_theta^2``), i.e. the
  map entry whose kernel is highest at that camera pose;
* for each predicted observation the posterior the filter would reach is, over the same
  particles, ``w_k ∝ pi_k p(y_i(u) | camera_pose(x_k, u))`` with the filter's own sensor model
  (:class:`lino_loc.sensor_model.NearestNeighbourSensorModel`: the J map entries nearest in
  feature space, the lambda weights, the kernels, the outlier component);
* its entropy is the DISCRETE entropy of the reweighted particle set,
  ``H_i(u) = -sum_k w_k log w_k`` (nats), and ``H(u) = sum_i pi_i H_i(u)``.

The chosen action is ``argmin_u H(u) + move_cost * |u - pan|`` (the head-movement cost is an
optional tie-breaker, nats per radian). The discrete entropy is bounded by log M, is
invariant to the units of the pose and needs no density estimate; the differential entropy
of a Gaussian fitted to the particles, ``0.5 log((2 pi e)^3 det Sigma)``, is the usual
alternative but misjudges multi-modal beliefs (two tight, distant hypotheses have a large
covariance), which are exactly the beliefs where the camera should move.

Vectorization. Since a predicted observation IS a map entry, the sensor-model mixture of
every map entry's features (its J feature-space neighbours and log-lambdas) is computed once
(an N x J table). The kernel phi(c | m) of the sensor model is an isotropic Gaussian in the
embedding ``e(x, y, theta) = (x / sigma_xy, y / sigma_xy, sqrt(kappa) cos theta,
sqrt(kappa) sin theta)``: ``log phi = -|e(c) - e(m)|^2 / 2 + const`` exactly (von Mises:
``kappa cos d = kappa - kappa chord(d)^2 / 2``). So one call costs one (N x 4) @ (4 x A M)
product and one exponential for the kernels of all map entries at all camera poses (A actions
x M particles), then per action a sparse (M x N, J non-zeros per row) times dense (N x M)
product gives the likelihood of every predicted observation at every particle, and the
(A x M x M) entropies follow. The nearest map entry of the A M camera poses comes from a
k-d tree over the same embedding. Kernel factors and particle weights below
``exp(LOG_NEGLIGIBLE)`` of their peak are floored (:data:`LOG_NEGLIGIBLE`: below the float32
resolution of the sums, it keeps them free of subnormal numbers).

The policy (:class:`ActivePolicy`) decides WHEN to look (belief not converged: the filter
state is ``global`` or ``lost``, or the belief entropy is above ``trigger_entropy``; or the
observations fit the map badly: the lost detector's evidence has reached ``trigger_doubt`` of
its threshold, or the last predictive log-likelihood is below ``min_log_likelihood``),
WHEN to stop (converged, or no action lowers the expected entropy by ``min_entropy_gain``),
turns the head back to ``home_pan`` (ahead) once converged, waits for the head to settle and for a frame taken after it settled, and never commands a
pan outside the intersection of its own range and the head's limits. With
``reliability.enabled`` it discounts H(u) at pans near views that fit no map entry
(:mod:`lino_loc.pan_reliability`; the caller feeds the views with :meth:`ActivePolicy.observe`).
It is pure logic: the caller (the daemon) passes the head's present pan, its moving flag and the time,
and may pass ``view_values``: action values that replace H(u) when it gives some (the service's
standing match, once the belief is gathered on a standing base: :mod:`lino_loc.view_spread`).

Usage::

    evaluator = ActionEvaluator(sensor_model, ActiveVisionConfig())
    values = evaluator.evaluate(pf.particles, pf.log_weights)      # values.expected_entropy (A,)
    policy = ActivePolicy(evaluator, head_limits=(-2.6, 2.6))
    d = policy.decide(pf.particles, pf.log_weights, state=est.state,
                      log_likelihood=est.log_likelihood, pan=head.pan, moving=head.moving,
                      now=time.time(), frame_stamp=frame.stamp)
    if d.command is not None:
        head.command(d.command, 0.0)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy import sparse
from scipy.spatial import cKDTree
from scipy.special import i0e

from lino_loc.interpolated_appearance import InterpolatedSensorModel
from lino_loc.pan_reliability import PanReliability, PanReliabilityConfig
from lino_loc.poses import wrap_angle
from lino_loc.resampling import logsumexp
from lino_loc.sensor_model import LOG_2PI, NearestNeighbourSensorModel, lambda_log_weights
from lino_loc.weights import Weights

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class ActiveVisionConfig(BaseModel):
    """Action evaluation and policy settings (the field names of the service's
    ``[active_vision]`` section, plus the ones the policy adds)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = True
    n_actions: int = Field(22, ge=2, le=360, description="candidate pan angles (the paper: 22)")
    pan_min: float = Field(-2.6, ge=-math.pi, le=math.pi, description="radians")
    pan_max: float = Field(2.6, ge=-math.pi, le=math.pi, description="radians")
    max_particles: int = Field(
        150, ge=1, description="particles used to evaluate H(u) (the paper: up to 150)"
    )
    min_entropy_gain: float = Field(
        0.05, ge=0.0, description="nats; move only if the best action lowers H by this much"
    )
    trigger_entropy: float | None = Field(
        None,
        description="nats; also look while the belief entropy (over cells) is above this "
        "(unset: only the filter state and the observation fit decide)",
    )
    trigger_doubt: float | None = Field(
        0.5,
        ge=0.0,
        description="look when the evidence that the views no longer fit the belief reaches this "
        "fraction of the lost threshold (lino_loc.lost_detection; 1 = lost); unset: not used",
    )
    min_log_likelihood: float | None = Field(
        None,
        description="look when the last observation's predictive log-likelihood is below this "
        "(the observation fits the map badly); unset: not used",
    )
    min_interval_s: float = Field(1.0, ge=0.0, description="seconds between head movements")
    settle_s: float = Field(0.2, ge=0.0, description="wait after the head stops before using frames")
    move_cost: float = Field(
        1e-3, ge=0.0, description="nats per radian of head movement added to H(u) (tie-breaker)"
    )
    pan_tolerance: float = Field(
        0.02, ge=0.0, description="radians; a best action this close to the present pan = stay"
    )
    home_pan: float | None = Field(
        0.0,
        description="radians; once localized the head returns here (0: looking ahead, where a "
        "driving robot wants its camera); unset: it stays where the last look left it",
    )
    predicted_neighbours: Literal["all", "leave_one_out"] = Field(
        "all",
        description="sensor model of a predicted observation (a map entry's features): its J "
        "nearest map entries ('all', the entry itself first) or the J nearest among the OTHER "
        "entries ('leave_one_out': an image taken off the map grid never matches an entry exactly)",
    )
    reliability: PanReliabilityConfig = Field(
        default_factory=PanReliabilityConfig,
        description="discount H(u) at pans whose recent views fit no map entry (lino_loc.pan_reliability)",
    )
    entropy_cell_xy: float = Field(0.5, gt=0.0, description="cell size (m) of the belief entropy")
    entropy_cell_theta: float = Field(
        math.radians(30.0), gt=0.0, description="cell size (rad) of the belief entropy"
    )

    @model_validator(mode="after")
    def _range(self) -> ActiveVisionConfig:
        if not self.pan_min < self.pan_max:
            raise ValueError(f"pan_min ({self.pan_min}) must be < pan_max ({self.pan_max})")
        return self

    def actions(self) -> FloatArray:
        """The candidate pan angles: ``n_actions`` evenly spaced over [pan_min, pan_max]."""
        return np.linspace(self.pan_min, self.pan_max, self.n_actions)


# --------------------------------------------------------------------------- entropies


def discrete_entropy(log_weights: ArrayLike, axis: int = -1) -> FloatArray:
    """Shannon entropy (nats) of normalized-or-not log-weights along ``axis``:
    ``-sum w log w`` with ``w = softmax(log_weights)``; log N for equal weights, 0 for one
    particle holding all the weight."""
    lw = np.asarray(log_weights, dtype=np.float64)
    lw = lw - logsumexp(lw, axis=axis, keepdims=True)
    w = np.exp(lw)
    terms = np.zeros_like(w)
    np.multiply(w, lw, out=terms, where=w > 0)
    return -np.sum(terms, axis=axis)


def belief_entropy(
    particles: ArrayLike,
    log_weights: ArrayLike,
    cell_xy: float = 0.5,
    cell_theta: float = math.radians(30.0),
) -> float:
    """Entropy (nats) of the belief's mass over pose cells (``cell_xy`` x ``cell_xy`` x
    ``cell_theta``, heading cells aligned at -pi).

    Unlike the discrete entropy of the weights (log N after every resampling, however spread
    the particles are), this measures how spread the belief is: near 0 when the particles sit
    in one cell, log(number of cells) for a belief spread evenly over them (log N for N
    particles in N distinct cells with equal weights)."""
    p = np.asarray(particles, dtype=np.float64).reshape(-1, 3)
    w = np.exp(Weights.from_log(log_weights, one_pass=False).log)
    n_th = max(1, int(round(2.0 * math.pi / cell_theta)))
    ix = np.floor(p[:, 0] / cell_xy).astype(np.int64)
    iy = np.floor(p[:, 1] / cell_xy).astype(np.int64)
    it = np.floor((wrap_angle(p[:, 2]) + math.pi) / (2.0 * math.pi / n_th)).astype(np.int64) % n_th
    keys = np.stack([ix, iy, it], axis=1)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    mass = np.bincount(inv.reshape(-1), weights=w)
    mass = mass[mass > 0]
    return float(-np.sum(mass * np.log(mass)))


# --------------------------------------------------------------------------- evaluation


@dataclass(frozen=True)
class ActionValues:
    """Result of one action evaluation."""

    actions: FloatArray  # (A,) pan angles, radians
    expected_entropy: FloatArray  # (A,) H(u), nats
    current_entropy: float  # discrete entropy of the (subsampled) belief, nats
    n_particles: int  # particles used (after subsampling and merging duplicates)

    @property
    def gain(self) -> FloatArray:
        """Expected entropy reduction of each action, nats."""
        return self.current_entropy - self.expected_entropy

    def best(self, pan: float | None = None, move_cost: float = 0.0, exclude: ArrayLike | None = None) -> int:
        """Index of argmin H(u) + move_cost |u - pan| (``exclude``: indices not allowed)."""
        score = self.expected_entropy.copy()
        if pan is not None and move_cost > 0.0:
            score = score + move_cost * np.abs(self.actions - pan)
        if exclude is not None:
            score[np.asarray(exclude, dtype=np.int64)] = np.inf
        return int(np.argmin(score))


def subsample(
    particles: ArrayLike,
    log_weights: ArrayLike,
    max_particles: int,
    rng: np.random.Generator | None = None,
) -> tuple[FloatArray, FloatArray]:
    """At most ``max_particles`` distinct particles and their normalized log-weights.

    Identical particles are merged (weights summed). If more remain, a systematic resample of
    ``max_particles`` draws (offset from ``rng``, or 0.5 without one) is taken and merged
    again, so the weights stay proportional to the belief."""
    p = np.asarray(particles, dtype=np.float64).reshape(-1, 3)
    lw = Weights.from_log(np.asarray(log_weights, dtype=np.float64).reshape(-1), one_pass=False).log
    p, lw = _merge(p, lw)
    if p.shape[0] > max_particles:
        w = np.exp(lw)
        u0 = rng.random() if rng is not None else 0.5
        pos = (u0 + np.arange(max_particles)) / max_particles
        cdf = np.cumsum(w)
        cdf[-1] = 1.0
        idx = np.minimum(np.searchsorted(cdf, pos), p.shape[0] - 1)
        p, lw = _merge(p[idx], np.full(max_particles, -math.log(max_particles)))
    return p, lw


def _merge(p: FloatArray, lw: FloatArray) -> tuple[FloatArray, FloatArray]:
    uniq, inv = np.unique(p, axis=0, return_inverse=True)
    if uniq.shape[0] == p.shape[0]:
        return p, lw
    w = np.bincount(inv.reshape(-1), weights=np.exp(lw - lw.max()))
    return uniq, np.log(w) - math.log(w.sum())


LOG_NEGLIGIBLE = -40.0
"""The floor of :class:`ActionEvaluator`'s float32 sums: every kernel factor (peak 1) and every
particle weight relative to the largest, ``x``, enters as ``max(x, c) - c`` with
``c = exp(LOG_NEGLIGIBLE)``. That differs from ``x`` by less than ``c`` and equals it in
float32 for ``x >= c 2^25``, so a likelihood that holds the outlier floor, or any kernel above
``c 2^25``, is unchanged. It keeps the sums free of float32 subnormal numbers (far kernels,
products of two small factors), which the CPU multiplies and adds in microcode, many times
slower than normal ones."""


def _kernel_exp(t: np.ndarray) -> np.ndarray:
    """``max(exp(t), c) - c`` in place, in the dtype of ``t`` (``c = exp(LOG_NEGLIGIBLE)``)."""
    lo = t.dtype.type(LOG_NEGLIGIBLE)
    np.maximum(t, lo, out=t)
    np.exp(t, out=t)
    t -= np.exp(np.full(1, lo, dtype=t.dtype))[0]
    return np.maximum(t, t.dtype.type(0.0), out=t)  # exp's last-bit rounding may differ per path


class ActionEvaluator:
    """H(u) for candidate pan angles with the filter's own sensor model (module docstring).

    Two ways to get the kernels of all map entries at all camera poses: when the map is a
    product grid (every surveyed position holds the same set of headings, as a survey by
    ``lino-loc survey`` does) the kernel factors into a position part (unique positions x
    particles) and a heading part (unique headings x actions x particles), one broadcast
    product away from the full table, and the nearest map entry is the nearest position with
    the nearest heading; otherwise the full (N x A M) table is one product in the kernel
    embedding and one exponential, and a k-d tree gives the nearest entries (slower, see
    ``benchmarks/bench_active.py``). ``grid`` is True on the fast path.
    """

    def __init__(
        self,
        model: NearestNeighbourSensorModel,
        config: ActiveVisionConfig | None = None,
        use_grid: bool = True,
    ) -> None:
        self.config = config or ActiveVisionConfig()
        self.model = model
        c = model.config
        self.sigma_xy = float(c.sigma_xy)
        self.kappa = 1.0 / float(c.sigma_theta) ** 2
        self.outlier_weight = float(c.outlier_weight)
        self.map_poses = np.asarray(model.poses, dtype=np.float64)
        n_map = self.map_poses.shape[0]
        # The sensor mixture of every map entry's own features: N x J neighbours, log-lambdas.
        idx, d2 = self._predicted_neighbours(model)
        self.nn_index = idx
        self.nn_log_lambda = lambda_log_weights(d2, c.lambda_scale, c.lambda_scale_factor)
        # log of the kernel's normalizer: phi = exp(-|de|^2 / 2 + log_norm)
        self.log_norm = -(LOG_2PI + 2.0 * math.log(self.sigma_xy)) - (
            LOG_2PI + math.log(float(i0e(self.kappa)))
        )
        self.log_floor = (
            math.log(self.outlier_weight) + model.bounds.log_uniform_density
            if self.outlier_weight > 0.0
            else -math.inf
        )
        self._floor_over_norm = (
            math.exp(self.log_floor - self.log_norm) if self.log_floor > -math.inf else 0.0
        )
        grid = self._product_grid() if use_grid else None
        self.grid = grid is not None
        if grid is not None:
            self._positions, self._headings, column = grid  # column[j]: p * H + h of entry j
        else:
            column = np.arange(n_map)
            self._emb_map32 = self.embed(self.map_poses).astype(np.float32)
            self._sq_map = np.einsum("ij,ij->i", self._emb_map32, self._emb_map32)
            self._tree = cKDTree(self.embed(self.map_poses))
        self._column = column
        if grid is not None:
            self._cos_h = np.cos(self._headings).astype(np.float32)
            self._sin_h = np.sin(self._headings).astype(np.float32)
        self._entry_of_column = np.empty(n_map, dtype=np.int64)
        self._entry_of_column[column] = np.arange(n_map)
        # Per map entry (indexed by column): its neighbours' columns and (1 - outlier) lambdas.
        self._nn_cols = column[idx][self._entry_of_column].astype(np.int32)
        self._nn_lam = (np.exp(self.nn_log_lambda) * (1.0 - self.outlier_weight)).astype(np.float32)[
            self._entry_of_column
        ]
        if grid is not None:  # position and heading index of each neighbour column
            self._nn_pcol = (self._nn_cols // self._headings.size).astype(np.intp)
            self._nn_hcol = (self._nn_cols % self._headings.size).astype(np.intp)

    def _predicted_neighbours(
        self, model: NearestNeighbourSensorModel
    ) -> tuple[IntArray, FloatArray]:
        """(indices, squared feature distances), (N, J), of the J map entries nearest to each map
        entry's own features: the sensor mixture of a view predicted at that entry. With
        ``predicted_neighbours = "leave_one_out"`` the entry itself is left out (the J nearest
        others; when the entry is not among its J + 1 nearest, the farthest of them goes)."""
        n_map = model.poses.shape[0]
        if self.config.predicted_neighbours != "leave_one_out" or model.j >= n_map:
            return model.neighbours(model.features)
        idx, d2 = model.neighbours(model.features, model.j + 1)
        own = idx == np.arange(n_map)[:, None]
        drop = np.where(own.any(axis=1), np.argmax(own, axis=1), model.j)
        keep = np.ones_like(own)
        keep[np.arange(n_map), drop] = False
        return idx[keep].reshape(n_map, model.j), d2[keep].reshape(n_map, model.j)

    def _product_grid(self) -> tuple[FloatArray, FloatArray, IntArray] | None:
        """(positions (P, 2), headings (H,), column of each entry) if the map is a product grid."""
        p = self.map_poses
        pos, pinv = np.unique(np.round(p[:, :2], 6), axis=0, return_inverse=True)
        hd, hinv = np.unique(np.round(wrap_angle(p[:, 2]), 6), return_inverse=True)
        n_p, n_h = pos.shape[0], hd.shape[0]
        if n_p * n_h != p.shape[0]:
            return None
        column = pinv.reshape(-1) * n_h + hinv.reshape(-1)
        if np.unique(column).size != p.shape[0]:
            return None
        return pos, hd, column.astype(np.int64)

    def embed(self, poses: ArrayLike) -> FloatArray:
        """Kernel embedding (x/s, y/s, sqrt(kappa) cos t, sqrt(kappa) sin t) of poses (..., 3)."""
        p = np.asarray(poses, dtype=np.float64)
        rk = math.sqrt(self.kappa)
        return np.stack(
            [
                p[..., 0] / self.sigma_xy,
                p[..., 1] / self.sigma_xy,
                rk * np.cos(p[..., 2]),
                rk * np.sin(p[..., 2]),
            ],
            axis=-1,
        )

    @property
    def actions(self) -> FloatArray:
        return self.config.actions()

    def _kernels(self, p: FloatArray, u: FloatArray) -> tuple[np.ndarray, IntArray]:
        """Kernel table exp(-|e(m_j) - e(c_ak)|^2 / 2) as (A, N, M) float32 (floored:
        :data:`LOG_NEGLIGIBLE`) with entries in column order, and the column of the nearest map entry to each camera pose (A, M)."""
        a_n, m = u.size, p.shape[0]
        if self.grid:
            g, v, pred = self._grid_factors(p, u)
            kern = g[None, :, None, :] * v[:, None, :, :]  # (A, P, H, M)
            return kern.reshape(a_n, -1, m), pred.astype(np.int64)
        cam = np.repeat(p[None, :, :], a_n, axis=0)
        cam[:, :, 2] = cam[:, :, 2] + u[:, None]
        emb = self.embed(cam).reshape(a_n * m, 4)
        _, near = self._tree.query(emb, k=1)
        e32 = emb.astype(np.float32)
        t = self._emb_map32 @ e32.T  # -|e_n - e_c|^2 / 2 = e_n.e_c - |e_n|^2/2 - |e_c|^2/2
        t -= 0.5 * self._sq_map[:, None]
        t -= 0.5 * np.einsum("ij,ij->i", e32, e32)[None, :]
        np.minimum(t, 0.0, out=t)  # round-off
        t = _kernel_exp(t)
        kern = t.reshape(-1, a_n, m).transpose(1, 0, 2)
        return np.ascontiguousarray(kern), np.asarray(near, dtype=np.int64).reshape(a_n, m)

    def _grid_factors(self, p: FloatArray, u: FloatArray) -> tuple[np.ndarray, np.ndarray, IntArray]:
        """On a product grid the kernel factorizes, exp(-|e(m_(p,h)) - e(c_ak)|^2 / 2) =
        g[p, k] v[a, h, k]: position factor g (P, M), heading factor v (A, H, M) (float32, each
        floored: :data:`LOG_NEGLIGIBLE`), and the column of the nearest map entry to each
        camera pose (A, M)."""
        pos = self._positions
        dx = pos[:, 0:1] - p[None, :, 0]
        dy = pos[:, 1:2] - p[None, :, 1]
        lg = -(dx * dx + dy * dy) / (2.0 * self.sigma_xy**2)  # (P, M)
        near_p = np.argmax(lg, axis=0)
        g = _kernel_exp(lg.astype(np.float32))
        cam = p[None, :, 2] + u[:, None]  # (A, M)
        # cos(cam - h) = cos cam cos h + sin cam sin h, in float32 (A, H, M)
        ang = np.cos(cam).astype(np.float32)[:, None, :] * self._cos_h[None, :, None]
        ang += np.sin(cam).astype(np.float32)[:, None, :] * self._sin_h[None, :, None]
        near_h = np.argmax(ang, axis=1)
        ang -= np.float32(1.0)
        ang *= np.float32(self.kappa)
        v = _kernel_exp(ang)
        return g, v, near_p[None, :] * self._headings.size + near_h

    def _mixture_sums(self, p: FloatArray, u: FloatArray) -> tuple[np.ndarray, IntArray]:
        """S[a, i, k] = sum_j (1 - w_out) lambda_j exp(-|e(m_j) - e(c_ak)|^2 / 2) for the
        predicted observation of particle i (float32, without the kernel normalizer), and the
        predicted map entries (A, M)."""
        a_n, m = u.size, p.shape[0]
        if self.grid and self._headings.size * self._positions.shape[0] > 2 * self._nn_cols.shape[1] * m:
            return self._mixture_sums_gather(p, u)
        kern, pred_col = self._kernels(p, u)
        n_map = kern.shape[1]
        j = self._nn_cols.shape[1]
        cols = self._nn_cols[pred_col] + (np.arange(a_n, dtype=np.int32) * n_map)[:, None, None]
        lam = sparse.csr_matrix(
            (self._nn_lam[pred_col].reshape(-1), cols.reshape(-1), np.arange(0, a_n * m * j + 1, j)),
            shape=(a_n * m, a_n * n_map),
        )
        s = lam @ kern.reshape(a_n * n_map, m)
        return np.asarray(s).reshape(a_n, m, m), self._entry_of_column[pred_col]

    def _mixture_sums_gather(self, p: FloatArray, u: FloatArray) -> tuple[np.ndarray, IntArray]:
        """:meth:`_mixture_sums` on a product grid without the (A, P, H, M) kernel table: the
        kernel factorizes, phi(c | m_(p,h)) ~ g[p, k] v[a, h, k] (position x heading), so
        only the J neighbours of each predicted observation are gathered, A M J M products
        whatever the map size. Used when the table would be larger (many headings: maps with
        virtual headings, :mod:`lino_loc.virtual_views`). One action at a time, into two
        reused (M J, M) buffers that stay in cache, instead of one (A, M, J, M) array for all
        actions (1.8 MB of temporaries instead of 40 MB at 150 x 22, J = 10; faster too)."""
        a_n, m = u.size, p.shape[0]
        j = self._nn_cols.shape[1]
        g, v, pred_col = self._grid_factors(p, u)
        lam = self._nn_lam[pred_col][:, :, None, :]  # (A, M, 1, J)
        pcol = self._nn_pcol[pred_col].reshape(a_n, m * j)  # position of each neighbour
        hcol = self._nn_hcol[pred_col].reshape(a_n, m * j)  # heading of each neighbour
        s = np.empty((a_n, m, 1, m), dtype=np.float32)
        kern = np.empty((m * j, m), dtype=np.float32)
        head = np.empty((m * j, m), dtype=np.float32)
        for a in range(a_n):
            np.take(g, pcol[a], axis=0, out=kern)  # position factor of each neighbour
            np.take(v[a], hcol[a], axis=0, out=head)  # heading factor
            kern *= head
            np.matmul(lam[a], kern.reshape(m, j, m), out=s[a])  # sum_j lambda_j phi_j
        return s.reshape(a_n, m, m), self._entry_of_column[pred_col]

    def likelihoods(self, particles: ArrayLike, actions: ArrayLike) -> tuple[FloatArray, IntArray]:
        """log p(y_i(u) | camera_pose(x_k, u)) as (A, M_i, M_k), and the predicted map entries (A, M).

        Equals ``model.log_likelihood_matrix(features[n], camera_pose(particles, u))`` row by
        row (the tests check it); computed with the cached N x J mixtures and the floor of
        :data:`LOG_NEGLIGIBLE` (outside the bounds a likelihood below it can be -inf)."""
        p = np.asarray(particles, dtype=np.float64).reshape(-1, 3)
        u = np.asarray(actions, dtype=np.float64).reshape(-1)
        s, pred = self._mixture_sums(p, u)
        with np.errstate(divide="ignore"):
            out = np.log(s.astype(np.float64)) + self.log_norm
        if self.log_floor > -math.inf:
            floor = np.where(self.model.bounds.contains(p[:, :2]), self.log_floor, -np.inf)
            np.logaddexp(out, floor[None, None, :], out=out)
        return out, pred

    def evaluate(
        self,
        particles: ArrayLike,
        log_weights: ArrayLike,
        actions: ArrayLike | None = None,
        rng: np.random.Generator | None = None,
    ) -> ActionValues:
        """H(u) for every candidate pan angle (default: the configured ``n_actions``)."""
        u = self.actions if actions is None else np.asarray(actions, dtype=np.float64).reshape(-1)
        p, lw = subsample(particles, log_weights, self.config.max_particles, rng)
        pi = np.exp(lw)
        s, _ = self._mixture_sums(p, u)  # (A, i, k) float32, likelihood / kernel normalizer
        # q = pi_k p(y_i | x_k) / const, in linear space (the floor keeps it positive inside
        # the bounds); H_i = log Z - sum_k q log q / Z with Z = sum_k q.
        inside = self.model.bounds.contains(p[:, :2])
        s += (self._floor_over_norm * inside).astype(np.float32)[None, None, :]
        s *= _kernel_exp(lw - lw.max()).astype(np.float32)[None, None, :]  # pi_k / max pi, floored
        z = s.sum(axis=-1, dtype=np.float64)
        lq = np.zeros_like(s)
        np.log(s, out=lq, where=s > 0)
        sq = np.einsum("aik,aik->ai", s, lq, dtype=np.float64)
        ok = z > 0
        h = np.full(z.shape, float(discrete_entropy(lw)))  # nothing explains y_i: no information
        h[ok] = np.log(z[ok]) - sq[ok] / z[ok]
        expected = h @ pi
        return ActionValues(
            actions=u,
            expected_entropy=expected,
            current_entropy=float(discrete_entropy(lw)),
            n_particles=int(p.shape[0]),
        )


class InterpolatedActionEvaluator:
    """H(u) with the interpolated sensor model (``lino_loc.interpolated_appearance``).

    The predicted observation of particle i after the move is the map's appearance
    interpolated at its camera pose, ``y_i(u) = f(camera_pose(x_i, u))`` (not the nearest map
    entry), and the likelihood of it at particle k is the model's own,
    ``(1 - w_out) L_ik / Z_i + w_out u``, ``L_ik = exp(-|W (f(c_i) - f(c_k))|^2 / 2)``. The
    normalizer Z of a predicted observation is interpolated from those of the map entries'
    own features (:attr:`InterpolatedSensorModel.node_log_normalizer`, computed once) with the
    same trilinear weights: exact at the lattice poses. H_i(u) and H(u) as in the module
    docstring; a predicted observation at a pose without map corners carries no information
    (H_i = the current entropy). Cost: A M interpolations and A (M x M) distance products; the
    weights are summed in linear space in float32, each row scaled by Z_i / (1 - w_out) (which
    leaves its normalized weights unchanged), as :class:`ActionEvaluator` does."""

    def __init__(self, model: InterpolatedSensorModel, config: ActiveVisionConfig | None = None) -> None:
        self.config = config or ActiveVisionConfig()
        self.model = model
        self._node_log_z = model.node_log_normalizer

    @property
    def actions(self) -> FloatArray:
        return self.config.actions()

    def _predicted(self, p: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """Whitened interpolated features (A, M, d), log Z (A, M) and validity (A, M) of the
        camera poses of particles ``p`` at pans ``u``."""
        a_n, m = u.size, p.shape[0]
        th = (p[None, :, 2] + u[:, None]).reshape(-1)
        px, py = np.tile(p[:, 0], a_n), np.tile(p[:, 1], a_n)
        app = self.model.appearance
        idx, w = app.lattice.corners(px, py, th)
        f, ok = app.features_trig(px, py, th)
        log_z = np.einsum("mc,mc->m", w, self._node_log_z[np.maximum(idx, 0)])
        fw = (f / self.model.scale).reshape(a_n, m, -1)
        return fw, log_z.reshape(a_n, m), ok.reshape(a_n, m)

    def evaluate(
        self,
        particles: ArrayLike,
        log_weights: ArrayLike,
        actions: ArrayLike | None = None,
        rng: np.random.Generator | None = None,
    ) -> ActionValues:
        """H(u) for every candidate pan angle (default: the configured ``n_actions``)."""
        u = self.actions if actions is None else np.asarray(actions, dtype=np.float64).reshape(-1)
        p, lw = subsample(particles, log_weights, self.config.max_particles, rng)
        fw, log_z, ok = self._predicted(p, u)
        pi = np.exp(lw)
        f32 = fw.astype(np.float32)
        sq = np.einsum("amd,amd->am", f32, f32)
        # -|f_i - f_k|^2 / 2 (A, i, k), then L = exp(.) in [0, 1]; a particle without features: 0
        t = np.matmul(f32, f32.transpose(0, 2, 1))
        t -= 0.5 * sq[:, :, None]
        t -= 0.5 * sq[:, None, :]
        np.minimum(t, 0.0, out=t)
        np.exp(t, out=t)
        t *= ok[:, None, :]
        # q_ik / ((1 - w) / Z_i) = pi_k (L_ik + w u Z_i / (1 - w) [k inside]): the row's scale
        # does not change its normalized weights
        if self.model.log_floor > -math.inf:
            c = np.exp(np.minimum(log_z + self.model.log_floor - self.model.log_inlier, 80.0))
            inside = self.model.bounds.contains(p[:, :2])
            t += (c[:, :, None] * inside[None, None, :]).astype(np.float32)
        t *= (pi / pi.max()).astype(np.float32)[None, None, :]
        z = t.sum(axis=-1, dtype=np.float64)
        lq = np.zeros_like(t)
        np.log(t, out=lq, where=t > 0)
        sql = np.einsum("aik,aik->ai", t, lq, dtype=np.float64)
        h0 = float(discrete_entropy(lw))
        good = ok & (z > 0)
        h = np.full(z.shape, h0)
        h[good] = np.log(z[good]) - sql[good] / z[good]
        return ActionValues(actions=u, expected_entropy=h @ pi, current_entropy=h0,
                            n_particles=int(p.shape[0]))


def action_evaluator(
    model: NearestNeighbourSensorModel | InterpolatedSensorModel, config: ActiveVisionConfig | None = None
) -> ActionEvaluator | InterpolatedActionEvaluator:
    """The H(u) evaluator of a sensor model: :class:`ActionEvaluator` for the nearest-neighbour
    model, :class:`InterpolatedActionEvaluator` for the interpolated one."""
    if isinstance(model, InterpolatedSensorModel):
        return InterpolatedActionEvaluator(model, config)
    return ActionEvaluator(model, config)


# --------------------------------------------------------------------------- policy


Reason = Literal[
    "disabled",
    "head moving",
    "settling",
    "interval",
    "no new frame",
    "converged",
    "no gain",
    "stay",
    "move",
    "home",
    "confirm",  # the service's confirmation look (services.active_head), never the policy's
]


@dataclass
class HeadSettle:
    """The head-settle rule: does a frame (or a reading) taken at time ``t`` show the head at rest?

    A frame taken while the head turns, or less than ``settle_s`` after its last motion, is
    smeared on the real camera and its pan uncertain: the daemon gives it to the filter for
    prediction only, and the policy waits for a frame taken after the head settled. With
    ``last_motion`` the latest time the head was seen moving::

        at_rest(t) = not moving(t) and not (0 <= t - last_motion < settle_s)

    ``last_motion = None``: the head has not moved, at rest unless ``moving``. The daemon passes
    the frame's interpolated moving flag and the last moving sample of the head's history
    (``services.device_threads.HeadHistory``); the policy, which sees only the present
    readings, tracks ``last_motion`` with :meth:`observe` and counts any time before it as
    moving (it does not know what the head did then).
    """

    settle_s: float
    last_motion: float | None = None
    _moving: bool = False

    def at_rest(self, t: float, moving: bool, last_motion: float | None) -> bool:
        """The rule above for a time ``t`` (s), the head's moving flag at ``t`` and its last
        motion (s, or None)."""
        if moving:
            return False
        return last_motion is None or not 0.0 <= t - last_motion < self.settle_s

    def observe(self, moving: bool, now: float) -> None:
        """Track :attr:`last_motion` from readings given in time order: while moving it is
        unknown (None); the first reading at rest after moving ones sets it to ``now``; a head
        first seen at rest stopped long ago (``-inf``)."""
        if moving:
            self._moving = True
            self.last_motion = None
        elif self._moving:
            self._moving = False
            self.last_motion = now
        elif self.last_motion is None:
            self.last_motion = -math.inf

    def observed_at_rest(self, t: float) -> bool:
        """:meth:`at_rest` from the tracked readings: a time before the tracked last motion
        counts as moving."""
        lm = self.last_motion
        return self.at_rest(t, lm is not None and t < lm, lm)


@dataclass(frozen=True)
class Decision:
    """What the policy decided: ``command`` is the pan angle to send (None: do nothing)."""

    command: float | None
    reason: Reason
    belief_entropy: float = math.nan
    values: ActionValues | None = None


class ActivePolicy:
    """When to look, where, and when to stop (module docstring). Call :meth:`decide` after
    each filter update with the head's present state; send ``command`` when it is not None.

    ``head_limits`` = (pan_min, pan_max) of the head (the service: ``devices.head.pan_min/pan_max``);
    commands never leave the intersection of those and the configured range."""

    def __init__(
        self,
        evaluator: ActionEvaluator | InterpolatedActionEvaluator,
        config: ActiveVisionConfig | None = None,
        head_limits: tuple[float, float] | None = None,
    ) -> None:
        self.evaluator = evaluator
        self.config = config or evaluator.config
        lo, hi = self.config.pan_min, self.config.pan_max
        if head_limits is not None:
            lo, hi = max(lo, float(head_limits[0])), min(hi, float(head_limits[1]))
        if not lo <= hi:
            raise ValueError(
                f"active vision: pan range [{self.config.pan_min}, {self.config.pan_max}] does "
                f"not overlap the head's limits {head_limits}"
            )
        self.pan_lo, self.pan_hi = lo, hi
        self.last_command_time = -math.inf
        self.last_command: float | None = None
        self.settle = HeadSettle(self.config.settle_s)
        self.reliability = PanReliability(self.config.reliability)

    def observe(self, pan: float, novelty: float, delta: ArrayLike | None = None) -> None:
        """A view the filter used: taken at ``pan`` with ``novelty`` (``PoseMixture.novelty``)
        after the base moved by ``delta`` (odometry increment, robot frame; None: not moved).
        Feeds the per-pan reliability (:mod:`lino_loc.pan_reliability`; a no-op when disabled)."""
        if delta is not None:
            self.reliability.move(delta)
        self.reliability.observe(pan, novelty)

    def clamp(self, pan: float) -> float:
        """A pan angle inside the allowed range (NaN becomes the range's centre)."""
        if not math.isfinite(pan):
            return 0.5 * (self.pan_lo + self.pan_hi)
        return min(max(float(pan), self.pan_lo), self.pan_hi)

    def candidates(self) -> FloatArray:
        """The configured actions, clamped to the allowed range, duplicates removed."""
        u = np.clip(self.config.actions(), self.pan_lo, self.pan_hi)
        return np.unique(u)

    def _values(self, p: FloatArray, lw: FloatArray, rng: np.random.Generator | None,
                view_values: Callable[[FloatArray], ActionValues | None] | None) -> ActionValues:
        """The candidates' values, discounted by the per-pan reliability: ``view_values``'
        when it gives some, else the evaluator's H(u)."""
        candidates = self.candidates()
        values = None if view_values is None else view_values(candidates)
        if values is None:
            values = self.evaluator.evaluate(p, lw, candidates, rng)
        return self.reliability.discount(values)

    def needs_look(self, state: str, belief_h: float, log_likelihood: float, doubt: float = 0.0) -> bool:
        c = self.config
        if state in ("global", "lost"):
            return True
        if c.trigger_doubt is not None and doubt >= c.trigger_doubt:
            return True
        if c.trigger_entropy is not None and belief_h > c.trigger_entropy:
            return True
        return (
            c.min_log_likelihood is not None
            and math.isfinite(log_likelihood)
            and log_likelihood < c.min_log_likelihood
        ) or (c.min_log_likelihood is not None and log_likelihood == -math.inf)

    def decide(
        self,
        particles: ArrayLike,
        log_weights: ArrayLike,
        *,
        state: str,
        log_likelihood: float,
        pan: float,
        moving: bool,
        now: float,
        frame_stamp: float | None = None,
        rng: np.random.Generator | None = None,
        doubt: float = 0.0,
        view_values: Callable[[FloatArray], ActionValues | None] | None = None,
    ) -> Decision:
        """The next pan command or None (with the reason).

        ``pan``/``moving``: the head's present pan angle and whether it is moving; ``now``: the
        time of that reading (s); ``frame_stamp``: time of the last frame the filter used (the
        policy waits for a frame taken ``settle_s`` after the head stopped, :class:`HeadSettle`); ``state``/
        ``log_likelihood``: the filter's state and the last observation's predictive
        log-likelihood; ``doubt``: the estimate's evidence that the views no longer fit the
        belief (``Estimate.doubt``, 1 = lost); ``view_values``: called with :meth:`candidates`
        when a look is needed, action values to use instead of the evaluator's H(u), or None
        for the evaluator's (the service passes ``Localizer.view_values``: the standing
        match's, once the belief is gathered)."""
        c = self.config
        if not c.enabled:
            return Decision(None, "disabled")
        self.settle.observe(moving, now)
        if moving:
            return Decision(None, "head moving")
        if not self.settle.observed_at_rest(now):
            return Decision(None, "settling")
        if now - self.last_command_time < c.min_interval_s:
            return Decision(None, "interval")
        if frame_stamp is not None and not self.settle.observed_at_rest(frame_stamp):
            return Decision(None, "no new frame")
        p = np.asarray(particles, dtype=np.float64).reshape(-1, 3)
        lw = np.asarray(log_weights, dtype=np.float64).reshape(-1)
        h_b = belief_entropy(p, lw, c.entropy_cell_xy, c.entropy_cell_theta)
        if not self.needs_look(state, h_b, log_likelihood, doubt):
            home = None if c.home_pan is None else self.clamp(c.home_pan)
            if home is not None and math.isfinite(pan) and abs(float(pan) - home) > c.pan_tolerance:
                self.last_command_time = now
                self.last_command = home
                return Decision(home, "home", h_b)
            return Decision(None, "converged", h_b)
        values = self._values(p, lw, rng, view_values)
        here = float(pan) if math.isfinite(pan) else None
        best = values.best(here, c.move_cost)
        if values.gain[best] < c.min_entropy_gain:
            return Decision(None, "no gain", h_b, values)
        target = self.clamp(float(values.actions[best]))
        if here is not None and abs(target - here) <= c.pan_tolerance:
            return Decision(None, "stay", h_b, values)
        self.last_command_time = now
        self.last_command = target
        return Decision(target, "move", h_b, values)

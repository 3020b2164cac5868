"""Appearance sensor model: the J nearest map entries as a mixture of kernels in pose space.

For an observed feature vector ``y`` (eq. 1) the model takes the J map entries whose features
are nearest to ``y`` and approximates the sensor model by the mixture (paper, section 3 and
eq. 8 for one channel; the paper's ref. [12]; Vlassis, Terwijn and Kroese, "Auxiliary
particle filter robot localization from high-dimensional sensor observations", ICRA 2002)

    p(y | x)  ~  sum_j lambda_j phi(x | x_j)

where ``x_j`` are the (camera) poses of those map entries, ``lambda_j`` weights that favour
the closer feature vectors, and ``phi`` a kernel in pose space: an isotropic Gaussian of
width ``sigma_xy`` in (x, y) times a von Mises density of concentration
``kappa = 1 / sigma_theta^2`` in theta, with the angle difference wrapped. Strictly the
mixture is the inverse model p(x | y); it is proportional to p(y | x) when the map samples the
pose space uniformly (Bayes with a flat prior over the map), which a grid survey does.

The kernel widths come from configuration; the feature weights are

    lambda_j = softmax_j( -d_j^2 / (2 s^2) ),  d_j = |y - y_j|,

with an adaptive scale ``s`` = ``lambda_scale_factor`` times the median (default) or the
smallest of the J neighbour distances ("uniform" gives lambda_j = 1/J). Making ``s`` relative
to the neighbour distances keeps the weights meaningful whatever the number of features and
the preprocessing (distances in feature space have no fixed unit).

An optional outlier component (weight ``outlier_weight``, a uniform density over the mapped
area and all headings) keeps the model from vanishing away from the J poses, so that one
wrong match (an unmodelled change in the scene) does not wipe out the belief.

Evaluating a mixture (``PoseMixture.log_pdf_trig``): the kernels need the heading only
through cos and sin (the wrap of the angle difference is implicit), so callers that already
hold them (the filter: from the action model's rotation, or to reuse them for the estimate)
skip two trigonometric passes. With ``phi = (x, y, cos t, sin t, x^2 + y^2, 1)`` the
log-kernels of all K components are one small (K, 6) @ (6, M) product ``T = A phi``
(``PoseMixture.component_log_pdf``), computed in blocks of columns, with every term shifted
by the constant c0, the largest value any term can take, so the log-sum-exp needs no
per-pose maximum: ``log p = c0 + log(sum_k exp(T_k) + u [inside the bounds])``, u the
shifted outlier density. Where that sum underflows (a pose farther than ~13 kernel widths
from every kernel and outside the bounds), the exact per-pose maximum is used instead.

Everything is kept in log space. A :class:`PoseMixture` can be evaluated at any set of poses
(``log_pdf``) and sampled (``sample``), which is what global localization and kidnap recovery
use.

Usage::

    model = NearestNeighbourSensorModel(map_poses, map_features, SensorModelConfig(j=10))
    mixture = model.observe(y)
    log_lik = mixture.log_pdf(camera_pose(particles, pan))
    seeds = mixture.sample(100, rng)
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.special import i0e

from lino_loc.errors import LinoLocError
from lino_loc.exact_neighbours import MARGIN, settle
from lino_loc.poses import wrap_angle
from lino_loc.resampling import logsumexp

if TYPE_CHECKING:
    from lino_loc.hnsw_index import HnswIndex

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
#: Which sensor model builds p(y | x): this module's J nearest map entries, or the map's
#: appearance interpolated between survey poses (lino_loc.interpolated_appearance).
SensorModelKind = Literal["nearest_neighbour", "interpolated"]

LOG_2PI = math.log(2.0 * math.pi)
# Below this map size "auto" takes brute force without timing the tree (see docs/results.md).
AUTO_KDTREE_MIN_ENTRIES = 2000
#: Brute-force J-nearest search answers at most this many observations at a time, and at most
#: BRUTE_QUERY_ELEMENTS / N of them on a map of N entries: its (queries x map entries) float64
#: work arrays stay tens of megabytes (a map's own entries queried at once, as the action
#: evaluator does, would otherwise need several per cent of a robot's memory for a 5000-entry
#: map; 256 queries alone peaked at 0.7 GB on a map of 100k entries, docs/scale.md).
BRUTE_QUERY_BLOCK = 256
BRUTE_QUERY_ELEMENTS = 1 << 22


def log_von_mises_norm(kappa: ArrayLike) -> FloatArray:
    """log(2 pi I0(kappa)), computed stably with the scaled Bessel function i0e."""
    k = np.asarray(kappa, dtype=np.float64)
    return LOG_2PI + np.log(i0e(k)) + k


# Columns per block of a log-density evaluation, times the number of kernels: keeps the
# (K, 6) @ (6, block) product below OpenBLAS's threading threshold (a threaded product of this
# size is several times slower, see docs/results.md) and a block's terms in the L2 cache.
_MATMUL_BLOCK = 32768
# A shifted sum below this may have lost precision to subnormal exp() results: recompute.
_TINY_SUM = 1e-280
# Kernels whose terms stay this many nats below every pose's density are left out of a sum
# (relative change K exp(-40), below float64 round-off).
_PRUNE_NATS = 40.0
# Fewest poses for which the pruning bound is computed (it costs more than it saves on few
# poses; see docs/results.md).
_PRUNE_MIN_POSES = 500


def _small_matmul(a: FloatArray, b: FloatArray, out: FloatArray) -> None:
    """out = a @ b for a few-column ``a`` (K, 6) and ``b`` (6, M), by blocks of columns small
    enough for a single-threaded BLAS call (see _MATMUL_BLOCK); einsum (no BLAS) when K is
    too large for any block to be."""
    k, m = a.shape[0], b.shape[1]
    block = _MATMUL_BLOCK // max(k, 1)
    if block < 256:
        np.einsum("kj,jm->km", a, b, out=out)
    elif m <= block:
        np.matmul(a, b, out=out)
    else:
        for lo in range(0, m, block):
            np.matmul(a, b[:, lo : lo + block], out=out[:, lo : lo + block])


@lru_cache(maxsize=64)
def _kernel_constants(sigma_xy: float, sigma_theta: float) -> tuple[float, float, float, float]:
    """(1 / s^2, kappa, log(2 pi s^2), log(2 pi I0(kappa)) - kappa) of one kernel width pair
    (the last two: minus the log of the Gaussian's and of the von Mises density's peak)."""
    s2 = sigma_xy * sigma_xy
    kappa = 1.0 / (sigma_theta * sigma_theta)
    return 1.0 / s2, kappa, LOG_2PI + math.log(s2), LOG_2PI + math.log(float(i0e(kappa)))


@dataclass(frozen=True)
class Bounds:
    """Axis-aligned box of the mapped area, metres (all headings are allowed)."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float

    @property
    def area(self) -> float:
        """(x_max - x_min) (y_max - y_min) in m^2, each side floored at 1e-9 m (a degenerate
        box keeps a finite density)."""
        return max(self.x_max - self.x_min, 1e-9) * max(self.y_max - self.y_min, 1e-9)

    @property
    def log_uniform_density(self) -> float:
        """log of the uniform density over the box and all headings, 1 / (area * 2 pi)."""
        return -math.log(self.area) - LOG_2PI

    def sample(self, n: int, rng: np.random.Generator) -> FloatArray:
        """n poses uniform over the box and all headings."""
        u = rng.random((n, 3))
        return np.column_stack(
            [
                self.x_min + u[:, 0] * (self.x_max - self.x_min),
                self.y_min + u[:, 1] * (self.y_max - self.y_min),
                -np.pi + u[:, 2] * 2.0 * np.pi,
            ]
        )

    def contains(self, xy: ArrayLike) -> NDArray[np.bool_]:
        """True where the positions xy (..., >= 2; x, y first) lie in the box, edges included."""
        p = np.asarray(xy, dtype=np.float64)
        return (
            (p[..., 0] >= self.x_min)
            & (p[..., 0] <= self.x_max)
            & (p[..., 1] >= self.y_min)
            & (p[..., 1] <= self.y_max)
        )

    @classmethod
    def from_poses(cls, poses: ArrayLike, margin: float = 0.0) -> Bounds:
        """The smallest box holding every position of ``poses`` (N, >= 2), grown by ``margin``
        metres on each side."""
        p = np.asarray(poses, dtype=np.float64)
        return cls(
            float(p[:, 0].min() - margin),
            float(p[:, 0].max() + margin),
            float(p[:, 1].min() - margin),
            float(p[:, 1].max() + margin),
        )


@dataclass(frozen=True)
class PoseMixture:
    """A density over poses: sum_k w_k N(x,y; mu_k, sigma_xy_k^2 I) VM(theta; mu_k, 1/sigma_theta_k^2)
    plus an optional uniform outlier component over ``bounds``, times exp(``log_scale``).

    ``log_weights`` (K,) and ``outlier_log_weight`` together sum to one (in linear space), so
    the mixture part is a normalized density in (x, y, theta); ``log_scale`` is a constant
    factor (the normalizer of a product of mixtures, eq. 7) that ``log_pdf`` includes and
    ``sample`` ignores.
    """

    poses: FloatArray
    log_weights: FloatArray
    sigma_xy: FloatArray
    sigma_theta: FloatArray
    outlier_log_weight: float = -math.inf
    bounds: Bounds | None = None
    log_scale: float = 0.0
    neighbours: IntArray | None = field(default=None, compare=False)
    # distance in feature space from the observation to its nearest map entry, relative to
    # the map's own typical nearest-neighbour distance (NearestNeighbourSensorModel.novelty);
    # nan: unknown. The filter trusts the mixture for kidnap recovery only when it is small.
    novelty: float = field(default=math.nan, compare=False)
    # the channels' own mixtures when this one fuses them (lino_loc.localizer: name -> mixture,
    # also for a single channel); None: not known. The filter tests each against the belief.
    channels: Mapping[str, PoseMixture] | None = field(default=None, compare=False)

    @classmethod
    def create(
        cls,
        poses: ArrayLike,
        log_weights: ArrayLike,
        sigma_xy: ArrayLike,
        sigma_theta: ArrayLike,
        outlier_weight: float = 0.0,
        bounds: Bounds | None = None,
        log_scale: float = 0.0,
        neighbours: ArrayLike | None = None,
    ) -> PoseMixture:
        """Build a mixture; normalizes the component weights to ``1 - outlier_weight``."""
        p = np.atleast_2d(np.asarray(poses, dtype=np.float64))
        k = p.shape[0]
        lw = np.asarray(log_weights, dtype=np.float64).reshape(k)
        sxy = np.broadcast_to(np.asarray(sigma_xy, dtype=np.float64), (k,)).copy()
        sth = np.broadcast_to(np.asarray(sigma_theta, dtype=np.float64), (k,)).copy()
        if np.any(sxy <= 0) or np.any(sth <= 0):
            raise ValueError("kernel widths must be positive")
        if not 0.0 <= outlier_weight < 1.0:
            raise ValueError("outlier_weight must be in [0, 1)")
        if outlier_weight > 0.0 and bounds is None:
            raise ValueError("an outlier component needs the bounds of the mapped area")
        lw = lw - logsumexp(lw) + math.log1p(-outlier_weight)
        ow = math.log(outlier_weight) if outlier_weight > 0.0 else -math.inf
        nb = None if neighbours is None else np.asarray(neighbours, dtype=np.int64)
        return cls(p, lw, sxy, sth, ow, bounds, float(log_scale), nb)

    @property
    def n_components(self) -> int:
        """K, the number of kernels (the outlier component not counted)."""
        return int(self.poses.shape[0])

    @property
    def kappa(self) -> FloatArray:
        """von Mises concentrations kappa_k = 1 / sigma_theta_k^2 (K,)."""
        return 1.0 / self.sigma_theta**2

    @cached_property
    def _psi(self) -> FloatArray:
        """(6, K) coefficients of the log-kernels (see :meth:`component_log_pdf`)."""
        return np.ascontiguousarray(self._coefficients[0].T)

    @cached_property
    def _coefficients(self) -> tuple[FloatArray, float, float, FloatArray]:
        """(A, c0, u, peak): the log-kernels as A (K, 6) @ (x, y, cos t, sin t, x^2 + y^2, 1)
        minus c0, the largest value any term of the log-sum-exp can take, c0 (a kernel's
        log-weight times its peak density, or the outlier's log density), exp(log outlier
        density - c0) (0 without outlier), and each kernel's largest term minus c0 (K,).
        Shifting every term by c0 keeps exp() <= 1 without a per-pose max.

        The widths are usually one shared value (``NearestNeighbourSensorModel``); their
        normalizers are then computed once from scalars (cached per width pair)."""
        mu = self.poses
        k = mu.shape[0]
        sxy, sth = self.sigma_xy, self.sigma_theta
        if k and float(sxy.min()) == float(sxy.max()) and float(sth.min()) == float(sth.max()):
            inv, kappa, lnorm_xy, lnorm_th = _kernel_constants(float(sxy[0]), float(sth[0]))
            log_peak = self.log_weights - (lnorm_xy + lnorm_th)  # log w_k + log phi_k(mu_k)
        else:
            s2 = sxy**2
            inv = 1.0 / s2
            kappa = 1.0 / sth**2
            log_peak = self.log_weights - (LOG_2PI + np.log(s2)) - (LOG_2PI + np.log(i0e(kappa)))
        a = np.empty((k, 6))
        np.multiply(mu[:, 0], inv, out=a[:, 0])
        np.multiply(mu[:, 1], inv, out=a[:, 1])
        np.multiply(np.cos(mu[:, 2]), kappa, out=a[:, 2])
        np.multiply(np.sin(mu[:, 2]), kappa, out=a[:, 3])
        np.multiply(inv, -0.5, out=a[:, 4])
        # const_k = log peak_k - kappa_k - |m_k|^2 / (2 s_k^2)
        a[:, 5] = log_peak - kappa + a[:, 4] * (mu[:, 0] ** 2 + mu[:, 1] ** 2)
        c0 = float(log_peak.max()) if k else -math.inf
        log_out = -math.inf
        if self.outlier_log_weight > -math.inf and self.bounds is not None:
            log_out = self.outlier_log_weight + self.bounds.log_uniform_density
            c0 = max(c0, log_out)
        if not math.isfinite(c0):
            c0 = 0.0
        a[:, 5] -= c0
        u = math.exp(log_out - c0) if log_out > -math.inf else 0.0
        return a, c0, u, log_peak - c0

    def _active_rows(self, box: tuple[float, float, float, float]) -> FloatArray:
        """The rows of A (:attr:`_coefficients`) whose terms can matter at poses whose
        bounding box ``(x_lo, x_hi, y_lo, y_hi)`` lies inside the bounds.

        Every such pose has a density at least the outlier's (u after the shift); a kernel
        whose largest term over the box (its peak minus the squared distance from its centre
        to the box over 2 s^2) is below u exp(-_PRUNE_NATS) changes no sum by more than
        K exp(-40) ~ 4e-17 relative (below float64 round-off) and is left out. The result
        equals the unpruned sum to round-off; it saves the exp() of the pruned rows (see
        docs/results.md). Edge cases: no outlier component (u = 0) or a single kernel: no
        pruning."""
        a, _, u, peak = self._coefficients
        if u <= 0.0 or a.shape[0] <= 1:
            return a
        x_lo, x_hi, y_lo, y_hi = box
        mx, my = self.poses[:, 0], self.poses[:, 1]
        dx = np.maximum(np.maximum(x_lo - mx, mx - x_hi), 0.0)
        dy = np.maximum(np.maximum(y_lo - my, my - y_hi), 0.0)
        bound = peak + a[:, 4] * (dx * dx + dy * dy)  # a[:, 4] = -1 / (2 s^2)
        keep = bound >= math.log(u) - _PRUNE_NATS
        return a if keep.all() else a[keep]

    def _component_terms(self, x: FloatArray, extra_rows: int = 0) -> FloatArray:
        """(K, M) log of w_k phi_k(x_m), components along the first axis (fast reductions);
        ``extra_rows`` appends uninitialized rows for the caller (K + extra_rows, M)."""
        phi = np.empty((6, x.shape[0]))
        phi[0:2] = x[:, 0:2].T
        np.cos(x[:, 2], out=phi[2])
        np.sin(x[:, 2], out=phi[3])
        np.multiply(phi[0], phi[0], out=phi[4])
        phi[4] += phi[1] * phi[1]
        phi[5] = 1.0
        out = np.empty((self.n_components + extra_rows, x.shape[0]))
        _small_matmul(self._coefficients[0], phi, out[: self.n_components])
        out[: self.n_components] += self._coefficients[1]
        return out

    def component_log_pdf(self, poses: ArrayLike) -> FloatArray:
        """(M, K) log of w_k phi_k(x_m), without outlier and scale.

        Written as one (K, 6) x (6, M) product: with s_k = sigma_xy_k and kappa_k,
        log w_k phi_k(x) = -|p - m_k|^2 / (2 s_k^2) + kappa_k cos(theta - mu_k) + const_k, and
        |p - m|^2 = |p|^2 - 2 p.m + |m|^2, cos(t - mu) = cos t cos mu + sin t sin mu, so the
        M x K cosines and distances cost one small matrix product (the wrap of the angle
        difference is implicit in the cosine).
        """
        x = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        return self._component_terms(x).T

    def log_pdf(self, poses: ArrayLike) -> FloatArray:
        """Log density at poses (M, 3) -> (M,), including the outlier component and log_scale."""
        x = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        return self.log_pdf_trig(x[:, 0], x[:, 1], np.cos(x[:, 2]), np.sin(x[:, 2]))

    def log_pdf_trig(
        self, px: FloatArray, py: FloatArray, cos_t: FloatArray, sin_t: FloatArray
    ) -> FloatArray:
        """:meth:`log_pdf` at poses given as x, y, cos(theta), sin(theta) (each (M,)).

        ``log p = c0 + log(sum_k exp(T_k) + u [inside the bounds]) + log_scale`` with
        ``T = A @ phi`` in blocks of columns (see "Evaluating a mixture" in the module
        docstring); poses where the shifted sum underflows get :meth:`_log_pdf_exact`.
        """
        _, c0, u, _ = self._coefficients
        m = px.shape[0]
        b = self.bounds
        a, inside_all = self._rows_for(px, py)
        k = a.shape[0]
        out = np.empty(m)
        block = max(256, _MATMUL_BLOCK // max(k, 1))
        phi_buf = np.empty((6, min(m, block)))
        t_buf = np.empty((k, min(m, block)))
        for lo in range(0, m, block):
            hi = min(m, lo + block)
            w = hi - lo
            phi, t = phi_buf[:, :w], t_buf[:, :w]
            phi[0] = px[lo:hi]
            phi[1] = py[lo:hi]
            phi[2] = cos_t[lo:hi]
            phi[3] = sin_t[lo:hi]
            np.multiply(phi[0], phi[0], out=phi[4])
            np.multiply(phi[1], phi[1], out=phi[5])
            phi[4] += phi[5]
            phi[5] = 1.0
            res = out[lo:hi]
            if k:
                _small_matmul(a, phi, t)
                np.exp(t, out=t)
                np.add.reduce(t, axis=0, out=res)
            else:
                res[:] = 0.0
            if inside_all:
                res += u
            elif u > 0.0:
                assert b is not None
                inside = (phi[0] >= b.x_min) & (phi[0] <= b.x_max)
                inside &= (phi[1] >= b.y_min) & (phi[1] <= b.y_max)
                res += inside * u
        if m and float(out.min()) < _TINY_SUM:
            return self._log_of_sums(out, px, py, cos_t, sin_t)
        np.log(out, out=out)
        out += c0 + self.log_scale
        return out

    def _rows_for(self, px: FloatArray, py: FloatArray) -> tuple[FloatArray, bool]:
        """The rows of A (:attr:`_coefficients`) to sum at poses (px, py), and whether every
        pose lies inside the bounds (then the outlier term is one constant). With an outlier
        component and at least ``_PRUNE_MIN_POSES`` poses all inside, :meth:`_active_rows`;
        otherwise every row."""
        u = self._coefficients[2]
        m = px.shape[0]
        b = self.bounds
        inside_all = False
        if u > 0.0 and b is not None and m:
            box = (float(px.min()), float(px.max()), float(py.min()), float(py.max()))
            inside_all = (
                box[0] >= b.x_min and box[1] <= b.x_max and box[2] >= b.y_min and box[3] <= b.y_max
            )
        a = self._active_rows(box) if inside_all and m >= _PRUNE_MIN_POSES else (
            self._coefficients[0]
        )
        return a, inside_all

    def _log_of_sums(
        self, out: FloatArray, px: FloatArray, py: FloatArray, cos_t: FloatArray, sin_t: FloatArray
    ) -> FloatArray:
        """``out`` (the shifted sums of :meth:`log_pdf_trig`, in place) turned into log
        densities: ``log(out) + c0 + log_scale`` where the sum is at least ``_TINY_SUM``, and
        :meth:`_log_pdf_exact` at the other poses."""
        c0 = self._coefficients[1]
        low = out < _TINY_SUM
        out[~low] = np.log(out[~low])
        out[~low] += c0 + self.log_scale
        out[low] = self._log_pdf_exact(px[low], py[low], cos_t[low], sin_t[low])
        return out

    def _log_pdf_exact(
        self, px: FloatArray, py: FloatArray, cos_t: FloatArray, sin_t: FloatArray
    ) -> FloatArray:
        """:meth:`log_pdf_trig` with a per-pose maximum in the log-sum-exp (for poses where the
        shifted sum underflows)."""
        a, c0, _, _ = self._coefficients
        k = a.shape[0]
        phi = np.stack([px, py, cos_t, sin_t, px * px + py * py, np.ones_like(px)])
        t = np.empty((k + 1, px.shape[0]))
        _small_matmul(a, phi, t[:k])
        t[:k] += c0
        if self.outlier_log_weight > -math.inf and self.bounds is not None:
            b = self.bounds
            inside = (px >= b.x_min) & (px <= b.x_max) & (py >= b.y_min) & (py <= b.y_max)
            t[k] = np.where(inside, self.outlier_log_weight + b.log_uniform_density, -np.inf)
        else:
            t[k] = -np.inf
        top = t.max(axis=0)
        fin = np.isfinite(top)
        lp = np.full(px.shape[0], -np.inf)
        if fin.any():
            tt = t[:, fin] - top[fin]
            lp[fin] = np.log(np.exp(tt).sum(axis=0)) + top[fin]
        return lp + self.log_scale

    def proposal_log_pdf(self, poses: ArrayLike) -> FloatArray:
        """Log density (M,) at poses (M, 3) of the distribution :meth:`sample` draws from:
        ``log_pdf - log_scale`` (the mixture itself, normalized)."""
        return self.log_pdf(poses) - self.log_scale

    def pdf(self, poses: ArrayLike) -> FloatArray:
        """Density at poses (M, 3) -> (M,), consistent with ``sample`` when log_scale == 0."""
        return np.exp(self.log_pdf(poses))

    def sample(self, n: int, rng: np.random.Generator) -> FloatArray:
        """n poses drawn from the normalized mixture (log_scale ignored) -> (n, 3)."""
        lw = self.log_weights
        if self.outlier_log_weight > -math.inf:
            lw = np.append(lw, self.outlier_log_weight)
        w = np.exp(lw - logsumexp(lw))
        comp = rng.choice(w.size, size=n, p=w / w.sum())
        out = np.empty((n, 3))
        kernel = comp < self.n_components
        kc = comp[kernel]
        m = int(kernel.sum())
        mu = self.poses[kc]
        out[kernel, 0] = mu[:, 0] + self.sigma_xy[kc] * rng.standard_normal(m)
        out[kernel, 1] = mu[:, 1] + self.sigma_xy[kc] * rng.standard_normal(m)
        out[kernel, 2] = wrap_angle(rng.vonmises(mu[:, 2], self.kappa[kc]))
        if m < n:
            assert self.bounds is not None
            out[~kernel] = self.bounds.sample(n - m, rng)
        return out

    def with_log_weight(self, log_w: float) -> PoseMixture:
        """The same mixture with every weight (components and outlier) multiplied by exp(log_w)."""
        return PoseMixture(
            self.poses,
            self.log_weights + log_w,
            self.sigma_xy,
            self.sigma_theta,
            self.outlier_log_weight + log_w,
            self.bounds,
            self.log_scale,
            self.neighbours,
            self.novelty,
        )


class SensorModelConfig(BaseModel):
    """Configuration of the nearest-neighbour sensor model (paper, section 3 and eq. 8; see
    the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    j: int = Field(10, ge=1, description="number of nearest map entries J")
    sigma_xy: float = Field(0.35, gt=0.0, description="kernel width in x and y, metres")
    sigma_theta: float = Field(0.3, gt=0.0, description="kernel width in theta, radians")
    lambda_scale: Literal["median", "nearest", "uniform"] = "median"
    lambda_scale_factor: float = Field(1.0, gt=0.0)
    # 0.5, chosen by measurement (docs/results.md, 'Notes moved from the code'): under light
    # and scene changes the map does not know, most J-nearest sets are wrong, and a larger
    # uniform component keeps a wrong set from overruling the odometry.
    outlier_weight: float = Field(
        0.5, ge=0.0, lt=1.0, description="weight of the uniform component"
    )
    map_margin: float = Field(0.5, ge=0.0, description="margin (m) added around the map poses")
    index: Literal["brute", "kdtree", "hnsw", "auto"] = Field(
        "auto",
        description="J-nearest search: vectorized brute force, scipy cKDTree, hnsw (approximate: "
        "an HNSW graph, lino_loc/hnsw_index.py, the optional extra 'scale'; for maps of 100k "
        "entries and more, docs/scale.md), or auto (exact: measure brute force and the tree on "
        "the map at construction, take the tree only if it is clearly faster)",
    )
    index_cache: Path | None = Field(
        None,
        description="folder where the hnsw search keeps its graph between starts (built once "
        "per map, verified by SHA-256 when read); None: built at every start",
    )


def lambda_log_weights(dist2: ArrayLike, scale: str = "median", factor: float = 1.0) -> FloatArray:
    """log lambda_j = log softmax_j(-d_j^2 / (2 s^2)) over the last axis (see module docstring).

    ``dist2`` are squared feature distances (..., J); s^2 = ``factor``^2 times their median
    (``scale="median"``, the mean of the two middle values for even J) or their minimum
    (``"nearest"``); ``"uniform"`` gives log(1/J). A zero scale (an exact match) falls back to
    the largest distance, and all-zero distances give uniform weights. ValueError on an
    unknown ``scale``.
    """
    d2 = np.asarray(dist2, dtype=np.float64)
    if d2.ndim == 1 and d2.size and scale != "uniform":
        return _lambda_log_weights_1d(d2, scale, factor)
    if scale == "uniform":
        return np.full(d2.shape, -math.log(d2.shape[-1]))
    if scale == "median":  # J is small: a sort is cheaper than np.median's overhead
        srt = np.sort(d2, axis=-1)
        k = d2.shape[-1]
        s2 = 0.5 * (srt[..., (k - 1) // 2 : (k - 1) // 2 + 1] + srt[..., k // 2 : k // 2 + 1])
    elif scale == "nearest":
        s2 = np.min(d2, axis=-1, keepdims=True)
    else:
        raise ValueError(f"unknown lambda scale {scale!r}")
    s2 = factor**2 * s2
    # Guard a zero scale (exact match): fall back to the largest distance, then to uniform.
    s2 = np.where(s2 > 0, s2, np.max(d2, axis=-1, keepdims=True))
    logits = np.where(s2 > 0, -d2 / (2.0 * np.where(s2 > 0, s2, 1.0)), 0.0)
    return logits - logsumexp(logits, axis=-1, keepdims=True)


def _lambda_log_weights_1d(d2: FloatArray, scale: str, factor: float) -> FloatArray:
    """:func:`lambda_log_weights` for one observation (J,), with scalar arithmetic for the scale
    (the general version's array reductions dominated its cost at J = 10)."""
    if scale == "median":
        srt = np.sort(d2)
        k = srt.size
        s2 = 0.5 * (float(srt[(k - 1) // 2]) + float(srt[k // 2]))
    elif scale == "nearest":
        s2 = float(d2.min())
    else:
        raise ValueError(f"unknown lambda scale {scale!r}")
    s2 *= factor**2
    if not s2 > 0.0:
        s2 = float(d2.max())
    if not s2 > 0.0:
        return np.full(d2.shape, -math.log(d2.size))
    logits = d2 * (-0.5 / s2)
    logits -= logits.max()
    return logits - math.log(float(np.exp(logits).sum()))


class NearestNeighbourSensorModel:
    """J-nearest-neighbour appearance sensor model over one map channel (see the module
    docstring: the mixture of eq. 8 for one channel, feature weights lambda_j, outlier).

    ``map_poses`` (N, 3) are CAMERA poses; evaluate the mixtures at
    ``camera_pose(robot_particles, pan)``.
    """

    def __init__(
        self,
        map_poses: ArrayLike,
        map_features: ArrayLike,
        config: SensorModelConfig | None = None,
        j: int | None = None,
        bounds: Bounds | None = None,
    ) -> None:
        self.config = config or SensorModelConfig()
        self.poses = np.asarray(map_poses, dtype=np.float64)
        raw = np.asarray(map_features)
        if self.config.index == "hnsw" and raw.dtype in (np.float32, np.float64):
            # the graph holds its own float32 copy and the J distances are computed from
            # these rows: no float64 copy of the whole map (it may be memory-mapped)
            self.features = raw
        else:
            self.features = np.ascontiguousarray(raw, dtype=np.float64)
        if self.poses.ndim != 2 or self.poses.shape[1] != 3:
            raise LinoLocError(f"map poses: expected shape (N, 3), got {self.poses.shape}")
        if self.features.ndim != 2 or self.features.shape[0] != self.poses.shape[0]:
            raise LinoLocError(
                f"map features: expected shape ({self.poses.shape[0]}, d), got {self.features.shape}"
            )
        self.j = int(j if j is not None else self.config.j)
        if not 1 <= self.j <= self.poses.shape[0]:
            raise LinoLocError(
                f"sensor model j={self.j}: must be between 1 and the map size {self.poses.shape[0]}"
            )
        self.bounds = bounds or Bounds.from_poses(self.poses, self.config.map_margin)
        self._reference_distance: float | None = None
        self._widths: dict[int, tuple[FloatArray, FloatArray]] = {}
        self._tree = None
        self._graph: HnswIndex | None = None
        self.index_kind = "brute"
        if self.config.index == "hnsw":
            from lino_loc.hnsw_index import HnswIndex

            self._graph = HnswIndex.build_or_load(self.features, self.config.index_cache)
            self.index_kind = "hnsw"
            return
        self._sqnorm = np.einsum("ij,ij->i", self.features, self.features)
        if self.config.index == "kdtree" or (
            self.config.index == "auto" and self.poses.shape[0] >= AUTO_KDTREE_MIN_ENTRIES
        ):
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.features)
            self.index_kind = "kdtree"
            if self.config.index == "auto" and not self._tree_pays():
                self._tree = None
                self.index_kind = "brute"

    def _tree_pays(self, n_probe: int = 24) -> bool:
        """True when the KD-tree search is clearly faster than brute force on this map.

        Both searches answer ``n_probe`` probe queries (map features plus 0.25 feature-std of
        Gaussian noise, fixed seed 12345), twice each in alternation; the best time of each is
        kept and the tree is taken when it needs under 0.8 of brute force's. Which one wins
        depends on the data (a KD-tree suits PCA features with decaying variances, not equally
        varying ones; see docs/results.md), so "auto" measures. The two searches return the
        same neighbours up to ties; their squared distances differ by round-off (brute force
        expands |f - y|^2).
        """
        import time

        rng = np.random.default_rng(12345)
        rows = rng.integers(0, self.features.shape[0], n_probe)
        # the spread from at most ~10k rows: std() of the whole map makes a temporary copy of
        # it (160 MB at 1M entries, docs/scale.md)
        spread = self.features[:: max(1, self.features.shape[0] // 10000)].std(axis=0)
        probes = self.features[rows] + 0.25 * spread * rng.standard_normal((n_probe, self.dim))
        tree, timings = self._tree, {}
        for kind in ("kdtree", "brute", "kdtree", "brute"):
            self._tree = tree if kind == "kdtree" else None
            t0 = time.perf_counter()
            for q in probes:
                self.neighbours(q)
            timings[kind] = min(timings.get(kind, math.inf), time.perf_counter() - t0)
        self._tree = tree
        return timings["kdtree"] < 0.8 * timings["brute"]

    @property
    def reference_distance(self) -> float:
        """The map's typical nearest-neighbour distance in feature space: median, over up to
        500 map entries (fixed seed), of the distance to the nearest OTHER entry."""
        if self._reference_distance is None:
            n = self.features.shape[0]
            if n < 2:
                self._reference_distance = 1.0
            else:
                rng = np.random.default_rng(0)
                rows = rng.choice(n, size=min(n, 500), replace=False)
                _, d2 = self.neighbours(self.features[rows], 2)
                ref = float(np.median(np.sqrt(d2[:, 1])))
                self._reference_distance = ref if ref > 0.0 else 1.0
        return self._reference_distance

    def novelty(self, nearest_dist2: float) -> float:
        """Distance to the nearest map entry over :attr:`reference_distance`:
        ``sqrt(max(d_1^2, 0)) / reference_distance``, about 1 for a view like the mapped ones
        and larger for a view the map does not know (changed light or scene; typical values
        in docs/evaluations.md, 'Kidnap recovery while tracking')."""
        return math.sqrt(max(float(nearest_dist2), 0.0)) / self.reference_distance

    @property
    def dim(self) -> int:
        """d, the length of a feature vector of this channel."""
        return int(self.features.shape[1])

    def neighbours(self, y: ArrayLike, j: int | None = None) -> tuple[IntArray, FloatArray]:
        """The J nearest map entries to each observation: y (d,) or (B, d) ->
        (indices (B, J), squared distances (B, J)), sorted by distance (ties by index). ``j``
        overrides J.

        The search (KD-tree, brute force or the approximate HNSW graph, :attr:`index_kind`)
        only proposes J + ``MARGIN`` candidates; the J set and their squared distances are
        then settled one way for every search (:func:`lino_loc.exact_neighbours.settle`:
        sum_k (f_k - y_k)^2, ties to the lowest indices, also among identical map rows), so
        the answer does not depend on which search "auto" chose (it times them on the machine
        it runs on): a replay of a recording gives the same weights to the bit."""
        q = np.atleast_2d(np.asarray(y, dtype=np.float64))
        if q.shape[1] != self.dim:
            raise LinoLocError(f"observed features: expected {self.dim} values, got {q.shape[1]}")
        if not np.all(np.isfinite(q)):
            raise LinoLocError("observed features: contain NaN or infinite values")
        j = self.j if j is None else min(int(j), self.poses.shape[0])
        block = max(1, min(BRUTE_QUERY_BLOCK, BRUTE_QUERY_ELEMENTS // self.poses.shape[0]))
        if q.shape[0] > block:  # bound the (B, N) work arrays of brute force
            parts = [self.neighbours(q[lo : lo + block], j) for lo in range(0, q.shape[0], block)]
            return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        n = self.poses.shape[0]
        return settle(self.features, q, self._nearest(q, min(j + MARGIN, n)), j)

    def _nearest(self, q: FloatArray, j: int) -> IntArray:
        """Indices (B, j), in no particular order, of the j map entries nearest to each row of q."""
        n = self.features.shape[0]
        if self._graph is not None:
            if j < n:
                try:
                    return self._graph.query(q, j)
                except RuntimeError:  # hnswlib found fewer than j entries (a tiny map): exact
                    pass
            d2 = np.stack([np.einsum("nk,nk->n", self.features - row, self.features - row) for row in q])
            return np.argsort(d2, axis=1, kind="stable")[:, :j].astype(np.int64)
        if self._tree is not None:
            # one query as a vector (cheaper than cKDTree's 2-D argument handling)
            _, idx = self._tree.query(q[0] if q.shape[0] == 1 else q, k=j)
            return np.asarray(idx, dtype=np.int64).reshape(q.shape[0], j)
        # |f|^2 - 2 f.y + |y|^2. For a few queries einsum (no BLAS) is used: a threaded BLAS
        # matrix-vector product is much slower on a loaded machine (see docs/results.md).
        if q.shape[0] <= 8:
            cross = np.einsum("bj,nj->bn", q, self.features)
        else:
            cross = q @ self.features.T
        d2 = self._sqnorm[None, :] - 2.0 * cross + np.einsum("ij,ij->i", q, q)[:, None]
        if j < n:
            return np.argpartition(d2, j - 1, axis=1)[:, :j].astype(np.int64)
        return np.broadcast_to(np.arange(n, dtype=np.int64), (q.shape[0], n)).copy()

    def observe(self, y: ArrayLike, j: int | None = None) -> PoseMixture:
        """The sensor model for one observed feature vector y (d,) as a PoseMixture."""
        idx, d2 = self.neighbours(y, j)
        return self._mixture(idx[0], d2[0], self.novelty(d2[0, 0]))

    def log_likelihood_matrix(
        self, y: ArrayLike, camera_poses: ArrayLike, j: int | None = None
    ) -> FloatArray:
        """log p(y_b | x_m) for many observations at once: y (B, d), camera poses (M, 3) -> (B, M).

        Row b equals ``self.observe(y[b], j).log_pdf(camera_poses)`` up to round-off;
        vectorized for the active-vision search (the entropy H(u) of the paper's section 4),
        which needs the sensor model of every predicted observation at every particle.
        """
        c = self.config
        idx, d2 = self.neighbours(y, j)
        bsz, k = idx.shape
        lam = lambda_log_weights(d2, c.lambda_scale, c.lambda_scale_factor)
        ow = c.outlier_weight
        mix = PoseMixture(
            self.poses[idx.reshape(-1)],
            (lam + math.log1p(-ow)).reshape(-1),
            np.full(bsz * k, c.sigma_xy),
            np.full(bsz * k, c.sigma_theta),
        )
        x = np.asarray(camera_poses, dtype=np.float64).reshape(-1, 3)
        terms = mix._component_terms(x).reshape(bsz, k, x.shape[0])
        top = terms.max(axis=1, keepdims=True)
        terms -= top
        np.exp(terms, out=terms)
        out = np.log(terms.sum(axis=1)) + top[:, 0, :]
        if ow > 0.0:
            inside = self.bounds.contains(x[:, :2])
            lo = np.where(inside, math.log(ow) + self.bounds.log_uniform_density, -np.inf)
            out = np.logaddexp(out, lo[None, :])
        return out

    def mixture_from_neighbours(self, idx: ArrayLike, dist2: ArrayLike) -> PoseMixture:
        """The mixture defined by given neighbour indices (J,) and squared feature distances (J,)."""
        return self._mixture(np.asarray(idx, dtype=np.int64), dist2, math.nan)

    def _mixture(self, ii: IntArray, dist2: ArrayLike, novelty: float) -> PoseMixture:
        c = self.config
        lam = lambda_log_weights(dist2, c.lambda_scale, c.lambda_scale_factor)  # normalized
        k = ii.size
        ow = c.outlier_weight
        if k not in self._widths:  # constant per J: built once (read-only)
            sxy, sth = np.full(k, c.sigma_xy), np.full(k, c.sigma_theta)
            sxy.flags.writeable = sth.flags.writeable = False
            self._widths[k] = (sxy, sth)
        sxy, sth = self._widths[k]
        return PoseMixture(
            self.poses[ii],
            lam + math.log1p(-ow),
            sxy,
            sth,
            math.log(ow) if ow > 0.0 else -math.inf,
            self.bounds,
            0.0,
            ii,
            novelty,
        )

"""Appearance interpolated between survey poses: a sensor model defined at every pose.

The parametric eigenspace of Murase and Nayar ("Visual learning and recognition of 3-D objects
from appearance", IJCV 14, 1995; the paper's reference [8]): the map's feature vectors, sampled
at the survey poses, are points of a manifold parametrized by the pose; between the samples
the manifold is interpolated. Here the survey is a lattice in (x, y, theta): positions every
``step`` metres (some missing: positions inside furniture), at every position the same
headings round the full turn (a survey's headings completed by virtual headings,
``lino_loc.virtual_views``; evenly spaced or not).

Interpolation (:class:`SurveyLattice`, :meth:`InterpolatedAppearance.features_at`): trilinear
in (x, y, theta). For a pose with lattice coordinates (i + a, j + b, k + c), 0 <= a, b, c < 1
(c the fraction of the gap from heading k to the next one),

    f(x) = sum over the 8 corners (i + di, j + dj, k + dk) of w_corner F[corner] / sum w_corner,
    w_corner = (a if di else 1 - a) (b if dj else 1 - b) (c if dk else 1 - c),

the heading index wrapped (k + 1 is 0 after the last heading) and the corners that are not in
the map (holes) left out of both sums; a pose none of whose corners is in the map has no
features. Positions outside the lattice's box take the nearest box position (constant
extrapolation). f is exact at the lattice poses and linear along each axis in between.

Likelihood (:class:`InterpolatedSensorModel`): the features are whitened by per-feature
scales ``s_k`` learnt from the map itself, the leave-one-out residuals of the interpolation:
every entry whose two neighbours along x (or along y) at the same heading are in the map is
predicted as their mean (the interpolation with that entry left out), and ``s_k^2`` is the
mean squared residual of feature k over those predictions, times ``residual_scale^2`` (and at
least ``SCALE_FLOOR`` times the largest of them: a feature the interpolation reproduces
exactly would otherwise get s = 0). Then

    L(x) = exp(-|W (y - f(x))|^2 / 2),   W = diag(1 / s_k),

and, as for the nearest-neighbour model (``lino_loc.sensor_model``), the sensor model is
used as a density over camera poses with the same uniform outlier component:

    p(y | x) ~ (1 - w_out) L(x) / Z(y) + w_out / (area 2 pi)   (the second term inside the bounds),
    Z(y) = V sum_n L(x_n)   (a Riemann sum over the map entries, V the lattice cell's volume).

An observation is an :class:`InterpolatedLikelihood`, a :class:`lino_loc.sensor_model.
PoseMixture` whose ``log_pdf`` / ``log_pdf_trig`` are the density above and whose kernels
are the proposal that ``sample`` draws from (global localization, kidnap recovery): the
nearest-neighbour model's mixture of y (``lino_loc.sensor_model``: its J nearest map entries,
lambda weights, kernel widths, outlier component; also its novelty); ``proposal_log_pdf`` is
that proposal's density. Disjunctive and conjunctive fusion
of such observations (eq. 7 / 8): :func:`fuse_likelihoods`.

Usage::

    model = InterpolatedSensorModel(map_poses, map_features, SensorModelConfig(outlier_weight=0.01))
    obs = model.observe(y)
    log_lik = obs.log_pdf(camera_pose(particles, pan))
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.errors import LinoLocError
from lino_loc.fusion import FusionConfig, fuse
from lino_loc.resampling import logsumexp
from lino_loc.sensor_model import (
    Bounds,
    NearestNeighbourSensorModel,
    PoseMixture,
    SensorModelConfig,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
LogDensity = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]

#: Tolerance (in lattice steps) for a map pose to count as a lattice node.
LATTICE_TOLERANCE = 1e-3
#: Smallest learnt feature scale, relative to the largest (module docstring).
SCALE_FLOOR = 0.05
#: Map entries at a time in the (entries x entries) distance sums of the normalizers.
_BLOCK = 512


class InterpolationConfig(BaseModel):
    """Settings of the interpolated sensor model (module docstring)."""

    model_config = ConfigDict(extra="forbid")

    residual_scale: float = Field(
        1.0, gt=0.0, description="s_k = this factor times the leave-one-out residual's RMS of feature k "
        "(the residuals are those of a span of two lattice steps)",
    )


def _axis(values: FloatArray, name: str) -> tuple[float, float, int]:
    """(origin, step, count) of the evenly spaced values ``values`` (a lattice axis); a single
    value gives step 1. LinoLocError when the values are not on one evenly spaced axis."""
    u = np.unique(np.round(values, 6))
    if u.size == 1:
        return float(u[0]), 1.0, 1
    step = float(np.min(np.diff(u)))
    k = (u - u[0]) / step
    if np.max(np.abs(k - np.round(k))) > LATTICE_TOLERANCE:
        raise LinoLocError(f"interpolated sensor model: map {name} values are not evenly spaced")
    return float(u[0]), step, int(round(float(k[-1]))) + 1


def _circle_values(angles: FloatArray, tol: float = 1e-6) -> FloatArray:
    """The distinct angles mod 2 pi, sorted in [0, 2 pi); angles within ``tol`` of each other
    (also across 2 pi) count as one, the smallest of them kept exactly."""
    t = np.sort(np.mod(angles, 2.0 * math.pi))
    h = t[np.concatenate([[True], np.diff(t) > tol])]
    if h.size > 1 and h[-1] > 2.0 * math.pi - tol + h[0]:
        h = h[:-1]
    return h


class SurveyLattice:
    """The map's poses as a lattice: ``table[i, j, k]`` is the entry at position (i, j) and
    heading k, -1 where the map has none (a hole). Positions evenly spaced in x and y; the
    headings are the map's distinct headings, sorted round the circle (not necessarily evenly
    spaced: a survey's headings with virtual ones each side), interpolated linearly across each
    gap, the last gap wrapping to the first heading.
    LinoLocError when the poses are not on such a lattice or two entries share a node."""

    def __init__(self, poses: ArrayLike) -> None:
        p = np.asarray(poses, dtype=np.float64)
        self.x0, self.step_x, self.nx = _axis(p[:, 0], "x")
        self.y0, self.step_y, self.ny = _axis(p[:, 1], "y")
        h = _circle_values(p[:, 2])
        self.nh = int(h.size)
        self.headings = h  # sorted, in [0, 2 pi)
        self.step_h = 2.0 * math.pi / self.nh  # the mean spacing
        # the gap from each heading to the next one round the circle
        self._gap = np.diff(np.append(h, h[0] + 2.0 * math.pi))
        kh = self._heading_index(p[:, 2])
        ix = (p[:, 0] - self.x0) / self.step_x
        iy = (p[:, 1] - self.y0) / self.step_y
        for name, k in (("x", ix), ("y", iy)):
            if np.max(np.abs(k - np.round(k))) > LATTICE_TOLERANCE:
                raise LinoLocError(f"interpolated sensor model: map {name} values are not on one lattice")
        idx = np.stack([np.round(ix), np.round(iy), np.round(kh) % self.nh]).astype(np.int64)
        self.table = np.full((self.nx, self.ny, self.nh), -1, dtype=np.int64)
        self.table[idx[0], idx[1], idx[2]] = np.arange(p.shape[0])
        if int((self.table >= 0).sum()) != p.shape[0]:
            raise LinoLocError("interpolated sensor model: two map entries share one lattice pose")
        self.node = idx.T  # (N, 3) lattice index of each entry

    @property
    def cell_volume(self) -> float:
        """step_x step_y step_h (a missing axis counts 1 m)."""
        sx = self.step_x if self.nx > 1 else 1.0
        sy = self.step_y if self.ny > 1 else 1.0
        return sx * sy * self.step_h

    def corners(self, px: FloatArray, py: FloatArray, th: FloatArray) -> tuple[IntArray, FloatArray]:
        """The 8 interpolation corners of each pose: entry indices (M, 8), -1 for a hole, and
        their normalized trilinear weights (M, 8), all 0 when no corner is in the map."""
        i0, a = self._split(px, self.x0, self.step_x, self.nx)
        j0, b = self._split(py, self.y0, self.step_y, self.ny)
        k0, c = self._heading_split(th)
        m = px.shape[0]
        idx = np.empty((m, 8), dtype=np.int64)
        w = np.empty((m, 8))
        n = 0
        for di, wa in ((0, 1.0 - a), (1, a)):
            ii = np.minimum(i0 + di, self.nx - 1)
            for dj, wb in ((0, 1.0 - b), (1, b)):
                jj = np.minimum(j0 + dj, self.ny - 1)
                for dk, wc in ((0, 1.0 - c), (1, c)):
                    idx[:, n] = self.table[ii, jj, (k0 + dk) % self.nh]
                    w[:, n] = wa * wb * wc
                    n += 1
        w[idx < 0] = 0.0
        tot = w.sum(axis=1, keepdims=True)
        np.divide(w, tot, out=w, where=tot > 0)
        return idx, w

    def _heading_index(self, th: FloatArray) -> FloatArray:
        """Index of the lattice heading equal to each heading (within 1e-5 rad)."""
        t = np.mod(th, 2.0 * math.pi)
        d = np.abs(np.angle(np.exp(1j * (t[:, None] - self.headings[None, :]))))
        k = np.argmin(d, axis=1)
        if np.max(d[np.arange(t.size), k]) > 1e-5:
            raise LinoLocError("interpolated sensor model: map heading values are not on one lattice")
        return k.astype(np.float64)

    def _heading_split(self, th: FloatArray) -> tuple[IntArray, FloatArray]:
        """Lower heading index (the nearest lattice heading at or below, round the circle) and
        the fraction of the gap to the next one."""
        t = np.mod(th, 2.0 * math.pi)
        k0 = (np.searchsorted(self.headings, t, side="right") - 1) % self.nh
        c = np.mod(t - self.headings[k0], 2.0 * math.pi) / self._gap[k0]
        return k0, np.clip(c, 0.0, 1.0)

    @staticmethod
    def _split(v: FloatArray, origin: float, step: float, count: int) -> tuple[IntArray, FloatArray]:
        """Lower lattice index and fraction along one axis, positions clamped to the lattice."""
        if count == 1:
            return np.zeros(v.shape[0], dtype=np.int64), np.zeros(v.shape[0])
        f = np.clip((v - origin) / step, 0.0, count - 1.0)
        i = np.minimum(np.floor(f).astype(np.int64), count - 2)
        return i, f - i


class InterpolatedAppearance:
    """The map's features f(x) at any pose, by trilinear interpolation over the survey lattice
    (module docstring), in the features' own units."""

    def __init__(self, poses: ArrayLike, features: ArrayLike) -> None:
        self.lattice = SurveyLattice(poses)
        f = np.asarray(features, dtype=np.float64)
        self.features = f
        self._padded = np.vstack([f, np.zeros((1, f.shape[1]))])  # row N: a hole

    def features_at(self, poses: ArrayLike) -> tuple[FloatArray, NDArray[np.bool_]]:
        """f at poses (M, 3) -> (features (M, d), valid (M,)); rows without a corner in the map
        are 0 and not valid."""
        x = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        return self.features_trig(x[:, 0], x[:, 1], x[:, 2])

    def features_trig(self, px: FloatArray, py: FloatArray, th: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """:meth:`features_at` with the poses as x, y and heading arrays."""
        idx, w = self.lattice.corners(px, py, th)
        idx = np.where(idx < 0, self.features.shape[0], idx)
        f = np.einsum("mc,mcd->md", w, self._padded[idx])
        return f, w.sum(axis=1) > 0.5

    def leave_one_out_residuals(self) -> FloatArray:
        """Residuals (K, d) of the entries predicted as the mean of their two neighbours along x
        or along y at the same heading (both in the map). LinoLocError when there is none."""
        lat, f = self.lattice, self.features
        out = []
        for axis in (0, 1):
            lo = np.roll(lat.table, 1, axis=axis)
            hi = np.roll(lat.table, -1, axis=axis)
            mid = lat.table
            ok = (mid >= 0) & (lo >= 0) & (hi >= 0)
            edge = np.zeros_like(ok)
            sl = [slice(None)] * 3
            for s in (0, -1):
                sl[axis] = s
                edge[tuple(sl)] = True
            ok &= ~edge
            out.append(f[mid[ok]] - 0.5 * (f[lo[ok]] + f[hi[ok]]))
        r = np.concatenate(out)
        if r.shape[0] == 0:
            raise LinoLocError(
                "interpolated sensor model: no map entry has two neighbours along x or y "
                "(the scale cannot be learnt)"
            )
        return r


@dataclass(frozen=True)
class InterpolatedLikelihood(PoseMixture):
    """One observation's sensor model (module docstring): ``log_pdf`` is ``density``, the
    kernels are the proposal ``sample`` draws from."""

    density: LogDensity | None = field(default=None, compare=False)

    def log_pdf_trig(self, px: FloatArray, py: FloatArray, cos_t: FloatArray, sin_t: FloatArray) -> FloatArray:
        """log p(y | x) at poses given as x, y, cos, sin (each (M,)), log_scale included."""
        assert self.density is not None
        return self.density(px, py, np.arctan2(sin_t, cos_t)) + self.log_scale

    def proposal_log_pdf(self, poses: ArrayLike) -> FloatArray:
        """log density of the kernels ``sample`` draws from (log_scale excluded)."""
        x = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        lp = PoseMixture.log_pdf_trig(self, x[:, 0], x[:, 1], np.cos(x[:, 2]), np.sin(x[:, 2]))
        return lp - self.log_scale


class InterpolatedSensorModel:
    """The sensor model of the interpolated appearance over one map channel (module
    docstring). ``map_poses`` (N, 3) are CAMERA poses on a survey lattice; the outlier weight,
    the map margin, J (the proposal's kernels) and the kernel widths come from ``config``."""

    def __init__(
        self,
        map_poses: ArrayLike,
        map_features: ArrayLike,
        config: SensorModelConfig | None = None,
        interpolation: InterpolationConfig | None = None,
        bounds: Bounds | None = None,
        j: int | None = None,
    ) -> None:
        self.config = config or SensorModelConfig()
        self.interpolation = interpolation or InterpolationConfig()
        self.nn = NearestNeighbourSensorModel(map_poses, map_features, self.config, j=j, bounds=bounds)
        self.poses, self.bounds, self.j = self.nn.poses, self.nn.bounds, self.nn.j
        self.appearance = InterpolatedAppearance(self.poses, self.nn.features)
        r = self.appearance.leave_one_out_residuals()
        s = self.interpolation.residual_scale * np.sqrt(np.mean(r * r, axis=0))
        # a feature the interpolation reproduces exactly (a linear field) would get s = 0 (or
        # round-off): floored at SCALE_FLOOR of the largest scale
        top = float(s.max())
        self.scale = np.maximum(s, SCALE_FLOOR * top) if top > 0.0 else np.ones_like(s)
        self._white = self.nn.features / self.scale  # whitened map features (N, d)
        self._white_sq = np.einsum("nd,nd->n", self._white, self._white)
        self._log_volume = math.log(self.appearance.lattice.cell_volume)
        ow = self.config.outlier_weight
        self.log_inlier = math.log1p(-ow)
        self.log_floor = math.log(ow) + self.bounds.log_uniform_density if ow > 0.0 else -math.inf
        self._node_log_z: FloatArray | None = None

    @property
    def dim(self) -> int:
        """d, the length of a feature vector."""
        return self.nn.dim

    def log_normalizer(self, yw: FloatArray) -> FloatArray:
        """log Z(y) for whitened observations (B, d) -> (B,): log(V sum_n L(x_n))."""
        d2 = self._white_sq[None, :] - 2.0 * yw @ self._white.T + np.einsum("bd,bd->b", yw, yw)[:, None]
        return logsumexp(-0.5 * np.maximum(d2, 0.0), axis=1) + self._log_volume

    @property
    def node_log_normalizer(self) -> FloatArray:
        """log Z(F_n) of every map entry's own features (N,), computed once."""
        if self._node_log_z is None:
            n = self._white.shape[0]
            self._node_log_z = np.concatenate(
                [self.log_normalizer(self._white[lo : lo + _BLOCK]) for lo in range(0, n, _BLOCK)]
            )
        return self._node_log_z

    def log_density(self, yw: FloatArray, log_z: float, px: FloatArray, py: FloatArray, th: FloatArray) -> FloatArray:
        """log p(y | x) (module docstring) of one whitened observation at poses (M,)."""
        f, ok = self.appearance.features_trig(px, py, th)
        r = f / self.scale - yw[None, :]
        out = self.log_inlier - log_z - 0.5 * np.einsum("md,md->m", r, r)
        out[~ok] = -np.inf
        if self.log_floor > -math.inf:
            inside = self.bounds.contains(np.column_stack([px, py]))
            out = np.logaddexp(out, np.where(inside, self.log_floor, -np.inf))
        return out

    def observe(self, y: ArrayLike, j: int | None = None) -> InterpolatedLikelihood:
        """The sensor model of one observed feature vector y (d,)."""
        q = np.asarray(y, dtype=np.float64).reshape(-1)
        base = self.nn.observe(q, j)  # validates y; its mixture is the proposal
        yw = q / self.scale
        log_z = float(self.log_normalizer(yw[None, :])[0])

        def density(px: FloatArray, py: FloatArray, th: FloatArray) -> FloatArray:
            return self.log_density(yw, log_z, px, py, th)

        return InterpolatedLikelihood(
            base.poses, base.log_weights, base.sigma_xy, base.sigma_theta, base.outlier_log_weight,
            base.bounds, 0.0, base.neighbours, base.novelty, None, density,
        )


def fuse_likelihoods(
    observations: Mapping[str, PoseMixture], config: FusionConfig | None = None
) -> PoseMixture:
    """Eq. 8 (disjunctive: log sum_c w_c p_c) or eq. 7 (conjunctive: sum_c log p_c) of the
    channels' observations (interpolated likelihoods, or any PoseMixture), as an
    :class:`InterpolatedLikelihood`; the proposal is :func:`lino_loc.fusion.fuse` of their
    kernels. Weights as in ``fuse`` (``w_i`` intensity, ``w_d`` disparity, normalized). A single
    channel is returned unchanged."""
    c = config or FusionConfig()
    if len(observations) == 1:
        return next(iter(observations.values()))
    names = list(observations)
    obs = [observations[n] for n in names]
    proposal = fuse(dict(observations), c)
    weight = {"disparity": c.w_d, "intensity": c.w_i}
    w = np.asarray([weight.get(n, 1.0) for n in names], dtype=np.float64)
    with np.errstate(divide="ignore"):
        logw = np.log(w / w.sum())

    def density(px: FloatArray, py: FloatArray, th: FloatArray) -> FloatArray:
        x = np.column_stack([px, py, th])
        parts = [o.log_pdf(x) for o in obs]
        if c.mode == "conjunctive":
            return np.sum(parts, axis=0)
        return logsumexp(np.stack([lp + lw for lp, lw in zip(parts, logw, strict=True)]), axis=0)

    novelty = observations["intensity"].novelty if "intensity" in observations else math.nan
    out_w = proposal.outlier_log_weight
    if c.mode == "conjunctive" and proposal.bounds is not None:
        # the density's floor far from every kernel is the product of the channels' floors
        lu = proposal.bounds.log_uniform_density
        out_w = sum(o.outlier_log_weight + lu for o in obs) - lu
    return InterpolatedLikelihood(
        proposal.poses, proposal.log_weights, proposal.sigma_xy, proposal.sigma_theta,
        out_w, proposal.bounds, 0.0, None, novelty, None, density,
    )


__all__ = [
    "InterpolatedAppearance",
    "InterpolatedLikelihood",
    "InterpolatedSensorModel",
    "InterpolationConfig",
    "SurveyLattice",
    "fuse_likelihoods",
]

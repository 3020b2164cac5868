"""The kernel floor of lino_loc.active_vision.ActionEvaluator (LOG_NEGLIGIBLE) leaves H(u) as
it was: the evaluator before the floor is kept here as the reference (its float32 sums with
subnormal numbers), and both are compared on seeded beliefs, on every path (product grid with
the kernel table, with gathered kernels, the generic k-d tree path), with both predicted-
neighbour rules, with and without the outlier floor."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import ArrayLike

from lino_loc.active_vision import (
    ActionEvaluator,
    ActionValues,
    ActiveVisionConfig,
    discrete_entropy,
    subsample,
)
from lino_loc.poses import wrap_angle
from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig
from services.evaluation.action_cost import office_like_map

# The floor changes terms below exp(-40) only, far below the float32 resolution of every sum:
# the float32 likelihoods come out bit-equal, and H(u) (summed in float64) to round-off.
RTOL = 1e-9
ATOL = 1e-12


class ReferenceEvaluator(ActionEvaluator):
    """:class:`ActionEvaluator` as it was before the kernel floor (the three methods it changed)."""

    def _kernels(self, p: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a_n, m = u.size, p.shape[0]
        if self.grid:
            g, v, pred = self._grid_factors(p, u)
            kern = g[None, :, None, :] * v[:, None, :, :]
            return kern.reshape(a_n, -1, m), pred.astype(np.int64)
        cam = np.repeat(p[None, :, :], a_n, axis=0)
        cam[:, :, 2] = cam[:, :, 2] + u[:, None]
        emb = self.embed(cam).reshape(a_n * m, 4)
        _, near = self._tree.query(emb, k=1)
        e32 = emb.astype(np.float32)
        t = self._emb_map32 @ e32.T
        t -= 0.5 * self._sq_map[:, None]
        t -= 0.5 * np.einsum("ij,ij->i", e32, e32)[None, :]
        np.minimum(t, 0.0, out=t)
        np.exp(t, out=t)
        kern = t.reshape(-1, a_n, m).transpose(1, 0, 2)
        return np.ascontiguousarray(kern), np.asarray(near, dtype=np.int64).reshape(a_n, m)

    def _grid_factors(self, p: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pos = self._positions
        dx = pos[:, 0:1] - p[None, :, 0]
        dy = pos[:, 1:2] - p[None, :, 1]
        lg = -(dx * dx + dy * dy) / (2.0 * self.sigma_xy**2)
        near_p = np.argmax(lg, axis=0)
        g = np.exp(lg.astype(np.float32))
        cam = p[None, :, 2] + u[:, None]
        ang = np.cos(cam).astype(np.float32)[:, None, :] * self._cos_h[None, :, None]
        ang += np.sin(cam).astype(np.float32)[:, None, :] * self._sin_h[None, :, None]
        near_h = np.argmax(ang, axis=1)
        ang -= np.float32(1.0)
        ang *= np.float32(self.kappa)
        v = np.exp(ang, out=ang)
        return g, v, near_p[None, :] * self._headings.size + near_h

    def evaluate(self, particles: ArrayLike, log_weights: ArrayLike, actions: ArrayLike | None = None,
                 rng: np.random.Generator | None = None) -> ActionValues:
        u = self.actions if actions is None else np.asarray(actions, dtype=np.float64).reshape(-1)
        p, lw = subsample(particles, log_weights, self.config.max_particles, rng)
        pi = np.exp(lw)
        s, _ = self._mixture_sums(p, u)
        inside = self.model.bounds.contains(p[:, :2])
        s += (self._floor_over_norm * inside).astype(np.float32)[None, None, :]
        s *= (pi / pi.max()).astype(np.float32)[None, None, :]
        z = s.sum(axis=-1, dtype=np.float64)
        lq = np.zeros_like(s)
        np.log(s, out=lq, where=s > 0)
        sq = np.einsum("aik,aik->ai", s, lq, dtype=np.float64)
        ok = z > 0
        h = np.full(z.shape, float(discrete_entropy(lw)))
        h[ok] = np.log(z[ok]) - sq[ok] / z[ok]
        return ActionValues(actions=u, expected_entropy=h @ pi, current_entropy=float(discrete_entropy(lw)),
                            n_particles=int(p.shape[0]))


def small_grid(heading_step_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """5 x 3 positions 75 cm apart, headings every ``heading_step_deg``, smooth features."""
    rng = np.random.default_rng(3)
    hs = wrap_angle(np.radians(np.arange(int(round(360 / heading_step_deg))) * heading_step_deg))
    gx, gy, gh = np.meshgrid(np.arange(5) * 0.75, np.arange(3) * 0.75, hs, indexing="ij")
    poses = np.column_stack([gx.ravel(), gy.ravel(), gh.ravel()])
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    feats = np.column_stack([3 * c + 0.4 * poses[:, 0], 3 * s + 0.4 * poses[:, 1], np.sin(2 * poses[:, 0]) * c,
                             0.2 * rng.standard_normal(len(poses))])
    return poses, feats


def beliefs(extent: tuple[float, float], m: int = 150) -> list[tuple[np.ndarray, np.ndarray]]:
    """Seeded beliefs: uniform; uniform with weights spread over e^-60; two tight clusters with
    duplicate particles (a resampled, bimodal belief); some particles far outside the map."""
    rng = np.random.default_rng(11)
    w, h = extent

    def uniform(n: int) -> np.ndarray:
        return np.column_stack([rng.uniform(-0.3, w + 0.3, n), rng.uniform(-0.3, h + 0.3, n),
                                rng.uniform(-math.pi, math.pi, n)])

    out = [(uniform(m), np.full(m, -math.log(m)))]
    out.append((uniform(m), rng.uniform(-60.0, 0.0, m)))
    centres = np.array([[0.4, 0.5, 0.3], [w - 0.5, h - 0.4, -2.5]])
    clusters = centres[rng.integers(0, 2, m // 3)] + rng.normal(0, [0.1, 0.1, 0.1], (m // 3, 3))
    out.append((np.repeat(clusters, 3, axis=0), np.full(3 * (m // 3), 0.0)))
    far = uniform(m)
    far[: m // 4, 0] += w + 4.0  # beyond the bounds: no outlier floor, far kernels only
    out.append((far, rng.normal(0.0, 3.0, m)))
    return out


CASES = [  # (map, sensor outlier weight, predicted neighbours, use_grid)
    ("grid15", 0.01, "all", True), ("grid15", 0.0, "leave_one_out", True), ("grid15", 0.5, "all", False),
    ("grid3", 0.01, "all", True), ("grid3", 0.0, "all", True), ("grid3", 0.01, "leave_one_out", True),
    ("office15", 0.5, "all", True), ("office3", 0.01, "all", True),
]


@pytest.mark.parametrize(("name", "outlier", "neighbours", "use_grid"), CASES)
def test_the_floor_leaves_the_expected_entropies_and_the_choice(name: str, outlier: float, neighbours: str,
                                                                 use_grid: bool) -> None:
    step = 15.0 if name.endswith("15") else 3.0
    poses, feats = office_like_map(heading_step_deg=step) if name.startswith("office") else small_grid(step)
    extent = (float(np.ptp(poses[:, 0])), float(np.ptp(poses[:, 1])))
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=10, outlier_weight=outlier))
    config = ActiveVisionConfig(predicted_neighbours=neighbours)  # type: ignore[arg-type]
    fast, ref = ActionEvaluator(model, config, use_grid=use_grid), ReferenceEvaluator(model, config, use_grid=use_grid)
    assert fast.grid is use_grid
    for p, lw in beliefs(extent):
        got, want = fast.evaluate(p, lw), ref.evaluate(p, lw)
        np.testing.assert_allclose(got.expected_entropy, want.expected_entropy, rtol=RTOL, atol=ATOL)
        assert got.current_entropy == want.current_entropy
        order = np.sort(want.expected_entropy)
        if order[1] - order[0] > 2 * ATOL + 2 * RTOL * abs(order[0]):  # no tie within the tolerance
            assert got.best() == want.best()

"""How precise an estimate section 6.1's criterion asks for, and how precise appearance can be.

The criterion (:func:`lino_loc.metrics.success`) counts a run right when the map position
nearest the estimate is the one nearest the truth: the estimate must fall in the truth's
Voronoi cell of the survey grid. Two references for the active-localization figures
(:mod:`services.evaluation.active`), both independent of the filter:

* :func:`success_under_noise`: the success rate of an estimate that is the truth plus an
  isotropic Gaussian position error of standard deviation sigma per axis, at the experiment's
  own test positions (:func:`services.evaluation.active.place_test_positions`). On a square grid
  of spacing ``s`` far from walls the two axes are independent and the rate is ``q(sigma)^2``
  with ``q = (1/s) int_0^s [Phi((s - u)/sigma) - Phi(-u/sigma)] du`` (the unit tests check this
  closed form). :func:`precision_for` reads off the sigma that gives a target rate.
* :func:`appearance_oracle`: the best a map of views on a lattice finer than the survey could
  do at a test position. The views the robot takes there (the sweep's pans) are compared with
  views rendered on the lattice of spacing step / m aligned with the survey grid, near the
  truth and at the true heading; the lattice point whose views match best (sum of squared
  distances over the views) is the decision. m = 1 is the survey itself; m = 3, 9 are
  what a perfect synthesis of views between survey poses (virtual translations, Murase &
  Nayar's interpolated eigenspace sampled on the lattice) could reach at best: real renders,
  the truth's neighbourhood and heading given. Two distances: in the map's PCA features
  (eq. 1) and in the cropped pixels themselves. The refinements are odd: a lattice with even
  m has points on the survey cells' borders, equidistant to two survey positions, which the
  criterion counts right for either (its ties), so such a lattice's success would be inflated;
  with odd m every lattice cell lies inside one survey cell.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from drivers.sim.world import World
from lino_loc.metrics import map_positions, success
from lino_loc.virtual_views import crop_columns
from services.evaluation.active_bounds import sweep_order
from services.evaluation.active_setup import ActiveSetup
from services.evaluation.views import ViewSpec, render_vectors

#: Per-axis standard deviations (m) of the position error at which the criterion is evaluated.
SIGMAS: tuple[float, ...] = (0.01, 0.02, 0.03, 0.04, 0.05, 0.075, 0.1, 0.15, 0.2, 0.25, 0.3)


def success_under_noise(truths: np.ndarray, grid: np.ndarray, sigmas: tuple[float, ...] = SIGMAS,
                        draws: int = 200, seed: int = 0) -> np.ndarray:
    """Success rate (len(sigmas),) of ``truth + N(0, sigma^2 I)`` in (x, y) over the test poses
    ``truths`` (P, 3) and ``draws`` errors each, against the survey ``grid`` (N, 3)."""
    t = np.asarray(truths, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] == 0:
        raise ValueError(f"success_under_noise: truths must be (P, 3) with P > 0, got {t.shape}")
    rng = np.random.default_rng(seed)
    rep = np.repeat(t, draws, axis=0)
    out = []
    for sigma in sigmas:
        if sigma < 0:
            raise ValueError(f"success_under_noise: sigma {sigma} is negative")
        est = rep.copy()
        est[:, :2] += sigma * rng.standard_normal((rep.shape[0], 2))
        out.append(float(np.mean(success(est, rep, grid))))
    return np.asarray(out)


def precision_for(sigmas: tuple[float, ...], rates: np.ndarray, target: float) -> float | None:
    """The sigma (m) at which the success rate falls to ``target``, linearly interpolated
    between the evaluated sigmas (rates fall with sigma); None when even the smallest sigma
    misses the target, the largest when every sigma meets it."""
    s = np.asarray(sigmas, dtype=np.float64)
    r = np.asarray(rates, dtype=np.float64)
    if r[0] < target:
        return None
    below = np.nonzero(r < target)[0]
    if below.size == 0:
        return float(s[-1])
    i = int(below[0])
    return float(s[i - 1] + (s[i] - s[i - 1]) * (r[i - 1] - target) / (r[i - 1] - r[i]))


def lattice(origin: np.ndarray, spacing: float, truth: np.ndarray, radius: float) -> np.ndarray:
    """Integer indices (M, 2) of the points ``origin + spacing * (i, j)`` of a square lattice
    that lie within ``radius`` of the truth's (x, y) in both axes (Chebyshev distance)."""
    if spacing <= 0 or radius < 0:
        raise ValueError(f"lattice: spacing {spacing} must be > 0 and radius {radius} >= 0")
    lo = np.ceil((np.asarray(truth[:2]) - radius - origin) / spacing - 1e-9).astype(np.int64)
    hi = np.floor((np.asarray(truth[:2]) + radius - origin) / spacing + 1e-9).astype(np.int64)
    gi, gj = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    return np.column_stack([gi.ravel(), gj.ravel()])


def appearance_oracle(setup: ActiveSetup, world: World, grid: np.ndarray, pca: Any, margin: int,
                      truths: np.ndarray, views: int = 4, radius: float = 0.6,
                      refinements: tuple[int, ...] = (1, 3, 9),
                      progress: Callable[[str, int, int], None] | None = None) -> dict[str, Any]:
    """The lattice oracle at each test pose of ``truths`` (P, 3).

    The robot's views: the first ``views`` pans of run 0's sweep
    (:func:`services.evaluation.active_bounds.sweep_order`), rendered with the experiment's test
    seed. The candidates: for each refinement m, the lattice of spacing ``setup.step / m``
    aligned with the survey grid (m = 1 is the survey's own positions), its free points within
    ``radius`` of the truth, each seen at the truth's heading and the same pans; rendered once
    on the finest lattice with another seed (independent sensor noise), the coarser lattices
    being its subsets. The decision is the candidate with the least sum of squared distances
    over the first k views; it succeeds by :func:`lino_loc.metrics.success` against ``grid``.

    Returns ``out[distance][m][k]`` with ``distance`` ``"features"`` (the map's PCA, eq. 1) or
    ``"pixels"`` (the cropped image), ``m`` and ``k`` as strings: ``success`` (P,) bools and
    ``error`` (P,) metres."""
    refs = tuple(sorted(set(int(m) for m in refinements)))
    finest = refs[-1]
    if refs[0] < 1 or any(finest % m for m in refs):
        raise ValueError(f"appearance_oracle: refinements {refinements} must be positive divisors of the largest")
    pans = setup.active.actions()
    origin = np.min(map_positions(grid), axis=0)
    spacing = setup.step / finest
    spec = ViewSpec(world=setup.world, lighting=setup.lighting, width=setup.width, height=setup.height,
                    size=setup.size, preprocess=(setup.preprocess,), seed=setup.seed + 1000)
    order = np.asarray([sweep_order(setup, p, 0, pans.size)[:views] for p in range(truths.shape[0])])
    cams = np.repeat(truths[:, None, :], views, axis=1)
    cams[:, :, 2] = cams[:, :, 2] + pans[order]
    test = crop_columns(render_vectors(spec, cams.reshape(-1, 3), workers=setup.workers)[setup.preprocess],
                        setup.size, margin).reshape(truths.shape[0], views, -1)
    lat_spec = replace(spec, seed=setup.seed + 7000)
    out: dict[str, Any] = {d: {str(m): {str(k): {"success": [], "error": []} for k in range(1, views + 1)}
                               for m in refs} for d in ("features", "pixels")}
    for p, truth in enumerate(truths):
        ij = lattice(origin, spacing, truth, radius)
        xy = origin[None, :] + spacing * ij
        keep = world.is_free(xy[:, 0], xy[:, 1])
        ij, xy = ij[keep], xy[keep]
        poses = np.column_stack([np.repeat(xy, views, axis=0), np.tile(truth[2] + pans[order[p]], xy.shape[0])])
        lat = crop_columns(render_vectors(lat_spec, poses, workers=setup.workers)[setup.preprocess],
                           setup.size, margin).reshape(xy.shape[0], views, -1)
        vecs = {"pixels": (lat.astype(np.float64), test[p].astype(np.float64)),
                "features": (np.asarray(pca.project(lat.reshape(-1, lat.shape[-1])), dtype=np.float64
                                        ).reshape(xy.shape[0], views, -1),
                             np.asarray(pca.project(test[p]), dtype=np.float64))}
        for name, (L, y) in vecs.items():
            cost = np.cumsum(np.sum((L - y[None]) ** 2, axis=2), axis=1)  # (M, views)
            for m in refs:
                on = np.all(ij % (finest // m) == 0, axis=1)
                idx = np.nonzero(on)[0]
                for k in range(1, views + 1):
                    cell = out[name][str(m)][str(k)]
                    if idx.size == 0:  # no candidate of this lattice is free near the truth
                        cell["success"].append(False)
                        cell["error"].append(float("inf"))
                        continue
                    best = int(idx[np.argmin(cost[idx, k - 1])])
                    est = np.array([xy[best, 0], xy[best, 1], truth[2]])
                    cell["success"].append(bool(success(est, truth, grid)[0]))
                    cell["error"].append(float(np.hypot(*(xy[best] - truth[:2]))))
        if progress:
            progress("oracle", p + 1, truths.shape[0])
    for by_m in out.values():
        for by_k in by_m.values():
            for v in by_k.values():
                v["success"] = np.asarray(v["success"])
                v["error"] = np.asarray(v["error"])
    return out

"""The estimate's mode finding: the hashed clustering gives the same partition (and the same
numbering) as the dense-grid labelling it replaced, across the heading seam too; it stays
bounded in memory and time for a cloud kilometres wide; non-finite particles belong to no
mode and have no weight in the estimate."""

from __future__ import annotations

import math
import time
import tracemalloc

import numpy as np
import pytest
from scipy import ndimage

from lino_loc.pose_estimate import (
    CLUSTER_CELL_THETA,
    CLUSTER_CELL_XY,
    cluster_labels,
    dominant_mode,
    weighted_pose_stats,
)
from lino_loc.poses import wrap_angle


def grid_labels(
    poses: np.ndarray, cell_xy: float = CLUSTER_CELL_XY, cell_theta: float = CLUSTER_CELL_THETA
) -> np.ndarray:
    """The reference: ``scipy.ndimage.label`` on the dense occupancy grid of the particles'
    bounding box, labels touching across the heading seam merged (the former implementation;
    memory grows with the square of the cloud's spread)."""
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
    present = np.zeros(int(grid.max()) + 1, dtype=bool)
    present[lab] = True
    return (np.cumsum(present) - 1)[lab].astype(np.int64)


def _cloud(rng: np.random.Generator, n: int, spread: float, blobs: int) -> np.ndarray:
    """n poses: a few Gaussian blobs of random widths inside a box of side ``spread``."""
    centres = rng.uniform(-spread / 2, spread / 2, size=(blobs, 2)) + rng.uniform(-50, 50, 2)
    widths = rng.uniform(0.05, 2.0, size=blobs)
    k = rng.integers(0, blobs, size=n)
    xy = centres[k] + rng.normal(size=(n, 2)) * widths[k, None]
    th = rng.uniform(-np.pi, np.pi, size=blobs)[k] + rng.normal(size=n) * rng.uniform(0.05, 2.0)
    return np.column_stack([xy, wrap_angle(th)])


@pytest.mark.parametrize("seed", range(40))
def test_same_partition_and_numbering_as_the_dense_grid(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 1500))
    poses = _cloud(rng, n, spread=float(rng.choice([1.0, 5.0, 20.0, 60.0])), blobs=int(rng.integers(1, 8)))
    cell_xy = float(rng.choice([CLUSTER_CELL_XY, 0.25, 1.0]))
    cell_theta = float(rng.choice([CLUSTER_CELL_THETA, math.radians(45), math.radians(200), 2 * math.pi]))
    assert np.array_equal(cluster_labels(poses, cell_xy, cell_theta), grid_labels(poses, cell_xy, cell_theta))


def test_uniform_global_belief_same_partition() -> None:
    rng = np.random.default_rng(7)
    poses = np.column_stack([rng.uniform(0, 12, 1000), rng.uniform(0, 8, 1000), rng.uniform(-np.pi, np.pi, 1000)])
    assert np.array_equal(cluster_labels(poses), grid_labels(poses))


def test_the_heading_seam_joins_cells() -> None:
    """Bin n - 1 touches bin 0 (also diagonally in x and y); bins two apart across the seam
    do not."""
    eps = 0.01
    two = np.array([[1.0, 1.0, np.pi - eps], [1.0, 1.0, -np.pi + eps], [5.0, 1.0, 0.0]])
    lab = cluster_labels(two)
    assert lab[0] == lab[1] != lab[2]
    diagonal = np.array([[1.2, 1.2, np.pi - eps], [1.7, 0.7, -np.pi + eps]])  # cells (2,2) and (3,1)
    assert np.unique(cluster_labels(diagonal)).size == 1
    apart = np.array([[1.0, 1.0, np.pi - eps], [1.0, 1.0, -np.pi + CLUSTER_CELL_THETA + eps]])
    assert np.unique(cluster_labels(apart)).size == 2
    rng = np.random.default_rng(3)
    th = wrap_angle(np.pi + rng.normal(0, 0.3, 400))
    ring = np.column_stack([rng.normal(2, 0.3, 400), rng.normal(2, 0.3, 400), th])
    assert np.array_equal(cluster_labels(ring), grid_labels(ring))


def test_a_cloud_ten_kilometres_wide_in_bounded_memory_and_time() -> None:
    """The dense grid of this cloud would hold 20,000 x 20,000 x 12 cells (4.8 GB)."""
    rng = np.random.default_rng(11)
    poses = np.column_stack(
        [rng.uniform(-5000, 5000, 1000), rng.uniform(-5000, 5000, 1000), rng.uniform(-np.pi, np.pi, 1000)]
    )
    poses[:10] = [3000.0, 3000.0, 0.1]  # one occupied cell holding 10 particles
    w = np.full(1000, 1e-3)
    w[:10] = 0.05  # ... and half the weight
    tracemalloc.start()
    t0 = time.perf_counter()
    labels = cluster_labels(poses)
    mean, cov, mass = dominant_mode(poses, w / w.sum())
    elapsed = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 5e6 and elapsed < 2.0
    assert np.unique(labels[:10]).size == 1 and np.sum(labels == labels[0]) == 10
    assert np.allclose(mean, [3000.0, 3000.0, 0.1]) and np.all(np.isfinite(cov))
    assert mass == pytest.approx(0.5 / (0.5 + 0.99), rel=1e-9)


def test_a_set_pose_of_covariance_1e9_gives_a_finite_estimate_in_bounded_memory() -> None:
    """The belief of the request that once crashed the daemon (a pose at (3000, 3000) with
    variances of 1e9: particles spread over some 100 km)."""
    rng = np.random.default_rng(0)
    poses = rng.multivariate_normal([3000.0, 3000.0, 0.0], np.eye(3) * 1e9, size=1000, method="eigh")
    poses[:, 2] = wrap_angle(poses[:, 2])
    tracemalloc.start()
    mean, cov, mass = dominant_mode(poses, np.full(1000, 1e-3))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 5e6
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(cov)) and 0 < mass <= 1


def test_non_finite_particles_belong_to_no_mode() -> None:
    rng = np.random.default_rng(5)
    good = np.column_stack([rng.normal(2, 0.1, 100), rng.normal(3, 0.1, 100), rng.normal(0.5, 0.05, 100)])
    far = np.column_stack([rng.normal(9, 0.1, 50), rng.normal(3, 0.1, 50), rng.normal(0.5, 0.05, 50)])
    bad = np.array([[np.nan, 1.0, 0.0], [np.inf, 0.0, 0.0], [1.0, -np.inf, 0.0], [2.0, 3.0, np.nan]])
    poses = np.vstack([good, bad, far])
    labels = cluster_labels(poses)
    assert np.all(labels[100:104] == -1)
    assert np.array_equal(labels[np.r_[0:100, 104:154]], grid_labels(np.vstack([good, far])))
    w = np.full(154, 1.0 / 154)
    mean, cov, mass = dominant_mode(poses, w)
    ref_mean, ref_cov = weighted_pose_stats(good, np.ones(100))
    assert np.allclose(mean, ref_mean) and np.allclose(cov, ref_cov)
    assert mass == pytest.approx(100 / 154)
    # a compact finite cloud with one non-finite particle: the mode holds the finite weight
    mean, cov, mass = dominant_mode(np.vstack([good, bad[:1]]), np.full(101, 1 / 101))
    assert np.allclose(mean, ref_mean) and mass == pytest.approx(100 / 101)
    # a non-finite weight counts as no particle
    wn = np.full(100, 0.01)
    wn[0] = np.nan
    mean, _, mass = dominant_mode(good, wn)
    assert np.allclose(mean, weighted_pose_stats(good[1:], np.ones(99))[0])
    mean, cov, mass = dominant_mode(bad, np.full(4, 0.25))
    assert mass == 0.0 and np.all(np.isnan(mean)) and np.all(np.isnan(cov))
    assert np.all(cluster_labels(bad) == -1)


def test_a_localizer_whose_particles_span_kilometres_estimates_in_bounded_memory() -> None:
    """The Localizer given the belief of the request that once crashed the daemon (the
    filter's own set_pose, below the service's checks), then dead reckoning and an image: every
    estimate finite, each step well under 50 MB."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_localizer import _config, _world

    from lino_loc.localizer import Localizer

    m, f_img, _ = _world()
    loc = Localizer(m, _config())
    loc.set_pose([3000.0, 3000.0, 0.0], np.eye(3) * 1e9)
    image = f_img(np.array([[2.0, 1.5, 0.0]]))[0]
    for step in (lambda: loc.predict_only((0.1, 0.0, 0.0), stamp=1.0), lambda: loc.update((0.1, 0.0, 0.0), 0.0, image)):
        tracemalloc.start()
        est = step()
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert peak < 50e6
        assert np.all(np.isfinite(est.pose)) and np.all(np.isfinite(est.covariance))

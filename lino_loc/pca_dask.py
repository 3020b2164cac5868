"""The intensity channel of a map built on Dask arrays: loading, preprocessing, PCA, features.

What ``lino-loc map build --engine dask`` runs. The survey's data matrix X (N images x D
working-size pixels, float32) is a Dask array of row blocks, one task per block of
``chunk_rows`` images (:func:`lino_loc.survey_vectors.vectors_of_files`: decode, preprocess,
area-average, with virtual headings each image's turned views), persisted in the workers'
memory. On it:

- the mean, one reduction;
- the PCA: the project's randomized SVD (Halko, Martinsson & Tropp 2011) with the same test
  matrix (drawn here from the same seed), the same oversampling (ell = 2 d + 10 columns) and
  power iterations (q = 5) and the same implicit centring as the local build. Each power
  iteration is one fused pass (:func:`lino_loc.pca.randomized_svd_fused`): every block
  computes ``X_b^T Y_b``, ``Y_b^T Y_b`` and ``1^T Y_b`` for ``Y_b = (X_b - mean) Z`` on the
  worker that holds it, a tree of sums on the workers reduces them, and only the (D, ell)
  and (ell, ell) sums reach the client, which orthonormalises by Cholesky QR in float64.
  q + 1 = 6 passes, one ``compute`` each; no block of X ever moves. Should the sketch be too
  ill-conditioned for Cholesky QR, the 2 q + 2 passes of :func:`lino_loc.pca.randomized_svd`
  with Dask matrix products and Dask's TSQR (Benson, Gleich & Demmel 2013) for the tall
  (N, ell) QR. Not ``dask.array.linalg.svd_compressed``: its own random test matrix and no
  centring would give a different sketch, and the map must equal the local build's
  (principal angles near zero, features equal up to sign);
- the features ``(X - mean) W^T`` and the total variance, one pass.

The computations run on the current Dask scheduler: a ``distributed.Client`` set up by the
caller (``services.dask_cluster``; lino_loc sets up no cluster and opens no connection), or
Dask's local threads without one. Workers must see the dataset's files at the same paths
(one machine, or a shared file system) and have lino-loc installed.

The disparity channel (EM-PCA with missing data, :mod:`lino_loc.pca_missing`) is not built
here: its EM runs tens of iterations (SQUAREM steps with objective checks) whose every
step needs the whole N x D masked data for a global per-pixel M-step, i.e. a cluster round
trip and a reduction of D x (d+1)(d+2)/2 tables per step, and the fit keeps its dense float
data in one process anyway; it runs in the calling process as in the local build.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from lino_loc.dataset import Dataset
from lino_loc.errors import LinoLocError
from lino_loc.pca import (
    DEFAULT_OVERSAMPLES,
    DEFAULT_POWER_ITERATIONS,
    PCA,
    IllConditioned,
    block_products,
    centred_products,
    finished_pca,
    randomized_svd,
    randomized_svd_fused,
)
from lino_loc.preprocessing import Preprocess
from lino_loc.survey_vectors import vectors_of_files
from lino_loc.virtual_views import VirtualHeadings, augment_vectors

log = logging.getLogger(__name__)


def _phase(name: str, seconds: float) -> None:
    """Log how long a phase of the build took (``extra``: ``phase``, ``seconds``)."""
    log.info("dask map build: %s %.2f s", name, seconds, extra={"phase": name, "seconds": seconds})


#: Most bytes of rows per Dask block by default (16 MiB: 873 images of 80 x 60), and the
#: fewest rows per block and the number of blocks aimed at below that size: large enough that
#: the scheduler's per-task overhead is small against the block's work, small enough that the
#: loading spreads over the workers (a 100 000-view survey gives 115 blocks, 20 000 views 32).
DEFAULT_BLOCK_BYTES = 16 * 2**20
MIN_BLOCK_ROWS = 256
TARGET_BLOCKS = 32
CLUSTER_EXTRA_HINT = "pip install lino-loc[cluster]"


def dask_array_module() -> Any:
    """``dask.array``, or a one-line LinoLocError naming the extra to install."""
    try:
        import dask.array as da
    except ImportError:
        raise LinoLocError(f"the dask engine needs Dask: {CLUSTER_EXTRA_HINT}") from None
    return da


def _block(paths: Sequence[str], method: Preprocess, size: tuple[int, int], camera_size: tuple[int, int],
           virtual: VirtualHeadings | None) -> np.ndarray:
    """One task: the vectors (rows image-major with ``virtual``) of the image files ``paths``."""
    X = vectors_of_files(paths, method, size, camera_size)
    if virtual is not None:
        X = augment_vectors(X, size, virtual.K, virtual.offsets, virtual.margin)
    return X


def _block_images(n: int, v: int, dim: int) -> int:
    """Images per block by default: ``TARGET_BLOCKS`` blocks of at least ``MIN_BLOCK_ROWS``
    rows, at most ``DEFAULT_BLOCK_BYTES`` each (rows = images x ``v`` views of ``dim`` floats)."""
    most = max(1, DEFAULT_BLOCK_BYTES // (4 * dim * v))
    return max(1, min(most, max(math.ceil(MIN_BLOCK_ROWS / v), math.ceil(n / TARGET_BLOCKS))))


def survey_array(
    dataset: Dataset,
    preprocess: Preprocess,
    size: tuple[int, int],
    *,
    virtual: VirtualHeadings | None = None,
    chunk_rows: int | None = None,
) -> Any:
    """The dataset's data matrix as a lazy Dask array (N*V, D') of row blocks, one task per
    ``chunk_rows`` images (default :func:`_block_images`), a single block of
    columns (what TSQR needs)."""
    da = dask_array_module()
    import dask

    w, h = int(size[0]), int(size[1])
    cam = dataset.meta.camera
    n = len(dataset)
    v = 1 if virtual is None else len(virtual.offsets)
    dim = w * h if virtual is None else (w - 2 * virtual.margin) * h
    step = int(chunk_rows) if chunk_rows else _block_images(n, v, dim)
    if step < 1:
        raise LinoLocError(f"map build: chunk_rows must be >= 1, got {step}")
    paths = [str(dataset.image_path(i)) for i in range(n)]
    load = dask.delayed(_block, pure=True)
    blocks = [
        da.from_delayed(load(paths[lo : lo + step], preprocess, (w, h), (cam.width, cam.height), virtual),
                        shape=(v * len(paths[lo : lo + step]), dim), dtype=np.float32)
        for lo in range(0, n, step)
    ]
    return da.concatenate(blocks, axis=0)


def fit_pca_dask(X: Any, n_components: int, seed: int = 0, *, n_iter: int = DEFAULT_POWER_ITERATIONS) -> PCA:
    """:func:`lino_loc.pca.fit_pca` ``method="randomized"`` of the rows of a Dask array X
    (N, D) float32 with one block of columns (persist it first: every pass reads it)."""
    da = dask_array_module()
    import dask

    t0 = time.perf_counter()
    n, D = (int(v) for v in X.shape)
    d = int(n_components)
    if d < 1 or n < 2 or d > min(n - 1, D):
        raise LinoLocError(f"fit_pca: {d} components asked but {n} images of {D} pixels allow at most "
                           f"{max(min(n - 1, D), 0)}")
    mean, finite = dask.compute(X.mean(axis=0, dtype=np.float64), da.isfinite(X).all())
    if not finite:
        raise LinoLocError("fit_pca: data contain NaN or infinite values (use pca_missing for sparse data)")
    m = np.asarray(mean).astype(np.float32)
    ell = min(2 * d + DEFAULT_OVERSAMPLES, n, D)
    t1 = time.perf_counter()
    _phase("mean", t1 - t0)  # the first pass: with a freshly persisted X, the loading too

    blocks = list(X.to_delayed().ravel())

    def fused_pass(Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z, mm = dask.delayed(Z, pure=True), dask.delayed(m, pure=True)  # one graph key each, sent once
        parts = [dask.delayed(block_products, pure=True)(b, mm, z) for b in blocks]
        while len(parts) > 1:  # pairwise tree sum on the workers: only (D, ell) arrays move
            parts = [dask.delayed(_sum3, pure=True)(*parts[i : i + 2]) if i + 1 < len(parts) else parts[i]
                     for i in range(0, len(parts), 2)]
        (sums,) = dask.compute(parts[0])
        return centred_products(sums, m)

    try:
        V, s = randomized_svd_fused(fused_pass, D, d, ell, n_iter, seed, np.float32)
        _phase("svd", time.perf_counter() - t1)
        return finished_pca(V, s, mean, n)
    except IllConditioned:
        log.info("dask map build: range sketch ill-conditioned for Cholesky QR, using TSQR passes")

    def a_mul(M: np.ndarray) -> Any:  # Xc @ M, lazy (N, ell)
        return X @ M - (m @ M)

    def tall_q(Y: Any) -> Any:
        return da.linalg.tsqr(Y)[0]

    def at_mul(Q: Any) -> np.ndarray:  # Xc^T @ Q, computed (D, ell)
        prod, colsum = dask.compute(X.T @ Q, Q.sum(axis=0))
        return np.asarray(prod, dtype=np.float32) - np.outer(m, colsum).astype(np.float32)

    V, s = randomized_svd(a_mul, at_mul, D, d, ell, n_iter, seed, np.float32, qr_tall=tall_q)
    _phase("svd", time.perf_counter() - t1)
    return finished_pca(V, s, mean, n)


def _sum3(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    return tuple(x + y for x, y in zip(a, b, strict=True))


def project_dask(pca: PCA, X: Any) -> tuple[np.ndarray, float]:
    """Features (N, d) of every row of the Dask array X (eq. 1) and the total variance
    sum_j var(x_j), in one pass (as :func:`lino_loc.appearance_map.project_rows`)."""
    import dask

    t0 = time.perf_counter()
    mean, W = dask.delayed(pca.mean, pure=True), dask.delayed(pca.components, pure=True)
    parts = dask.compute(*[dask.delayed(_project_block, pure=True)(b, mean, W) for b in X.to_delayed().ravel()])
    Y = np.concatenate([y for y, _ in parts]) if parts else np.empty((0, pca.n_components), np.float32)
    _phase("features", time.perf_counter() - t0)
    return Y, sum(ss for _, ss in parts) / int(X.shape[0])


def _project_block(rows: np.ndarray, mean: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, float]:
    """One block's features ``(rows - mean) W^T`` and sum of squared centred values."""
    Xc = rows - mean
    return (Xc @ W.T).astype(np.float32, copy=False), float(np.einsum("ij,ij->", Xc, Xc, dtype=np.float64))


def intensity_pca_dask(
    dataset: Dataset,
    n_features: int,
    preprocess: Preprocess,
    size: tuple[int, int],
    *,
    seed: int = 0,
    virtual: VirtualHeadings | None = None,
    chunk_rows: int | None = None,
) -> tuple[PCA, np.ndarray, float]:
    """The intensity channel's PCA, features (N*V, d) and total variance, as Dask tasks on the
    current scheduler: what :func:`lino_loc.appearance_map.build_intensity_channel` computes
    with ``method="randomized"``, up to float32 rounding."""
    X = survey_array(dataset, preprocess, size, virtual=virtual, chunk_rows=chunk_rows).persist()
    pca = fit_pca_dask(X, n_features, seed=seed)
    Y, total = project_dask(pca, X)
    return pca, Y, total

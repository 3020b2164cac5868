"""Principal component analysis for appearance maps: the projection ``W`` of eq. 1.

Given N image vectors ``z_i`` (rows of X, D pixels each) the map keeps the mean image and
the d leading principal directions ``W`` (rows orthonormal, d x D); a view is compressed to
``y = W (z - mean)`` (eq. 1, with the mean subtracted as usual for PCA).

Three ways to compute ``W`` from the centred data ``Xc = X - mean``:

``randomized`` (the default)
    Randomized SVD (Halko, Martinsson & Tropp 2011, Alg. 4.4 + 5.1): sketch the range of
    Xc with a Gaussian test matrix of d + p columns (p = d + 10 oversampling, so 2 d + 10
    columns), refine it with q = 5 power iterations ``(Xc Xc^T)^q Xc Omega``,
    re-orthonormalising with QR after every product, then take the exact SVD of the small
    (d+p) x D matrix ``Q^T Xc``. Cost O(N D (d+p) (2q+2)) flops and O((N + D)(d+p)) extra
    memory; the centring is implicit (``Xc M = X M - 1 (mean M)``), so no centred copy of
    X is made.
``gram``
    Leading eigenpairs (LAPACK ``?syevx``) of the smaller Gram matrix: ``Xc Xc^T`` (N x N)
    when N <= D, else the covariance ``Xc^T Xc`` (D x D); for the former
    ``W = (U^T Xc) / s``. O(N^2 D + N^3) flops and an N x N float64 matrix; exact up to
    the squared condition number (irrelevant for the leading components).
``svd``
    numpy's full thin SVD of Xc: the reference, O(N D min(N, D)).

Why randomized is the default: on a survey-sized problem (N and D in the thousands) it
needs a small fraction of the Gram route's time and memory and keeps the leading subspace
to well within what the sensor model notices (feature distances, captured variance); the
Gram route is exact, but its O(N^3) eigen-solve alone would take most of a map build's time
budget (figures in docs/results.md, 'Map build'). Appearance spectra decay slowly, which is
why the oversampling and the power iterations are larger than the textbook p = 10, q = 2,
which distort the flattest spectrum's (``gradient``) feature distances noticeably.

``explained_variance[k]`` is the variance of the k-th feature over the map images,
``s_k^2 / N``. Signs are made deterministic: the largest-magnitude coefficient of each
component is positive, so every method returns the same W for a well-separated spectrum.

Usage::

    from lino_loc.pca import fit_pca
    pca = fit_pca(X, 20)            # X: (N, D) float32
    Y = pca.project(X)              # (N, 20) features, eq. 1
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal, Protocol, get_args

import numpy as np
import scipy.linalg

from lino_loc.errors import LinoLocError

PcaMethod = Literal["randomized", "gram", "svd"]
PCA_METHODS: tuple[str, ...] = get_args(PcaMethod)
# Randomized SVD: oversampling (plus n_components: the sketch has 2 d + 10 columns) and power
# iterations, both above the textbook values because appearance spectra decay slowly
# (measured, docs/results.md 'Map build').
DEFAULT_OVERSAMPLES = 10
DEFAULT_POWER_ITERATIONS = 5


@dataclass
class PCA:
    """A fitted projection: ``mean`` (D,), ``components`` (d, D) with orthonormal rows, and
    ``explained_variance`` (d,), all float32."""

    mean: np.ndarray
    components: np.ndarray
    explained_variance: np.ndarray

    @property
    def n_components(self) -> int:
        return int(self.components.shape[0])

    @property
    def dim(self) -> int:
        return int(self.components.shape[1])

    def project(self, X: np.ndarray) -> np.ndarray:
        """eq. 1: ``y = W (z - mean)`` for one vector (D,) -> (d,) or rows (N, D) -> (N, d)."""
        Z = np.asarray(X, dtype=np.float32)
        if Z.shape[-1] != self.mean.shape[0]:
            raise LinoLocError(f"PCA.project: vector length {Z.shape[-1]}, map expects {self.mean.shape[0]}")
        return ((Z - self.mean) @ self.components.T).astype(np.float32, copy=False)

    def reconstruct(self, Y: np.ndarray) -> np.ndarray:
        """Back-projection ``mean + W^T y`` (for diagnostics)."""
        return (np.asarray(Y, dtype=np.float32) @ self.components + self.mean).astype(np.float32)


def _sign_fix(V: np.ndarray) -> np.ndarray:
    """Flip each row so that its largest-magnitude entry is positive."""
    idx = np.argmax(np.abs(V), axis=1)
    signs = np.sign(V[np.arange(V.shape[0]), idx])
    signs[signs == 0] = 1
    return V * signs[:, None]


def randomized_svd(
    a_mul: Callable[[np.ndarray], Any],
    at_mul: Callable[[Any], np.ndarray],
    dim: int,
    d: int,
    ell: int,
    n_iter: int,
    seed: int,
    dtype: np.dtype | type = np.float32,
    qr_tall: Callable[[Any], Any] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Top-d right singular vectors and values of a centred data matrix Xc (N, D) given only
    its products (Halko, Martinsson & Tropp 2011, Alg. 4.4 + 5.1, the module docstring's
    ``randomized``): ``a_mul(M) = Xc @ M`` for M (D, ell) and ``at_mul(Q) = Xc^T @ Q``
    (a numpy (D, ell) array) for what ``qr_tall`` returns.

    The test matrix is ``default_rng(seed).standard_normal((dim, ell))`` in ``dtype``, so
    every way of computing the products (in memory, streamed from disk in row chunks,
    :func:`fit_pca_streamed`; on Dask arrays, :mod:`lino_loc.pca_dask`) starts from the same
    sketch and gives the same subspace up to rounding. ``qr_tall(Y)`` returns the Q factor
    of the tall (N, ell) products (default numpy's QR; a Dask caller passes tsqr). Every
    ``a_mul`` / ``at_mul`` is one pass over the data: ``2 n_iter + 2`` passes in all.
    """
    rng = np.random.default_rng(seed)
    qr = qr_tall if qr_tall is not None else (lambda Y: np.linalg.qr(Y)[0])
    omega = rng.standard_normal((dim, ell)).astype(dtype)
    Q = qr(a_mul(omega))
    for _ in range(n_iter):
        Z, _ = np.linalg.qr(at_mul(Q))
        Q = qr(a_mul(Z))
    B = at_mul(Q).T  # (ell, D) = Q^T Xc
    _, s, Vt = np.linalg.svd(B.astype(np.float64), full_matrices=False)
    return Vt[:d], s[:d]


class IllConditioned(ArithmeticError):
    """A fused pass's Gram matrix was too ill-conditioned for Cholesky QR (the caller falls back
    to :func:`randomized_svd`'s separate passes)."""


#: Largest condition number of the range sketch ``Y`` for which :func:`randomized_svd_fused`
#: orthonormalises it by Cholesky QR: in float64 the basis then loses at most about
#: ``cond(Y)^2 * 1e-16 = 1e-6`` of orthogonality, float32's own rounding.
MAX_CHOLESKY_COND = 1.0e5


def block_products(rows: np.ndarray, mean32: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One block of rows' share of a fused pass: with ``Y_b = (rows - mean) @ Z`` (the mean
    subtracted implicitly, as ``rows @ Z - mean @ Z``), the sums ``rows^T Y_b`` (D, k),
    ``Y_b^T Y_b`` and ``1^T Y_b`` (float32 products, float64 results) that
    :func:`centred_products` turns into ``(Xc^T Y, Y^T Y)`` once summed over the blocks."""
    Yb = rows @ Z
    Yb -= mean32 @ Z
    return (rows.T @ Yb).astype(np.float64), Yb.T.astype(np.float64) @ Yb.astype(np.float64), Yb.sum(axis=0, dtype=np.float64)


def centred_products(sums: tuple[np.ndarray, np.ndarray, np.ndarray], mean32: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Xc^T Y, Y^T Y)`` from the summed :func:`block_products` (``Y = Xc Z`` is centred by
    construction; ``Xc^T Y = X^T Y - mean 1^T Y``)."""
    XtY, G, colsum = sums
    return XtY - np.outer(mean32.astype(np.float64), colsum), G


def randomized_svd_fused(
    fused_pass: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    dim: int,
    d: int,
    ell: int,
    n_iter: int,
    seed: int,
    dtype: np.dtype | type = np.float32,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`randomized_svd` with one pass over the data per power iteration instead of two.

    ``fused_pass(Z)`` returns ``(Xc^T Y, Y^T Y)`` for ``Y = Xc Z`` (float64), which every block
    of rows gives on its own (:func:`block_products`): Y is orthonormalised by Cholesky QR,
    ``Q = Y R^-1`` with ``R^T R = Y^T Y`` (the Q of Householder QR up to column signs), so
    ``Xc^T Q = (Xc^T Y) R^-1`` needs no second pass. ``n_iter + 1`` passes; the same test
    matrix and the same subspace as :func:`randomized_svd` up to rounding. Raises
    :class:`IllConditioned` when ``cond(Y)`` exceeds :data:`MAX_CHOLESKY_COND` (or Y is rank
    deficient): then the caller uses :func:`randomized_svd`.
    """
    rng = np.random.default_rng(seed)
    Z = rng.standard_normal((dim, ell)).astype(dtype)
    P = np.empty((dim, ell))
    for it in range(n_iter + 1):
        XtY, G = fused_pass(Z)
        try:
            R = np.linalg.cholesky(G).T  # upper, positive diagonal
        except np.linalg.LinAlgError:
            raise IllConditioned("range sketch is rank deficient") from None
        lam = np.linalg.eigvalsh(G)  # cond(Y)^2 = lam_max / lam_min
        if not lam[0] > 0 or lam[-1] / lam[0] > MAX_CHOLESKY_COND**2:
            raise IllConditioned(f"range sketch condition {np.sqrt(lam[-1] / max(lam[0], 1e-300)):.3g}")
        P = scipy.linalg.solve_triangular(R, XtY.T, trans="T", lower=False).T  # Xc^T Q = XtY R^-1
        if it < n_iter:
            Z = np.linalg.qr(P.astype(dtype))[0]
    _, s, Vt = np.linalg.svd(P.T, full_matrices=False)
    return Vt[:d], s[:d]


def _randomized(
    X: np.ndarray, mean: np.ndarray, d: int, oversamples: int, n_iter: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Top-d right singular vectors and values of ``X - mean`` (Halko et al. 2011), X in memory."""
    n, D = X.shape
    ell = min(d + oversamples, n, D)
    dt = X.dtype
    m = mean.astype(dt)

    def a_mul(M: np.ndarray) -> np.ndarray:  # Xc @ M, (n, ell)
        out = X @ M
        out -= m @ M
        return out

    def at_mul(Q: np.ndarray) -> np.ndarray:  # Xc^T @ Q, (D, ell)
        out = X.T @ Q
        out -= np.outer(m, Q.sum(axis=0))
        return out

    return randomized_svd(a_mul, at_mul, D, d, ell, n_iter, seed, dt)


class RowChunks(Protocol):
    """A data matrix (N, D) read in chunks of rows (e.g. :class:`lino_loc.row_file.RowFile`)."""

    @property
    def shape(self) -> tuple[int, int]: ...

    def chunks(self) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(first_row, rows)`` for consecutive chunks covering all N rows in order."""
        ...


def fit_pca_streamed(
    data: RowChunks,
    n_components: int,
    seed: int = 0,
    *,
    oversamples: int | None = None,
    n_iter: int = DEFAULT_POWER_ITERATIONS,
) -> PCA:
    """:func:`fit_pca` ``method="randomized"`` on a float32 data matrix read in chunks of
    rows, never all in memory: one pass for the mean, then the ``n_iter + 1`` fused passes of
    :func:`randomized_svd_fused` (each chunk's products on their own, summed), or, should the
    sketch be too ill-conditioned for Cholesky QR, the ``2 n_iter + 2`` passes of
    :func:`randomized_svd` with the (N, ell) basis in memory. Peak memory: one chunk and a few
    (D, ell) products, ell = 2 d + 10. The same test matrix, oversampling, power iterations and
    implicit centring as in memory: the same W up to rounding."""
    n, D = data.shape
    d = _checked_counts(n, D, n_components)
    total = np.zeros(D, dtype=np.float64)
    for _, rows in data.chunks():
        if not np.all(np.isfinite(rows)):
            raise LinoLocError("fit_pca: data contain NaN or infinite values (use pca_missing for sparse data)")
        total += rows.sum(axis=0, dtype=np.float64)
    mean = total / n
    m = mean.astype(np.float32)
    ell = min(d + (d + DEFAULT_OVERSAMPLES if oversamples is None else int(oversamples)), n, D)

    def fused_pass(Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sums = None
        for _, rows in data.chunks():
            part = block_products(rows, m, Z)
            sums = part if sums is None else tuple(a + b for a, b in zip(sums, part, strict=True))
        return centred_products(sums, m)  # type: ignore[arg-type]

    try:
        V, s = randomized_svd_fused(fused_pass, D, d, ell, n_iter, seed, np.float32)
        return finished_pca(V, s, mean, n)
    except IllConditioned:
        pass

    def a_mul(M: np.ndarray) -> np.ndarray:
        out = np.empty((n, M.shape[1]), dtype=np.float32)
        for lo, rows in data.chunks():
            out[lo : lo + len(rows)] = rows @ M
        out -= m @ M
        return out

    def at_mul(Q: np.ndarray) -> np.ndarray:
        out = np.zeros((D, Q.shape[1]), dtype=np.float32)
        for lo, rows in data.chunks():
            out += rows.T @ Q[lo : lo + len(rows)]
        out -= np.outer(m, Q.sum(axis=0))
        return out

    V, s = randomized_svd(a_mul, at_mul, D, d, ell, n_iter, seed, np.float32)
    return finished_pca(V, s, mean, n)


def finished_pca(V: np.ndarray, s: np.ndarray, mean: np.ndarray, n: int) -> PCA:
    """The :class:`PCA` of right singular vectors V (d, D) and values s of the centred data of
    n rows with ``mean``: signs fixed (:func:`_sign_fix`), explained variance ``s^2 / n``."""
    V = _sign_fix(np.asarray(V, dtype=np.float64))
    return PCA(
        mean=np.asarray(mean).astype(np.float32),
        components=np.ascontiguousarray(V, dtype=np.float32),
        explained_variance=(np.asarray(s, dtype=np.float64) ** 2 / n).astype(np.float32),
    )


def _checked_counts(n: int, D: int, n_components: int) -> int:
    """d = n_components; LinoLocError unless 1 <= d <= min(n - 1, D) and n >= 2."""
    d = int(n_components)
    if d < 1:
        raise LinoLocError(f"fit_pca: n_components must be >= 1, got {d}")
    if n < 2 or d > min(n - 1, D):
        raise LinoLocError(
            f"fit_pca: {d} components asked but {n} images of {D} pixels allow at most {max(min(n - 1, D), 0)}"
        )
    return d


def _top_eigh(G: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """The d largest eigenpairs of a symmetric matrix (LAPACK ?syevx on that index range)."""
    n = G.shape[0]
    return scipy.linalg.eigh(G, subset_by_index=[n - d, n - 1], driver="evx", overwrite_a=True)


def _gram(X: np.ndarray, mean: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Top-d right singular vectors and values of ``X - mean`` from the smaller Gram matrix."""
    n, D = X.shape
    Xc = X - mean.astype(X.dtype)
    if n <= D:
        G = (Xc @ Xc.T).astype(np.float64)
        evals, U = _top_eigh(G, d)
        order = np.argsort(evals)[::-1]
        lam = np.clip(evals[order], 0.0, None)
        s = np.sqrt(lam)
        V = (U[:, order].T.astype(Xc.dtype) @ Xc).astype(np.float64)
        # normalise rows (= divide by s, but robust for tiny s)
        V /= np.maximum(np.linalg.norm(V, axis=1, keepdims=True), 1e-300)
        return V, s
    C = (Xc.T @ Xc).astype(np.float64)
    evals, V = _top_eigh(C, d)
    order = np.argsort(evals)[::-1]
    return V[:, order].T, np.sqrt(np.clip(evals[order], 0.0, None))


def fit_pca(
    X: np.ndarray,
    n_components: int,
    method: PcaMethod = "randomized",
    seed: int = 0,
    *,
    oversamples: int | None = None,
    n_iter: int = DEFAULT_POWER_ITERATIONS,
) -> PCA:
    """Fit the d = ``n_components`` leading principal directions of the rows of X (N, D).

    X is used in its own precision when float64, else converted to float32. Needs
    N >= 2 and d <= min(N - 1, D) (centred data have rank at most N - 1).
    ``oversamples`` (default d + 10) and ``n_iter`` (default 5) tune the randomized method.
    """
    X = np.asarray(X)
    if X.ndim != 2:
        raise LinoLocError(f"fit_pca: expected a 2-D (N, D) matrix, got shape {X.shape}")
    if X.dtype != np.float64:
        X = X.astype(np.float32, copy=False)
    n, D = X.shape
    d = _checked_counts(n, D, n_components)
    if not np.all(np.isfinite(X)):
        raise LinoLocError("fit_pca: data contain NaN or infinite values (use pca_missing for sparse data)")
    mean = X.mean(axis=0, dtype=np.float64)
    if method == "randomized":
        p = d + DEFAULT_OVERSAMPLES if oversamples is None else int(oversamples)
        V, s = _randomized(X, mean, d, p, n_iter, seed)
    elif method == "gram":
        V, s = _gram(X, mean, d)
    elif method == "svd":
        Xc = X - mean.astype(X.dtype)
        _, s_all, Vt = np.linalg.svd(Xc, full_matrices=False)
        V, s = Vt[:d], s_all[:d]
    else:
        raise LinoLocError(f"fit_pca: unknown method {method!r} (choose from {', '.join(PCA_METHODS)})")
    return finished_pca(V, s, mean, n)


def principal_angles(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Principal angles (radians, ascending) between the row spaces of A (k, D) and B (l, D)."""
    qa, _ = np.linalg.qr(np.asarray(A, dtype=np.float64).T)
    qb, _ = np.linalg.qr(np.asarray(B, dtype=np.float64).T)
    cos = np.linalg.svd(qa.T @ qb, compute_uv=False)
    return np.arccos(np.clip(cos, -1.0, 1.0))

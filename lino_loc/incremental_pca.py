"""Incremental PCA: update a fitted basis with new rows without the old data.

The sequential Karhunen-Loeve update with a moving mean of Ross, Lim, Lin & Yang, "Incremental
learning for robust visual tracking" (IJCV 2008, Alg. 1; Brand's 2002 incremental SVD with the
mean handled by one extra column). The old data are summarised by their mean ``mu_A``, their
count ``n_A``, the d leading right singular vectors ``V`` (rows of ``components``) and singular
values ``s_A = sqrt(n_A * explained_variance)`` of the centred old data. With m new rows ``B``
(mean ``mu_B``)::

    n   = n_A + m,   mu = (n_A mu_A + m mu_B) / n
    B^  = [B - mu_B ; sqrt(n_A m / n) (mu_B - mu_A)]       (m + 1 rows)
    P   = B^ V^T                                            (coefficients in the old basis)
    R   = B^ - P V,  Q = orth(R)  (rows)                    (what the old basis misses)
    K   = [[diag(s_A), 0], [P, R Q^T]]                      ((d + m + 1) x (d + r))
    K   = U' S' V'^T,   new components = first d rows of V'^T [V ; Q],  s = diag(S')[:d]

This is exact when the old centred data lie in the span of ``V`` (rank <= d): the result is
then the batch SVD of old and new rows together. Otherwise the tail the old basis discarded
is lost, and the update is the batch result of "old data reconstructed from the map + new
data"; ``tests/test_incremental_pca.py`` measures how close that is to the batch SVD
(principal angles, reconstruction error). Cost O((m + d) D (d + m)) flops; memory O(m D).

:func:`residual_fraction` is the measure used to decide whether new rows need the update:
the share of their centred energy that the basis does not represent.
"""

from __future__ import annotations

import numpy as np

from lino_loc.errors import LinoLocError
from lino_loc.pca import PCA, _sign_fix


def residual_fraction(pca: PCA, X: np.ndarray, mean: np.ndarray | None = None) -> np.ndarray:
    """Per row of X (N, D): ``|xc - W^T W xc|^2 / |xc|^2`` with ``xc = x - mean`` (the PCA's
    mean by default): the fraction of the row's centred energy outside the basis, in [0, 1]
    (0 for a row equal to the mean)."""
    Z = np.asarray(X, dtype=np.float64)
    mu = np.asarray(pca.mean if mean is None else mean, dtype=np.float64)
    W = np.asarray(pca.components, dtype=np.float64)
    Xc = Z - mu
    total = np.einsum("ij,ij->i", Xc, Xc)
    Y = Xc @ W.T
    kept = np.einsum("ij,ij->i", Y, Y)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(total > 0, (total - kept) / total, 0.0)
    return np.clip(frac, 0.0, 1.0)


def _update(
    mu_a: np.ndarray, V: np.ndarray, s_a: np.ndarray, n_old: int, B: np.ndarray, d: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One step of the update (float64): (mean, components (d, D), singular values (d,))."""
    d_old = V.shape[0]
    m = B.shape[0]
    n = n_old + m
    mu_b = B.mean(axis=0)
    mu = (n_old * mu_a + m * mu_b) / n
    Bh = np.vstack([B - mu_b, np.sqrt(n_old * m / n) * (mu_b - mu_a)])
    P = Bh @ V.T
    R = Bh - P @ V
    q, r = np.linalg.qr(R.T)  # q: (D, m+1) orthonormal columns spanning the residual rows
    # drop directions with no residual energy (rows already in the span of V)
    keep = np.abs(np.diag(r)) > 1e-10 * max(1.0, float(np.abs(r).max(initial=0.0)))
    Q = q[:, keep].T  # (k, D)
    K = np.zeros((d_old + m + 1, d_old + Q.shape[0]))
    K[:d_old, :d_old] = np.diag(s_a)
    K[d_old:, :d_old] = P
    K[d_old:, d_old:] = R @ Q.T
    _, s, Vt = np.linalg.svd(K, full_matrices=False)
    d = min(d, len(s))
    comps = Vt[:d] @ np.vstack([V, Q])
    # re-orthonormalise against rounding (the rows are orthonormal up to ~1e-15 per step)
    qq, rr = np.linalg.qr(comps.T)
    comps = (qq * np.where(np.diag(rr) < 0, -1.0, 1.0)).T
    return mu, comps, s[:d]


def update_pca(
    pca: PCA, n_old: int, X: np.ndarray, n_components: int | None = None, block: int | None = None
) -> PCA:
    """The PCA of the ``n_old`` rows ``pca`` was fitted on plus the rows of ``X`` (m, D),
    by the incremental update above. ``n_components`` (default the current d) may be larger
    than d, up to d + m. ``block``: add the rows in blocks of this many (None: all at once).
    One step costs O(D (d + b)^2 + (d + b)^3) for b rows, so blocks of a few d are much
    cheaper than one step of m >> d rows; each block truncates to d components again
    (the sequential KL update), which all at once does only once. Raises LinoLocError for
    a shape mismatch, ``n_old`` < 1, no new rows, ``block`` < 1 or non-finite data."""
    B = np.asarray(X, dtype=np.float64)
    if B.ndim != 2 or B.shape[1] != pca.dim:
        raise LinoLocError(f"update_pca: new rows of shape {B.shape}, the basis has {pca.dim} pixels")
    m = B.shape[0]
    if m < 1:
        raise LinoLocError("update_pca: no new rows")
    if n_old < 1:
        raise LinoLocError(f"update_pca: n_old must be >= 1, got {n_old}")
    if block is not None and block < 1:
        raise LinoLocError(f"update_pca: block must be >= 1, got {block}")
    if not np.all(np.isfinite(B)):
        raise LinoLocError("update_pca: new rows contain NaN or infinite values")
    d_old = pca.n_components
    d = d_old if n_components is None else int(n_components)
    if not 1 <= d <= d_old + m:
        raise LinoLocError(f"update_pca: {d} components asked, at most {d_old + m} possible")
    V = np.asarray(pca.components, dtype=np.float64)
    mu = np.asarray(pca.mean, dtype=np.float64)
    s = np.sqrt(np.maximum(np.asarray(pca.explained_variance, dtype=np.float64), 0.0) * n_old)
    n = n_old
    step = m if block is None else int(block)
    for lo in range(0, m, step):
        chunk = B[lo : lo + step]
        mu, V, s = _update(mu, V, s, n, chunk, d)
        n += chunk.shape[0]
    comps = _sign_fix(V)
    return PCA(
        mean=mu.astype(np.float32),
        components=np.ascontiguousarray(comps, dtype=np.float32),
        explained_variance=(s**2 / n).astype(np.float32),
    )

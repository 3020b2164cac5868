"""Incremental PCA (Ross et al. 2008) against the batch SVD of old and new rows together."""

from __future__ import annotations

import numpy as np
import pytest

from lino_loc.errors import LinoLocError
from lino_loc.incremental_pca import residual_fraction, update_pca
from lino_loc.pca import PCA, fit_pca, principal_angles


def _data(n: int, basis: np.ndarray, scale: float, offset: float, noise: float, rng: np.random.Generator):
    k = basis.shape[0]
    return offset + (rng.standard_normal((n, k)) * scale) @ basis + noise * rng.standard_normal((n, basis.shape[1]))


def _recon_error(pca: PCA, X: np.ndarray) -> float:
    """Mean squared reconstruction error of the rows of X with the PCA's mean and basis."""
    Xc = X - pca.mean.astype(np.float64)
    W = pca.components.astype(np.float64)
    return float(np.mean(np.sum((Xc - Xc @ W.T @ W) ** 2, axis=1)))


def test_exact_when_old_data_are_low_rank() -> None:
    """Old data of rank <= d: the update is the batch SVD (to float32 precision)."""
    rng = np.random.default_rng(3)
    L = np.linalg.qr(rng.standard_normal((200, 4)))[0].T * 10  # 4 directions in 200 pixels
    A = _data(150, L, 1.0, 2.0, 0.0, rng)
    B = _data(60, L, 2.0, 2.0, 0.0, rng)
    old = fit_pca(A, 4, method="svd")
    upd = update_pca(old, len(A), B)
    ref = fit_pca(np.vstack([A, B]), 4, method="svd")
    assert np.degrees(principal_angles(upd.components, ref.components)).max() < 1e-3
    np.testing.assert_allclose(upd.mean, ref.mean, atol=1e-5)
    np.testing.assert_allclose(upd.explained_variance, ref.explained_variance, rtol=1e-4)
    np.testing.assert_allclose(upd.components @ upd.components.T, np.eye(4), atol=1e-5)


@pytest.mark.parametrize("block", [None, 20])
def test_new_directions_are_learned_close_to_batch(block: int | None) -> None:
    """New rows in directions the old basis lacks (a new light): the update finds them. Its
    subspace is within a few degrees of the batch SVD's on the leading directions, and its
    reconstruction error of all rows within 5 % of the batch's (the old tail is lost)."""
    rng = np.random.default_rng(4)
    D = 300
    L = np.linalg.qr(rng.standard_normal((D, 12)))[0].T
    old_dirs = L[:8] * np.array([8, 7, 6, 5, 4, 3, 2, 1.5])[:, None]
    new_dirs = L[6:12] * np.array([6, 5, 4, 4, 3, 3])[:, None]
    A = _data(400, old_dirs, 1.0, 5.0, 0.05, rng)
    B = _data(200, new_dirs, 1.0, 5.5, 0.05, rng)
    d = 10
    old = fit_pca(A, d, method="svd")
    assert residual_fraction(old, B).mean() > 0.3  # the old basis misses the new light
    upd = update_pca(old, len(A), B, block=block)
    ref = fit_pca(np.vstack([A, B]), d, method="svd")
    ang = np.degrees(principal_angles(upd.components, ref.components))
    assert ang[:8].max() < 2.0
    X = np.vstack([A, B])
    assert _recon_error(upd, X) <= 1.05 * _recon_error(ref, X)
    assert _recon_error(upd, X) < 0.5 * _recon_error(old, X)
    assert residual_fraction(upd, B).mean() < 0.7 * residual_fraction(old, B).mean()
    assert residual_fraction(upd, B).mean() <= 1.1 * residual_fraction(ref, B).mean()


def test_residual_fraction_bounds() -> None:
    rng = np.random.default_rng(5)
    X = rng.standard_normal((50, 30))
    pca = fit_pca(X, 5, method="svd")
    r = residual_fraction(pca, X)
    assert r.shape == (50,) and np.all((r >= 0) & (r <= 1))
    few = X[:10]  # 10 rows: their centred span has 9 dimensions
    full = fit_pca(few, 9, method="svd")
    assert residual_fraction(full, few).max() < 1e-4
    assert residual_fraction(pca, pca.mean[None, :])[0] == 0.0


def test_bad_input() -> None:
    rng = np.random.default_rng(6)
    pca = fit_pca(rng.standard_normal((20, 10)), 3, method="svd")
    with pytest.raises(LinoLocError, match="pixels"):
        update_pca(pca, 20, np.zeros((3, 11)))
    with pytest.raises(LinoLocError, match="no new rows"):
        update_pca(pca, 20, np.zeros((0, 10)))
    with pytest.raises(LinoLocError, match="NaN"):
        update_pca(pca, 20, np.full((2, 10), np.nan))
    with pytest.raises(LinoLocError, match="n_old"):
        update_pca(pca, 0, np.zeros((2, 10)))


@pytest.mark.parametrize("block", [1, 7, 40])
def test_blocks_match_one_step_on_low_rank_data(block: int) -> None:
    """Blocks of any size give the batch result when everything has rank <= d."""
    rng = np.random.default_rng(7)
    L = np.linalg.qr(rng.standard_normal((120, 3)))[0].T * 5
    A = _data(50, L, 1.0, 1.0, 0.0, rng)
    B = _data(45, L, 1.5, 1.0, 0.0, rng)
    ref = fit_pca(np.vstack([A, B]), 3, method="svd")
    upd = update_pca(fit_pca(A, 3, method="svd"), len(A), B, block=block)
    assert np.degrees(principal_angles(upd.components, ref.components)).max() < 1e-2
    np.testing.assert_allclose(upd.explained_variance, ref.explained_variance, rtol=1e-3)
    np.testing.assert_allclose(upd.mean, ref.mean, atol=1e-5)

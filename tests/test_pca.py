"""PCA (eq. 1) against numpy's SVD; randomized vs exact on low-rank data."""

from __future__ import annotations

import numpy as np
import pytest

from lino_loc.errors import LinoLocError
from lino_loc.pca import PCA_METHODS, fit_pca, principal_angles


def _reference(X: np.ndarray, d: int):
    Xc = X - X.mean(0)
    _, s, vt = np.linalg.svd(Xc, full_matrices=False)
    return vt[:d], s[:d] ** 2 / X.shape[0]


def _low_rank(
    n: int, D: int, rank: int, noise: float, seed: int, dtype=np.float32, decay: float = 0.5
) -> np.ndarray:
    rng = np.random.default_rng(seed)
    scales = decay ** np.arange(rank)  # well separated spectrum
    U = rng.standard_normal((n, rank)) * scales
    V = np.linalg.qr(rng.standard_normal((D, rank)))[0].T
    X = 5.0 + U @ V * 10 + noise * rng.standard_normal((n, D))
    return X.astype(dtype)


@pytest.mark.parametrize("method", PCA_METHODS)
@pytest.mark.parametrize("shape", [(60, 40), (30, 50)])  # covariance and Gram sides
def test_against_numpy_svd_small(method: str, shape) -> None:
    n, D = shape
    X = _low_rank(n, D, rank=8, noise=1e-3, seed=1, dtype=np.float64)
    d = 5
    pca = fit_pca(X, d, method=method, seed=0)
    ref_v, ref_var = _reference(X, d)
    angles = principal_angles(pca.components, ref_v)
    assert angles.max() < 1e-6
    np.testing.assert_allclose(pca.components @ pca.components.T, np.eye(d), atol=1e-5)
    np.testing.assert_allclose(pca.explained_variance, ref_var, rtol=1e-4)
    # projections equal up to the sign of each component
    Y = pca.project(X)
    Yref = (X - X.mean(0)) @ ref_v.T
    signs = np.sign(np.sum(Y * Yref, axis=0))
    assert set(np.abs(signs)) == {1.0}
    np.testing.assert_allclose(Y, Yref * signs, atol=1e-4 * np.abs(Yref).max())


def test_randomized_matches_exact_on_low_rank_float32() -> None:
    # every kept component well above the noise (smallest kept std 10 * 0.75**9 = 0.75,
    # noise 0.01 per pixel) and separated from the next by a factor 0.75
    X = _low_rank(200, 300, rank=12, noise=0.01, seed=2, decay=0.75)
    exact = fit_pca(X, 10, method="svd")
    rand = fit_pca(X, 10, method="randomized", seed=5)
    gram = fit_pca(X, 10, method="gram")
    # (without power iterations and oversampling the largest angle here is about 0.5 rad)
    assert principal_angles(rand.components, exact.components).max() < 1e-4
    assert principal_angles(gram.components, exact.components).max() < 1e-4
    np.testing.assert_allclose(rand.explained_variance, exact.explained_variance, rtol=1e-4)
    # the same sign convention makes the components themselves agree
    np.testing.assert_allclose(rand.components, exact.components, atol=1e-4)
    np.testing.assert_allclose(rand.project(X), exact.project(X), atol=1e-3)


def test_eq1_closed_form_and_shapes() -> None:
    X = _low_rank(50, 30, rank=6, noise=1e-2, seed=3)
    pca = fit_pca(X, 4)
    assert pca.mean.dtype == np.float32 and pca.components.dtype == np.float32
    assert pca.components.shape == (4, 30) and pca.explained_variance.shape == (4,)
    np.testing.assert_allclose(pca.project(pca.mean), 0.0, atol=1e-5)
    z = pca.mean + 2.5 * pca.components[2]
    np.testing.assert_allclose(pca.project(z), [0, 0, 2.5, 0], atol=1e-5)
    np.testing.assert_allclose(pca.project(X)[7], pca.project(X[7]), atol=1e-5)
    # largest-magnitude coefficient of each component is positive
    big = pca.components[np.arange(4), np.argmax(np.abs(pca.components), axis=1)]
    assert (big > 0).all()


def test_seeded_randomized_is_deterministic() -> None:
    X = _low_rank(80, 40, rank=5, noise=0.1, seed=4)
    a = fit_pca(X, 3, seed=7)
    b = fit_pca(X, 3, seed=7)
    np.testing.assert_array_equal(a.components, b.components)


def test_errors() -> None:
    X = _low_rank(10, 8, rank=3, noise=0.1, seed=5)
    with pytest.raises(LinoLocError, match="at most 8"):
        fit_pca(X, 9)
    with pytest.raises(LinoLocError, match="unknown method"):
        fit_pca(X, 2, method="qr")  # type: ignore[arg-type]
    Y = X.copy()
    Y[0, 0] = np.nan
    with pytest.raises(LinoLocError, match="NaN"):
        fit_pca(Y, 2)
    with pytest.raises(LinoLocError, match="length"):
        fit_pca(X, 2).project(np.zeros(5))

"""PCA with missing data by EM (paper section 5, ref. [11]): agreement with plain PCA,
recovery of a low-rank subspace from sparse samples, never-valid pixels, sparse projection;
the MAP fit (prior on the covariance): PCA's subspace on complete data, a non-decreasing
objective, convergence and one answer on block-missing data without a spectral gap."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import subspace_angles

from lino_loc.errors import LinoLocError
from lino_loc.pca_missing import MissingDataPCA, fit_pca_missing, plain_pca


def _low_rank(rng: np.random.Generator, n: int, dim: int, d: int, noise: float) -> tuple:
    scales = np.linspace(4.0, 1.5, d)[:, None]
    basis = rng.normal(size=(d, dim)) * scales
    z = rng.normal(size=(n, d))
    offset = rng.normal(size=dim) * 3.0
    x = z @ basis + offset + rng.normal(0.0, noise, (n, dim))
    return x, basis, offset


def _max_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Largest principal angle between the row spaces of a and b, degrees."""
    return float(np.degrees(subspace_angles(a.T, b.T)).max())


def test_complete_data_agrees_with_plain_pca():
    rng = np.random.default_rng(0)
    x, _, _ = _low_rank(rng, 200, 120, 5, noise=0.3)
    model = fit_pca_missing(x, 5, seed=0)
    mu, comps, var = plain_pca(x, 5)
    assert _max_angle_deg(model.components, comps) < 1.0
    assert np.allclose(model.mean, mu, atol=1e-8)
    # each component matches its plain-PCA counterpart (ordered by variance, up to sign)
    cos = np.abs(np.sum(model.components * comps, axis=1))
    assert np.all(cos > 0.999)
    # PPCA model variances along the components = plain PCA eigenvalues (ML, 1/N vs 1/(N-1))
    assert np.allclose(model.explained_variance, var * (199 / 200), rtol=1e-3)
    assert np.all(np.diff(model.explained_variance) <= 0)
    assert np.allclose(model.components @ model.components.T, np.eye(5), atol=1e-10)


@pytest.mark.parametrize("missing", [0.3, 0.5])
def test_recovers_subspace_with_values_missing_at_random(missing):
    rng = np.random.default_rng(1)
    x, basis, _ = _low_rank(rng, 300, 150, 4, noise=0.05)
    xs = x.copy()
    xs[rng.random(x.shape) < missing] = np.nan
    # the prior pulls towards the (noisier) pairwise covariance: a little further off
    assert _max_angle_deg(fit_pca_missing(xs, 4, seed=1).components, basis) < 3.0
    model = fit_pca_missing(xs, 4, seed=1, prior_weight=0.0)  # ML
    assert _max_angle_deg(model.components, basis) < 1.0
    assert np.allclose(model.mean, x.mean(0), atol=0.03)  # ML mean ~ the complete-data mean
    assert model.sigma2 == pytest.approx(0.05**2, rel=0.3)
    # the log-likelihood never decreases (EM)
    ll = np.array(model.log_likelihood)
    assert np.all(np.diff(ll) >= -1e-9 * np.abs(ll[1:]))
    # mean imputation + plain PCA is visibly worse: the EM does something
    mean_imp = np.where(np.isnan(xs), np.nanmean(xs, axis=0), xs)
    _, comps_imp, _ = plain_pca(mean_imp, 4)
    assert _max_angle_deg(comps_imp, basis) > 2 * _max_angle_deg(model.components, basis)


def test_pixels_never_valid_do_not_break_it():
    rng = np.random.default_rng(2)
    x, basis, _ = _low_rank(rng, 200, 100, 3, noise=0.05)
    xs = x.copy()
    xs[rng.random(x.shape) < 0.4] = np.nan
    dead = np.array([0, 1, 2, 50, 99])
    xs[:, dead] = np.nan
    xs[7] = np.nan  # one sample with no valid pixel at all
    model = fit_pca_missing(xs, 3, seed=2)
    assert model.W.shape == (100, 3) and model.components.shape == (3, 100)
    for arr in (model.mean, model.components, model.W, model.explained_variance):
        assert np.all(np.isfinite(arr))
    assert np.all(model.W[dead] == 0.0)
    assert np.all(model.components[:, dead] == 0.0)
    assert np.all(model.mean[dead] == 0.0)
    assert np.all(model.observed_count[dead] == 0)
    live = np.setdiff1d(np.arange(100), dead)
    assert _max_angle_deg(model.components[:, live], basis[:, live]) < 2.5
    y, has = model.project(xs, return_valid=True)
    assert np.all(np.isfinite(y))
    assert not has[7] and has.sum() == 199
    assert np.all(y[7] == 0.0)
    # a query valid only on never-trained pixels carries no information: prior mean
    q = np.full(100, np.nan)
    q[dead] = 5.0
    yq, ok = model.project(q, return_valid=True)
    assert ok and np.allclose(yq, 0.0)
    yq, ok = model.project(np.full(100, np.nan), return_valid=True)
    assert not ok and np.all(yq == 0.0)


def test_sparse_projection_equals_full_projection_on_noiseless_data():
    rng = np.random.default_rng(3)
    x, _, _ = _low_rank(rng, 150, 80, 4, noise=0.0)
    xs = x.copy()
    xs[rng.random(x.shape) < 0.4] = np.nan
    model = fit_pca_missing(xs, 4, seed=3, max_iter=300, prior_weight=0.0)  # ML: exact on noiseless data
    y_full = model.project(x)
    y_sparse = model.project(xs)
    scale = np.abs(y_full).max()
    assert np.abs(y_sparse - y_full).max() < 1e-4 * scale
    # features are coordinates in the components' basis: reconstruction is exact
    assert np.allclose(model.reconstruct(y_full), x, atol=1e-4 * np.abs(x).max())
    # a single sample (1-D) gives the same as its row
    assert np.allclose(model.project(xs[5]), y_sparse[5])


def test_projection_matches_plain_pca_features_on_complete_data():
    rng = np.random.default_rng(4)
    x, _, _ = _low_rank(rng, 200, 60, 3, noise=0.01)
    model = fit_pca_missing(x, 3, seed=4)
    y = model.project(x)
    y_plain = (x - model.mean) @ model.components.T
    # posterior mean shrinks by s_k^2 / (s_k^2 + sigma^2): tiny at this noise level
    assert np.allclose(y, y_plain, rtol=1e-3, atol=1e-3)


def test_deterministic_with_seed_and_rejects_bad_input():
    rng = np.random.default_rng(5)
    x, _, _ = _low_rank(rng, 60, 40, 2, noise=0.1)
    x[rng.random(x.shape) < 0.3] = np.nan
    a = fit_pca_missing(x, 2, seed=7)
    b = fit_pca_missing(x, 2, seed=7)
    assert np.array_equal(a.components, b.components) and a.sigma2 == b.sigma2
    with pytest.raises(LinoLocError):
        fit_pca_missing(x, 0)
    with pytest.raises(LinoLocError):
        fit_pca_missing(np.full((5, 4), np.nan), 1)
    with pytest.raises(LinoLocError):
        a.project(np.zeros(39))


def test_float32_products_agree_with_float64():
    rng = np.random.default_rng(6)
    x, _, _ = _low_rank(rng, 200, 100, 3, noise=0.1)
    x[rng.random(x.shape) < 0.4] = np.nan
    a = fit_pca_missing(x.astype(np.float32), 3, seed=0)
    b = fit_pca_missing(x, 3, seed=0, dtype=np.float32)
    assert _max_angle_deg(a.components, b.components) < 0.05


def test_model_rebuilt_from_stored_projection_gives_the_same_features():
    rng = np.random.default_rng(7)
    x, _, _ = _low_rank(rng, 150, 90, 4, noise=0.2)
    x[rng.random(x.shape) < 0.4] = np.nan
    x[:, 3] = np.nan
    model = fit_pca_missing(x, 4, seed=0)
    again = MissingDataPCA.from_projection(
        model.mean, model.components, model.explained_variance, model.sigma2
    )
    assert np.allclose(again.project(x), model.project(x), atol=1e-9)
    assert np.allclose(again.components, model.components)
    # the per-frame path (few samples) and the batch path give the same features
    batch = model.project(x)
    assert np.allclose(model.project(x[:3]), batch[:3], atol=1e-9)
    assert np.allclose(model.project(x[10]), batch[10], atol=1e-9)
    with pytest.raises(LinoLocError):
        MissingDataPCA.from_projection(
            model.mean[:-1], model.components, model.explained_variance, 1.0
        )


def _block_missing(rng: np.random.Generator, n: int, side: int, d: int) -> np.ndarray:
    """Smooth images with a decaying spectrum (no gap at d) and rectangular holes, like
    sparse disparity maps: the case where plain EM converges slowly."""
    yy, xx = np.mgrid[0:side, 0:side] / side
    k = 3 * d
    freqs = rng.uniform(0.5, 4.0, (k, 2))
    phases = rng.uniform(0, 2 * np.pi, k)
    basis = np.cos(2 * np.pi * (freqs[:, 0, None, None] * xx + freqs[:, 1, None, None] * yy)
                   + phases[:, None, None]).reshape(k, -1)
    z = rng.normal(size=(n, k)) * (0.85 ** np.arange(k))
    x = z @ basis * 5.0 + 10.0 + rng.normal(0.0, 0.05, (n, side * side))
    img = x.reshape(n, side, side)
    for i in range(n):
        for _ in range(3):
            r0, c0 = rng.integers(0, side, 2)
            h, w = rng.integers(side // 4, side // 2 + 1, 2)
            img[i, r0 : r0 + h, c0 : c0 + w] = np.nan
    img[:, :, : side // 8] = np.nan  # a band never observed
    return img.reshape(n, -1)


@pytest.mark.parametrize("prior_weight", [0.0, 0.1])
def test_acceleration_reaches_the_same_fixed_point_as_plain_em(prior_weight):
    """SQUAREM (default) and plain PX-EM converge to the same estimate (ML, MAP) on
    block-missing data; the accelerated fit needs fewer iterations and its objective never
    drops."""
    rng = np.random.default_rng(8)
    x = _block_missing(rng, 150, 16, 5)
    assert 0.3 < np.isnan(x).mean() < 0.8
    kw = dict(seed=0, tol=1e-12, subspace_tol=1e-9, prior_weight=prior_weight)
    fast = fit_pca_missing(x, 5, max_iter=2000, **kw)
    slow = fit_pca_missing(x, 5, max_iter=20000, accelerate=False, **kw)
    assert fast.converged and slow.converged
    assert fast.n_iter * (3 if prior_weight == 0 else 1) < slow.n_iter
    ll = np.array(fast.log_likelihood)
    assert np.all(np.diff(ll) >= -1e-9 * np.abs(ll[1:]))
    assert fast.log_likelihood[-1] == pytest.approx(slow.log_likelihood[-1], rel=1e-8)
    assert _max_angle_deg(fast.components, slow.components) < 0.01
    assert fast.sigma2 == pytest.approx(slow.sigma2, rel=1e-5)
    assert np.allclose(fast.explained_variance, slow.explained_variance, rtol=1e-5)
    assert np.allclose(fast.mean, slow.mean, atol=1e-5 * np.abs(slow.mean).max())
    y_fast, y_slow = fast.project(x), slow.project(x)
    assert np.abs(y_fast - y_slow).max() < 1e-4 * np.abs(y_slow).max()


def test_input_is_not_modified():
    rng = np.random.default_rng(9)
    x, _, _ = _low_rank(rng, 80, 50, 3, noise=0.1)
    x[rng.random(x.shape) < 0.4] = np.nan
    for arr in (x, x.astype(np.float32)):
        before = arr.copy()
        fit_pca_missing(arr, 3, seed=0, dtype=np.float32)
        fit_pca_missing(arr, 3, seed=0)
        assert np.array_equal(arr, before, equal_nan=True)


def _blocks_no_gap(seed: int, n: int = 800, blocks: int = 25, side: int = 30, d: int = 8, keep: int = 3):
    """Each sample observes ``keep`` of ``blocks`` blocks of ``side`` pixels (88 % missing, most
    pairs of blocks rarely seen together); spectrum linear over 2 d directions: no gap at d."""
    rng = np.random.default_rng(seed)
    dim = blocks * side
    lam = np.linspace(3.0, 1.0, 2 * d)
    basis = np.linalg.qr(rng.normal(size=(dim, 2 * d)))[0] * np.sqrt(lam) * np.sqrt(dim) / 4
    x = rng.normal(size=(n, 2 * d)) @ basis.T + rng.normal(0.0, 0.5, (n, dim)) + 5.0
    for i in range(n):
        off = np.ones(blocks, dtype=bool)
        off[rng.choice(blocks, keep, replace=False)] = False
        x[i, np.repeat(off, side)] = np.nan
    return x


def test_map_with_a_vanishing_prior_is_pca_on_complete_data():
    """Complete data: S is the sample covariance, the start (PPCA of S) is PCA's subspace and
    EM stays there, for a vanishing and for the default prior."""
    rng = np.random.default_rng(10)
    x, _, _ = _low_rank(rng, 300, 700, 6, noise=0.5)  # D > 600: the iterative eigensolver
    _, comps, var = plain_pca(x, 6)
    for w in (1e-9, 0.1):
        model = fit_pca_missing(x, 6, prior_weight=w)
        assert np.degrees(subspace_angles(model.components.T, comps.T)).max() < 1e-4
        assert np.allclose(model.explained_variance, var * (299 / 300), rtol=1e-4)


def test_map_objective_never_decreases_and_converges_on_a_hard_sparse_case():
    """Block-missing data with no spectral gap: the MAP fit converges well inside the
    iteration limit, its recorded objective never decreases, and two seeds give the same
    subspace (the ML fit's answer depends on the seed's random start)."""
    x = _blocks_no_gap(0)
    assert np.isnan(x).mean() > 0.85
    a = fit_pca_missing(x, 8, seed=0, max_iter=100)
    b = fit_pca_missing(x, 8, seed=1, max_iter=100)
    assert a.converged and a.n_iter <= 40
    ll = np.array(a.log_likelihood)
    assert np.all(np.diff(ll) >= -1e-12 * np.abs(ll[1:]))
    assert np.degrees(subspace_angles(a.components.T, b.components.T)).max() < 1e-6
    ml0 = fit_pca_missing(x, 8, seed=0, max_iter=100, prior_weight=0.0)
    ml1 = fit_pca_missing(x, 8, seed=1, max_iter=100, prior_weight=0.0)
    assert np.degrees(subspace_angles(ml0.components.T, ml1.components.T)).max() > 0.1


def test_map_answer_does_not_depend_on_the_start():
    """EM on the MAP objective from the ML fit's start (mean-imputed PCA) reaches the
    subspace of the default start (the prior's mode)."""
    from lino_loc import pca_missing as pm

    x = _blocks_no_gap(1, n=600, blocks=12, keep=3)
    ref = fit_pca_missing(x, 8, tol=1e-10, subspace_tol=1e-8, max_iter=500)
    a, _ = pm._checked_data(x, 8, np.float64)
    data, _, _ = pm._centred_data(a, np.float64, 1e-9, True)
    S = pm._pairwise_covariance(data)
    data.prior = pm._CovPrior(nu=0.1 * len(x), S=S, trace=float(np.trace(S)))
    W, s2 = pm._initial_params(data, 8, np.random.default_rng(3))
    fit = pm._run_em(W, np.zeros(a.shape[1]), s2, data, 500, 1e-10, 1e-8, True)
    q, _ = np.linalg.qr(fit.W)
    assert fit.converged
    assert np.degrees(subspace_angles(q, ref.components.T)).max() < 0.05


def test_prior_weight_is_checked():
    x = np.random.default_rng(11).normal(size=(20, 6))
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(LinoLocError, match="prior_weight"):
            fit_pca_missing(x, 2, prior_weight=bad)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_pairwise_covariance_is_the_available_case_covariance(dtype):
    from lino_loc import pca_missing as pm

    rng = np.random.default_rng(12)
    x = rng.normal(size=(40, 1100))  # more pixels than one block of the symmetrisation
    x[rng.random(x.shape) < 0.5] = np.nan
    a, _ = pm._checked_data(x, 3, dtype)
    data, _, _ = pm._centred_data(a, dtype, 1e-9, True)
    S = pm._pairwise_covariance(data)
    m = np.isfinite(x)
    xc = np.where(m, x - np.nanmean(x, 0), 0.0)
    want = (xc.T @ xc) / np.maximum(m.T.astype(float) @ m, 1.0)
    assert np.allclose(S, want, atol=1e-5 if dtype == np.float32 else 1e-12)
    assert np.array_equal(S, S.T)


def test_a_posterior_matrix_made_indefinite_by_rounding_is_restored_to_its_exact_bound() -> None:
    """M = W_o^T W_o + sigma^2 I has every eigenvalue >= sigma^2; float32 sums over thousands
    of pixels can break that (a real map's disparity did): the diagonal is raised back to the
    bound, and a matrix that is fine is left as it is."""
    from lino_loc.pca_missing import _restore_definite

    rng = np.random.default_rng(0)
    good = rng.normal(size=(3, 4, 4))
    good = good @ good.transpose(0, 2, 1) + 0.5 * np.eye(4)
    bad = good.copy()
    bad[1] -= (np.linalg.eigvalsh(bad[1])[0] + 0.3) * np.eye(4)  # smallest eigenvalue -0.3
    out = _restore_definite(bad, 0.5)
    np.testing.assert_array_equal(out[[0, 2]], bad[[0, 2]])
    assert np.linalg.eigvalsh(out[1])[0] == pytest.approx(0.5)
    np.linalg.cholesky(out)  # positive definite


def _few_directions_block_missing(seed: int, n: int = 200, blocks: int = 20, side: int = 20, k: int = 10) -> np.ndarray:
    """Each sample observes 3 of ``blocks`` blocks (85 % missing) of data with k directions
    and little noise: the available-case covariance is far from positive semi-definite and
    the mean of its eigenvalues beyond the 8th is negative (an improper prior, as with the
    corridor's sparse disparity)."""
    rng = np.random.default_rng(seed)
    dim = blocks * side
    basis = np.linalg.qr(rng.normal(size=(dim, k)))[0] * np.sqrt(np.linspace(3.0, 1.0, k)) * np.sqrt(dim) / 4
    x = rng.normal(size=(n, k)) @ basis.T + rng.normal(0.0, 0.05, (n, dim)) + 5.0
    for i in range(n):
        off = np.ones(blocks, dtype=bool)
        off[rng.choice(blocks, 3, replace=False)] = False
        x[i, np.repeat(off, side)] = np.nan
    return x


def test_an_improper_prior_is_made_proper_and_the_fit_converges():
    """Where the available-case covariance S gives an improper prior (the mean of its
    eigenvalues beyond the d-th is negative), S's diagonal is raised by the smallest ridge
    that makes it proper (the eigenvalues beyond the d-th raised): sigma^2 stays far above its floor (it ran to the floor before), the fit converges well inside the limit, the objective never drops and
    a second seed gives the same subspace. Data whose S is proper are left as they are."""
    from lino_loc import pca_missing as pm

    x = _few_directions_block_missing(0)
    a, _ = pm._checked_data(x, 8, np.float64)
    data, _, _ = pm._centred_data(a, np.float64, 1e-9, True)
    S = pm._pairwise_covariance(data)
    lam, _ = pm._top_eigen(S, 8)
    trace, D = float(np.trace(S)), S.shape[0]
    assert (trace - lam.sum()) / (D - 8) < 0  # improper as it is
    delta = pm._proper_shift(trace, lam, D)
    assert (trace + (D - 8) * delta - lam.sum()) / (D - 8) == pytest.approx(pm.PRIOR_MIN_NOISE * trace / D)
    model = fit_pca_missing(x, 8, seed=0, max_iter=100)
    assert model.converged and model.n_iter <= 80
    assert model.sigma2 > 1e3 * data.sigma2_floor  # before: at the floor, not converged in 100
    ll = np.array(model.log_likelihood)
    assert np.all(np.diff(ll) >= -1e-12 * np.abs(ll[1:]))
    other = fit_pca_missing(x, 8, seed=5, max_iter=100)
    assert _max_angle_deg(model.components, other.components) < 1e-6
    # a proper S (the test problem without a spectral gap) is not touched
    a, _ = pm._checked_data(_blocks_no_gap(0), 8, np.float64)
    data, _, _ = pm._centred_data(a, np.float64, 1e-9, True)
    S = pm._pairwise_covariance(data)
    lam, _ = pm._top_eigen(S, 8)
    assert pm._proper_shift(float(np.trace(S)), lam, S.shape[0]) == 0.0


def test_float32_fit_stops_at_its_rounding_resolution_near_the_exact_answer():
    """With no tolerance at all, the float32 fit stops (converged) once an EM step can no
    longer raise its objective beyond rounding, well before the iteration limit, and its
    subspace is that of the float64 fit run to a tight tolerance."""
    rng = np.random.default_rng(13)
    x = _block_missing(rng, 300, 16, 5)
    exact = fit_pca_missing(x, 5, tol=1e-13, subspace_tol=1e-9, max_iter=3000)
    assert exact.converged
    fast = fit_pca_missing(x, 5, tol=0.0, subspace_tol=0.0, max_iter=3000, dtype=np.float32)
    assert fast.converged and fast.n_iter < 3000
    assert _max_angle_deg(fast.components, exact.components) < 0.05


def test_the_objective_tolerance_is_absolute_per_value():
    """The stopping rule's objective test is on its change in nats per value: invariant to
    the data's units (a scale shifts the objective by a constant), so a fit of 10 x the data
    stops at the same iteration with nearly the same subspace (SQUAREM's step length mixes
    W's and sigma^2's units, so the iterates are not exactly scale-equivariant)."""
    x = _blocks_no_gap(2, n=400, blocks=12, keep=3)
    a = fit_pca_missing(x, 8, seed=0, max_iter=200)
    b = fit_pca_missing(10.0 * x, 8, seed=0, max_iter=200)
    assert a.converged and b.converged
    assert a.n_iter == b.n_iter
    assert _max_angle_deg(a.components, b.components) < 0.1


def test_samples_without_a_valid_pixel_change_nothing():
    """Rows with no valid value add nothing to the MAP fit (they are dropped before it):
    the same model with or without them, and their features are the prior mean."""
    x = _blocks_no_gap(3, n=300, blocks=12, keep=3)
    padded = np.vstack([x[:100], np.full((40, x.shape[1]), np.nan), x[100:]])
    a = fit_pca_missing(x, 8, seed=0)
    b = fit_pca_missing(padded, 8, seed=0)
    assert a.n_iter == b.n_iter and a.converged and b.converged
    assert np.allclose(a.components, b.components, atol=1e-9)
    assert a.sigma2 == pytest.approx(b.sigma2, rel=1e-12)
    y, has = b.project(padded, return_valid=True)
    assert not has[100:140].any() and np.all(y[100:140] == 0.0)


def test_the_batched_posterior_is_the_per_sample_one():
    """The E-step's batched products and inverses give, sample by sample, the posterior of
    the observed pixels alone: M_n = W_o^T W_o + sigma^2 I, E[z] = M_n^-1 W_o^T (x_o - mu_o),
    and log N(x_o | mu_o, W_o W_o^T + sigma^2 I)."""
    from scipy.stats import multivariate_normal

    from lino_loc.pca_missing import _posterior

    rng = np.random.default_rng(14)
    n, D, d = 12, 30, 4
    W, mu, s2 = rng.normal(size=(D, d)), rng.normal(size=D), 0.7
    x = rng.normal(size=(n, D)) * 2.0
    x[rng.random(x.shape) < 0.5] = np.nan
    x[3] = np.nan
    mask = np.isfinite(x)
    X0 = np.where(mask, x, 0.0)
    Ez, Minv, ll = _posterior(W, mu, s2, X0, mask.astype(float), mask.sum(1).astype(float),
                              np.einsum("nj,nj->n", X0, X0))
    for i in range(n):
        o = mask[i]
        M = W[o].T @ W[o] + s2 * np.eye(d)
        assert np.allclose(Minv[i], np.linalg.inv(M), atol=1e-12)
        assert np.allclose(Ez[i], np.linalg.solve(M, W[o].T @ (x[i, o] - mu[o])), atol=1e-12)
        want = 0.0 if not o.any() else multivariate_normal(mu[o], W[o] @ W[o].T + s2 * np.eye(o.sum())).logpdf(x[i, o])
        assert ll[i] == pytest.approx(want, rel=1e-10, abs=1e-10)


def test_projection_by_blocks_is_the_projection_of_all_rows(monkeypatch):
    import lino_loc.pca_missing as pm

    rng = np.random.default_rng(3)
    X = rng.normal(size=(300, 40)) @ rng.normal(size=(40, 40))
    X[rng.random(X.shape) < 0.4] = np.nan
    X[7] = np.nan  # a row with nothing
    model = pm.fit_pca_missing(X, 4, seed=0)
    whole, has = model.project(X, return_valid=True)
    monkeypatch.setattr(pm, "_PROJECT_BLOCK", 64)
    blocks, has_b = model.project(X, return_valid=True)
    np.testing.assert_allclose(blocks, whole, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(has_b, has)
    assert not has[7] and np.all(whole[7] == 0.0)

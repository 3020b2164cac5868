"""Nearest-neighbour sensor model and its pose mixture: density, samples, wrap-around, search."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from lino_loc.errors import LinoLocError
from lino_loc.sensor_model import (
    Bounds,
    NearestNeighbourSensorModel,
    PoseMixture,
    SensorModelConfig,
    lambda_log_weights,
)

BOUNDS = Bounds(0.0, 4.0, 0.0, 3.0)


def _mixture(outlier: float = 0.0) -> PoseMixture:
    poses = np.array([[1.0, 1.0, 0.5], [2.5, 2.0, np.pi - 0.1], [3.0, 0.8, -2.0]])
    return PoseMixture.create(
        poses,
        np.log([0.5, 0.3, 0.2]),
        [0.3, 0.2, 0.4],
        [0.3, 0.5, 0.2],
        outlier_weight=outlier,
        bounds=BOUNDS,
    )


def _grid(nx=90, ny=80, nt=72):
    xs = -1.5 + (np.arange(nx) + 0.5) * 7.0 / nx  # cell centres over [-1.5, 5.5] x [-1.5, 4.5]
    ys = -1.5 + (np.arange(ny) + 0.5) * 6.0 / ny
    ts = -np.pi + (np.arange(nt) + 0.5) * 2 * np.pi / nt
    X, Y, T = np.meshgrid(xs, ys, ts, indexing="ij")
    cell = (xs[1] - xs[0]) * (ys[1] - ys[0]) * (2 * np.pi / nt)
    return np.column_stack([X.ravel(), Y.ravel(), T.ravel()]), cell, (nx, ny, nt), (xs, ys, ts)


@pytest.mark.parametrize("outlier", [0.0, 0.1])
def test_density_integrates_to_one(outlier: float) -> None:
    m = _mixture(outlier)
    pts, cell, _, _ = _grid()
    assert float(np.sum(m.pdf(pts)) * cell) == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize("outlier", [0.0, 0.1])
def test_samples_follow_density(outlier: float) -> None:
    """Chi-square of sample histograms against the density integrated on a grid."""
    m = _mixture(outlier)
    rng = np.random.default_rng(7)
    s = m.sample(40_000, rng)
    pts, cell, shape, (xs, ys, ts) = _grid(70, 60, 36)
    dens = m.pdf(pts).reshape(shape) * cell
    # heading marginal, 12 bins of 30 deg
    p_th = dens.sum(axis=(0, 1)).reshape(12, 3).sum(axis=1)
    p_th /= p_th.sum()
    obs_th = np.histogram(s[:, 2], bins=np.linspace(-np.pi, np.pi, 13))[0]
    chi_th = stats.chisquare(obs_th, p_th * obs_th.sum())
    assert chi_th.pvalue > 1e-3, chi_th
    # x marginal: exact CDF of the Gaussian mixture (plus the uniform part) -> KS test
    w = np.exp(m.log_weights)

    def cdf(x):
        c = sum(
            wk * stats.norm.cdf(x, mk, sk)
            for wk, mk, sk in zip(w, m.poses[:, 0], m.sigma_xy, strict=True)
        )
        return c + outlier * np.clip((x - BOUNDS.x_min) / (BOUNDS.x_max - BOUNDS.x_min), 0, 1)

    ks = stats.kstest(s[:, 0], cdf)
    assert ks.pvalue > 1e-3, ks
    # (x, y) histogram on 1 m cells against the grid integral
    edges_x, edges_y = np.linspace(-1.5, 5.5, 8), np.linspace(-1.5, 4.5, 7)
    obs = np.histogram2d(s[:, 0], s[:, 1], bins=[edges_x, edges_y])[0]
    pxy = dens.sum(axis=2)
    ix = np.digitize(xs, edges_x) - 1
    iy = np.digitize(ys, edges_y) - 1
    exp = np.zeros_like(obs)
    np.add.at(exp, (ix[:, None].repeat(len(ys), 1), iy[None, :].repeat(len(xs), 0)), pxy)
    keep = exp * len(s) > 20
    e = exp[keep] / exp[keep].sum() * obs[keep].sum()
    chi = stats.chisquare(obs[keep], e)
    assert chi.pvalue > 1e-4, chi


def test_angle_wraps_at_pi() -> None:
    m = PoseMixture.create([[1.0, 1.0, np.pi - 0.01]], [0.0], 0.3, 0.2)
    across = m.log_pdf([[1.0, 1.0, -np.pi + 0.01]])[0]
    same_side = m.log_pdf([[1.0, 1.0, np.pi - 0.03]])[0]  # the same 0.02 rad away, unwrapped
    far = m.log_pdf([[1.0, 1.0, 0.0]])[0]
    assert across == pytest.approx(same_side, abs=1e-9)
    assert across > far + 20
    s = m.sample(5000, np.random.default_rng(0))
    assert np.all((s[:, 2] >= -np.pi) & (s[:, 2] < np.pi))
    d = np.angle(np.exp(1j * (s[:, 2] - (np.pi - 0.01))))
    assert abs(d.mean()) < 0.01 and d.std() == pytest.approx(0.2, rel=0.05)


def test_component_log_pdf_matches_direct_formula() -> None:
    m = _mixture()
    rng = np.random.default_rng(1)
    x = np.column_stack(
        [rng.uniform(0, 4, 50), rng.uniform(0, 3, 50), rng.uniform(-np.pi, np.pi, 50)]
    )
    direct = []
    for k in range(m.n_components):
        mu, s, st = m.poses[k], m.sigma_xy[k], m.sigma_theta[k]
        g = stats.multivariate_normal(mu[:2], s**2 * np.eye(2)).logpdf(x[:, :2])
        vm = stats.vonmises(1 / st**2, loc=mu[2]).logpdf(x[:, 2])
        direct.append(m.log_weights[k] + g + vm)
    np.testing.assert_allclose(m.component_log_pdf(x), np.column_stack(direct), atol=1e-9)



@pytest.mark.parametrize("shared_widths", [True, False])
@pytest.mark.parametrize("outlier", [0.0, 0.3])
def test_log_pdf_matches_direct_formula_near_and_far(shared_widths: bool, outlier: float) -> None:
    """log_pdf (constant shift, no per-pose max) equals the direct log-sum-exp of the kernels
    and the outlier component, also far outside the bounds where the shifted sum underflows
    and the exact fallback is taken; log_pdf_trig is the same from cos/sin of the heading."""
    poses = np.array([[1.0, 1.0, 0.5], [2.5, 2.0, np.pi - 0.1], [3.0, 0.8, -2.0], [0.5, 2.5, 1.0]])
    sxy = 0.35 if shared_widths else [0.3, 0.2, 0.4, 0.25]
    sth = 0.3 if shared_widths else [0.3, 0.5, 0.2, 0.4]
    m = PoseMixture.create(poses, np.log([0.4, 0.3, 0.2, 0.1]), sxy, sth, outlier, BOUNDS, 0.7)
    rng = np.random.default_rng(3)
    near = np.column_stack([rng.uniform(-1, 5, 300), rng.uniform(-1, 4, 300), rng.uniform(-4, 4, 300)])
    far = np.array([[30.0, 1.0, 0.2], [-25.0, -40.0, 3.0], [2.0, 200.0, -1.0]])
    x = np.concatenate([near, far])
    terms = []
    for k in range(m.n_components):
        mu, s, st = m.poses[k], m.sigma_xy[k], m.sigma_theta[k]
        g = stats.multivariate_normal(mu[:2], s**2 * np.eye(2)).logpdf(x[:, :2])
        terms.append(m.log_weights[k] + g + stats.vonmises(1 / st**2, loc=mu[2]).logpdf(x[:, 2]))
    if outlier > 0:
        inside = BOUNDS.contains(x[:, :2])
        terms.append(np.where(inside, np.log(outlier) + BOUNDS.log_uniform_density, -np.inf))
    from scipy.special import logsumexp

    ref = logsumexp(np.column_stack(terms), axis=1) + 0.7
    got = m.log_pdf(x)
    assert np.all(np.isfinite(got[-3:])) and got[-1] < -1e4  # the fallback, not -inf or nan
    np.testing.assert_allclose(got, ref, rtol=1e-11, atol=1e-9)
    trig = m.log_pdf_trig(x[:, 0], x[:, 1], np.cos(x[:, 2]), np.sin(x[:, 2]))
    np.testing.assert_allclose(trig, got, rtol=1e-13, atol=1e-12)

def test_log_pdf_leaves_out_only_negligible_kernels() -> None:
    """Poses in a small cloud inside the bounds: the far kernels are left out of the sum (their
    terms are > 40 nats below the outlier floor) and the density is the direct formula's."""
    bounds = Bounds(0.0, 20.0, 0.0, 10.0)
    poses = np.array([[1.0, 1.0, 0.3], [1.4, 1.1, 2.0], [18.0, 9.0, 0.3], [10.0, 5.0, -1.0]])
    m = PoseMixture.create(poses, np.log([0.4, 0.3, 0.2, 0.1]), 0.35, 0.3, 0.5, bounds)
    rng = np.random.default_rng(5)
    x = np.column_stack([rng.normal(1.1, 0.2, 800), rng.normal(1.0, 0.2, 800), rng.uniform(-4, 4, 800)])
    box = (x[:, 0].min(), x[:, 0].max(), x[:, 1].min(), x[:, 1].max())
    assert m._active_rows(box).shape[0] == 2  # the path under test is taken
    from scipy.special import logsumexp

    terms = [
        m.log_weights[k]
        + stats.multivariate_normal(poses[k, :2], 0.35**2 * np.eye(2)).logpdf(x[:, :2])
        + stats.vonmises(1 / 0.3**2, loc=poses[k, 2]).logpdf(x[:, 2])
        for k in range(4)
    ]
    terms.append(np.full(800, np.log(0.5) + bounds.log_uniform_density))
    np.testing.assert_allclose(m.log_pdf(x), logsumexp(np.column_stack(terms), axis=1), rtol=1e-13)


def _random_map(n=500, d=6, seed=0):
    rng = np.random.default_rng(seed)
    poses = np.column_stack(
        [rng.uniform(0, 9, n), rng.uniform(0, 5, n), rng.uniform(-np.pi, np.pi, n)]
    )
    feats = rng.normal(size=(n, d)) / np.arange(1, d + 1)
    return poses, feats


@pytest.mark.parametrize("index", ["brute", "kdtree"])
def test_neighbours_are_the_exact_j_nearest(index: str) -> None:
    poses, feats = _random_map()
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=10, index=index))
    rng = np.random.default_rng(2)
    q = rng.normal(size=(20, feats.shape[1])) * 0.5
    idx, d2 = model.neighbours(q)
    full = ((q[:, None, :] - feats[None]) ** 2).sum(-1)
    ref = np.argsort(full, axis=1)[:, :10]
    np.testing.assert_array_equal(idx, ref)
    np.testing.assert_allclose(d2, np.take_along_axis(full, ref, axis=1), atol=1e-10)
    assert np.all(np.diff(d2, axis=1) >= 0)


def test_auto_index_gives_same_answer() -> None:
    poses, feats = _random_map(n=2500)
    a = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(index="auto"))
    b = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(index="brute"))
    q = feats[5] + 0.01
    assert a.index_kind in ("brute", "kdtree")
    np.testing.assert_array_equal(a.neighbours(q)[0], b.neighbours(q)[0])


def test_observe_puts_most_weight_on_the_matching_pose() -> None:
    poses, feats = _random_map()
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=10, outlier_weight=0.01))
    mix = model.observe(feats[42])
    assert mix.n_components == 10
    assert mix.neighbours is not None and mix.neighbours[0] == 42
    w = np.exp(mix.log_weights)
    assert w.sum() == pytest.approx(0.99)
    assert np.argmax(w) == 0 and np.all(np.diff(w) <= 1e-12)
    np.testing.assert_array_equal(mix.poses[0], poses[42])
    # the density is highest at the matched pose
    assert mix.log_pdf(poses[42:43])[0] > mix.log_pdf(poses[43:44])[0]


def test_lambda_weights() -> None:
    d2 = np.array([[1.0, 2.0, 4.0, 9.0]])
    for scale in ("median", "nearest"):
        lw = lambda_log_weights(d2, scale)
        assert np.exp(lw).sum() == pytest.approx(1.0)
        assert np.all(np.diff(lw) < 0)
    # median scale: s^2 = 3 -> logits -d2/6
    np.testing.assert_allclose(
        lambda_log_weights(d2, "median"), -d2 / 6 - np.log(np.exp(-d2 / 6).sum())
    )
    np.testing.assert_allclose(np.exp(lambda_log_weights(d2, "uniform")), 0.25)
    exact = lambda_log_weights(np.array([[0.0, 0.0, 1.0]]), "nearest")
    assert np.all(np.isfinite(exact))


def test_bad_inputs_raise_user_errors() -> None:
    poses, feats = _random_map(n=20)
    with pytest.raises(LinoLocError, match="features"):
        NearestNeighbourSensorModel(poses, feats[:10])
    with pytest.raises(LinoLocError, match="j=30"):
        NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=30))
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=5))
    with pytest.raises(LinoLocError, match="expected 6 values"):
        model.observe(np.zeros(4))


def test_log_likelihood_matrix_matches_observe() -> None:
    poses, feats = _random_map()
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=7, outlier_weight=0.02))
    rng = np.random.default_rng(5)
    ys = feats[rng.integers(0, len(feats), 6)] + 0.05 * rng.normal(size=(6, feats.shape[1]))
    x = np.column_stack(
        [rng.uniform(-1, 10, 40), rng.uniform(-1, 6, 40), rng.uniform(-np.pi, np.pi, 40)]
    )
    mat = model.log_likelihood_matrix(ys, x)
    assert mat.shape == (6, 40)
    for b in range(6):
        np.testing.assert_allclose(mat[b], model.observe(ys[b]).log_pdf(x), rtol=1e-10, atol=1e-10)


def test_lambda_weights_of_one_observation_match_the_batch_version() -> None:
    rng = np.random.default_rng(3)
    for k in (1, 2, 7, 10):
        d2 = rng.uniform(0.1, 5.0, k)
        for scale in ("median", "nearest"):
            np.testing.assert_allclose(
                lambda_log_weights(d2, scale, 1.5),
                lambda_log_weights(d2[None, :], scale, 1.5)[0],
                rtol=1e-12,
                atol=1e-12,
            )
    # exact match with a zero median: falls back to the largest distance, stays finite
    assert np.all(np.isfinite(lambda_log_weights(np.array([0.0, 0.0, 0.0, 4.0]), "median")))
    np.testing.assert_allclose(np.exp(lambda_log_weights(np.zeros(4), "median")), 0.25)


def test_novelty_is_relative_to_the_maps_own_neighbour_distance() -> None:
    poses, feats = _random_map()
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=5))
    ref = model.reference_distance
    rows = np.random.default_rng(0).choice(len(feats), size=min(len(feats), 500), replace=False)
    d = np.sqrt(((feats[rows, None, :] - feats[None, :, :]) ** 2).sum(-1))
    d[np.arange(len(rows)), rows] = np.inf
    assert ref == pytest.approx(float(np.median(d.min(axis=1))), rel=1e-9)
    assert model.observe(feats[3]).novelty == pytest.approx(0.0, abs=1e-6)
    far = feats[3] + 10.0 * ref / np.sqrt(feats.shape[1])  # 10 reference distances away
    assert model.observe(far).novelty > 5.0
    mix = model.observe(feats[3])
    assert mix.with_log_weight(-1.0).novelty == mix.novelty


def test_brute_force_answers_many_queries_in_blocks_of_bounded_memory() -> None:
    """A map's own entries queried at once (as the action evaluator does): the same exact J
    nearest as one query at a time, with work arrays of BRUTE_QUERY_BLOCK rows, not all."""
    import tracemalloc

    from lino_loc.sensor_model import BRUTE_QUERY_BLOCK

    poses, feats = _random_map(n=3000, d=20, seed=3)
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=10, index="brute"))
    q = feats + 0.01
    tracemalloc.start()
    idx, d2 = model.neighbours(q)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    for i in (0, BRUTE_QUERY_BLOCK - 1, BRUTE_QUERY_BLOCK, 2999):
        one_idx, one_d2 = model.neighbours(q[i])
        np.testing.assert_array_equal(idx[i], one_idx[0])
        np.testing.assert_allclose(d2[i], one_d2[0], rtol=1e-12, atol=1e-12)
    # unblocked, the (3000, 3000) float64 distances alone are 72 MB
    assert peak < 6 * BRUTE_QUERY_BLOCK * 3000 * 8, f"{peak / 1e6:.0f} MB"


def test_brute_force_and_kdtree_give_the_same_bits() -> None:
    """'auto' picks its search by timing; the answer must not depend on the pick (a replay
    reproduces the service's poses to the bit), so both give identical indices and distances."""
    poses, feats = _random_map(n=2500, d=20, seed=4)
    brute = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=10, index="brute"))
    tree = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=10, index="kdtree"))
    rng = np.random.default_rng(5)
    for q in (feats[7] + 0.01, feats[:40] + rng.normal(scale=0.2, size=(40, 20))):
        bi, bd = brute.neighbours(q)
        ti, td = tree.neighbours(q)
        np.testing.assert_array_equal(bi, ti)
        assert np.array_equal(bd, td)  # the same bits, not only close
        assert np.all(np.diff(bd, axis=1) >= 0)


@pytest.mark.parametrize("index", ["brute", "kdtree", "hnsw"])
def test_identical_map_rows_tie_to_the_lowest_indices_whatever_the_search(index: str) -> None:
    """Groups of identical map rows (a virtual translation with no depth to move is its source
    image again) straddle the J-th neighbour: which of them enter the J set must not depend on
    the search 'auto' picked, nor on the order the rows were met: the lowest indices, by
    sum_k (f_k - y_k)^2 (lino_loc.exact_neighbours.settle)."""
    if index == "hnsw":
        pytest.importorskip("hnswlib")
    poses, feats = _random_map(n=2500, d=20, seed=6)
    rng = np.random.default_rng(7)
    groups = list(rng.permutation(2500)[:270].reshape(30, 9))  # disjoint groups of 9
    for g in groups:
        feats[g] = feats[g[0]]
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=10, index=index))
    for g in groups:
        for j in (1, 4, 10):
            q = feats[g[0]] + 1e-3 * rng.normal(size=20)
            idx, d2 = model.neighbours(q, j)
            exact = np.einsum("nk,nk->n", feats - q, feats - q)
            want = np.lexsort((np.arange(2500), exact))[:j]
            np.testing.assert_array_equal(idx[0], want)  # the group's lowest indices first
            np.testing.assert_array_equal(d2[0], exact[want])
    tied = model.neighbours(np.stack([feats[g[0]] for g in groups]), 4)[0]
    assert all(set(row) <= set(g) and list(row) == sorted(g)[:4] for row, g in zip(tied, groups, strict=True))

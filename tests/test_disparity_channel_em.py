"""The map's disparity channel carries the EM's converged answer, and says when it does not."""

from __future__ import annotations

import numpy as np

from lino_loc.appearance_map import DISPARITY_EM_MAX_ITER, disparity_channel_from_vectors


def _sparse_disparity(n: int = 400, size: tuple[int, int] = (16, 12), seed: int = 0) -> np.ndarray:
    """Low-rank disparity-like rows (smooth ramps plus noise) with 70 % of the pixels missing
    in 4 x 4 blocks, as the stereo matcher leaves untextured areas."""
    rng = np.random.default_rng(seed)
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w] / max(w, h)
    basis = np.stack([np.ones_like(xx), xx, yy, xx * yy, np.sin(3 * xx), np.cos(2 * yy)]).reshape(6, -1)
    X = 10.0 + rng.normal(size=(n, 6)) @ (3.0 * basis) + rng.normal(scale=0.3, size=(n, w * h))
    blocks = rng.random((n, h // 4, w // 4)) < 0.7
    mask = np.repeat(np.repeat(blocks, 4, axis=1), 4, axis=2).reshape(n, -1)
    X[mask] = np.nan
    return X.astype(np.float32)


def test_the_channel_is_fit_to_convergence_within_the_limit() -> None:
    X = _sparse_disparity()
    ch = disparity_channel_from_vectors(X, (16, 12), 6)
    assert ch.pca is not None
    assert ch.pca.converged and ch.pca.n_iter < DISPARITY_EM_MAX_ITER


def test_a_fit_stopped_at_its_limit_is_marked_unconverged() -> None:
    X = _sparse_disparity()
    ch = disparity_channel_from_vectors(X, (16, 12), 6, max_iter=2)
    assert ch.pca is not None
    assert not ch.pca.converged and ch.pca.n_iter == 2


def test_entries_with_no_valid_pixel_are_marked_unobserved() -> None:
    X = _sparse_disparity()
    X[[3, 50, 51]] = np.nan  # three views with no stereo match at all
    ch = disparity_channel_from_vectors(X, (16, 12), 6)
    rows = ch.observed_rows()
    empty = ~np.isfinite(X).any(axis=1)  # these three and the ones the generator left empty
    assert empty[[3, 50, 51]].all()
    np.testing.assert_array_equal(rows, ~empty)
    np.testing.assert_array_equal(ch.features[[3, 50, 51]], 0.0)  # the prior mean: no observation


def test_the_fit_takes_every_row_within_the_budget_else_as_many_as_it_allows() -> None:
    from lino_loc.appearance_map import DISPARITY_FIT_COPIES, disparity_fit_rows

    row_mb = 1 / 256  # one row of the EM's data, MiB (binary-exact); its working set is DISPARITY_FIT_COPIES of it
    per_row_mb = row_mb * DISPARITY_FIT_COPIES
    assert disparity_fit_rows(500, row_mb, 500 * per_row_mb, 5) == 500  # exactly fits: all
    assert disparity_fit_rows(500, row_mb, 120.5 * per_row_mb, 5) == 120  # as many whole rows as fit
    assert disparity_fit_rows(500, row_mb, 0.001, 5) == 6  # never fewer than n_features + 1
    assert disparity_fit_rows(4, row_mb, 0.001, 5) == 4  # nor more than there are


def _rank_four(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Rows of 16 x 12 pixels on four known smooth directions (scales 4, 3, 2, 1.5 about a mean
    of 10) plus noise of 0.3, half their pixels missing in 4 x 4 blocks; and an orthonormal
    basis (192, 4) of those directions."""
    rng = np.random.default_rng(seed)
    w, h = 16, 12
    yy, xx = np.mgrid[0:h, 0:w] / max(w, h)
    Q = np.linalg.qr(np.stack([xx, yy, xx * yy, np.cos(2 * yy)]).reshape(4, -1).T)[0]
    X = 10.0 + (rng.normal(size=(n, 4)) * [4.0, 3.0, 2.0, 1.5]) @ (Q.T * np.sqrt(w * h))
    X += rng.normal(scale=0.3, size=X.shape)
    blocks = rng.random((n, h // 4, w // 4)) < 0.5
    X[np.repeat(np.repeat(blocks, 4, axis=1), 4, axis=2).reshape(n, -1)] = np.nan
    return X.astype(np.float32), Q


def test_over_the_budget_a_sample_of_the_rows_finds_the_subspace_and_every_row_gets_its_features() -> None:
    from scipy.linalg import subspace_angles

    from lino_loc.appearance_map import DISPARITY_FIT_COPIES

    X, truth = _rank_four(1200)
    row_mb = X.shape[1] * 4 * DISPARITY_FIT_COPIES / 2**20
    full = disparity_channel_from_vectors(X, (16, 12), 4)
    part = disparity_channel_from_vectors(X, (16, 12), 4, memory_budget_mb=400 * row_mb)
    assert full.params["fit_rows"] == 1200 and part.params["fit_rows"] == 400
    assert full.pca is not None and part.pca is not None

    def off_truth(ch: object) -> float:  # largest principal angle to the true directions, degrees
        return float(np.degrees(subspace_angles(ch.pca.components.T.astype(float), truth).max()))  # type: ignore[attr-defined]

    assert off_truth(full) < 3.0 and off_truth(part) < 6.0  # a third of the rows, a little less sharp
    assert part.features.shape == (1200, 4)
    np.testing.assert_allclose(part.features, part.pca.project(X), rtol=1e-5, atol=1e-4)  # every row
    assert part.params["valid_fraction"] == full.params["valid_fraction"] == float(np.isfinite(X).mean())
    again = disparity_channel_from_vectors(X, (16, 12), 4, memory_budget_mb=400 * row_mb)
    np.testing.assert_array_equal(again.features, part.features)  # the sample is seeded

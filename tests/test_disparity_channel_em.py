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

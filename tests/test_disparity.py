"""Sparse disparity (paper section 5): block matching on synthetic pairs of known disparity,
no value on textureless areas, depth conversions, NaN-aware downsampling."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from lino_loc.disparity import (
    StereoConfig,
    compute_disparity,
    depth_to_disparity,
    depth_to_inverse_depth,
    downsample_sparse,
)
from lino_loc.errors import LinoLocError

H, W = 240, 320
FLAT = (slice(80, 160), slice(150, 250))  # textureless patch in the left image


def _pair(disparity: float, seed: int = 0, noise: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Left/right of a fronto-parallel textured plane at ``disparity`` px, with a flat patch.

    left(x) = T(x), right(x) = T(x + disparity): a left pixel x appears at x - disparity on
    the right, so d = x_left - x_right = disparity. Sub-pixel shifts by cubic resampling.
    """
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (H, W + 64)), (0, 0), 1.5)
    tex = ((tex - tex.min()) / (tex.max() - tex.min()) * 230 + 10).astype(np.float32)
    ys = np.repeat(np.arange(H, dtype=np.float32)[:, None], W, 1)
    xs = np.tile(np.arange(W, dtype=np.float32) + 32, (H, 1))
    left = cv2.remap(tex, xs, ys, cv2.INTER_CUBIC)
    right = cv2.remap(tex, xs + np.float32(disparity), ys, cv2.INTER_CUBIC)
    left[FLAT] = 120.0
    shift = int(round(disparity))
    right[FLAT[0], FLAT[1].start - shift : FLAT[1].stop - shift] = 120.0
    if noise:
        left += rng.normal(0, noise, left.shape).astype(np.float32)
        right += rng.normal(0, noise, right.shape).astype(np.float32)
    return (np.clip(left, 0, 255).astype(np.uint8), np.clip(right, 0, 255).astype(np.uint8))


@pytest.mark.parametrize("true_d", [8.0, 13.0, 12.5, 20.25, 5.75])
def test_shifted_pair_gives_its_disparity_and_flat_area_gets_none(true_d):
    left, right = _pair(true_d, seed=int(true_d * 4))
    disp = compute_disparity(left, right, StereoConfig())
    assert disp.dtype == np.float32 and disp.shape == (H, W)
    valid = np.isfinite(disp)
    # textured area away from the flat patch and the left border is densely matched
    region = np.zeros((H, W), bool)
    region[10:-10, 80:-10] = True
    region[FLAT[0].start - 10 : FLAT[0].stop + 10, FLAT[1].start - 10 : FLAT[1].stop + 10] = False
    assert valid[region].mean() > 0.95
    err = np.abs(disp[region & valid] - true_d)
    assert np.percentile(err, 99) <= 0.25
    assert abs(np.median(disp[valid]) - true_d) <= 0.125
    # the textureless patch (its interior, away from textured windows) gets NO value
    inner = disp[FLAT[0].start + 6 : FLAT[0].stop - 6, FLAT[1].start + 6 : FLAT[1].stop - 6]
    assert np.isnan(inner).all()
    # left border the search range cannot cover gets no value
    assert np.isnan(disp[:, : StereoConfig().num_disparities - 1]).all()


def test_flat_area_with_sensor_noise_still_gets_no_value():
    left, right = _pair(10.0, seed=3, noise=2.0)
    disp = compute_disparity(left, right)
    inner = disp[FLAT[0].start + 6 : FLAT[0].stop - 6, FLAT[1].start + 6 : FLAT[1].stop - 6]
    assert np.isfinite(inner).mean() < 0.01
    assert np.nanmedian(disp) == pytest.approx(10.0, abs=0.125)


def test_texture_threshold_controls_sparsity():
    left, right = _pair(10.0, seed=4)
    # the same scene at a tenth of the contrast (amplitude about +-12 grey levels)
    low_l = ((left.astype(np.float32) - 120) * 0.1 + 120).astype(np.uint8)
    low_r = ((right.astype(np.float32) - 120) * 0.1 + 120).astype(np.uint8)
    default = compute_disparity(low_l, low_r, StereoConfig())
    assert np.isfinite(default).mean() > 0.6
    assert np.nanmedian(default) == pytest.approx(10.0, abs=0.125)
    strict = compute_disparity(low_l, low_r, StereoConfig(texture_threshold=1000))
    assert np.isfinite(strict).mean() < 0.05
    # the full-contrast scene passes the same threshold
    assert (
        np.isfinite(compute_disparity(left, right, StereoConfig(texture_threshold=1000))).mean()
        > 0.6
    )


def test_config_validation_and_covering():
    with pytest.raises(ValidationError):
        StereoConfig(num_disparities=50)
    with pytest.raises(ValidationError):
        StereoConfig(block_size=10)
    with pytest.raises(ValidationError):
        StereoConfig(unknown_field=1)
    c = StereoConfig().covering(60.0)
    assert c.num_disparities == 64 and c.max_disparity >= 60
    assert StereoConfig().covering(64.0).num_disparities == 80
    assert StereoConfig(min_disparity=10).covering(40).num_disparities == 32
    with pytest.raises(LinoLocError):
        StereoConfig().covering(float("nan"))


def test_bad_images_raise_user_errors():
    left, right = _pair(8.0)
    with pytest.raises(LinoLocError):
        compute_disparity(left, right[:, :-1])
    with pytest.raises(LinoLocError):
        compute_disparity(left.astype(np.float32), right)
    # BGR input is converted to grey
    disp = compute_disparity(cv2.cvtColor(left, cv2.COLOR_GRAY2BGR), right)
    assert np.nanmedian(disp) == pytest.approx(8.0, abs=0.125)


def test_depth_to_disparity_closed_form():
    z = np.array([[0.5, 1.0, 2.0], [0.0, -1.0, np.nan]])
    d = depth_to_disparity(z, fx=440.0, baseline_m=0.075)
    assert d.dtype == np.float32
    assert np.allclose(d[0], [66.0, 33.0, 16.5])
    assert np.isnan(d[1]).all()
    inv = depth_to_inverse_depth(z)
    assert np.allclose(inv[0], [2.0, 1.0, 0.5]) and np.isnan(inv[1]).all()
    # disparity = f * B * inverse depth
    assert np.allclose(d[0], 440.0 * 0.075 * inv[0])
    with pytest.raises(LinoLocError):
        depth_to_disparity(z, fx=0.0, baseline_m=0.075)


def test_downsample_sparse_hand_made():
    n = np.nan
    a = np.array(
        [
            [1.0, 3.0, n, n],
            [n, 2.0, n, 8.0],
            [4.0, 4.0, 5.0, 7.0],
            [4.0, 4.0, 6.0, 8.0],
        ],
        dtype=np.float32,
    )
    out = downsample_sparse(a, (2, 2), min_valid_fraction=0.25)
    assert out.shape == (2, 2)
    # block means of the valid pixels only
    assert out[0, 0] == pytest.approx(2.0)  # (1 + 3 + 2) / 3
    assert out[0, 1] == pytest.approx(8.0)  # one valid pixel of four = 0.25
    assert out[1, 0] == pytest.approx(4.0)
    assert out[1, 1] == pytest.approx(6.5)
    out = downsample_sparse(a, (2, 2), min_valid_fraction=0.5)
    assert np.isnan(out[0, 1]) and out[0, 0] == pytest.approx(2.0)
    # an all-missing block is NaN even with min_valid_fraction = 0
    b = a.copy()
    b[:2, 2:] = n
    assert np.isnan(downsample_sparse(b, (2, 2), 0.0)[0, 1])
    # whole map to one pixel
    assert downsample_sparse(a, (1, 1), 0.0)[0, 0] == pytest.approx(np.nanmean(a))


def _area_matrix(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in): share of input cell j inside output cell i (exact area resampling)."""
    edges = np.arange(n_out + 1) * (n_in / n_out)
    lo = np.arange(n_in, dtype=np.float64)
    a = np.minimum(edges[1:, None], lo[None, :] + 1.0) - np.maximum(edges[:-1, None], lo[None, :])
    return np.clip(a, 0.0, None)


def test_downsample_sparse_size_is_width_height_and_non_integer_factor():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 10, (60, 80)).astype(np.float32)
    out = downsample_sparse(a, (40, 30), 0.0)
    assert out.shape == (30, 40)
    assert np.allclose(out, a.reshape(30, 2, 40, 2).mean(axis=(1, 3)), atol=1e-5)
    # sparse data, non-integer factor: area-weighted mean of the valid pixels
    sp = a.copy()
    sp[rng.random(sp.shape) < 0.5] = np.nan
    out = downsample_sparse(sp, (30, 25), 0.0)
    rows, cols = _area_matrix(60, 25), _area_matrix(80, 30).T
    valid = np.isfinite(sp).astype(np.float64)
    with np.errstate(invalid="ignore"):
        ref = (rows @ np.nan_to_num(sp).astype(np.float64) @ cols) / (rows @ valid @ cols)
    assert np.allclose(out, ref, atol=1e-4, equal_nan=True)
    # a constant map with holes stays constant wherever a value is given
    c = np.full((60, 80), 3.0, np.float32)
    c[rng.random(c.shape) < 0.6] = np.nan
    out = downsample_sparse(c, (30, 25), 0.0)
    assert np.allclose(out[np.isfinite(out)], 3.0)
    # stacks of maps
    stack = downsample_sparse(np.stack([a, a]), (40, 30), 0.0)
    assert stack.shape == (2, 30, 40)
    with pytest.raises(LinoLocError):
        downsample_sparse(a, (100, 30))


@pytest.mark.parametrize("true_d", [8.0, 12.5, 20.25])
def test_semi_global_matching_gives_the_disparity_of_a_shifted_pair(true_d):
    left, right = _pair(true_d, seed=int(true_d * 4))
    disp = compute_disparity(left, right, StereoConfig(matcher="sgbm"))
    assert disp.dtype == np.float32 and disp.shape == (H, W)
    region = np.zeros((H, W), bool)
    region[10:-10, 80:-10] = True
    region[FLAT[0].start - 10 : FLAT[0].stop + 10, FLAT[1].start - 10 : FLAT[1].stop + 10] = False
    valid = np.isfinite(disp)
    assert valid[region].mean() > 0.95
    assert np.percentile(np.abs(disp[region & valid] - true_d), 95) <= 0.5
    assert np.isnan(disp[:, : StereoConfig().num_disparities - 1]).all()  # no search range there


@pytest.mark.parametrize("true_d", [8.0, 20.0])
def test_a_downscaled_match_is_smaller_and_in_full_size_pixels(true_d):
    left, right = _pair(true_d, seed=3)
    cfg = StereoConfig(downscale=2, num_disparities=32)
    disp = compute_disparity(left, right, cfg)
    assert disp.shape == (H // 2, W // 2)
    region = np.zeros((H // 2, W // 2), bool)
    region[5:-5, 40:-5] = True
    region[FLAT[0].start // 2 - 8 : FLAT[0].stop // 2 + 8, FLAT[1].start // 2 - 8 : FLAT[1].stop // 2 + 8] = False
    valid = np.isfinite(disp)
    assert valid[region].mean() > 0.9
    # the matched disparity is true_d / 2 at half size; the map says true_d (full-size pixels)
    assert abs(np.median(disp[region & valid]) - true_d) <= 0.25
    assert np.isnan(disp[:, : cfg.num_disparities - 1]).all()

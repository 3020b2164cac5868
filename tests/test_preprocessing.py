"""Preprocessing (none / histeq / gradient) and area-averaged vectors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lino_loc.errors import LinoLocError
from lino_loc.preprocessing import preprocess, to_vector


def _img(seed: int = 0, h: int = 24, w: int = 32, hi: int = 256) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, hi, (h, w), dtype=np.uint8)


def test_none_is_grey_over_255() -> None:
    img = _img()
    out = preprocess(img, "none")
    assert out.dtype == np.float32 and out.shape == img.shape
    np.testing.assert_allclose(out, img / 255.0, rtol=1e-6)


def test_histeq_is_equalize_hist_and_ignores_monotonic_change() -> None:
    img = _img(1, hi=100)
    out = preprocess(img, "histeq")
    np.testing.assert_allclose(out, cv2.equalizeHist(img) / 255.0, rtol=1e-6)
    # a strictly increasing grey-level map (gain 2, offset 30) keeps the ranks: same result
    brighter = (2 * img.astype(np.int32) + 30).astype(np.uint8)
    np.testing.assert_allclose(preprocess(brighter, "histeq"), out, atol=1e-6)


def test_gradient_cancels_global_gain_and_offset() -> None:
    img = _img(2, hi=100)
    out = preprocess(img, "gradient")
    assert out.dtype == np.float32
    np.testing.assert_allclose(out.mean(), 1.0, rtol=1e-5)  # divided by its mean
    gain = (2 * img.astype(np.int32)).astype(np.uint8)
    offset = (img.astype(np.int32) + 100).astype(np.uint8)
    np.testing.assert_allclose(preprocess(gain, "gradient"), out, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(preprocess(offset, "gradient"), out, rtol=1e-4, atol=1e-5)
    # whereas plain grey levels change
    assert not np.allclose(preprocess(gain, "none"), preprocess(img, "none"))


def test_gradient_of_a_ramp_is_flat_inside() -> None:
    # I = 3 x: the Sobel derivative is 8 * 3 everywhere inside, so |grad| / mean is constant
    ramp = np.tile((3 * np.arange(40)).astype(np.uint8), (30, 1))
    out = preprocess(ramp, "gradient")
    inner = out[5:-5, 5:-5]
    np.testing.assert_allclose(inner, inner[0, 0], rtol=1e-5)
    assert preprocess(np.full((10, 10), 77, np.uint8), "gradient").max() == 0.0


def test_colour_is_converted_and_bad_input_rejected() -> None:
    rng = np.random.default_rng(3)
    colour = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    np.testing.assert_allclose(
        preprocess(colour, "none"), cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY) / 255.0, rtol=1e-6
    )
    with pytest.raises(LinoLocError, match="unknown method"):
        preprocess(colour, "sharpen")  # type: ignore[arg-type]
    with pytest.raises(LinoLocError, match="uint8"):
        preprocess(np.zeros((4, 4), np.float32), "none")


def test_to_vector_is_block_mean() -> None:
    img = np.random.default_rng(4).random((6, 8)).astype(np.float32)
    v = to_vector(img, (4, 3))
    assert v.shape == (12,) and v.dtype == np.float32
    blocks = img.reshape(3, 2, 4, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(v, blocks.reshape(-1), rtol=1e-6)
    np.testing.assert_array_equal(to_vector(img, (8, 6)), img.reshape(-1))

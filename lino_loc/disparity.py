"""Sparse disparity maps: block matching, depth conversion and NaN-aware downsampling.

The paper (section 5) uses a commercial stereo system whose filters leave low-texture pixels
without a value, giving a *sparse* disparity map (Fig. 2). The counterpart here is OpenCV's
block matcher (``cv2.StereoBM``) with a texture threshold, a uniqueness check, a left-right
consistency check and speckle filtering: pixels that fail any of them get no value.

Conventions of this module
- A disparity map is a float32 array in pixels of the *left* image (``d = x_left - x_right``)
  with ``NaN`` where there is no value. OpenCV's int16 output (16 x disparity, invalid =
  ``(min_disparity - 1) * 16``) never leaves :func:`compute_disparity`.
- Data sets that carry depth instead of disparity are converted with ``d = f * B / Z``
  (:func:`depth_to_disparity`), or to inverse depth ``1 / Z`` when there is no baseline
  (RGB-D data, :func:`depth_to_inverse_depth`).
- Maps work on small images (e.g. 80 x 60): :func:`downsample_sparse` averages the valid
  pixels of each block and leaves a block without a value when too few of its pixels have one.
- Two cheaper or denser variants (``StereoConfig.matcher``, ``StereoConfig.downscale``):
  semi-global matching (``cv2.StereoSGBM``, Hirschmueller 2008, what stereo cameras such as
  the OAK-D compute on the device) with the same uniqueness, left-right and speckle checks
  but no texture threshold; and matching a pair area-averaged by ``downscale`` (2: 320 x 240
  matched at 160 x 120), whose map comes out at the matched size with values in pixels of the
  full-size left image (the matched disparity times ``downscale``).

Usage::

    from lino_loc.disparity import StereoConfig, compute_disparity, downsample_sparse
    disp = compute_disparity(left, right, StereoConfig())      # (H, W) float32, NaN = none
    small = downsample_sparse(disp, (80, 60), min_valid_fraction=0.25)
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator

from lino_loc.errors import LinoLocError

FloatImage = NDArray[np.float32]

#: OpenCV's StereoBM returns disparities in fixed point with 4 fractional bits.
DISPARITY_SCALE = 16


class StereoConfig(BaseModel):
    """Settings of the block matcher (OpenCV ``StereoBM``).

    The defaults are the product's: tuned for 320 x 240 and 640 x 400 grey pairs (OAK-D
    geometry: 7.5 cm baseline, f about 440 px at 640 x 400, so 64 disparities reach
    about 0.5 m at 640 x 400 and 0.25 m at 320 x 240) and checked on the Middlebury
    "Motorcycle" pair with ``lino-loc eval stereo`` (figures in docs/results.md, 'Stereo on
    real images'; guarded by tests/test_stereo_eval.py). ``texture_threshold`` is OpenCV's:
    a sum over the window of the pre-filtered response, so it scales with ``block_size ** 2``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    num_disparities: int = Field(64, gt=0, description="disparity search range (multiple of 16)")
    min_disparity: int = Field(0, description="smallest disparity searched, pixels")
    block_size: int = Field(9, ge=5, le=255, description="matching window side (odd), pixels")
    texture_threshold: int = Field(
        10,
        ge=0,
        description="minimum texture (sum of |pre-filtered| over the window); below: no value",
    )
    uniqueness_ratio: int = Field(
        15, ge=0, le=100, description="best cost must beat the second best by this many percent"
    )
    speckle_window: int = Field(
        100, ge=0, description="connected blobs smaller than this many pixels are removed (0 = off)"
    )
    speckle_range: float = Field(
        1.0, ge=0.0, description="max disparity step inside one blob, pixels"
    )
    disp12_max_diff: int = Field(
        1, description="left-right consistency tolerance, pixels (negative = check off)"
    )
    pre_filter_type: str = Field("xsobel", description="'xsobel' or 'normalized_response'")
    pre_filter_size: int = Field(9, ge=5, le=255, description="normalized-response window (odd)")
    pre_filter_cap: int = Field(31, ge=1, le=63, description="clip of the pre-filtered image")
    matcher: Literal["bm", "sgbm"] = Field(
        "bm", description="block matching (StereoBM) or semi-global matching (StereoSGBM)"
    )
    downscale: Literal[1, 2, 4] = Field(
        1, description="match the pair area-averaged by this factor (the map comes out that much smaller)"
    )

    @field_validator("num_disparities")
    @classmethod
    def _multiple_of_16(cls, v: int) -> int:
        if v % 16:
            raise ValueError(f"num_disparities must be a multiple of 16, got {v}")
        return v

    @field_validator("block_size", "pre_filter_size")
    @classmethod
    def _odd(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"must be odd, got {v}")
        return v

    @field_validator("pre_filter_type")
    @classmethod
    def _pre_filter_type(cls, v: str) -> str:
        if v not in ("xsobel", "normalized_response"):
            raise ValueError(
                f"pre_filter_type must be 'xsobel' or 'normalized_response', got {v!r}"
            )
        return v

    @property
    def max_disparity(self) -> int:
        """Largest disparity the matcher can return, pixels."""
        return self.min_disparity + self.num_disparities - 1

    def covering(self, max_disparity: float) -> StereoConfig:
        """The same settings with ``num_disparities`` just large enough to reach ``max_disparity``."""
        if not math.isfinite(max_disparity) or max_disparity < self.min_disparity:
            raise LinoLocError(
                f"max disparity {max_disparity} must be a number >= min_disparity {self.min_disparity}"
            )
        n = int(math.floor(max_disparity)) - self.min_disparity + 1
        n = max(16, 16 * math.ceil(n / 16))
        return self.model_copy(update={"num_disparities": n})


#: Named matchers (``--stereo`` of the evaluations): the product's StereoBM at the camera's
#: size, at half size (32 disparities: the same depth range), and semi-global matching.
STEREO_PRESETS: dict[str, StereoConfig] = {
    "bm": StereoConfig(),
    "bm/2": StereoConfig(downscale=2, num_disparities=32),
    "sgbm": StereoConfig(matcher="sgbm"),
    "sgbm/2": StereoConfig(matcher="sgbm", downscale=2, num_disparities=32),
}


def _as_grey_u8(img: ArrayLike, name: str) -> NDArray[np.uint8]:
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(
            np.ascontiguousarray(a), cv2.COLOR_BGRA2GRAY if a.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        )
    if a.ndim != 2:
        raise LinoLocError(f"{name} image must be 2-D grey (or BGR), got shape {a.shape}")
    if a.dtype != np.uint8:
        raise LinoLocError(f"{name} image must be uint8, got {a.dtype}")
    return np.ascontiguousarray(a)


def create_matcher(config: StereoConfig) -> cv2.StereoMatcher:
    """An OpenCV ``StereoBM`` or ``StereoSGBM`` set up from ``config`` (speckle filtering is
    done outside). SGBM's smoothness penalties are OpenCV's suggested ``P1 = 8 b^2``,
    ``P2 = 32 b^2`` for a grey image and block side b."""
    if config.matcher == "sgbm":
        b = config.block_size
        return cv2.StereoSGBM_create(
            minDisparity=config.min_disparity, numDisparities=config.num_disparities, blockSize=b,
            P1=8 * b * b, P2=32 * b * b, disp12MaxDiff=config.disp12_max_diff,
            preFilterCap=config.pre_filter_cap, uniquenessRatio=config.uniqueness_ratio,
            speckleWindowSize=0, speckleRange=0, mode=cv2.STEREO_SGBM_MODE_SGBM,
        )
    bm = cv2.StereoBM_create(numDisparities=config.num_disparities, blockSize=config.block_size)
    bm.setMinDisparity(config.min_disparity)
    bm.setTextureThreshold(config.texture_threshold)
    bm.setUniquenessRatio(config.uniqueness_ratio)
    bm.setDisp12MaxDiff(config.disp12_max_diff)
    bm.setPreFilterType(
        cv2.STEREO_BM_PREFILTER_XSOBEL
        if config.pre_filter_type == "xsobel"
        else cv2.STEREO_BM_PREFILTER_NORMALIZED_RESPONSE
    )
    bm.setPreFilterSize(config.pre_filter_size)
    bm.setPreFilterCap(config.pre_filter_cap)
    # Speckle filtering is applied by compute_disparity with an explicit range in pixels,
    # so that its meaning does not depend on how an OpenCV version scales speckleRange.
    bm.setSpeckleWindowSize(0)
    bm.setSpeckleRange(0)
    return bm


def compute_disparity(
    left: ArrayLike, right: ArrayLike, config: StereoConfig | None = None
) -> FloatImage:
    """Sparse disparity of a rectified pair, float32 pixels of the left image, NaN = no value
    (with ``config.downscale`` s > 1: the map is (H/s, W/s), its values still in pixels of
    the full-size left image; the search range and the window are the matched image's).

    Pixels get no value where the window is not textured enough (``texture_threshold``),
    where the best match is not unique enough (``uniqueness_ratio``), where the left-right
    check fails (``disp12_max_diff``), in small isolated blobs (``speckle_window`` /
    ``speckle_range``) and in the left border the search range cannot cover. This is the
    filtered, sparse stereo of the paper's section 5.
    """
    config = config or StereoConfig()
    lu = _as_grey_u8(left, "left")
    ru = _as_grey_u8(right, "right")
    if lu.shape != ru.shape:
        raise LinoLocError(f"left and right images differ in size: {lu.shape} vs {ru.shape}")
    s = config.downscale
    if s > 1:
        size = (lu.shape[1] // s, lu.shape[0] // s)
        lu = cv2.resize(lu, size, interpolation=cv2.INTER_AREA)
        ru = cv2.resize(ru, size, interpolation=cv2.INTER_AREA)
    h, w = lu.shape
    if min(h, w) < config.block_size or w <= config.num_disparities + config.min_disparity:
        raise LinoLocError(
            f"image {w}x{h} too small for block_size {config.block_size} and "
            f"num_disparities {config.num_disparities}"
        )
    raw = create_matcher(config).compute(lu, ru)  # int16, 16 x disparity
    invalid_value = (config.min_disparity - 1) * DISPARITY_SCALE
    invalid = raw <= invalid_value
    if config.speckle_window > 0:
        raw = raw.copy()
        cv2.filterSpeckles(
            raw,
            invalid_value,
            config.speckle_window,
            int(round(config.speckle_range * DISPARITY_SCALE)),
        )
        invalid |= raw == invalid_value
    disp = raw.astype(np.float32) * np.float32(s / DISPARITY_SCALE)
    disp[invalid] = np.nan
    return disp


def depth_to_disparity(depth_m: ArrayLike, fx: float, baseline_m: float) -> FloatImage:
    """Disparity ``d = f * B / Z`` in pixels from depth in metres; NaN where Z is missing or <= 0."""
    if not (fx > 0 and baseline_m > 0):
        raise LinoLocError(f"fx ({fx}) and baseline_m ({baseline_m}) must be positive")
    z = np.asarray(depth_m, dtype=np.float64)
    out = np.full(z.shape, np.nan, dtype=np.float32)
    ok = np.isfinite(z) & (z > 0)
    out[ok] = (fx * baseline_m / z[ok]).astype(np.float32)
    return out


def depth_to_inverse_depth(depth_m: ArrayLike) -> FloatImage:
    """Inverse depth ``1 / Z`` in 1/m (disparity up to the unknown factor f*B); NaN where missing."""
    z = np.asarray(depth_m, dtype=np.float64)
    out = np.full(z.shape, np.nan, dtype=np.float32)
    ok = np.isfinite(z) & (z > 0)
    out[ok] = (1.0 / z[ok]).astype(np.float32)
    return out


def downsample_sparse(
    disp: ArrayLike, size: tuple[int, int], min_valid_fraction: float = 0.25
) -> FloatImage:
    """NaN-aware area downsampling of a sparse map to ``size = (width, height)``.

    Each output pixel is the mean of the *valid* (finite) input pixels of its block (area
    weights when the factor is not an integer, as ``cv2.INTER_AREA``), and NaN when the valid
    share of the block is below ``min_valid_fraction`` (a block with no valid pixel is always
    NaN). Works on (H, W) or (..., H, W) stacks.
    """
    a = np.asarray(disp, dtype=np.float32)
    if a.ndim < 2:
        raise LinoLocError(f"downsample_sparse needs a 2-D map, got shape {a.shape}")
    out_w, out_h = int(size[0]), int(size[1])
    h, w = a.shape[-2:]
    if not (0 < out_w <= w and 0 < out_h <= h):
        raise LinoLocError(f"downsample size {out_w}x{out_h} must be within the map size {w}x{h}")
    if not 0.0 <= min_valid_fraction <= 1.0:
        raise LinoLocError(f"min_valid_fraction must be in [0, 1], got {min_valid_fraction}")
    valid = np.isfinite(a)
    vals = np.where(valid, a, 0.0).astype(np.float32)
    frac = valid.astype(np.float32)
    lead = a.shape[:-2]
    vals = vals.reshape((-1, h, w))
    frac = frac.reshape((-1, h, w))
    # OpenCV's area interpolation: exact area-weighted block averages when shrinking
    # (faster and steadier than BLAS products for small images on a busy machine).
    s = np.stack([cv2.resize(v, (out_w, out_h), interpolation=cv2.INTER_AREA) for v in vals])
    c = np.stack([cv2.resize(f, (out_w, out_h), interpolation=cv2.INTER_AREA) for f in frac])
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s / c  # mean of the valid pixels (area weights)
    ok = (c > 1e-6) & (c >= min_valid_fraction - 1e-6)
    return np.where(ok, mean, np.nan).astype(np.float32).reshape(lead + (out_h, out_w))

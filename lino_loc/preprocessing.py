"""Image preprocessing before PCA: the ``z`` of eq. 1 is ``to_vector(preprocess(image))``.

The paper (section 6.2, Table 1) compares three treatments of the intensity image against
changes of illumination:

``none``
    grey levels scaled to [0, 1] (``image / 255``). Sensitive to any change of light.
``histeq``
    ``cv2.equalizeHist`` then ``/ 255``: the grey-level histogram is flattened, which
    cancels any monotonic global change of brightness/contrast (gain, offset, gamma) but
    not a change in *where* the light comes from.
``gradient``
    the gradient-based filter: the image is blurred by a Gaussian (sigma = 1 px, to keep
    the derivative from amplifying sensor noise), the Sobel derivatives give the gradient
    magnitude ``|grad I|``, and that is divided by its mean over the image. A global gain
    ``I -> g I`` multiplies ``|grad I|`` by ``g`` and so cancels in the ratio; a global offset
    has no gradient at all. A flat image (mean gradient 0) maps to zeros.

All three return float32 at the input resolution; :func:`to_vector` then area-averages to
the map's working size (w, h) and flattens, so preprocessing sees the full-resolution image
(the gradient is computed before the information is averaged away).

Sparse maps (disparity, NaN = no value) are area-averaged over their valid pixels only by
``lino_loc.disparity.downsample_sparse`` instead.
"""

from __future__ import annotations

from typing import Literal, get_args

import cv2
import numpy as np

from lino_loc.errors import LinoLocError

Preprocess = Literal["none", "histeq", "gradient"]
PREPROCESS_METHODS: tuple[str, ...] = get_args(Preprocess)


def _grey_u8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        else:
            raise LinoLocError(f"image: cannot convert {img.shape} to grey")
    if img.ndim != 2:
        raise LinoLocError(f"image: expected a 2-D grey or HxWx3 image, got shape {img.shape}")
    if img.dtype != np.uint8:
        raise LinoLocError(f"image: expected uint8 grey levels, got {img.dtype}")
    return img


def preprocess(image: np.ndarray, method: Preprocess) -> np.ndarray:
    """Preprocess a uint8 image (grey, or BGR converted to grey) -> float32, same size.

    See the module docstring for what each method does and why. LinoLocError for an unknown
    ``method``.
    """
    img = _grey_u8(image)
    if method == "none":
        return img.astype(np.float32) * np.float32(1.0 / 255.0)
    if method == "histeq":
        return cv2.equalizeHist(img).astype(np.float32) * np.float32(1.0 / 255.0)
    if method == "gradient":
        f = cv2.GaussianBlur(img.astype(np.float32), (0, 0), sigmaX=1.0, sigmaY=1.0,
                             borderType=cv2.BORDER_REFLECT_101)
        gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT_101)
        gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT_101)
        mag = cv2.magnitude(gx, gy)
        mean = float(mag.mean())
        if mean <= 1e-12:
            return np.zeros_like(mag)
        return mag * np.float32(1.0 / mean)
    raise LinoLocError(f"preprocess: unknown method {method!r} (choose from {', '.join(PREPROCESS_METHODS)})")


def to_vector(image_f32: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Area-average (``cv2.INTER_AREA``) to ``size = (w, h)`` and flatten row-major -> (w*h,)
    float32; an image already of that size is only flattened."""
    w, h = int(size[0]), int(size[1])
    img = np.asarray(image_f32, dtype=np.float32)
    if img.shape[:2] != (h, w):
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img, dtype=np.float32).reshape(-1)


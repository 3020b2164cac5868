"""Lossless image encodings of a recording: the camera image as PNG, the disparity map as
16-bit integers with a scale.

Lossless because a replay must give the filter the very pixels the service saw (a JPEG would
change the features of eq. 1 and so the poses); PNG of an 8-bit grey 320 x 240 image is about
half its raw size and is drawn by every image viewer (Foxglove's Image panel among them).

Disparity (float32 pixels, NaN = no value, ``drivers.interfaces.StereoFrame``) becomes
``16UC1`` with ``v = d * DISPARITY_SCALE`` and ``v = 0`` for no value: exact for the block
matcher's 1/16-pixel steps (OpenCV stores 16 x disparity) and the OAK-D's subpixel steps up
to 5 fractional bits, for disparities in (0, 65535 / DISPARITY_SCALE] = (0, 2048) pixels.
A map with any other value (a disparity of exactly 0, a negative one, a finer step, larger)
is stored as ``32FC1`` float32 instead, NaN kept: the decoder reads both
(:func:`decode_disparity`), so the replay always gets the service's values bit for bit.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from lino_loc.errors import LinoLocError

#: Disparity units per pixel in a 16UC1 disparity image (1/32 pixel steps).
DISPARITY_SCALE = 32.0
#: PNG compression (OpenCV's level 0-9 and zlib strategy): level 1 with Huffman coding only
#: is the fastest and the smallest of those tried on the simulated camera's 320 x 240 images
#: (about 3 ms and 35 kB a frame, against 5-8 ms and 42 kB for levels 1-3 with the default
#: strategy; benchmarks/bench_recording.py measures the whole recorder).
PNG_PARAMS = (cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY)


def encode_png(image: NDArray[np.uint8]) -> bytes:
    """PNG bytes of an 8- or 16-bit grey (H, W) or colour (H, W, 3) image (OpenCV's encoder);
    LinoLocError for another type (PNG would not hold it exactly)."""
    if image.dtype not in (np.uint8, np.uint16):
        raise LinoLocError(f"a camera image of type {image.dtype} has no lossless PNG (uint8 or uint16)")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image), list(PNG_PARAMS))
    if not ok:
        raise LinoLocError(f"PNG encoding failed for an image of shape {image.shape}")
    return buf.tobytes()


def decode_png(data: bytes) -> NDArray[np.uint8]:
    """The image of PNG bytes, as stored (grey stays (H, W))."""
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise LinoLocError("a /camera/image message is not a PNG image")
    return img


def encode_disparity(disp: NDArray[np.float32]) -> tuple[str, int, bytes]:
    """(encoding, step in bytes, data) of a disparity map (module docstring)."""
    d = np.asarray(disp, dtype=np.float32)
    h, w = d.shape
    valid = np.isfinite(d)
    scaled = np.where(valid, d * np.float32(DISPARITY_SCALE), np.float32(0))
    v = np.rint(scaled)
    exact = bool(np.all(v == scaled)) and bool(np.all((v[valid] >= 1) & (v[valid] <= 65535)))
    if exact:
        return "16UC1", 2 * w, v.astype("<u2").tobytes()
    return "32FC1", 4 * w, d.astype("<f4").tobytes()


def decode_disparity(encoding: str, width: int, height: int, data: bytes) -> NDArray[np.float32]:
    """The float32 disparity map (NaN = no value) of a /camera/disparity message."""
    if encoding == "16UC1":
        v = np.frombuffer(data, dtype="<u2").reshape(height, width)
        out = v.astype(np.float32) / np.float32(DISPARITY_SCALE)
        out[v == 0] = np.nan
        return out
    if encoding == "32FC1":
        return np.frombuffer(data, dtype="<f4").reshape(height, width).astype(np.float32)
    raise LinoLocError(f"a /camera/disparity message has encoding {encoding!r} (16UC1 or 32FC1)")

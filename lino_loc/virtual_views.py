"""Virtual map views: what the camera would have seen after turning on the spot.

The paper maps every 75 cm and every 15 deg. An image taken off that grid is, at best,
7.5 deg away in heading from every map image, and with a 70 deg lens a 7.5 deg turn shifts the
picture by a tenth of its width: for global (PCA) features that is a larger change than moving
the robot 30 cm sideways, which shifts the picture the same way. The nearest map images of an
off-grid view are therefore often those of the NEIGHBOURING grid position at a compensating
heading, and the sensor model (kernels at the map poses, as in eq. 8) puts its weight one cell
off. Completing the map by virtual headings reduces that bias (the measured effect on single
views and on active localization is in docs/results.md, 'Virtual headings').

A turn of the camera about its optical centre needs no depth: image points move by the
homography (Hartley & Zisserman, Multiple View Geometry, 2nd ed., eq. 8.8 / result 8.12)

    p' ~ K R(delta)^T K^-1 p,

with K the intrinsics at the working size and R(delta) the yaw of the camera by ``delta``
(REP-103: positive = to the left). From every map image the map builder makes views at
headings theta + delta for the offsets in ``deltas`` (e.g. -6, -3, 0, 3, 6 deg between 15 deg
map headings: a map every 3 deg from the same images). The columns a turn brings in from
outside the field of view are unknown, so every channel vector (map and live images alike) is
cropped by the ``margin`` columns that the largest offset can bring in; the rows stay.

Disparity turns with the rig too: a point at depth Z seen at pixel p has depth
Z' = Z (R^T K^-1 p)_z in the turned camera, so its disparity f B / Z becomes
d' = d / (R^T K^-1 p)_z before it is moved to p' (nearest pixel: disparities are not blended,
missing values stay NaN).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from lino_loc.errors import LinoLocError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class VirtualHeadings:
    """How a map's images are turned: ``K`` (3, 3) at the working size, the heading
    ``offsets`` (radians) and the ``margin`` columns cropped each side of every vector."""

    K: FloatArray
    offsets: tuple[float, ...]
    margin: int

    @classmethod
    def for_camera(
        cls, fx: float, fy: float, cx: float, cy: float, camera_size: tuple[int, int], size: tuple[int, int],
        offsets: Sequence[float],
    ) -> VirtualHeadings:
        """The virtual headings of a camera with intrinsics (fx, fy, cx, cy) at camera_size = (W, H)
        used at the working size = (w, h): K scaled by :func:`scaled_intrinsics`, the margin
        that the largest |offset| needs (:func:`margin_columns`). LinoLocError without offsets.
        """
        K = scaled_intrinsics(fx, fy, cx, cy, camera_size, size)
        d = tuple(float(x) for x in offsets)
        if not d:
            raise LinoLocError("virtual headings: no offsets given")
        return cls(K, d, margin_columns(K, int(size[0]), max(abs(x) for x in d)))

    def params(self) -> dict[str, int | str]:
        """What a map header keeps: ``margin`` and ``virtual_offsets_deg`` ("-6,-3,0,3,6")."""
        return {"margin": self.margin, "virtual_offsets_deg": ",".join(f"{math.degrees(x):.6g}" for x in self.offsets)}


def scaled_intrinsics(
    fx: float, fy: float, cx: float, cy: float, camera_size: tuple[int, int], size: tuple[int, int]
) -> FloatArray:
    """K (3, 3) of the camera at the working size ``size = (w, h)`` of an area-averaged image
    (pixel centres: u_w + 0.5 = (u + 0.5) w / W)."""
    sx, sy = size[0] / camera_size[0], size[1] / camera_size[1]
    return np.array(
        [[fx * sx, 0.0, (cx + 0.5) * sx - 0.5], [0.0, fy * sy, (cy + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]]
    )


def _turn(delta: float) -> FloatArray:
    """R^T for a camera yaw of ``delta`` (left positive) in camera axes (x right, y down,
    z forward): a world direction at azimuth a appears at azimuth a - delta."""
    c, s = math.cos(delta), math.sin(delta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def yaw_homography(K: FloatArray, delta: float) -> FloatArray:
    """H = K R^T K^-1 (3, 3): pixel of the map image -> pixel of the view turned by ``delta``."""
    return K @ _turn(delta) @ np.linalg.inv(K)


def margin_columns(K: FloatArray, width: int, max_delta: float) -> int:
    """Columns (each side) that a turn of up to ``max_delta`` (either way) brings in from
    outside the image, rounded up."""
    if max_delta <= 0.0:
        return 0
    fx, cx = K[0, 0], K[0, 2]
    edges = abs(math.atan((width - 1 - cx) / fx)), abs(math.atan(cx / fx))
    if max_delta >= min(edges):
        raise LinoLocError(f"virtual headings: a turn of {math.degrees(max_delta):.1f} deg leaves the field of view")
    # a column of the turned view at azimuth a (from the axis) shows azimuth a +- delta of the
    # map image: unknown where |a| > edge - delta, a strip f (tan edge - tan(edge - delta)) wide
    shift = max(fx * (math.tan(e) - math.tan(e - max_delta)) for e in edges)
    m = int(math.ceil(shift - 1e-9))
    if 2 * m >= width - 1:
        raise LinoLocError(f"virtual headings: a turn of {math.degrees(max_delta):.1f} deg leaves no columns to compare")
    return m


def turn_image(image: np.ndarray, K: FloatArray, delta: float) -> np.ndarray:
    """The view of ``image`` (h, w) float after a camera yaw of ``delta`` (bilinear; columns
    from outside the field of view replicate the border and must be cropped)."""
    h, w = image.shape
    return cv2.warpPerspective(
        np.asarray(image, dtype=np.float32), yaw_homography(K, delta), (w, h),
        flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE,
    )


def turn_disparity(disparity: np.ndarray, K: FloatArray, delta: float) -> np.ndarray:
    """The disparity map (h, w, NaN = none) of the turned view: d' = d / (R^T K^-1 p)_z moved
    to p' = K R^T K^-1 p, nearest pixel; NaN where nothing maps."""
    h, w = disparity.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    z = (_turn(delta) @ rays)[2].reshape(h, w)
    scaled = (np.asarray(disparity, dtype=np.float64) / z).astype(np.float32)
    # inverse map: for every target pixel, its source pixel (nearest), NaN outside
    out = cv2.warpPerspective(
        scaled, yaw_homography(K, delta), (w, h), flags=cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"),
    )
    return out


def crop_columns(X: np.ndarray, size: tuple[int, int], margin: int) -> np.ndarray:
    """Rows of ``X`` (..., w*h) as images of ``size = (w, h)`` without ``margin`` columns on
    each side, flattened again -> (..., (w - 2 margin) * h), contiguous."""
    if margin == 0:
        return X
    w, h = int(size[0]), int(size[1])
    lead = X.shape[:-1]
    img = X.reshape(*lead, h, w)[..., margin : w - margin]
    return np.ascontiguousarray(img).reshape(*lead, h * (w - 2 * margin))


def augment_vectors(
    X: np.ndarray,
    size: tuple[int, int],
    K: FloatArray,
    deltas: Sequence[float],
    margin: int,
    *,
    disparity: bool = False,
) -> np.ndarray:
    """Map vectors ``X`` (N, w*h) -> cropped vectors (N*V, (w - 2 margin) * h) of the V virtual
    headings theta + delta (image-major: rows i*V .. i*V+V-1 are image i, in the order of
    ``deltas``). ``disparity``: the rows are sparse disparity (see :func:`turn_disparity`)."""
    w, h = int(size[0]), int(size[1])
    d = [float(x) for x in deltas]
    if not d:
        raise LinoLocError("virtual headings: no offsets given")
    n = X.shape[0]
    out = np.empty((n, len(d), h * (w - 2 * margin)), dtype=np.float32)
    for i in range(n):
        img = X[i].reshape(h, w)
        for k, delta in enumerate(d):
            if delta == 0.0:
                view = img
            elif disparity:
                view = turn_disparity(img, K, delta)
            else:
                view = turn_image(img, K, delta)
            out[i, k] = view[:, margin : w - margin].reshape(-1)
    return out.reshape(n * len(d), -1)


def augment_poses(poses: np.ndarray, deltas: Sequence[float]) -> FloatArray:
    """Poses (N*V, 3) matching :func:`augment_vectors`: theta + delta, wrapped to (-pi, pi]."""
    d = np.asarray(deltas, dtype=np.float64)
    P = np.repeat(np.asarray(poses, dtype=np.float64).reshape(-1, 3), d.size, axis=0)
    P[:, 2] = np.angle(np.exp(1j * (P[:, 2] + np.tile(d, P.shape[0] // max(d.size, 1)))))
    return P


def offsets(step: float, count: int) -> FloatArray:
    """``count`` heading offsets ``step`` apart, centred on 0 (count odd keeps the real view):
    offsets(3 deg, 5) = -6, -3, 0, 3, 6 deg."""
    if count < 1 or step < 0.0:
        raise LinoLocError(f"virtual headings: need count >= 1 and step >= 0 (got {count}, {step})")
    return step * (np.arange(count, dtype=np.float64) - (count - 1) / 2.0)

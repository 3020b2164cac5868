"""Virtual translations: a survey view as seen from a nearby floor position.

Virtual headings (:mod:`lino_loc.virtual_views`) synthesize turned views exactly; a view from
another position needs the scene's depth. Here the depth is the one a robot's survey has, the
sparse stereo disparity of the view (:func:`lino_loc.disparity.compute_disparity`): filled
where the matcher gave no value by its nearest valid neighbour, then every pixel is moved as a
3-D point of the pinhole model (forward warping with a z-buffer, the nearest surface wins):

    X = (u - cx) Z / fx,  Y = (v - cy) Z / fy,  (X', Z') = (X - r, Z - f),
    u' = fx X' / Z' + cx,  v' = fy Y / Z' + cy

for a camera moved ``r`` metres to its right and ``f`` forward at the same height and heading
(the robot moves on the floor; camera frame x right, y down, z forward). Target pixels no
source pixel lands on (disocclusions, the border a forward or sideways move uncovers) are NaN.
A survey holds more than one view per position: the borders a move uncovers were seen by the
views at the neighbouring headings, which are warped the same way into the moved camera (a
camera also turned by the heading difference, ``turn`` to the left:
``X' = cos(turn) (X - r) + sin(turn) (Z - f)``, ``Z' = cos(turn) (Z - f) - sin(turn) (X - r)``)
and fill the holes they cover; what no view saw is filled by the nearest landed pixel.

The paper's ref. [8] (Murase & Nayar) interpolates the appearance manifold between sampled
poses; this is the geometric alternative the depth channel makes possible.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import distance_transform_edt

from lino_loc.errors import LinoLocError
from lino_loc.poses import wrap_angle

FloatImage = NDArray[np.float32]


def fill_nearest(sparse: ArrayLike) -> FloatImage:
    """A sparse map (NaN = no value) with every NaN replaced by its nearest valid value
    (Euclidean pixel distance, ties as ``scipy.ndimage.distance_transform_edt`` breaks them).
    LinoLocError when no value is valid."""
    a = np.asarray(sparse, dtype=np.float32)
    missing = ~np.isfinite(a)
    if missing.all():
        raise LinoLocError("fill_nearest: the map has no valid value")
    if not missing.any():
        return a.copy()
    idx = distance_transform_edt(missing, return_distances=False, return_indices=True)
    return a[tuple(idx)]


def dense_depth(disparity: ArrayLike, shape: tuple[int, int], fx: float, baseline_m: float,
                max_depth_m: float = 20.0) -> FloatImage:
    """Depth (metres) at every pixel of an image of ``shape = (height, width)`` from a sparse
    disparity map of any size whose values are pixels of that image (``compute_disparity``,
    ``downsample_sparse`` keep them so): holes filled by :func:`fill_nearest`, resized
    bilinearly, ``Z = fx B / d``, clipped to ``max_depth_m`` (zero or negative disparity)."""
    if not (fx > 0 and baseline_m > 0):
        raise LinoLocError(f"dense_depth: fx ({fx}) and baseline_m ({baseline_m}) must be positive")
    d = fill_nearest(disparity)
    h, w = int(shape[0]), int(shape[1])
    if d.shape != (h, w):
        d = cv2.resize(d, (w, h), interpolation=cv2.INTER_LINEAR)
    z = np.full(d.shape, max_depth_m, dtype=np.float32)
    ok = d > fx * baseline_m / max_depth_m
    z[ok] = (fx * baseline_m / d[ok]).astype(np.float32)
    return z


def _forward_project(depth: ArrayLike, intrinsics: tuple[float, float, float, float], right_m: float,
                     forward_m: float, min_depth_m: float, turn: float = 0.0, into: np.ndarray | None = None,
                     ) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatImage]:
    """The pinhole forward projection of the module docstring with a z-buffer: for every target
    pixel some source pixel lands on, the flat index of the nearest such source pixel, the
    target's flat index and the point's depth in the moved camera. ``turn`` (rad, REP-103: to
    the left) turns the moved camera about the vertical axis: ``X' = cos(turn) (X - r) +
    sin(turn) (Z - f)``, ``Z' = cos(turn) (Z - f) - sin(turn) (X - r)``. ``into`` (H * W bool):
    only the target pixels it marks are filled. Pixels of non-finite depth do not move."""
    z = np.asarray(depth, dtype=np.float64)
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    h, w = z.shape
    v, u = np.mgrid[0:h, 0:w]
    x = (u - cx) * z / fx - right_m
    zf = z - forward_m
    c, s = math.cos(turn), math.sin(turn)
    x2, z2 = (x, zf) if turn == 0.0 else (c * x + s * zf, c * zf - s * x)
    keep = np.flatnonzero(np.isfinite(z2) & (z2 > min_depth_m))
    zk, z2k = z.ravel()[keep], z2.ravel()[keep]
    u2 = np.rint(fx * x2.ravel()[keep] / z2k + cx).astype(np.int64)
    v2 = np.rint(fy * ((v.ravel()[keep] - cy) * zk / fy) / z2k + cy).astype(np.int64)
    inside = (u2 >= 0) & (u2 < w) & (v2 >= 0) & (v2 < h)
    if into is not None:
        inside[inside] = np.asarray(into, dtype=bool).ravel()[(v2 * w + u2)[inside]]
    source, target, depth2 = keep[inside], (v2 * w + u2)[inside], z2k[inside]
    if target.size == 0:
        return source, target, depth2.astype(np.float32)
    # z-buffer: by target pixel, nearest first (the depths, all > 0, scaled into (0, 1/2] of a
    # pixel index; one stable sort instead of a two-key lexsort), the first of each pixel kept
    order = np.argsort(target + depth2 / (2.0 * float(depth2.max())), kind="stable")
    ranked = target[order]
    first = order[np.concatenate(([True], ranked[1:] != ranked[:-1]))]
    return source[first], target[first], depth2[first].astype(np.float32)


def warp(image: ArrayLike, depth: ArrayLike, intrinsics: tuple[float, float, float, float],
         right_m: float, forward_m: float, min_depth_m: float = 0.05, turn: float = 0.0,
         into: np.ndarray | None = None) -> FloatImage:
    """The view of a camera moved ``right_m`` to its right and ``forward_m`` forward, and
    turned ``turn`` radians to the left (see the module docstring): ``image`` (H, W) and its
    ``depth`` (H, W) metres, ``intrinsics`` (fx, fy, cx, cy) pixels. Float32 (H, W), NaN where
    nothing lands (or that ``into``, an (H, W) bool mask, leaves out). Points that end less than
    ``min_depth_m`` in front of the moved camera are dropped."""
    img = np.asarray(image, dtype=np.float32)
    z = np.asarray(depth, dtype=np.float64)
    if img.shape != z.shape or img.ndim != 2:
        raise LinoLocError(f"warp: image {img.shape} and depth {z.shape} must be the same 2-D shape")
    source, target, _ = _forward_project(z, intrinsics, right_m, forward_m, min_depth_m, turn, into)
    out = np.full(img.size, np.nan, dtype=np.float32)
    out[target] = img.ravel()[source]
    return out.reshape(img.shape)


def scaled_intrinsics(intrinsics: tuple[float, float, float, float], image_shape: tuple[int, int],
                      shape: tuple[int, int]) -> tuple[float, float, float, float]:
    """The intrinsics (fx, fy, cx, cy) of an image of ``image_shape`` (height, width) expressed
    in the pixels of an area-resampled map of ``shape`` (height, width): f scaled by the size
    ratio, and the principal point mapped between pixel centres, c' = (c + 1/2) s - 1/2."""
    sy, sx = shape[0] / image_shape[0], shape[1] / image_shape[1]
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5


def warp_disparity(disparity: ArrayLike, intrinsics: tuple[float, float, float, float], fx_baseline: float,
                   right_m: float, forward_m: float, min_depth_m: float = 0.05) -> FloatImage:
    """The sparse disparity map a camera moved ``right_m`` to its right and ``forward_m``
    forward would measure, from the one measured here (NaN = no value): every valid pixel is
    the 3-D point at ``Z = fx_baseline / d`` (``fx_baseline`` = f B in the disparity's units,
    pixels of the full image times metres), moved as :func:`warp` moves it (``intrinsics`` in
    the map's own pixels, :func:`scaled_intrinsics`), and gets the disparity ``fx_baseline /
    Z'`` of its new depth. Target pixels no valid point lands on stay NaN (missing data, as
    the stereo matcher's holes are)."""
    d = np.asarray(disparity, dtype=np.float64)
    if d.ndim != 2:
        raise LinoLocError(f"warp_disparity: the disparity map must be 2-D, got shape {d.shape}")
    if not fx_baseline > 0:
        raise LinoLocError(f"warp_disparity: fx_baseline ({fx_baseline}) must be positive")
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(np.isfinite(d) & (d > 0), fx_baseline / d, np.nan)
    _, target, depth2 = _forward_project(z, intrinsics, right_m, forward_m, min_depth_m)
    out = np.full(d.size, np.nan, dtype=np.float32)
    out[target] = (fx_baseline / depth2.astype(np.float64)).astype(np.float32)
    return out.reshape(d.shape)


def camera_move(dx: float, dy: float, heading: float) -> tuple[float, float]:
    """A floor displacement (dx, dy) in the world frame (REP-103: x forward of the map, y left)
    as (right, forward) of a camera whose optical axis points at ``heading`` (rad)."""
    c, s = math.cos(heading), math.sin(heading)
    forward = dx * c + dy * s
    left = -dx * s + dy * c
    return -left, forward


def translate_view(image: ArrayLike, depth: ArrayLike, intrinsics: tuple[float, float, float, float],
                   pose: ArrayLike, target: ArrayLike,
                   others: Sequence[tuple[ArrayLike, ArrayLike, ArrayLike]] = ()) -> FloatImage | None:
    """The view of a robot at ``pose`` (x, y, theta) with its ``depth`` (metres, every pixel),
    as seen from the floor position ``target`` (x, y, ...) at the same heading: :func:`warp` by
    :func:`camera_move`. Its holes are filled, in order, from ``others``, views (image, depth,
    pose) taken near ``pose`` at other headings warped to the same camera (a move uncovers the
    image's borders, which a turned view of the same place saw), then by :func:`fill_nearest`;
    None when nothing of ``image`` lands."""
    p = np.asarray(pose, dtype=np.float64)
    t = np.asarray(target, dtype=np.float64)
    right, forward = camera_move(float(t[0] - p[0]), float(t[1] - p[1]), float(p[2]))
    view = warp(image, depth, intrinsics, right, forward)
    if not np.isfinite(view).any():
        return None
    for o_image, o_depth, o_pose in others:
        holes = ~np.isfinite(view)
        if not holes.any():
            break
        q = np.asarray(o_pose, dtype=np.float64)
        r, f = camera_move(float(t[0] - q[0]), float(t[1] - q[1]), float(q[2]))
        moved = warp(o_image, o_depth, intrinsics, r, f, turn=float(wrap_angle(p[2] - q[2])), into=holes)
        view[holes] = moved[holes]
    return fill_nearest(view)


def heading_neighbours(poses: ArrayLike, max_turn: float = math.radians(45.0),
                       tolerance_m: float = 0.01, labels: Sequence[object] | None = None) -> list[tuple[int, ...]]:
    """For every pose (N, 3), the indices of the poses at the same floor position (their x and
    y rounded to ``tolerance_m``) and with the same label (e.g. the light a row was taken under;
    default: all alike) whose heading is the nearest on its left and on its right, each at most
    ``max_turn`` away (nearest first, ties to the lower index; fewer where the survey has
    none): the views :func:`translate_view` fills a moved view's uncovered borders from."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if labels is not None and len(labels) != p.shape[0]:
        raise LinoLocError(f"heading_neighbours: {len(labels)} labels for {p.shape[0]} poses")
    label = (np.zeros(p.shape[0], dtype=np.int64) if labels is None
             else np.unique(np.asarray([str(v) for v in labels]), return_inverse=True)[1].reshape(-1))
    key = np.column_stack([np.round(p[:, :2] / tolerance_m), label])
    _, group, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    group = group.reshape(-1)
    members = np.split(np.argsort(group, kind="stable"), np.cumsum(count)[:-1])  # each group's rows, ascending
    out: list[tuple[int, ...]] = []
    for i in range(p.shape[0]):
        same = members[int(group[i])]
        d = wrap_angle(p[same, 2] - p[i, 2])
        picks: list[tuple[float, int]] = []
        for side in (d > 1e-9, d < -1e-9):
            cand = np.flatnonzero(side & (np.abs(d) <= max_turn))
            if cand.size:
                k = cand[np.lexsort((same[cand], np.abs(d[cand])))[0]]
                picks.append((abs(float(d[k])), int(same[k])))
        out.append(tuple(k for _, k in sorted(picks)))
    return out


def as_uint8(view: ArrayLike) -> NDArray[np.uint8]:
    """A synthesized view in the camera's type: rounded to the nearest grey level, clipped to
    [0, 255] (holes must have been filled)."""
    return np.clip(np.rint(np.asarray(view, dtype=np.float32)), 0, 255).astype(np.uint8)


def lattice_offsets(step: float, refinement: int) -> NDArray[np.float64]:
    """Floor offsets (K, 2), K = refinement^2, of the lattice of spacing ``step / refinement``
    inside one survey cell: ``(i, j) step / refinement`` for i, j in -(m-1)/2 .. (m-1)/2. The
    refinement m is odd, so every offset lies inside the cell and none on its border (which
    section 6.1's criterion would count right for either neighbour); (0, 0) comes first."""
    m = int(refinement)
    if m < 1 or m % 2 == 0:
        raise LinoLocError(f"virtual translations: the refinement must be odd and positive (got {refinement})")
    k = np.arange(m) - (m - 1) // 2
    gi, gj = np.meshgrid(k, k, indexing="ij")
    off = np.column_stack([gi.ravel(), gj.ravel()]).astype(np.float64) * (step / m)
    return off[np.argsort(np.hypot(off[:, 0], off[:, 1]), kind="stable")]


@dataclass(frozen=True)
class TranslatedSurvey:
    """A survey seen from the lattice of its cells (:func:`translate_survey`): the views (M, H, W)
    float32, or the transform of each; their sparse disparity maps (M, h, w) float32, NaN = no
    value; their robot poses (M, 3); how many views fell back to the survey view."""

    images: np.ndarray
    disparities: FloatImage
    poses: NDArray[np.float64]
    fallbacks: int


def translate_survey(greys: ArrayLike, disparities: ArrayLike, poses: ArrayLike,
                     intrinsics: tuple[float, float, float, float], baseline_m: float, step: float,
                     refinement: int, keep: Callable[[NDArray[np.float64]], NDArray[np.bool_]] | None = None,
                     transform: Callable[[FloatImage], np.ndarray] | None = None,
                     neighbours: Sequence[Sequence[tuple[ArrayLike, ArrayLike, ArrayLike]]] | None = None,
                     ) -> TranslatedSurvey:
    """Every survey view (``greys`` (N, H, W), its sparse disparity (N, h, w) in pixels of the
    grey image, its robot pose (N, 3)) seen from each :func:`lattice_offsets` of its cell, same
    heading: the real view at offset (0, 0), virtual translations elsewhere (their holes filled
    as the next paragraph says), and beside each its disparity map, moved by
    :func:`warp_disparity` (its holes left as holes). ``keep(xy)`` (M, 2) -> bool (M,) drops
    positions (e.g. not free); the offsets kept depend on the position alone, so every lattice
    position holds the same headings as its survey position (the map stays a product grid of
    positions x headings, which the action evaluation's fast path needs). Where a view cannot
    be warped (its disparity has no value, or nothing lands in the moved camera) the survey
    view and its disparity stand for it, as in a map without translations.

    A moved view's holes (the borders a move uncovers) are filled from the survey's views at
    the same position and the nearest headings (:func:`translate_view`'s ``others``, each
    warped with its own disparity's depth), the rest by :func:`fill_nearest`. Per image,
    ``neighbours`` gives those views as (grey, disparity, pose); by default they are those of
    :func:`heading_neighbours` among the images given.

    With ``transform``, ``transform(image)`` of each view is kept (e.g. the map's working
    vector), so the full-size views are never all held."""
    g = np.asarray(greys)
    d = np.asarray(disparities, dtype=np.float32)
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if not (g.shape[0] == d.shape[0] == p.shape[0]):
        raise LinoLocError(f"translate_survey: {g.shape[0]} images, {d.shape[0]} disparity maps, {p.shape[0]} poses")
    offsets = lattice_offsets(step, refinement)
    images: list[np.ndarray] = []
    disps: list[np.ndarray] = []
    out_poses: list[np.ndarray] = []
    fallbacks = 0
    keep_as = transform or (lambda im: im)
    if neighbours is None:
        neighbours = [[(g[k], d[k], p[k]) for k in near] for near in heading_neighbours(p)]
    elif len(neighbours) != p.shape[0]:
        raise LinoLocError(f"translate_survey: {len(neighbours)} neighbour lists for {p.shape[0]} images")
    for img, disp, pose, near in zip(g, d, p, neighbours, strict=True):
        targets = np.column_stack([pose[0] + offsets[:, 0], pose[1] + offsets[:, 1], np.full(len(offsets), pose[2])])
        ok = np.ones(len(targets), dtype=bool) if keep is None else np.asarray(keep(targets[:, :2]), dtype=bool)
        source = keep_as(np.asarray(img, dtype=np.float32))
        images.append(source)
        disps.append(disp)
        out_poses.append(targets[0])
        moved_to = targets[1:][ok[1:]]
        for t, moved in zip(moved_to, _moved_views(img, disp, pose, moved_to, near, intrinsics, baseline_m),
                            strict=True):
            if moved is None:
                fallbacks += 1
                images.append(source)
                disps.append(disp)
            else:
                images.append(keep_as(moved[0]))
                disps.append(moved[1])
            out_poses.append(t)
    return TranslatedSurvey(np.asarray(images), np.asarray(disps, dtype=np.float32), np.asarray(out_poses), fallbacks)


def _moved_views(img: np.ndarray, disp: np.ndarray, pose: np.ndarray, targets: np.ndarray,
                 near: Sequence[tuple[ArrayLike, ArrayLike, ArrayLike]], intrinsics: tuple[float, float, float, float],
                 baseline_m: float) -> list[tuple[FloatImage, FloatImage] | None]:
    """:func:`translate_survey` for one survey view: per target its (view, moved disparity), or
    None where it cannot be warped."""
    out: list[tuple[FloatImage, FloatImage] | None] = []
    if targets.shape[0] == 0:
        return out
    if not np.isfinite(disp).any():  # no depth: every target falls back to the survey view
        return [None] * targets.shape[0]
    depth = dense_depth(disp, img.shape, intrinsics[0], baseline_m)
    small = scaled_intrinsics(intrinsics, img.shape, disp.shape)
    others = [(np.asarray(o_img), dense_depth(o_disp, img.shape, intrinsics[0], baseline_m), o_pose)
              for o_img, o_disp, o_pose in near if np.isfinite(np.asarray(o_disp)).any()]
    for t in targets:
        view = translate_view(img, depth, intrinsics, pose, t, others)
        if view is None:
            out.append(None)
            continue
        right, forward = camera_move(float(t[0] - pose[0]), float(t[1] - pose[1]), float(pose[2]))
        out.append((view, warp_disparity(disp, small, float(intrinsics[0]) * baseline_m, right, forward)))
    return out

"""Virtual map views (lino_loc.virtual_views): a turned view from one image against the
renderer's view at the turned heading, the disparity rescale, and maps built with them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.world import load_world
from lino_loc.appearance_map import AppearanceMap, build_map
from lino_loc.dataset import CameraInfo, Dataset, DatasetMeta, DatasetWriter
from lino_loc.errors import LinoLocError
from lino_loc.virtual_views import (
    augment_poses,
    augment_vectors,
    crop_columns,
    margin_columns,
    offsets,
    scaled_intrinsics,
    turn_disparity,
    turn_image,
    yaw_homography,
)

W, H = 160, 120
CAM = CameraModel(width=W, height=H)


@pytest.fixture(scope="module")
def office_views() -> tuple[Renderer, np.ndarray]:
    r = Renderer(load_world("office"), camera=CAM, lighting="tube")
    fx, fy, cx, cy = CAM.intrinsics()
    return r, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def test_homography_of_zero_turn_is_identity_and_turns_compose() -> None:
    K = scaled_intrinsics(228.5, 228.5, 159.5, 119.5, (320, 240), (80, 60))
    assert K[0, 0] == pytest.approx(57.125) and K[0, 2] == pytest.approx(39.5)
    np.testing.assert_allclose(yaw_homography(K, 0.0), np.eye(3), atol=1e-12)
    a, b = yaw_homography(K, 0.05), yaw_homography(K, 0.07)
    np.testing.assert_allclose(b @ a, yaw_homography(K, 0.12), atol=1e-9)
    # the optical axis of the turned camera looks at azimuth +delta: that point (left of the
    # centre in the map image) moves to the principal point
    p = K @ np.array([-math.tan(0.1), 0.0, 1.0])
    q = yaw_homography(K, 0.1) @ p
    assert q[:2] / q[2] == pytest.approx(K[:2, 2])


@pytest.mark.parametrize("delta_deg", [-6.0, 4.0, 7.5])
def test_turned_view_matches_the_rendered_view(office_views: tuple[Renderer, np.ndarray], delta_deg: float) -> None:
    r, K = office_views
    delta = math.radians(delta_deg)
    m = margin_columns(K, W, abs(delta))
    for x, y, th in [(1.0, 0.5, 0.3), (5.5, 2.0, -2.0), (3.0, 1.2, 1.6)]:
        src = r.render(x, y, th, noise=False, stereo=False).grey.astype(np.float32)
        dst = r.render(x, y, th + delta, noise=False, stereo=False).grey.astype(np.float32)
        turned = turn_image(src, K, delta)
        err = np.abs(turned[:, m : W - m] - dst[:, m : W - m]).mean()
        before = np.abs(src[:, m : W - m] - dst[:, m : W - m]).mean()
        assert err < 3.0, (x, y, th, err)  # grey levels: resampling only
        assert err < 0.25 * before


def test_turned_disparity_is_rescaled_by_the_new_depth(office_views: tuple[Renderer, np.ndarray]) -> None:
    r, K = office_views
    delta = math.radians(6.0)
    fB = K[0, 0] * 0.075
    m = margin_columns(K, W, delta)
    src = fB / r.render(2.0, 1.0, 0.4, noise=False, stereo=False).depth
    dst = fB / r.render(2.0, 1.0, 0.4 + delta, noise=False, stereo=False).depth
    turned = turn_disparity(src.astype(np.float32), K, delta)[:, m : W - m]
    ref = dst[:, m : W - m]
    ok = np.isfinite(turned) & np.isfinite(ref)
    assert ok.mean() > 0.9
    rel = np.abs(turned[ok] - ref[ok]) / ref[ok]
    assert np.median(rel) < 0.01  # exact but for nearest-pixel sampling at depth edges
    # without the rescale (only moving pixels) the error is systematic at the image sides
    moved = turn_image(src.astype(np.float32), K, delta)[:, m : W - m]
    assert np.median(np.abs(moved[ok] - ref[ok]) / ref[ok]) > np.median(rel)
    # NaN (no stereo match) stays NaN, never blended into a value
    holes = src.astype(np.float32).copy()
    holes[:, ::2] = np.nan
    t = turn_disparity(holes, K, delta)
    full = turn_disparity(src.astype(np.float32), K, delta)
    ok = np.isfinite(t)
    np.testing.assert_array_equal(t[ok], full[ok])  # the same source pixel, not a blend
    assert 0.3 < np.isnan(t[:, m : W - m]).mean() < 0.7


def test_margin_grows_with_the_turn_and_refuses_leaving_the_view() -> None:
    K = scaled_intrinsics(228.5, 228.5, 159.5, 119.5, (320, 240), (80, 60))
    assert margin_columns(K, 80, 0.0) == 0
    a, b = margin_columns(K, 80, math.radians(3)), margin_columns(K, 80, math.radians(6))
    assert 0 < a < b < 40
    # the border shift f (tan(35 deg) - tan(35 deg - 6 deg)) = 8.3 px at 80 px wide
    assert b == math.ceil(57.125 * (math.tan(math.atan(39.5 / 57.125)) - math.tan(math.atan(39.5 / 57.125) - math.radians(6))))
    with pytest.raises(LinoLocError, match="virtual headings"):
        margin_columns(K, 80, math.radians(60))


def test_augment_rows_are_image_major_and_poses_wrap() -> None:
    rng = np.random.default_rng(3)
    X = rng.random((3, 20 * 10)).astype(np.float32)
    K = scaled_intrinsics(20.0, 20.0, 9.5, 4.5, (20, 10), (20, 10))
    d = offsets(math.radians(3), 3)
    np.testing.assert_allclose(np.degrees(d), [-3, 0, 3])
    out = augment_vectors(X, (20, 10), K, d, 2)
    assert out.shape == (9, 16 * 10)
    np.testing.assert_array_equal(out[1], crop_columns(X[0], (20, 10), 2))  # offset 0 = the image itself
    np.testing.assert_array_equal(out[4], crop_columns(X[1], (20, 10), 2))
    P = augment_poses(np.array([[0, 0, math.pi - 0.01], [1, 2, 0.0], [2, 0, -1.0]]), d)
    assert P.shape == (9, 3)
    assert P[2, 2] == pytest.approx(math.pi - 0.01 + math.radians(3) - 2 * math.pi)
    np.testing.assert_allclose(P[3:6, :2], [[1, 2]] * 3)


def test_map_with_virtual_headings_round_trips_and_projects(tmp_path) -> None:  # type: ignore[no-untyped-def]
    r = Renderer(load_world("office"), camera=CameraModel(width=80, height=60), lighting="tube")
    fx, fy, cx, cy = r.camera.intrinsics()
    cam = CameraInfo(width=80, height=60, fx=fx, fy=fy, cx=cx, cy=cy, baseline_m=0.075)
    with DatasetWriter(tmp_path / "ds", DatasetMeta(name="tiny", camera=cam)) as w:
        for i in range(12):
            x, th = 1.0 + 0.5 * (i % 4), math.radians(90 * (i // 4))
            v = r.render(x, 1.0, th, noise=False, stereo=False)
            w.add(v.grey, (x, 1.0, th), depth=v.depth)
    ds = Dataset.open(tmp_path / "ds")
    d = offsets(math.radians(4), 3)
    amap = build_map(ds, n_features=4, size=(40, 30), virtual_offsets=d, channels=("intensity", "disparity"))
    assert len(amap) == 36
    ch = amap.channels["intensity"]
    assert ch.params["margin"] > 0 and ch.params["virtual_offsets_deg"] == "-4,0,4"
    loaded = AppearanceMap.load(amap.save(tmp_path / "m.npz"))
    np.testing.assert_allclose(loaded.poses, amap.poses)
    # a live image at a virtual heading projects next to that virtual entry
    live = r.render(2.0, 1.0, math.radians(94), noise=False, stereo=False).grey
    f = loaded.channels["intensity"].project(live)
    k = int(np.argmin(np.linalg.norm(loaded.channels["intensity"].features - f, axis=1)))
    assert loaded.poses[k] == pytest.approx([2.0, 1.0, math.radians(94)], abs=1e-9)
    disp = loaded.channels["disparity"].project(np.full((60, 80), 5.0, np.float32))
    assert disp.shape == (4,)

"""Renderer geometry against closed forms, stereo disparity, lighting, noise, ambiguity."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.world import World, WorldSpec, load_world

H_CAM = 1.1
CEIL = 2.5


def _box_world() -> World:
    """A 6 x 4 m room (x 0..6, y -2..2) with textured walls and one box; for closed forms."""
    tex = {
        "wall": {"kind": "tiles", "albedo": 0.6, "contrast": 0.5, "period": 0.2, "seed": 1},
        "floor": {"kind": "carpet", "albedo": 0.3, "seed": 2},
        "ceil": {"kind": "paint", "albedo": 0.8, "seed": 3},
        "poster": {"kind": "poster", "albedo": 0.8, "seed": 4},
        "wood": {"kind": "wood", "albedo": 0.5, "seed": 5},
    }
    walls = [
        {"id": "s", "start": [0, -2], "end": [6, -2], "texture": "wall"},
        {"id": "e", "start": [6, -2], "end": [6, 2], "texture": "wall",
         "decals": [{"texture": "poster", "u": 1.5, "z": 0.8, "width": 1.0, "height": 1.0}]},
        {"id": "n", "start": [6, 2], "end": [0, 2], "texture": "wall"},
        {"id": "w", "start": [0, 2], "end": [0, -2], "texture": "wall"},
    ]
    spec = {
        "name": "box", "room": {"xmin": 0, "xmax": 6, "ymin": -2, "ymax": 2},
        "mapped_area": {"xmin": 1, "xmax": 5, "ymin": -1, "ymax": 1}, "ceiling_height": CEIL,
        "floor_texture": "floor", "ceiling_texture": "ceil", "textures": tex, "walls": walls,
        "furniture": [{"id": "crate", "pose": [1.0, 1.5, 0],
                       "boxes": [{"size": [0.6, 0.6], "zmin": 0, "zmax": 0.8, "texture": "wood"}]}],
        "lighting": {
            "tube": {"ambient": 1.0, "lights": [{"type": "tube", "start": [1, 0, 2.45], "end": [5, 0, 2.45], "power": 3}]},
            "bulb": {"ambient": 0.1, "lights": [{"type": "point", "position": [5.5, 1.5, 2.0], "power": 5}]},
        },
    }
    return World(WorldSpec.model_validate(spec), source="<test box world>")


@pytest.fixture(scope="module")
def box_world() -> World:
    return _box_world()


@pytest.fixture(scope="module")
def office() -> World:
    return load_world("office")


def _cam(w: int = 80, h: int = 60, **kw) -> CameraModel:
    return CameraModel(width=w, height=h, hfov_deg=70.0, height_m=H_CAM, **kw)


def test_intrinsics() -> None:
    fx, fy, cx, cy = CameraModel().intrinsics()
    assert fx == pytest.approx(160 / math.tan(math.radians(35)))
    assert fy == fx and (cx, cy) == (159.5, 119.5)
    assert CameraModel(fx=200, fy=210, cx=150, cy=100).intrinsics() == (200, 210, 150, 100)


def test_wall_depth_closed_form(box_world: World) -> None:
    cam = _cam()
    r = Renderer(box_world, camera=cam, lighting="tube")
    res = r.render(2.0, 0.0, 0.0, stereo=False, noise=False)
    fx, fy, cx, cy = cam.intrinsics()
    X = (np.arange(cam.width) - cx) / fx
    Y = (np.arange(cam.height) - cy) / fy
    # closed form per pixel: nearest of east wall (Z = 4), side walls (Z = 2 / |X|),
    # floor (Z = h / Y), ceiling (Z = (CEIL - h) / -Y); no box in this view
    with np.errstate(divide="ignore"):
        z_wall = np.minimum(4.0, 2.0 / np.abs(X))[None, :]
        z_fc = np.where(Y[:, None] > 0, H_CAM / Y[:, None], (CEIL - H_CAM) / -Y[:, None])
    expected = np.minimum(z_wall, z_fc)
    np.testing.assert_allclose(res.depth, expected, rtol=1e-4)
    # a fronto-parallel wall: Z is the wall distance also off-centre
    band = np.abs(Y) * 4.0 < 1.0
    cols = np.abs(X) * 4.0 < 2.0
    assert np.allclose(res.depth[np.ix_(band, cols)], 4.0, rtol=1e-5)
    assert res.grey.shape == res.depth.shape == (60, 80) and res.grey.dtype == np.uint8
    assert res.depth.dtype == np.float32


def test_box_depth_front_and_top(box_world: World) -> None:
    # crate at (1.0, 1.5), 0.6 x 0.6, height 0.8; camera at (1.0, -0.5) looking +y: front face at 1.7 m
    cam = _cam()
    r = Renderer(box_world, camera=cam, lighting="tube")
    res = r.render(1.0, -0.5, math.pi / 2, stereo=False, noise=False)
    fx, fy, cx, cy = cam.intrinsics()
    Y = (np.arange(cam.height) - cy) / fy
    col = int(round(cx))
    z_front = 1.7
    hit_front = (H_CAM - Y * z_front <= 0.8) & (H_CAM - Y * z_front >= 0) & (Y > 0)
    assert np.allclose(res.depth[hit_front, col], z_front, rtol=1e-4)
    # rows that see the top face: ray height at the front face is above 0.8, and below 0.8 at the back
    z_back = 2.3
    top = (H_CAM - Y * z_front > 0.8) & (H_CAM - Y * z_back < 0.8)
    assert top.any()
    np.testing.assert_allclose(res.depth[top, col], (H_CAM - 0.8) / Y[top], rtol=1e-4)


def test_stereo_disparity_is_f_b_over_z(box_world: World) -> None:
    cam0 = _cam(160, 120)
    fx = cam0.intrinsics()[0]
    z, d = 2.0, 8  # wall at 2 m, choose the baseline for an 8-pixel disparity
    cam = _cam(160, 120, baseline_m=d * z / fx)
    r = Renderer(box_world, camera=cam, lighting="tube")
    res = r.render(4.0, 0.0, 0.0, stereo=True, noise=False)
    assert np.allclose(res.depth[50:70, 40:120], z, rtol=1e-5)
    left = res.left[50:70].astype(np.float64)
    right = res.right[50:70].astype(np.float64)
    errs = [np.abs(left[:, 30 + s: 130 + s] - right[:, 30:130]).mean() for s in range(0, 16)]
    assert int(np.argmin(errs)) == d
    assert errs[d] < 0.5 and min(errs[:d - 1] + errs[d + 2:]) > 3 * errs[d] + 1
    # the right camera is displaced to the right: a feature moves LEFT in the right image
    assert np.mean(left[:, 30 + d: 130 + d] == right[:, 30:130]) > 0.9


def test_pan_equals_rotating_the_robot(box_world: World) -> None:
    r = Renderer(box_world, camera=_cam(), lighting="tube")
    a = r.render(3.0, 0.5, 0.3, pan=math.pi / 2, noise=False)
    b = r.render(3.0, 0.5, 0.3 + math.pi / 2, pan=0.0, noise=False)
    assert np.array_equal(a.grey, b.grey) and np.array_equal(a.right, b.right)
    assert np.allclose(a.depth, b.depth)
    assert a.camera_pose == pytest.approx((3.0, 0.5, 0.3 + math.pi / 2))


def test_tilt_up_is_positive(box_world: World) -> None:
    cam = _cam(81, 61)  # odd sizes: a pixel on the optical axis
    r = Renderer(box_world, camera=cam, lighting="tube")
    down = r.render(2.0, 0.0, 0.0, tilt=-0.5, noise=False, stereo=False).depth[30, 40]
    up = r.render(2.0, 0.0, 0.0, tilt=0.5, noise=False, stereo=False).depth[30, 40]
    assert down == pytest.approx(H_CAM / math.sin(0.5), rel=1e-4)  # the floor
    assert up == pytest.approx((CEIL - H_CAM) / math.sin(0.5), rel=1e-4)  # the ceiling
    # a small tilt, fronto-parallel wall at 4 m: Z = D / (cos t + Y sin t) for every wall pixel
    t = 0.1
    res = r.render(2.0, 0.0, 0.0, tilt=t, noise=False, stereo=False)
    fx, fy, cx, cy = cam.intrinsics()
    Y = (np.arange(cam.height) - cy) / fy
    expected = 4.0 / (math.cos(t) + Y * math.sin(t))
    rows = np.abs(H_CAM + expected * (math.sin(t) - Y * math.cos(t)) - 1.25) < 0.9
    np.testing.assert_allclose(res.depth[rows, 30:51], np.repeat(expected[rows, None], 21, 1), rtol=5e-3)


def test_any_resolution(box_world: World) -> None:
    r = Renderer(box_world, camera=_cam(33, 17), lighting="tube")
    res = r.render(2.0, 0.0, 1.0)
    assert res.grey.shape == res.right.shape == res.depth.shape == (17, 33)
    assert np.isfinite(res.depth).all() and (res.depth > 0).all()


def test_noise_off_is_deterministic_and_seeded_noise_reproducible(box_world: World) -> None:
    cam = _cam()
    a = Renderer(box_world, camera=cam, seed=5)
    b = Renderer(box_world, camera=cam, seed=5)
    c = Renderer(box_world, camera=cam, seed=6)
    pose = (2.5, 0.3, 0.4)
    assert np.array_equal(a.render(*pose, noise=False).grey, c.render(*pose, noise=False).grey)
    na, nb, nc = a.render(*pose), b.render(*pose), c.render(*pose)
    assert np.array_equal(na.grey, nb.grey) and np.array_equal(na.right, nb.right)
    assert not np.array_equal(na.grey, nc.grey)
    clean = a.render(*pose, noise=False).grey.astype(int)
    assert 0.3 < np.abs(na.grey.astype(int) - clean).mean() < 5
    r1 = a.render(*pose, rng=np.random.default_rng(1)).grey
    r2 = c.render(*pose, rng=np.random.default_rng(1)).grey
    assert np.array_equal(r1, r2)


def test_lighting_changes_distribution_not_only_level(office: World) -> None:
    r = Renderer(office, camera=_cam(), lighting="tube")
    pose = (2.0, 1.0, 0.0)
    tube, _ = r.radiance(*pose)
    r.set_lighting("bulb")
    bulb, _ = r.radiance(*pose)
    dim = r.render(*pose, noise=False)
    r.set_lighting("natural")
    nat, _ = r.radiance(*pose)
    for other in (bulb, nat):
        ratio = other / tube
        blocks = ratio.reshape(6, 10, 8, 10).mean(axis=(1, 3))
        assert np.percentile(blocks, 90) / np.percentile(blocks, 10) > 2.0
    assert bulb.mean() < 0.5 * tube.mean()
    # dim light: the gain hits its maximum and the image is darker than the target
    assert dim.gain == pytest.approx(r.camera.gain_max)
    assert dim.grey.mean() < r.camera.target_grey - 20


def test_open_windows_saturate(office: World) -> None:
    r = Renderer(office, camera=_cam(), lighting="natural")
    towards_windows = r.render(4.0, 1.25, math.pi / 2, noise=False)
    assert (towards_windows.grey == 255).mean() > 0.05
    r.set_lighting("tube")
    curtains = r.render(4.0, 1.25, math.pi / 2, noise=False)
    assert (curtains.grey == 255).mean() < 0.02


def test_identical_elements_make_views_ambiguous(office: World) -> None:
    # desks, chairs and posters at x = 3.2 and 5.8 along the south wall are identical,
    # and so is the ceiling light around them
    r = Renderer(office, camera=_cam(), lighting="tube")
    a = r.render(3.2, 0.0, -math.pi / 2, noise=False).grey.astype(float)
    b = r.render(5.8, 0.0, -math.pi / 2, noise=False).grey.astype(float)
    near = r.render(3.7, 0.0, -math.pi / 2, noise=False).grey.astype(float)
    same = np.abs(a - b).mean()
    moved = np.abs(a - near).mean()
    assert same < 6.0
    assert moved > 2.5 * same


def test_views_change_smoothly(office: World) -> None:
    r = Renderer(office, camera=_cam(), lighting="tube")
    base = r.render(4.0, 1.0, 0.0, noise=False).grey.astype(float)
    diffs = [np.abs(r.render(4.0 + dx, 1.0, 0.0, noise=False).grey - base).mean() for dx in (0.02, 0.1, 0.5, 2.0)]
    assert diffs[0] < diffs[1] < diffs[2]
    assert diffs[0] < 5.0 and diffs[3] > 10.0


def test_scene_changes_show_up(office: World) -> None:
    r = Renderer(office, camera=_cam(), lighting="tube")
    pose = (2.0, 1.5, math.pi / 2)  # person1 stands at (2.0, 3.1)
    before = r.render(*pose, noise=False)
    r.set_scene_changes(["people"])
    after = r.render(*pose, noise=False)
    assert after.depth[30, 40] == pytest.approx(3.1 - 0.13 - 1.5, abs=0.05)
    assert after.depth[30, 40] < before.depth[30, 40] - 0.3
    assert r.scene_changes == ("people",)

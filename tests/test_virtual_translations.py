"""Virtual translations (lino_loc/virtual_translations.py): the pinhole warp against closed
forms on planes, the z-buffer, the lattice, and a real rendered view."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.errors import LinoLocError
from lino_loc.virtual_translations import (
    as_uint8,
    camera_move,
    dense_depth,
    fill_nearest,
    heading_neighbours,
    lattice_offsets,
    scaled_intrinsics,
    translate_survey,
    translate_view,
    warp,
    warp_disparity,
)

INTR = (100.0, 100.0, 31.5, 23.5)  # fx, fy, cx, cy of a 64 x 48 image


def test_fill_nearest_takes_the_nearest_valid_value() -> None:
    a = np.array([[1.0, np.nan, np.nan, 4.0]], dtype=np.float32)
    assert fill_nearest(a).tolist() == [[1.0, 1.0, 4.0, 4.0]]
    with pytest.raises(LinoLocError, match="no valid value"):
        fill_nearest(np.full((2, 2), np.nan))


def test_dense_depth_of_a_constant_disparity_is_f_b_over_d() -> None:
    disp = np.full((6, 8), 5.0, dtype=np.float32)
    disp[2, 3] = np.nan
    z = dense_depth(disp, (48, 64), fx=100.0, baseline_m=0.075)
    assert z.shape == (48, 64) and np.allclose(z, 100.0 * 0.075 / 5.0)
    # no disparity (infinitely far) is clipped to the largest depth
    assert np.allclose(dense_depth(np.zeros((6, 8)), (6, 8), 100.0, 0.075, max_depth_m=9.0), 9.0)


def test_a_sideways_move_before_a_plane_shifts_the_image_by_f_r_over_z() -> None:
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 255, (48, 64)).astype(np.float32)
    depth = np.full(img.shape, 2.0)
    out = warp(img, depth, INTR, right_m=0.04, forward_m=0.0)  # 100 * 0.04 / 2 = 2 px to the left
    assert np.array_equal(out[:, :-2], img[:, 2:])
    assert np.isnan(out[:, -2:]).all()


def test_a_forward_move_magnifies_about_the_principal_point() -> None:
    """Z = 2 m, 1 m forward: u' - cx = 2 (u - cx); the pixel 5 columns right of centre lands 10 right."""
    img = np.zeros((48, 64), dtype=np.float32)
    img[23, 36] = 200.0  # u - cx = 4.5, v - cy = -0.5
    out = warp(img, np.full(img.shape, 2.0), INTR, right_m=0.0, forward_m=1.0)
    vals = np.nan_to_num(out, nan=-1.0)
    v, u = np.unravel_index(np.argmax(vals), vals.shape)
    assert (u, v) == (round(31.5 + 9.0), round(23.5 - 1.0))
    # the magnified image leaves holes between the landed pixels
    assert np.isnan(out).mean() > 0.5


def test_the_nearest_surface_wins() -> None:
    """A near occluder (1 m) and the wall behind it (4 m): after a move, where both land the
    occluder's value is kept."""
    img = np.full((48, 64), 50.0, dtype=np.float32)
    depth = np.full(img.shape, 4.0)
    img[:, 28:36] = 250.0
    depth[:, 28:36] = 1.0
    out = warp(img, depth, INTR, right_m=0.1, forward_m=0.0)  # occluder moves 10 px left, wall 2.5 px
    assert np.all(out[:, 18:26] == 250.0)
    assert np.nanmax(out[:, 40:]) == 50.0


def test_camera_move_in_the_camera_frame() -> None:
    assert camera_move(1.0, 0.0, 0.0) == pytest.approx((0.0, 1.0))  # facing +x: forward
    assert camera_move(1.0, 0.0, math.pi / 2) == pytest.approx((1.0, 0.0))  # facing +y: +x is to the right
    assert camera_move(0.0, 1.0, 0.0) == pytest.approx((-1.0, 0.0))  # +y is to the left


def test_lattice_offsets_stay_inside_the_cell() -> None:
    off = lattice_offsets(0.75, 3)
    assert off.shape == (9, 2) and np.array_equal(off[0], [0.0, 0.0])
    assert np.max(np.abs(off)) == pytest.approx(0.25) and np.max(np.abs(off)) < 0.375
    assert lattice_offsets(0.75, 1).tolist() == [[0.0, 0.0]]
    with pytest.raises(LinoLocError, match="odd"):
        lattice_offsets(0.75, 2)


def test_scaled_intrinsics_map_pixel_centres() -> None:
    """A 64 x 48 image area-averaged to 16 x 12: f / 4, and the principal point between pixel
    centres (c + 1/2) / 4 - 1/2, so the image centre stays the map's centre."""
    fx, fy, cx, cy = scaled_intrinsics(INTR, (48, 64), (12, 16))
    assert (fx, fy) == (25.0, 25.0)
    assert cx == pytest.approx((31.5 + 0.5) / 4 - 0.5) == pytest.approx(7.5)
    assert cy == pytest.approx(5.5)


def test_warp_disparity_of_a_wall_closes_in_as_the_camera_moves_forward() -> None:
    """A fronto-parallel wall at Z = 3 m, f B = 7.5 px m: 1 m forward every landed pixel reads
    f B / 2 m = 3.75 px; a move to the side shifts the wall by fx r / Z pixels and leaves its
    disparity; the uncovered border and the source's holes stay NaN."""
    fb = 100.0 * 0.075
    disp = np.full((48, 64), fb / 3.0, dtype=np.float32)
    out = warp_disparity(disp, INTR, fb, right_m=0.0, forward_m=1.0)
    landed = np.isfinite(out)
    assert landed.mean() > 0.4 and np.allclose(out[landed], fb / 2.0)
    side = warp_disparity(disp, INTR, fb, right_m=0.06, forward_m=0.0)  # 100 * 0.06 / 3 = 2 px left
    assert np.all(np.isnan(side[:, -2:])) and np.allclose(side[:, :-2], fb / 3.0)
    holes = disp.copy()
    holes[:, 10:20] = np.nan
    moved = warp_disparity(holes, INTR, fb, right_m=0.06, forward_m=0.0)
    assert np.all(np.isnan(moved[:, 8:18])) and np.isfinite(moved[:, 18:62]).all()
    with pytest.raises(LinoLocError, match="fx_baseline"):
        warp_disparity(disp, INTR, 0.0, 0.0, 0.0)


def test_warp_disparity_keeps_the_nearest_surface() -> None:
    """An occluder (Z = 1 m) before a wall (Z = 4 m): after a move to the side the pixels where
    both land read the occluder's disparity (the z-buffer of :func:`warp`)."""
    fb = 100.0 * 0.075
    disp = np.full((48, 64), fb / 4.0, dtype=np.float32)
    disp[:, 30:40] = fb / 1.0
    out = warp_disparity(disp, INTR, fb, right_m=0.1, forward_m=0.0)  # occluder 10 px left, wall 2.5 px
    assert np.allclose(out[:, 20:30], fb)  # the occluder, moved 10 px, in front of the wall


def test_translate_survey_keeps_the_real_view_and_drops_what_keep_refuses() -> None:
    rng = np.random.default_rng(1)
    greys = rng.integers(0, 255, (2, 48, 64), dtype=np.uint8)
    disps = np.full((2, 12, 16), 100.0 * 0.075 / 3.0, dtype=np.float32)  # a wall 3 m away
    disps[1] = np.nan  # no stereo: only the real view
    poses = np.array([[1.0, 1.0, 0.0], [3.0, 1.0, 0.5]])
    survey = translate_survey(greys, disps, poses, INTR, 0.075, 0.75, 3, keep=lambda xy: xy[:, 1] >= 1.0)
    images, out, fallbacks = survey.images, survey.poses, survey.fallbacks
    # each pose: itself + the 5 offsets with y >= 1 (of 8 others: dy = 0 (2), dy = +0.25 (3))
    assert out.shape == (12, 3) and images.shape == (12, 48, 64)
    assert np.array_equal(images[0], greys[0].astype(np.float32)) and np.array_equal(out[0], poses[0])
    assert np.array_equal(out[6], poses[1]) and np.all(out[:, 1] >= 1.0) and np.all(out[:6, 2] == 0.0)
    assert np.all(out[6:, 2] == 0.5)  # every lattice position holds its survey position's headings
    assert np.isfinite(images).all()
    # pose 1 has no stereo: its five translations fall back to its own view
    assert fallbacks == 5 and all(np.array_equal(images[k], greys[1].astype(np.float32)) for k in range(6, 12))
    assert not np.array_equal(images[1], images[0])  # pose 0's are warped
    # the disparity maps move with the views: the real one first, the fallbacks' their survey's
    assert survey.disparities.shape == (12, 12, 16)
    assert np.array_equal(survey.disparities[0], disps[0])
    assert all(np.all(np.isnan(survey.disparities[k])) for k in range(6, 12))
    fb = 100.0 * 0.075
    for k in range(1, 6):  # the wall, 3 m minus the forward part of each move
        right, forward = camera_move(*(out[k, :2] - poses[0, :2]), 0.0)
        d = survey.disparities[k]
        assert np.isfinite(d).any() and np.allclose(d[np.isfinite(d)], fb / (3.0 - forward), rtol=1e-5)
    # with a transform only its outputs are kept (the map's working vectors)
    moved = translate_survey(greys, disps, poses, INTR, 0.075, 0.75, 3, keep=lambda xy: xy[:, 1] >= 1.0,
                             transform=lambda im: im[::8, ::8].ravel())
    vecs, out2 = moved.images, moved.poses
    assert vecs.shape == (12, 48) and np.array_equal(vecs, images[:, ::8, ::8].reshape(12, -1))
    assert np.array_equal(out2, out)


def test_a_rendered_view_translated_is_nearer_the_real_view_than_the_survey_view() -> None:
    """The simulated office: a survey view warped 25 cm with its own sparse stereo disparity is
    nearer (at the map's working size) to the real view rendered there than the survey view is."""
    from drivers.sim.renderer import CameraModel, Renderer
    from drivers.sim.world import load_world
    from lino_loc.disparity import StereoConfig, compute_disparity, downsample_sparse
    from lino_loc.preprocessing import preprocess, to_vector

    world = load_world("office")
    camera = CameraModel(width=160, height=120)
    renderer = Renderer(world, camera=camera)
    intr = camera.intrinsics()
    size = (40, 30)
    for k, (x, y, th, dx, dy) in enumerate([(2.0, 1.5, 0.3, 0.25, 0.0), (5.0, 1.0, 2.0, 0.0, 0.25)]):
        src = renderer.render(x, y, th, stereo=True, rng=np.random.default_rng((k, 0)))
        disp = downsample_sparse(compute_disparity(src.left, src.right, StereoConfig()), size)
        depth = dense_depth(disp, src.grey.shape, intr[0], camera.baseline_m)
        virtual = translate_view(src.grey, depth, intr, (x, y, th), (x + dx, y + dy))
        assert virtual is not None
        real = renderer.render(x + dx, y + dy, th, stereo=False, rng=np.random.default_rng((k, 1))).grey

        def vec(im: np.ndarray) -> np.ndarray:
            return to_vector(preprocess(as_uint8(im), "none"), size)

        d_virtual = np.linalg.norm(vec(real) - vec(virtual))
        d_survey = np.linalg.norm(vec(real) - vec(src.grey))
        assert d_virtual < 0.6 * d_survey, (k, d_virtual, d_survey)


def test_a_turned_camera_sees_a_point_at_its_bearing_plus_the_turn() -> None:
    """A pure turn of the camera to the left by d: a point at bearing a (to the right of the
    optical axis) appears at bearing a + d, u' = cx + fx tan(a + d), whatever its depth."""
    fx, _, cx, _ = INTR
    depth = np.full((48, 64), 3.0)
    depth[:, 40:] = 7.0
    image = np.tile(np.arange(64, dtype=np.float32), (48, 1))  # each column its own value
    for d in (math.radians(5.0), math.radians(-8.0)):
        out = warp(image, depth, INTR, 0.0, 0.0, turn=d)
        for u in (10, 31, 45, 55):
            a = math.atan((u - cx) / fx)
            u2 = int(round(cx + fx * math.tan(a + d)))
            if 0 <= u2 < 64:
                assert out[24, u2] == u, (d, u, u2, out[24, u2])


def test_a_turn_and_a_move_together_equal_the_move_seen_by_a_turned_camera() -> None:
    """A view warped into a camera moved (r, f) and turned by d lands every point where the
    world-frame geometry puts it: checked against the same point projected by hand."""
    fx, fy, cx, cy = INTR
    depth = np.full((48, 64), 4.0)
    image = np.arange(48 * 64, dtype=np.float32).reshape(48, 64)
    r, f, d = 0.2, 0.3, math.radians(10.0)  # forward: each point its own target pixel
    out = warp(image, depth, INTR, r, f, turn=d)
    for u, v in ((20, 10), (40, 30), (31, 24)):
        x, z = (u - cx) * 4.0 / fx - r, 4.0 - f
        x2, z2 = math.cos(d) * x + math.sin(d) * z, math.cos(d) * z - math.sin(d) * x
        u2, v2 = int(round(fx * x2 / z2 + cx)), int(round(fy * (v - cy) * 4.0 / fy / z2 + cy))
        assert out[v2, u2] == image[v, u]


def test_the_z_buffer_keeps_the_nearest_point_of_every_pixel_and_the_mask_only_selects() -> None:
    """Against a direct two-key ranking (target pixel, then depth, then source index): the
    nearest landed point of every pixel, ties to the lower source index; with ``into`` the same
    pixels' values, NaN elsewhere."""
    rng = np.random.default_rng(3)
    depth = np.round(rng.uniform(1.0, 3.0, (48, 64)), 1)  # many equal depths: ties
    image = rng.uniform(0.0, 255.0, (48, 64)).astype(np.float32)
    for r, f, d in ((0.3, -0.4, 0.0), (-0.2, 0.5, math.radians(12.0))):
        out = warp(image, depth, INTR, r, f, turn=d)
        fx, fy, cx, cy = INTR
        v, u = np.mgrid[0:48, 0:64]
        x, z = (u - cx) * depth / fx - r, depth - f
        x2, z2 = math.cos(d) * x + math.sin(d) * z, math.cos(d) * z - math.sin(d) * x
        u2 = np.rint(fx * x2 / z2 + cx).astype(int).ravel()
        v2 = np.rint(fy * ((v - cy) * depth / fy) / z2 + cy).astype(int).ravel()
        ok = np.flatnonzero((u2 >= 0) & (u2 < 64) & (v2 >= 0) & (v2 < 48) & (z2.ravel() > 0.05))
        tgt = v2[ok] * 64 + u2[ok]
        order = np.lexsort((ok, z2.ravel()[ok], tgt))
        first = order[np.unique(tgt[order], return_index=True)[1]]
        expected = np.full(48 * 64, np.nan, dtype=np.float32)
        expected[tgt[first]] = image.ravel()[ok[first]]
        assert np.array_equal(out.ravel(), expected, equal_nan=True)
        mask = rng.random((48, 64)) < 0.3
        masked = warp(image, depth, INTR, r, f, turn=d, into=mask)
        assert np.array_equal(masked[mask], out[mask], equal_nan=True) and np.isnan(masked[~mask]).all()


def test_the_borders_a_move_uncovers_are_filled_from_the_neighbouring_headings() -> None:
    """Moving back from a wall uncovers the image's borders; a view of the same place turned
    15 deg saw the wall there, so those holes take its values, not the nearest pixel's. Without
    the turned views the result is the nearest fill, as before."""
    depth = np.full((48, 64), 2.0)
    ahead = np.full((48, 64), 100.0, dtype=np.float32)
    turned = np.full((48, 64), 200.0, dtype=np.float32)
    pose = np.array([0.0, 0.0, 0.0])
    target = np.array([-0.5, 0.0, 0.0])  # 0.5 m back (heading 0 looks along +x)
    alone = translate_view(ahead, depth, INTR, pose, target)
    assert alone is not None and np.all(alone == 100.0)
    q = np.array([0.0, 0.0, math.radians(15.0)])  # turned to the left: it saw the left border
    filled = translate_view(ahead, depth, INTR, pose, target, [(turned, depth, q)])
    assert filled is not None
    holes = ~np.isfinite(warp(ahead, depth, INTR, *camera_move(-0.5, 0.0, 0.0)))
    assert holes[:, :3].all() and holes[:, -3:].all()
    assert np.all(filled[~holes] == 100.0)  # what the view itself saw is kept
    assert np.all(filled[20:28, 0] == 200.0)  # the left border: from the turned view
    assert np.all(filled[20:28, -1] == 100.0)  # the right border: no view saw it, nearest fill


def test_heading_neighbours_are_the_nearest_headings_each_side_at_the_same_place_and_light() -> None:
    headings = np.radians(np.arange(-180.0, 180.0, 15.0))
    poses = np.array([[x, 0.0, h] for x in (0.0, 0.75) for h in headings])
    near = heading_neighbours(poses)
    assert len(near) == 48
    # heading index 0 (-180 deg) at x = 0: the neighbours wrap around (+165 deg and -165 deg)
    assert sorted(near[0]) == [1, 23]
    assert sorted(near[30]) == [29, 31] and all(24 <= k < 48 for k in near[30])
    # another light at the same place is not a neighbour; a lone heading has none
    labels = ["tube"] * 48
    labels[1] = "bulb"
    assert sorted(heading_neighbours(poses, labels=labels)[0]) == [2, 23]
    assert heading_neighbours(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, math.radians(60.0)]])) == [(), ()]
    with pytest.raises(LinoLocError, match="labels"):
        heading_neighbours(poses, labels=["tube"])


def test_a_rendered_view_moved_back_is_nearer_the_real_view_with_the_turned_fill() -> None:
    """The simulated office, the product's path (sparse stereo depth for every view): a survey
    view moved 25 cm back, its uncovered borders filled from the survey's views 15 deg either
    side, is nearer (pixels at the map's working size) to the real view there than the same
    move filled by the nearest pixel alone."""
    from drivers.sim.renderer import CameraModel, Renderer
    from drivers.sim.world import load_world
    from lino_loc.disparity import StereoConfig, compute_disparity, downsample_sparse
    from lino_loc.preprocessing import preprocess, to_vector

    renderer = Renderer(load_world("office"), camera=CameraModel(width=160, height=120))
    intr = renderer.camera.intrinsics()
    size = (40, 30)

    def view(pose: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        r = renderer.render(*map(float, pose), stereo=True, rng=np.random.default_rng((k, 0)))
        disp = downsample_sparse(compute_disparity(r.left, r.right, StereoConfig()), size)
        return r.grey, dense_depth(disp, r.grey.shape, intr[0], renderer.camera.baseline_m)

    def vec(im: np.ndarray) -> np.ndarray:
        return to_vector(preprocess(as_uint8(im), "none"), size)

    gains = []
    for k, (x, y, th) in enumerate([(2.0, 1.5, 0.3), (4.0, 1.2, 2.0), (3.0, 2.0, -1.0)]):
        pose = np.array([x, y, th])
        target = pose - 0.25 * np.array([math.cos(th), math.sin(th), 0.0])
        grey, depth = view(pose, k)
        others = []
        for turn in (1.0, -1.0):
            q = pose + np.array([0.0, 0.0, turn * math.radians(15.0)])
            others.append((*view(q, 10 * k + int(turn > 0)), q))
        real = vec(renderer.render(*map(float, target), stereo=False, rng=np.random.default_rng((k, 9))).grey)
        plain = translate_view(grey, depth, intr, pose, target)
        filled = translate_view(grey, depth, intr, pose, target, others)
        assert plain is not None and filled is not None
        gains.append(np.linalg.norm(real - vec(filled)) / np.linalg.norm(real - vec(plain)))
    assert np.mean(gains) < 0.9 and max(gains) < 1.0, gains


def test_a_rendered_disparity_map_moved_is_nearer_the_disparity_there() -> None:
    """The simulated office: a survey view's sparse disparity moved 25 cm (four moves) is on
    average nearer the exact disparity at the new pose (the renderer's depth, used here only as
    the reference) than the unmoved map is, over the pixels valid in both. A move mostly along
    the optical axis changes the disparity of a far wall by less than the matcher's noise, so the
    mean over the moves is what is checked."""
    from drivers.sim.renderer import CameraModel, Renderer
    from drivers.sim.world import load_world
    from lino_loc.disparity import StereoConfig, compute_disparity, downsample_sparse

    renderer = Renderer(load_world("office"), camera=CameraModel(width=160, height=120))
    camera = renderer.camera
    intr = camera.intrinsics()
    fb = intr[0] * camera.baseline_m
    moved_err, survey_err = [], []
    for k, (x, y, th, dx, dy) in enumerate([(2.0, 1.5, 0.3, 0.25, 0.0), (5.0, 1.0, 2.0, 0.0, 0.25),
                                            (3.0, 2.0, -1.0, -0.25, 0.25), (4.0, 1.2, 3.0, 0.25, 0.25)]):
        src = renderer.render(x, y, th, stereo=True, rng=np.random.default_rng((k, 0)))
        disp = downsample_sparse(compute_disparity(src.left, src.right, StereoConfig()), (40, 30))
        right, forward = camera_move(dx, dy, th)
        moved = warp_disparity(disp, scaled_intrinsics(intr, src.grey.shape, disp.shape), fb, right, forward)
        depth = renderer.render(x + dx, y + dy, th, stereo=True, rng=np.random.default_rng((k, 1))).depth
        exact = downsample_sparse((fb / depth).astype(np.float32), (40, 30))
        ok = np.isfinite(moved) & np.isfinite(disp) & np.isfinite(exact)
        assert ok.mean() > 0.05
        moved_err.append(np.mean(np.abs(moved[ok] - exact[ok])))
        survey_err.append(np.mean(np.abs(disp[ok] - exact[ok])))
    assert np.mean(moved_err) < 0.9 * np.mean(survey_err), (moved_err, survey_err)


def test_a_translated_map_is_the_same_whatever_other_preprocessings_are_built_with_it() -> None:
    """``build_sim_maps`` warps each view once for all its preprocessings: the histeq map built
    beside the plain one equals the histeq map built alone."""
    from services.evaluation.views import build_sim_maps

    kw = dict(workers=1, width=160, height=120, size=(40, 30), cache=False, translations=3)
    both = build_sim_maps("office", 2.0, 45, 5, ("none", "histeq"), **kw)["histeq"]
    alone = build_sim_maps("office", 2.0, 45, 5, ("histeq",), **kw)["histeq"]
    assert both.poses.shape[0] > 0 and np.array_equal(both.poses, alone.poses)
    assert np.allclose(both.channels["intensity"].features, alone.channels["intensity"].features)

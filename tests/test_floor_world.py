"""Worlds of rooms: the format's rooms and openings, the floor world, and sound visibility culling."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from drivers.sim.floor_world import FLOOR_JSON, corridor_floor, floor_world_json
from drivers.sim.lighting import _walls_clear, bake
from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.survey import survey_poses
from drivers.sim.visibility import cells_at, potentially_visible, visible_cells
from drivers.sim.world import World, WorldSpec, load_world
from lino_loc.errors import LinoLocError

#: SHA-1 fingerprints of the single-room worlds before rooms existed (they key the caches).
OLD_FINGERPRINTS = {
    "lab": "7a7fa13ff7fc9dc54e34e43f5f5b5a70d677d70a",
    "office": "a735c6063c928c602a388c12f04b24a4810b96f0",
    "corridor": "21fbb4c8d6f079ca1da77cc72f23e99aedae7ca5",
}


@pytest.fixture(scope="module")
def floor() -> World:
    return load_world("floor")


@pytest.fixture(scope="module")
def small() -> World:
    """Two offices on a corridor: three rooms, two doorways."""
    return World(WorldSpec.model_validate(corridor_floor(1)))


def test_floor_file_is_the_generators_output() -> None:
    assert FLOOR_JSON.read_text(encoding="utf-8") == floor_world_json()


def test_floor_world_size_lights_changes_and_rooms(floor: World) -> None:
    xmin, xmax, ymin, ymax = floor.room
    assert (xmax - xmin, ymax - ymin) == pytest.approx((40.0, 25.0))
    assert floor.mapped_area == floor.room
    assert set(floor.lighting_names) == {"tube", "bulb", "natural"}
    assert set(floor.scene_change_names) == {"boxes", "moved_furniture", "people"}
    rooms = floor.spec.rooms
    assert len(rooms) >= 8 and len(floor.spec.openings) >= len(rooms) - 1
    looks = {(r.wall_texture, r.floor_texture, r.ceiling_texture) for r in rooms}
    assert len(looks) >= 4  # rooms differ
    ids = [f.id for f in floor.spec.furniture]
    offices = [r.id for r in rooms if r.id.startswith("s_office")]
    assert len(offices) >= 3  # ... and repeat: identical offices with identical furniture

    def layout(rid: str) -> list[tuple]:
        room = next(r for r in rooms if r.id == rid)
        out = []
        for f in floor.spec.furniture:
            if f.id.startswith(rid + "."):
                out.append((f.template, round(f.pose[0] - room.rect.xmin, 6), round(f.pose[1] - room.rect.ymin, 6),
                            f.pose[2]))
        return out

    assert layout(offices[0]) == layout(offices[1]) == layout(offices[2]) != []
    assert len(ids) == len(set(ids))
    for name in floor.scene_change_names:
        changed = floor.geometry([name]).boxes
        assert changed != floor.geometry().boxes


def _free_raster(world: World, cell: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xmin, xmax, ymin, ymax = world.room
    xs = np.arange(xmin + cell / 2, xmax, cell)
    ys = np.arange(ymin + cell / 2, ymax, cell)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    return world.is_free(gx, gy, radius=0.25), gx, gy


def test_floor_free_space_is_one_piece_joined_through_the_doors(floor: World) -> None:
    free, gx, gy = _free_raster(floor)
    labels, n = ndimage.label(free)
    sizes = np.bincount(labels.ravel())[1:]
    big = 1 + int(np.argmax(sizes))
    lay = floor.layout
    assert lay is not None
    inside = cells_at(lay.rects, gx.ravel(), gy.ravel()).reshape(*gx.shape, -1)
    for c, cell in enumerate(lay.cells[:len(floor.spec.rooms)]):
        assert np.any((labels == big) & inside[..., c]), f"room {cell.id} not reached"
    assert sizes.max() > 0.6 * free.sum()  # crumbs behind furniture aside, one piece
    # without the doorways the rooms fall apart: every room its own piece
    passages = inside[..., len(floor.spec.rooms):].any(axis=-1)
    _, n_closed = ndimage.label(free & ~passages)
    assert n_closed >= len(floor.spec.rooms)


def _two_rooms() -> dict:
    data = corridor_floor(1)
    return copy.deepcopy(data)


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda d: d["openings"][0].__setitem__("rooms", ["s0", "nowhere"]), "openings.0.rooms"),
        (lambda d: d["openings"][0].__setitem__("center", 50.0), "openings.0.center"),
        (lambda d: d["rooms"][0].__setitem__("wall_texture", "nope"), "rooms.0.wall_texture"),
        (lambda d: d["rooms"][1]["rect"].__setitem__("ymin", 3.0), "rooms.1"),
        (lambda d: d["rooms"][0]["sides"]["north"]["decals"][0].__setitem__("u", 1.0), "rooms.0.sides.north.decals.0"),
        (lambda d: d["walls"].append({"start": [0, 0], "end": [1, 0], "texture": "lino"}), "walls"),
        (lambda d: d["rooms"][2].__setitem__("height", 2.0), "rooms.2.height"),
    ],
)
def test_bad_rooms_name_the_field(tmp_path: Path, mutate, field: str) -> None:
    data = _two_rooms()
    mutate(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(LinoLocError) as err:
        load_world(path)
    msg = str(err.value)
    assert str(path) in msg and field in msg and "\n" not in msg


def test_old_worlds_keep_their_fingerprints_and_walls() -> None:
    for name, fp in OLD_FINGERPRINTS.items():
        w = load_world(name)
        assert w.fingerprint == fp
        assert w.layout is None
        assert w.geometry().walls == w.spec.walls


def test_cells_are_closed_by_walls_and_portals(floor: World) -> None:
    """Every cell's boundary is covered by its walls and portals, end to end (the culling's premise)."""
    lay = floor.layout
    assert lay is not None
    for c, cell in enumerate(lay.cells):
        xmin, xmax, ymin, ymax = cell.rect
        segs = [(w.start, w.end) for w, wc in zip(lay.walls, lay.wall_cell, strict=True) if wc == c]
        segs += [(p.p0, p.p1) for p in lay.portals if c in (p.a, p.b)]
        length = sum(math.dist(a, b) for a, b in segs)
        assert length == pytest.approx(2 * (xmax - xmin + ymax - ymin), abs=1e-9), cell.id
        for a, b in segs:  # all on the boundary
            for px, py in (a, b):
                on = min(abs(px - xmin), abs(px - xmax), abs(py - ymin), abs(py - ymax))
                assert on < 1e-12 and xmin - 1e-12 <= px <= xmax + 1e-12 and ymin - 1e-12 <= py <= ymax + 1e-12


def _cells_along(world: World, a: np.ndarray, b: np.ndarray, n: int = 400) -> set[int]:
    lay = world.layout
    t = np.linspace(0.0, 1.0, n)[:, None]
    pts = a[None, :] + t * (b - a)[None, :]
    return set(np.flatnonzero(cells_at(lay.rects, pts[:, 0], pts[:, 1]).any(axis=0)).tolist())


def test_unblocked_sight_lines_stay_in_the_visible_sets(floor: World) -> None:
    """Random segments between points of cells that cross no wall: every cell they pass lies in
    the potentially visible set of the start cell and in the view's visible cells."""
    lay = floor.layout
    pvs = potentially_visible(lay)
    segs = np.array([(*w.start, *w.end) for w in lay.walls])
    rng = np.random.default_rng(3)
    rects = lay.rects
    n = 3000
    c0 = rng.integers(len(rects), size=n)
    r = rects[c0]
    a = np.column_stack([rng.uniform(r[:, 0], r[:, 1]), rng.uniform(r[:, 2], r[:, 3]), np.ones(n)])
    ang = rng.uniform(-math.pi, math.pi, n)
    b = a + rng.uniform(1.0, 30.0, n)[:, None] * np.column_stack([np.cos(ang), np.sin(ang), np.zeros(n)])
    clear = np.flatnonzero(_walls_clear(a, b, segs, pairs=True))
    checked = 0
    for i in clear[:400]:
        passed = _cells_along(floor, a[i, :2], b[i, :2])
        start = set(np.flatnonzero(cells_at(rects, a[i, :1], a[i, 1:2])[0]).tolist())
        for s0 in start:
            assert passed <= set(pvs[s0].tolist())
        vis = visible_cells(lay, a[i, 0], a[i, 1], ang[i] - 0.01, ang[i] + 0.01)
        assert passed <= set(vis.tolist())
        checked += 1
    assert checked >= 300


def test_culled_render_equals_unculled(small: World) -> None:
    cam = CameraModel(width=96, height=72)
    culled = Renderer(small, camera=cam, lighting="tube", texel=0.02)
    full = Renderer(small, camera=cam, lighting="tube", texel=0.02, cull=False)
    rng = np.random.default_rng(5)
    poses = [(3.0, 3.0, 0.3, 0.0, 0.0), (6.0, 7.5, math.pi, 0.2, 0.1), (6.0, 5.9, 1.6, 0.0, -0.2),
             (1.2, 9.0, -1.5, 0.0, 0.0)]
    while len(poses) < 12:
        x, y = rng.uniform(*small.room[:2]), rng.uniform(*small.room[2:])
        if small.is_free(x, y):
            poses.append((x, y, rng.uniform(-math.pi, math.pi), rng.uniform(-1, 1), rng.uniform(-0.3, 0.3)))
    for x, y, th, pan, tilt in poses:
        a = culled.render(x, y, th, pan, tilt, rng=np.random.default_rng(1))
        b = full.render(x, y, th, pan, tilt, rng=np.random.default_rng(1))
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
        assert np.array_equal(a.depth, b.depth)
    # and culling drops something: an office's window view traces no other room
    rays = culled._rays_for(0.0)
    cells, walls, boxes = culled._selection(3.0, 1.0, -math.pi / 2, rays)
    assert cells.tolist() == [0] and len(walls) < len(culled._w0) and len(boxes) < len(culled._box)


def test_culled_bake_equals_unculled(small: World) -> None:
    for light in ("bulb", "natural"):  # point lights; windows and the sun
        a = bake(small, light, texel=0.02)
        b = bake(small, light, texel=0.02, cull=False)
        np.testing.assert_allclose(a.atlas, b.atlas, rtol=1e-6, atol=0)


def test_floor_survey_grid_is_the_labs_spacing_about_100k_views(floor: World) -> None:
    grid = floor.spec.survey
    assert grid is not None and (grid.step, grid.heading_step_deg) == (0.5, 10.0)
    poses, _ = survey_poses(floor, grid.step, math.radians(grid.heading_step_deg))
    assert 90_000 <= len(poses) <= 125_000
    assert np.all(floor.is_free(poses[:, 0], poses[:, 1], 0.25))
    assert load_world("lab").spec.survey is None  # the others keep the command's default


def test_survey_command_takes_the_worlds_grid(tmp_path: Path, small: World) -> None:
    import argparse

    from services.commands import survey_cmd

    data = corridor_floor(1)
    data["survey"] = {"step": 3.0, "heading_step_deg": 180.0}
    path = tmp_path / "tiny.json"
    path.write_text(json.dumps(data))
    parser = argparse.ArgumentParser()
    survey_cmd.register(parser.add_subparsers())
    args = parser.parse_args(["survey", "--world", str(path), "--out", str(tmp_path / "ds"), "--no-stereo",
                              "--width", "32", "--height", "24", "--json"])
    assert args.func(args) == 0
    expected, _ = survey_poses(small, 3.0, math.pi)
    assert (args.step, args.heading_step) == (3.0, 180.0)
    rows = (tmp_path / "ds" / "poses.csv").read_text().strip().splitlines()
    assert len(rows) - 1 == len(expected) > 0

"""The corridor world (config/worlds/corridor.json): it loads and renders, its three lights and
its named scene changes exist and differ, its repeated doors make distant views alike; interior
walls cast shadows; the office and the lab have none, so their bakes skip the wall test; the
tracking and global evaluations run on it (tiny sizes)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from world_checks import assert_change_shows, assert_lights_differ, grey_view

from drivers.sim.lighting import bake, interior_walls
from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.world import World, WorldSpec, grid_poses, load_world

SOUTH, NORTH = -math.pi / 2, math.pi / 2


@pytest.fixture(scope="module")
def corridor() -> World:
    return load_world("corridor")


@pytest.fixture(scope="module")
def renderer(corridor: World) -> Renderer:
    return Renderer(corridor, CameraModel(width=64, height=48), lighting="tube")


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum()))


def test_corridor_loads_with_the_lights_and_changes_of_the_other_worlds(corridor: World) -> None:
    office = load_world("office")
    assert corridor.lighting_names == office.lighting_names == ("tube", "bulb", "natural")
    assert corridor.scene_change_names == office.scene_change_names
    xmin, xmax, ymin, ymax = corridor.mapped_area
    assert (xmax - xmin, ymax - ymin) == pytest.approx((13.0, 1.0))
    # the robot can drive the corridor's centre line from end to end
    xs = np.linspace(xmin, xmax, 131)
    assert corridor.is_free(xs, np.full_like(xs, 0.9), radius=0.35).all()
    poses = grid_poses(corridor, 0.5, math.radians(10))
    assert 2000 <= len(poses) <= 3000
    assert np.all(corridor.is_free(poses[:, 0], poses[:, 1], 0.25))


def test_renders_small_under_every_light_and_the_lights_differ(corridor: World) -> None:
    assert_lights_differ(corridor, (2.0, 1.0, 0.0))


@pytest.mark.parametrize(
    ("change", "pose"),
    [("boxes", (4.5, 1.0, 0.0)), ("moved_furniture", (1.5, 1.0, 0.0)), ("people", (3.0, 1.0, 0.0))],
)
def test_each_scene_change_moves_geometry_and_shows_in_a_view(
    corridor: World, renderer: Renderer, change: str, pose: tuple[float, float, float]
) -> None:
    assert_change_shows(corridor, renderer, change, pose)


def test_identical_doors_make_distant_views_alike(renderer: Renderer) -> None:
    # open doors s1 and s3 (7 m apart), closed doors s0 and s2: the same view
    assert _ncc(grey_view(renderer, 5.25, 1.0, SOUTH), grey_view(renderer, 12.25, 1.0, SOUTH)) > 0.98
    assert _ncc(grey_view(renderer, 1.75, 1.0, SOUTH), grey_view(renderer, 8.75, 1.0, SOUTH)) > 0.98
    # an open door against a closed one, the notice board against plain wall: different
    assert _ncc(grey_view(renderer, 5.25, 1.0, SOUTH), grey_view(renderer, 1.75, 1.0, SOUTH)) < 0.8
    assert _ncc(grey_view(renderer, 7.65, 1.0, NORTH), grey_view(renderer, 11.15, 1.0, NORTH)) < 0.5


def _two_rooms(split: bool) -> World:
    """4 x 2 m, a lamp in the west half; with ``split`` a wall at x = 2 from side to side."""
    walls = [
        {"id": "s", "start": [0, 0], "end": [4, 0], "texture": "w"},
        {"id": "e", "start": [4, 0], "end": [4, 2], "texture": "w"},
        {"id": "n", "start": [4, 2], "end": [0, 2], "texture": "w"},
        {"id": "w", "start": [0, 2], "end": [0, 0], "texture": "w"},
    ]
    if split:
        walls.append({"id": "mid", "start": [2, 0], "end": [2, 2], "texture": "w"})
    spec = WorldSpec.model_validate({
        "name": "two_rooms", "room": {"xmin": 0, "xmax": 4, "ymin": 0, "ymax": 2},
        "mapped_area": {"xmin": 0.5, "xmax": 3.5, "ymin": 0.5, "ymax": 1.5}, "ceiling_height": 2.5,
        "floor_texture": "w", "ceiling_texture": "w",
        "textures": {"w": {"kind": "paint", "albedo": 0.5, "contrast": 0.0}},
        "walls": walls,
        "lighting": {"lamp": {"ambient": 0.1, "lights": [{"type": "point", "position": [1, 1, 2], "power": 5}]}},
    })
    return World(spec)


def _floor_radiance(world: World, x: float, y: float) -> float:
    b = bake(world, "lamp")
    assert b.names[0] == "floor"
    col, row = int(round(x / b.texel)), int(round(y / b.texel))
    return float(b.atlas[b.offset[0] + row * b.cols[0] + col])


def test_interior_walls_cast_shadows_boundary_walls_do_not() -> None:
    open_room, split = _two_rooms(False), _two_rooms(True)
    assert len(interior_walls(open_room, open_room.spec.walls)) == 0
    assert len(interior_walls(split, split.spec.walls)) == 1
    ambient_only = 0.5 * 0.1 / math.pi
    # the lamp's side: the same light with or without the wall
    assert _floor_radiance(split, 1.0, 1.0) == pytest.approx(_floor_radiance(open_room, 1.0, 1.0), rel=1e-5)
    # behind the wall: ambient alone; without it the lamp reaches there
    assert _floor_radiance(split, 3.0, 1.0) == pytest.approx(ambient_only, rel=1e-3)
    assert _floor_radiance(open_room, 3.0, 1.0) > 2.0 * ambient_only


def test_office_and_lab_have_no_interior_wall_the_corridor_has(corridor: World) -> None:
    # no interior wall: the bake runs exactly the code it ran before interior walls existed
    for name in ("office", "lab"):
        w = load_world(name)
        assert interior_walls(w, w.spec.walls).shape == (0, 4)
    assert len(interior_walls(corridor, corridor.spec.walls)) >= 14


def test_tracking_and_global_evaluations_run_on_the_corridor() -> None:
    from services.evaluation import global_loc, tracking

    small = {"width": 80, "height": 60, "size": (40, 30), "workers": 1}
    res = tracking.run(tracking.TrackingSetup(
        world="corridor", step=1.0, heading_step_deg=45.0, features=4, preprocess=("none",), lights=("tube",),
        scene_changes=("people",), duration=2.0, rate=2.0, particles=100, switch_lights=None, **small))
    assert res["world"] == "corridor" and res["frames"] == 5
    assert 0.0 <= res["conditions"]["tube"]["mean_error_m"] < 14.0
    g = global_loc.run(global_loc.GlobalSetup(
        world="corridor", starts=2, updates=3, particles=200, step=1.0, heading_step_deg=45.0, features=4,
        virtual_headings=1, **small))
    assert g["world"] == "corridor" and len(g["mean_error_m"]) == 3

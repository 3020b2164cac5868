"""drivers.sim.free_space.free_loop_box: a closed test loop derived from a world's free space
stays inside the mapped area and the free space, avoids furniture, is seeded and deterministic."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.free_space import free_loop_box, superellipse
from drivers.sim.world import World, WorldSpec, load_world
from lino_loc.errors import LinoLocError


def _room_with(boxes: list[dict]) -> World:
    """A 6 x 4 m room, mapped area 1 m inside the walls, with the given furniture."""
    spec = WorldSpec.model_validate({
        "name": "loop_room", "room": {"xmin": 0, "xmax": 6, "ymin": 0, "ymax": 4},
        "mapped_area": {"xmin": 1, "xmax": 5, "ymin": 1, "ymax": 3}, "ceiling_height": 2.5,
        "floor_texture": "w", "ceiling_texture": "w",
        "textures": {"w": {"kind": "paint"}},
        "walls": [
            {"start": [0, 0], "end": [6, 0], "texture": "w"}, {"start": [6, 0], "end": [6, 4], "texture": "w"},
            {"start": [6, 4], "end": [0, 4], "texture": "w"}, {"start": [0, 4], "end": [0, 0], "texture": "w"},
        ],
        "furniture": boxes,
        "lighting": {"tube": {}},
    })
    return World(spec)


def _loop_clear(world: World, box: tuple[float, float, float, float], clearance: float) -> bool:
    x, y = superellipse(box, 4.0, 4000)
    return bool(world.is_free(x, y, clearance).all())


@pytest.mark.parametrize("name", ["office", "lab", "corridor"])
def test_loop_is_inside_the_mapped_area_and_clear_on_every_world(name: str) -> None:
    world = load_world(name)
    box = free_loop_box(world, seed=0)
    mx0, mx1, my0, my1 = world.mapped_area
    assert mx0 <= box[0] < box[1] <= mx1 and my0 <= box[2] < box[3] <= my1
    assert _loop_clear(world, box, 0.25 + 0.1)  # the world itself, not only the raster
    assert box[1] - box[0] > 0.8 * (mx1 - mx0)  # it runs the length of the area


def test_same_seed_same_loop_other_seeds_nearby() -> None:
    world = load_world("corridor")
    a, b = free_loop_box(world, seed=3), free_loop_box(world, seed=3)
    assert a == b
    c = free_loop_box(world, seed=4)
    assert c != a and np.allclose(c, a, atol=0.25)


def test_loop_goes_round_furniture_in_the_middle() -> None:
    table = {"id": "table", "pose": [3.0, 2.0, 0], "boxes": [{"size": [1.2, 0.6], "zmax": 0.8, "texture": "w"}]}
    world = _room_with([table])
    box = free_loop_box(world, seed=0)
    assert box[0] < 3.0 - 0.6 - 0.35 and box[1] > 3.0 + 0.6 + 0.35  # the table inside the loop
    assert _loop_clear(world, box, 0.35)
    # the lab's loop goes round its two benches
    lab = load_world("lab")
    lb = free_loop_box(lab, seed=0)
    for b in lab.geometry().boxes:
        if b.owner.startswith("bench"):
            assert lb[0] < b.cx < lb[1] and lb[2] < b.cy < lb[3]


def test_grid_step_keeps_the_sides_between_grid_lines() -> None:
    world = load_world("lab")
    box = free_loop_box(world, seed=0, grid_step=0.5)
    for v, origin in zip(box, (0.0, 0.0, 0.0, 0.0), strict=True):
        r = (v - origin) % 0.5
        assert min(r, 0.5 - r) >= 0.125 - 1e-9
    assert _loop_clear(world, box, 0.35)


def test_no_room_for_a_loop_is_an_error_naming_the_world() -> None:
    block = {"id": "block", "pose": [3.0, 2.0, 0], "boxes": [{"size": [4.0, 2.0], "zmax": 1.0, "texture": "w"}]}
    with pytest.raises(LinoLocError, match="loop_room"):
        free_loop_box(_room_with([block]), seed=0, lattice=0.5)
    with pytest.raises(LinoLocError, match="bad parameters"):
        free_loop_box(_room_with([]), radius=0.0)

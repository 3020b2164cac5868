"""The reading room (config/worlds/reading_room.json), the held-out check world: no default is
chosen on it (docs/results.md says which figures come from it). It loads with the other
worlds' lights and scene changes, its lights differ, each scene change moves geometry and
shows in a view, the robot has room to drive and survey, and the tracking evaluation runs on
it (tiny sizes)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from world_checks import assert_change_shows, assert_lights_differ

from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.world import World, grid_poses, load_world


@pytest.fixture(scope="module")
def room() -> World:
    return load_world("reading_room")


def test_loads_with_the_lights_and_changes_of_the_other_worlds(room: World) -> None:
    office = load_world("office")
    assert room.lighting_names == office.lighting_names == ("tube", "bulb", "natural")
    assert room.scene_change_names == office.scene_change_names
    xmin, xmax, ymin, ymax = room.mapped_area
    assert (xmax - xmin, ymax - ymin) == pytest.approx((7.0, 4.4))
    # a lane between the south bookcases and the tables, end to end but for the column
    xs = np.linspace(0.3, 6.2, 60)
    assert room.is_free(xs, np.full_like(xs, 0.6), radius=0.35).all()
    assert not room.is_free(np.array([7.0]), np.array([0.2]), radius=0.1).any()  # the column
    poses = grid_poses(room, 0.5, math.radians(10))
    assert 3000 <= len(poses) <= 4500
    assert np.all(room.is_free(poses[:, 0], poses[:, 1], 0.25))


def test_renders_under_every_light_and_the_lights_differ(room: World) -> None:
    assert_lights_differ(room, (1.0, 2.2, math.pi))  # the windows of the west wall


@pytest.mark.parametrize(
    ("change", "pose"),
    [("boxes", (6.0, 3.8, math.pi)), ("moved_furniture", (3.5, 2.2, math.pi)), ("people", (2.0, 0.6, 0.0))],
)
def test_each_scene_change_moves_geometry_and_shows_in_a_view(
    room: World, change: str, pose: tuple[float, float, float]
) -> None:
    assert_change_shows(room, Renderer(room, CameraModel(width=64, height=48), lighting="tube"), change, pose)


def test_the_tracking_evaluation_runs_on_the_reading_room() -> None:
    from services.evaluation import tracking

    res = tracking.run(tracking.TrackingSetup(
        world="reading_room", step=1.0, heading_step_deg=45.0, features=4, preprocess=("none",),
        lights=("tube",), scene_changes=("people",), duration=2.0, rate=2.0, particles=100, switch_lights=None,
        width=80, height=60, size=(40, 30), workers=1))
    assert res["world"] == "reading_room" and res["frames"] == 5
    assert 0.0 <= res["conditions"]["tube"]["mean_error_m"] < 8.0

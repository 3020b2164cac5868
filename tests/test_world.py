"""World files: loading, validation errors, free space, survey grid, floor plan."""

from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from drivers.sim.world import WORLDS_DIR, World, grid_poses, load_world
from lino_loc.errors import LinoLocError


@pytest.fixture(scope="module")
def office() -> World:
    return load_world("office")


@pytest.fixture(scope="module")
def lab() -> World:
    return load_world("lab")


def test_worlds_match_the_paper_areas(office: World, lab: World) -> None:
    xmin, xmax, ymin, ymax = office.mapped_area
    assert (xmax - xmin, ymax - ymin) == pytest.approx((8.0, 2.5))
    xmin, xmax, ymin, ymax = lab.mapped_area
    assert (xmax - xmin, ymax - ymin) == pytest.approx((9.0, 5.0))
    for w in (office, lab):
        assert set(w.lighting_names) >= {"tube", "bulb", "natural"}
        assert set(w.scene_change_names) >= {"boxes", "moved_furniture", "people"}


def test_office_robot_can_stand_everywhere_in_the_mapped_area(office: World) -> None:
    xmin, xmax, ymin, ymax = office.mapped_area
    gx, gy = np.meshgrid(np.linspace(xmin, xmax, 33), np.linspace(ymin, ymax, 11))
    free = office.is_free(gx, gy, radius=0.25)
    assert free.shape == gx.shape
    assert free.all()


def test_lab_survey_grid_has_about_4000_poses(lab: World) -> None:
    poses = grid_poses(lab, 0.5, math.radians(10))
    assert 3500 <= len(poses) <= 5000
    # furniture blocks part of the 19 x 11 grid
    positions = {(round(x, 3), round(y, 3)) for x, y, _ in poses}
    assert len(positions) < 19 * 11
    assert np.all(lab.is_free(poses[:, 0], poses[:, 1], 0.25))


def test_lab_has_windows_all_along_one_wall(lab: World) -> None:
    walls = [w for w in lab.spec.walls if w.windows]
    assert len(walls) == 1
    w = walls[0]
    length = math.dist(w.start, w.end)
    assert sum(win.width for win in w.windows) > 0.6 * length
    assert lab.spec.lighting["natural"].windows_open
    assert not lab.spec.lighting["tube"].windows_open
    assert not lab.spec.lighting["bulb"].windows_open


def test_repeated_identical_elements(office: World, lab: World) -> None:
    for w in (office, lab):
        templates = Counter(f.template for f in w.spec.furniture if f.template)
        assert templates.most_common(1)[0][1] >= 3
        decals = Counter(d.texture for wall in w.spec.walls for d in wall.decals)
        assert decals.most_common(1)[0][1] >= 2


def test_is_free_blocks_furniture_and_walls(office: World) -> None:
    desk = next(b for b in office.geometry().boxes if b.owner == "desk_s1")
    assert not office.is_free(desk.cx, desk.cy, 0.25)
    xmin, xmax, ymin, ymax = office.room
    assert not office.is_free(xmin + 0.1, 1.0, 0.25)
    assert not office.is_free(xmin - 1.0, 1.0, 0.25)  # outside the room
    assert office.is_free(4.0, 1.25, 0.25)


def test_is_mapped_free_is_free_floor_inside_the_mapped_area(office: World) -> None:
    """Where a map's view positions may lie: free as mapped and inside the mapped area, its edges
    included; free floor outside the mapped area and furniture inside it are not."""
    desk = next(b for b in office.geometry().boxes if b.owner == "desk_s1")
    xmin, xmax, ymin, ymax = office.mapped_area
    x = np.array([4.0, xmin, desk.cx, xmax + 0.3])
    y = np.array([1.25, ymin, desk.cy, 1.25])
    assert office.is_free(x, y).tolist() == [True, True, False, True]  # the last: free floor beyond the area
    assert office.is_mapped_free(x, y).tolist() == [True, True, False, False]


def test_grid_poses_order_and_headings(office: World) -> None:
    poses = grid_poses(office, 0.75, math.radians(15))
    assert poses.shape == (11 * 4 * 24, 3)
    assert np.allclose(poses[:24, :2], poses[0, :2])
    assert np.allclose(np.diff(np.unwrap(poses[:24, 2])), math.radians(15))
    # a box in the mapped area removes the positions around it
    people = grid_poses(office, 0.75, math.radians(15), scene_changes=("people",))
    assert len(people) <= len(poses)


def test_scene_changes_add_move_remove(office: World) -> None:
    base = {b.owner for b in office.geometry().boxes}
    people = {b.owner for b in office.geometry(("people",)).boxes}
    assert people - base == {"person1", "person2"}
    moved = office.spec.scene_changes["moved_furniture"].move
    fid, pose = next(iter(moved.items()))
    b0 = next(b for b in office.geometry().boxes if b.owner == fid)
    b1 = next(b for b in office.geometry(("moved_furniture",)).boxes if b.owner == fid)
    assert (b0.cx, b0.cy) != (b1.cx, b1.cy)
    with pytest.raises(LinoLocError, match="unknown scene change"):
        office.geometry(("flood",))


def test_floor_plan(office: World) -> None:
    plan = office.floor_plan()
    assert plan["walls"].shape == (4, 2, 2)
    assert len(plan["boxes"]) == len(office.geometry().boxes)
    assert all(p.shape == (4, 2) for p in plan["boxes"])
    assert plan["windows"].shape[1:] == (2, 2) and len(plan["windows"]) == 3


def _write(tmp_path: Path, data: object, name: str = "bad.json") -> Path:
    p = tmp_path / name
    p.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return p


def _office_data() -> dict:
    return json.loads((WORLDS_DIR / "office.json").read_text())


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda d: d.pop("walls"), "walls"),
        (lambda d: d["walls"][0].__setitem__("texture", "nope"), "walls.0.texture"),
        (lambda d: d["furniture"][0].__setitem__("template", "sofa"), "furniture.0.template"),
        (lambda d: d["templates"]["desk"][0].__setitem__("zmax", -1.0), "templates.desk.0"),
        (lambda d: d.__setitem__("ceiling_height", "high"), "ceiling_height"),
        (lambda d: d["lighting"]["bulb"]["lights"][0].pop("position"), "lighting.bulb.lights.0"),
        (lambda d: d["walls"][1].__setitem__("colour", "red"), "walls.1.colour"),
    ],
)
def test_bad_world_file_names_file_and_field(tmp_path: Path, mutate, field: str) -> None:
    data = _office_data()
    mutate(data)
    path = _write(tmp_path, data)
    with pytest.raises(LinoLocError) as err:
        load_world(path)
    msg = str(err.value)
    assert str(path) in msg
    assert field in msg
    assert "\n" not in msg


def test_bad_json_and_missing_file(tmp_path: Path) -> None:
    path = _write(tmp_path, "{not json")
    with pytest.raises(LinoLocError, match="not valid JSON"):
        load_world(path)
    with pytest.raises(LinoLocError, match="not found"):
        load_world("no_such_world")


def test_plot_floor_plan(office: World) -> None:
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    office.plot_floor_plan(ax, scene_changes=("people",))
    xmin, xmax, ymin, ymax = office.room
    x0, x1 = ax.get_xlim()
    assert x0 <= xmin and x1 >= xmax
    plt.close(fig)

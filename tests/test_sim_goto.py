"""Sending the simulated base to a pose: the path through free space, the controller, and the
``goto`` / ``where`` requests of the simulator's control."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from drivers.sim.fault_control import (
    FaultController,
    Goto,
    RequestError,
    Where,
    parse_request,
    respond,
)
from drivers.sim.free_space import FreeSpace
from drivers.sim.goto import (
    HEADING_TOLERANCE_RAD,
    PATH_CLEARANCE_M,
    POSITION_TOLERANCE_M,
    GotoPlan,
    plan_path,
)
from drivers.sim.robot import base_step
from drivers.sim.world import load_world
from lino_loc.errors import LinoLocError
from lino_loc.poses import wrap_angle


@pytest.fixture(scope="module")
def office_free() -> FreeSpace:
    return FreeSpace(load_world("office"), 0.26)


@pytest.fixture(scope="module")
def lab_free() -> tuple[FreeSpace, FreeSpace]:
    world = load_world("lab")  # the lab's furniture stands in the mapped area
    return FreeSpace(world, 0.26), FreeSpace(world, 0.26 + PATH_CLEARANCE_M)


def _blocked_pairs(free: FreeSpace, n: int, seed: int = 3) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    rng = np.random.default_rng(seed)
    x0, x1, y0, y1 = free.world.mapped_area
    pts = [p for p in zip(rng.uniform(x0, x1, 400), rng.uniform(y0, y1, 400), strict=True) if free.free_point(*p)]
    pairs = []
    for a, b in zip(pts[::2], pts[1::2], strict=False):
        if not free.segment_free(a, b):
            pairs.append((a, b))
        if len(pairs) == n:
            break
    assert len(pairs) == n, "the world should have furniture between some free points"
    return pairs


def _drive(free: FreeSpace, plan: GotoPlan, start: tuple[float, float, float], seconds: float = 120.0):
    pose = start
    dt = 0.02
    for _ in range(int(seconds / dt)):
        _, _, pose, _ = base_step(pose, plan, free, dt)
        if plan.state != "driving":
            break
    return pose


def test_path_goes_around_furniture_and_the_base_follows_it(lab_free):
    free, wide = lab_free
    for a, b in _blocked_pairs(free, 5):
        path = plan_path(free, a, b, wide=wide)
        assert path[0] == a and path[-1] == b and len(path) > 2
        assert all(free.segment_free(p, q) for p, q in zip(path, path[1:], strict=False))
        plan = GotoPlan(path, theta=1.0, speed=0.5)
        end = _drive(free, plan, (a[0], a[1], -2.0))
        assert plan.state == "arrived"
        assert math.dist(end[:2], b) < POSITION_TOLERANCE_M
        assert abs(float(wrap_angle(end[2] - 1.0))) < HEADING_TOLERANCE_RAD


def test_goal_that_is_not_free_space_is_refused(office_free):
    with pytest.raises(LinoLocError, match="not free space"):
        plan_path(office_free, (4.0, 1.25), (-5.0, 1.0))


def test_goto_and_where_requests_validate():
    assert isinstance(parse_request(b'{"cmd": "goto", "x": 1, "y": 2}'), Goto)
    assert isinstance(parse_request(b'{"cmd": "where"}'), Where)
    for raw, needle in ((b'{"cmd": "goto", "x": 1}', "goto: y"), (b'{"cmd": "goto", "x": 1, "y": "a"}', "goto: y"),
                        (b'{"cmd": "goto", "x": 1, "y": 1, "speed": -1}', "speed"),
                        (b'{"cmd": "goto", "x": 1, "y": 1, "z": 0}', "z")):
        with pytest.raises(RequestError, match=needle):
            parse_request(raw)


class _Robot:
    """What the controller needs of a robot for goto/where, with the real path planner."""

    def __init__(self, free: FreeSpace) -> None:
        self.free = free
        self.plan: GotoPlan | None = None
        self.config = None

    def goto(self, x: float, y: float, theta: float, speed: float | None = None) -> GotoPlan:
        self.plan = GotoPlan(plan_path(self.free, (4.0, 1.25), (x, y)), theta)
        return self.plan

    def where(self) -> dict:
        return {"pose": [4.0, 1.25, 0.0], "state": self.plan.state if self.plan else "idle"}


def test_controller_answers_goto_and_where_and_refuses_an_unreachable_goal(office_free):
    ctl = FaultController(_Robot(office_free))
    assert respond(ctl, [b'{"cmd": "where"}'])["state"] == "idle"
    reply = respond(ctl, [json.dumps({"cmd": "goto", "x": 3.0, "y": 0.5, "theta": 0.5}).encode()])
    assert reply["ok"] and reply["goal"] == [3.0, 0.5, 0.5]
    assert respond(ctl, [b'{"cmd": "where"}'])["state"] == "driving"
    bad = respond(ctl, [b'{"cmd": "goto", "x": -5.0, "y": 1.0}'])
    assert bad["ok"] is False and "not free space" in bad["error"]


def test_a_goal_on_the_edge_of_free_space_is_reached_from_inside_it():
    """In the corridor the stops at y = 1.25 lie on the edge of the base's free space: a path
    along that edge stops the base at the smallest heading error (seen in a survey)."""
    world = load_world("corridor")
    free, wide = FreeSpace(world, 0.26), FreeSpace(world, 0.26 + PATH_CLEARANCE_M)
    a, b = (2.75, 1.25), (2.0, 1.25)
    assert free.segment_free(a, b) and not free.free_point(2.74, 1.2507)  # the edge, just above
    path = plan_path(free, a, b, wide=wide)
    assert len(path) > 2  # not the straight segment along the edge
    plan = GotoPlan(path, theta=0.0, speed=0.5)
    end = _drive(free, plan, (a[0], a[1], 1.065))
    assert plan.state == "arrived" and math.dist(end[:2], b) < POSITION_TOLERANCE_M

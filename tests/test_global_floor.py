"""Global localization on a floor of rooms with the camera fixed and turned by active vision
(services/evaluation/global_loc.py): the convergence measure, the simulated head, the frames
rendered on the way, and a small seeded run of both cameras on the same starts."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivers.sim.floor_world import corridor_floor
from services.cli import main as cli_main
from services.evaluation import global_loc
from services.evaluation.views import (
    ViewSpec,
    build_sim_maps,
    frame_renderer,
    render_frame,
    render_frames,
)

SMALL = {"width": 80, "height": 60, "size": (40, 30)}


def test_converged_update_is_the_start_of_the_last_run_of_successes() -> None:
    f = global_loc.converged_update
    assert f(np.array([1, 1, 1], bool)) == 1
    assert f(np.array([0, 1, 0, 1, 1], bool)) == 4
    assert f(np.array([1, 1, 0], bool)) is None
    assert f(np.array([], bool)) is None
    conv = global_loc._convergence(np.array([[0, 1, 1], [1, 0, 1], [1, 1, 0]], bool), rate=2.0)
    assert conv["converged_update"] == [2, 3, None]
    assert conv["converged_by_update"] == pytest.approx([0.0, 1 / 3, 2 / 3])
    assert conv["converge"] == {"share": pytest.approx(2 / 3), "median_updates": 2.5, "median_s": 1.25}
    err = np.array([[3.0, 0.4, 0.6, 0.2], [0.1, 0.1, 0.1, 0.1], [0.2, 0.2, 0.2, 0.9]])
    w = global_loc._within_step(err, step=0.5, rate=4.0)
    assert w["update"] == [4, 1, None] and w["threshold_m"] == 0.5
    assert w["share"] == pytest.approx(2 / 3) and w["median_updates"] == 2.5 and w["median_s"] == 0.625


def test_the_head_turns_at_its_speed_and_stops_at_the_goal() -> None:
    head = global_loc.Head(speed=1.5)
    assert head.at(0.0) == (0.0, False)
    head.command(1.0, 1.5)  # 1.5 rad at 1.5 rad/s: arrives at t = 2
    assert head.arrive == pytest.approx(2.0) and not head.reported
    pan, moving = head.at(1.5)
    assert moving and pan == pytest.approx(0.75)
    assert head.at(2.0) == (1.5, False)
    head.command(1.5, -1.5)  # turned back half way: from 0.75 to -1.5, 2.25 rad
    assert head.pan == pytest.approx(0.75) and head.arrive == pytest.approx(3.0)


@pytest.fixture(scope="module")
def floor2(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("floor") / "floor2.json"
    path.write_text(json.dumps(corridor_floor(1)), encoding="utf-8")
    return str(path)


def test_a_frame_at_pan_zero_is_the_fixed_cameras_frame(floor2: str) -> None:
    spec = ViewSpec(world=floor2, width=80, height=60, size=(40, 30), seed=3)
    poses = np.array([[2.0, 3.0, 0.4], [5.0, 2.0, -2.0], [3.0, 8.0, 1.0]])
    fixed, _ = render_frames(spec, poses, workers=1)
    r = frame_renderer(spec)
    for i, p in enumerate(poses):
        grey, disp = render_frame(r, spec, p, 0.0, i)
        assert disp is None
        np.testing.assert_array_equal(grey, fixed[i])
    turned, _ = render_frame(r, spec, poses[0], 1.2, 0)
    assert np.abs(turned.astype(int) - fixed[0].astype(int)).mean() > 5.0  # it does look elsewhere


def test_both_cameras_run_paired_on_a_floor(floor2: str) -> None:
    setup = global_loc.GlobalSetup(world=floor2, step=1.0, heading_step_deg=45.0, features=4, virtual_headings=1,
                                   starts=2, updates=8, workers=1, seed=1, **SMALL)
    amap = build_sim_maps(floor2, 1.0, 45.0, 4, ("none",), cache=False, workers=1, **SMALL)["none"]
    res = global_loc.run_grid(setup, (100, 300), global_loc.CAMERAS, appearance_map=amap)
    runs = res["runs"]
    assert [(r["particles"], r["camera"]) for r in runs] == [(100, "fixed"), (100, "active"),
                                                             (300, "fixed"), (300, "active")]
    cells = {"s0", "n0", "corridor"} | {f"passage{i}" for i in range(10)}
    for r in runs:
        assert len(r["success"]) == len(r["converged_by_update"]) == 8
        assert all(0.0 <= v <= 1.0 for v in r["success"] + r["converged_by_update"])
        assert r["converged_by_update"] == sorted(r["converged_by_update"])  # a share that only grows
        w = r["converged_within_step"]
        assert len(w["update"]) == len(r["final_error_m"]) == 2
        assert all((u is None) == (e > 1.0) for u, e in zip(w["update"], r["final_error_m"], strict=True))
        assert len(r["start_cells"]) == 2 and all(c is None or c in cells or c.startswith("door") for c in
                                                  r["start_cells"])
    for fixed, active in ((runs[0], runs[1]), (runs[2], runs[3])):
        # the same initial particles and the same first frame (pan 0): the same first estimate
        assert active["mean_error_m"][0] == pytest.approx(fixed["mean_error_m"][0], abs=1e-12)
        assert fixed["head_commands_mean"] == 0.0 and fixed["unused_frame_share"] == 0.0
        assert active["head_commands_mean"] >= 1.0 and 0.0 <= active["unused_frame_share"] < 1.0
        assert active["policy_cpu_ms"] is not None and fixed["policy_cpu_ms"] is None


def test_the_active_head_turns_at_its_speed_and_frames_wait_for_it(floor2: str) -> None:
    setup = global_loc.GlobalSetup(world=floor2, step=1.0, heading_step_deg=45.0, features=4, virtual_headings=1,
                                   starts=1, updates=12, workers=1, particles=100, camera="active", head_speed=1.0,
                                   **SMALL)
    amap = build_sim_maps(floor2, 1.0, 45.0, 4, ("none",), cache=False, workers=1, **SMALL)["none"]
    inp = global_loc.prepare(setup, amap)
    out = global_loc.run_start(inp, global_loc.localizer_config(setup, None), "active", 0)
    dt, settle = 1.0 / setup.rate, setup.active_vision.settle_s
    step = np.abs(np.diff(out.pans))
    assert out.commands >= 1 and step.max() > 0.0
    assert step.max() <= setup.head_speed * dt + 1e-9  # never faster than the head
    assert np.all(np.abs(out.pans) <= setup.active_vision.pan_max + 1e-9)
    # a frame after a turn too long to finish and settle within one frame interval is not used
    too_long = np.flatnonzero(step / setup.head_speed + settle > dt + 1e-9) + 1
    assert too_long.size and not out.used[too_long].any()
    assert out.used[0] and len(out.policy_ms) == 12 and len(out.update_ms) == out.used.sum()
    # the action evaluator is built once per sensor configuration, and reusing it changes nothing
    again = global_loc.run_start(inp, global_loc.localizer_config(setup, None), "active", 0)
    assert len(inp.evaluators) == 1
    np.testing.assert_array_equal(again.est, out.est)
    np.testing.assert_array_equal(again.pans, out.pans)


@pytest.mark.parametrize(("args", "message"), [
    (["--particles", "0"], "--particles"),
    (["--particles", "1000,x"], "--particles"),
    (["--camera", "sideways"], "--camera"),
    (["--camera", "fixed,fixed"], "--camera"),
    (["--head-speed", "0"], "--head-speed"),
])
def test_global_cli_rejects_bad_options_in_one_line(args: list[str], message: str, capsys) -> None:
    assert cli_main(["eval", "global", "--starts", "1", "--updates", "1", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]

"""`lino-loc eval active` on a tiny office map (coarse grid, few positions): JSON contract,
plots, argument errors. The full experiment's figures are in docs/evaluations.md."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from services.cli import main
from services.evaluation.active import place_test_positions
from services.evaluation.active_setup import ActiveSetup

TINY = ["--step", "2.0", "--heading-step", "45", "--positions", "2", "--runs", "2", "--movements", "2",
        "--actions", "4", "--particles", "60", "--workers", "1"]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, object]:
    import contextlib
    import io

    out_dir = tmp_path_factory.mktemp("plots")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        status = main(["eval", "active", "--json", "--plot", str(out_dir), "--scene-changes", "boxes", *TINY])
    assert status == 0
    lines = [ln for ln in buf.getvalue().splitlines() if ln.strip()]
    assert len(lines) == 1  # exactly one JSON object on stdout
    return json.loads(lines[0]), out_dir


def test_json_has_the_contract_keys(tiny_run: tuple[dict, object]) -> None:
    res, _ = tiny_run
    assert res["positions"] == 2 and res["runs"] == 2
    assert set(res["strategies"]) == {"entropy", "random", "sweep"}
    for block in (res["strategies"], res["scene_changes"]["strategies"]):
        for r in block.values():
            for key in ("mean_error_m", "std_error_m", "success", "success_pose"):
                assert len(r[key]) == 3  # 0..2 movements
            assert all(0.0 <= v <= 1.0 for v in r["success"] + r["success_pose"])
            # the (x, y, theta) cell criterion is stricter than the paper's position criterion
            assert all(p >= q for p, q in zip(r["success"], r["success_pose"], strict=True))
            assert all(v >= 0.0 for v in r["mean_error_m"] + r["std_error_m"])
    assert res["scene_changes"]["names"] == ["boxes"]
    # the default map: every image also turned by -6, -3, +3, +6 deg (lino_loc.virtual_views)
    assert res["map_entries"] == 5 * res["map_images"]
    for bands in (res["success_by_grid_distance"], res["scene_changes"]["success_by_grid_distance"]):
        assert sum(b["positions"] for b in bands.values()) == res["positions"]
        for b in bands.values():
            for s in ("entropy", "random", "sweep"):
                assert s not in b or len(b[s]) == 3
    for diag in res["diagnostics"].values():
        assert all(0.0 <= v <= 1.0 for v in diag.values() if isinstance(v, float))
        assert "truth_cell_among_j_nearest" in diag and "initial_particle_in_truth_cell" in diag
    # every strategy starts from the same first image and particles: identical at 0 movements
    first = {s: (r["mean_error_m"][0], r["success"][0]) for s, r in res["strategies"].items()}
    assert len(set(first.values())) == 1


def test_plots_are_written(tiny_run: tuple[dict, object]) -> None:
    _, out_dir = tiny_run
    for name in ("active_fig3_error.png", "active_fig4_particles.png"):
        f = out_dir / name  # type: ignore[operator]
        assert f.is_file() and f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_test_positions_are_free_and_off_the_grid() -> None:
    from drivers.sim.world import grid_poses, load_world

    world = load_world("office")
    setup = ActiveSetup(positions=15, scene_changes=("boxes",))
    grid = grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    t = place_test_positions(world, setup, grid)
    assert t.shape == (15, 3)
    assert world.is_free(t[:, 0], t[:, 1]).all()
    assert world.is_free(t[:, 0], t[:, 1], scene_changes=("boxes",)).all()
    d = np.hypot(t[:, None, 0] - grid[None, :, 0], t[:, None, 1] - grid[None, :, 1]).min(axis=1)
    assert (d >= setup.min_grid_distance).all()


def test_plain_map_has_one_entry_per_image(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "active", "--json", *TINY, "--virtual-headings", "1", "--movements", "1"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["map_entries"] == res["map_images"]


@pytest.mark.parametrize("bad", [["--positions", "0"], ["--scene-changes", "no_such_change"],
                                 ["--virtual-headings", "0"], ["--residual-scale", "0"]])
def test_bad_arguments_exit_2(bad: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "active", *TINY, *bad]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.strip()


def test_setup_report_is_the_flat_setup_of_the_result() -> None:
    """The result's ``setup`` object keeps its keys, order and values: the sensor-model and
    action-evaluation settings the setup composes are inlined."""
    expected = {
        "world": "office", "lighting": "tube", "step": 0.75, "heading_step_deg": 15.0, "virtual_headings": 5,
        "virtual_step_deg": 3.0, "features": 5, "preprocess": "none", "j": 10, "sigma_xy": 0.35,
        "sigma_theta": 0.3, "outlier_weight": 0.01, "particles": 150, "eval_particles": 150, "roughen_xy": 0.0,
        "roughen_theta": 0.0, "inject": 0.0, "n_actions": 22, "predicted_neighbours": "all", "pan_min": -2.6,
        "pan_max": 2.6, "positions": 20, "runs": 10, "movements": 10, "scene_changes": [],
        "min_grid_distance": 0.15, "sweep_stride": 7, "width": 320, "height": 240, "size": [80, 60], "seed": 0,
        "strategies": ["entropy", "random", "sweep"], "filter": {}, "motion": {}, "channels": ["intensity"],
    }
    report = ActiveSetup().report()
    assert report == expected and list(report) == list(expected)


def test_the_disparity_channel_is_fused_into_the_filter(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "active", "--json", *TINY, "--movements", "1", "--channels", "intensity,disparity"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["setup"]["channels"] == ["intensity", "disparity"]
    for strat in res["strategies"].values():
        assert all(math.isfinite(v) for v in strat["mean_error_m"])


def test_the_interpolated_sensor_model_runs_the_experiment(capsys: pytest.CaptureFixture[str]) -> None:
    """``--sensor-model interpolated``: the filter and H(u) with lino_loc.interpolated_appearance,
    also with both channels fused; the setup reports it."""
    assert main(["eval", "active", "--json", *TINY, "--movements", "1", "--sensor-model", "interpolated",
                 "--channels", "intensity,disparity"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["setup"]["sensor_model"] == "interpolated" and res["setup"]["residual_scale"] == 1.0
    for s in res["strategies"].values():
        assert len(s["success"]) == 2 and all(0.0 <= v <= 1.0 for v in s["success"])

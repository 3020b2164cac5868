"""`lino-loc eval active` on a tiny office map (coarse grid, few positions): JSON contract,
plots, argument errors. The full experiment's figures are in docs/evaluations.md."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from services.cli import main
from services.evaluation.active import place_test_positions
from services.evaluation.active_setup import ActiveSetup, paper_setup, product_defaults

TINY = ["--step", "2.0", "--heading-step", "45", "--positions", "2", "--runs", "2", "--movements", "2",
        "--actions", "4", "--particles", "60", "--workers", "1"]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, object]:
    import contextlib
    import io

    out_dir = tmp_path_factory.mktemp("plots")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        status = main(["eval", "active", "--json", "--plot", str(out_dir), "--scene-changes", "boxes", "--ideal",
                       *TINY])
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
    assert set(res["scene_changes"]["chosen_view_change"]) == {"entropy", "random", "sweep"}
    assert all(v >= 0.0 for v in res["scene_changes"]["chosen_view_change"].values())
    # the default map: every survey image also seen from its cell's lattice (translations = 3: up to
    # 9 positions, those on free floor), every view also turned by -6, -3, +3, +6 deg
    assert res["map_entries"] % 5 == 0 and res["map_images"] < res["map_entries"] // 5 <= 9 * res["map_images"]
    for bands in (res["success_by_grid_distance"], res["scene_changes"]["success_by_grid_distance"]):
        assert sum(b["positions"] for b in bands.values()) == res["positions"]
        for b in bands.values():
            for s in ("entropy", "random", "sweep"):
                assert s not in b or len(b[s]) == 3
    for diag in res["diagnostics"].values():
        assert all(0.0 <= v <= 1.0 for k, v in diag.items()
                   if isinstance(v, float) and k != "j_neighbours_distinct_positions")
        assert "truth_cell_among_j_nearest" in diag and "initial_particle_in_truth_cell" in diag
        assert 1.0 <= diag["j_neighbours_distinct_positions"] <= res["setup"]["j"]
    # every strategy starts from the same first image and particles: identical at 0 movements
    first = {s: (r["mean_error_m"][0], r["success"][0]) for s, r in res["strategies"].items()}
    assert len(set(first.values())) == 1


def _within(ci: list[float], value: float) -> bool:
    return len(ci) == 2 and 0.0 <= ci[0] <= value + 1e-9 and value - 1e-9 <= ci[1] <= 1.0


def test_every_success_figure_carries_its_95_percent_interval(tiny_run: tuple[dict, object]) -> None:
    res, _ = tiny_run
    assert res["intervals"] == {"method": "bootstrap over positions then runs", "interval": "percentile",
                                "level": 0.95, "resamples": 2000, "seed": 0}
    for cond in (res, res["scene_changes"]):
        for r in cond["strategies"].values():
            for key in ("success", "success_pose"):
                assert len(r[f"{key}_ci95"]) == len(r[key])
                assert all(_within(ci, v) for ci, v in zip(r[f"{key}_ci95"], r[key], strict=True))
        for b in cond["success_by_grid_distance"].values():
            for s in ("entropy", "random", "sweep"):
                if s in b:
                    assert all(_within(ci, v) for ci, v in zip(b[f"{s}_ci95"], b[s], strict=True))
    for diag in res["diagnostics"].values():
        for key in ("ideal_map_estimate_success", "map_oracle_success"):
            assert set(diag[f"{key}_ci95"]) == set(diag[key])
            assert all(_within(diag[f"{key}_ci95"][k], v) for k, v in diag[key].items())


def test_paired_comparisons_of_the_strategies(tiny_run: tuple[dict, object]) -> None:
    """entropy - random and entropy - sweep per movement: the mean paired difference of
    success, its bootstrap SE, and ahead = difference > SE (0 movements: the same run)."""
    res, _ = tiny_run
    for cond in (res, res["scene_changes"]):
        comp = cond["comparisons"]
        assert comp["se_method"] == "bootstrap over positions then runs"
        assert set(comp) == {"se_method", "entropy-random", "entropy-sweep"}
        for other in ("random", "sweep"):
            c = comp[f"entropy-{other}"]
            s = cond["strategies"]
            want = [a - b for a, b in zip(s["entropy"]["success"], s[other]["success"], strict=True)]
            assert c["difference"] == pytest.approx(want, abs=1e-4)
            assert c["difference"][0] == 0.0 and c["se"][0] == 0.0 and c["ahead"][0] is False
            assert all(se >= 0.0 for se in c["se"])
            assert c["ahead"] == [d > se for d, se in zip(c["difference"], c["se"], strict=True)]


def test_the_table_prints_the_intervals_and_comparisons(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "active", *TINY, "--positions", "1", "--runs", "1"]) == 0
    out = capsys.readouterr().out
    assert "95 %" in out and "bootstrap over positions then runs (2000 resamples, seed 0)" in out
    for name in ("entropy - random", "entropy - sweep"):
        line = next(ln for ln in out.splitlines() if ln.strip().startswith(name))
        assert "k=1" in line and "k=2" in line and "SE" in line


def test_plots_are_written(tiny_run: tuple[dict, object]) -> None:
    _, out_dir = tiny_run
    for name in ("active_fig3_error.png", "active_fig4_particles.png"):
        f = out_dir / name  # type: ignore[operator]
        assert f.is_file() and f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("world_name", ["office", "lab", "corridor"])
def test_test_positions_are_free_and_off_the_grid(world_name: str) -> None:
    """The default 50 test positions: distinct, free (also with all the world's scene
    changes), at least min_grid_distance from every grid position."""
    from drivers.sim.world import grid_poses, load_world

    world = load_world(world_name)
    setup = ActiveSetup(world=world_name, scene_changes=world.scene_change_names)
    grid = grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    t = place_test_positions(world, setup, grid)
    assert t.shape == (50, 3) and setup.positions == 50
    assert np.unique(np.round(t[:, :2], 3), axis=0).shape[0] == 50
    assert world.is_free(t[:, 0], t[:, 1]).all()
    assert world.is_free(t[:, 0], t[:, 1], scene_changes=setup.scene_changes).all()
    d = np.hypot(t[:, None, 0] - grid[None, :, 0], t[:, None, 1] - grid[None, :, 1]).min(axis=1)
    assert (d >= setup.min_grid_distance).all()


def test_plain_map_has_one_entry_per_image(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "active", "--json", *TINY, "--virtual-headings", "1", "--translations", "1",
                 "--movements", "1"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["map_entries"] == res["map_images"]


@pytest.mark.parametrize("bad", [["--positions", "0"], ["--scene-changes", "no_such_change"],
                                 ["--virtual-headings", "0"], ["--residual-scale", "0"], ["--actions", "1"]])
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
        "pan_max": 2.6, "positions": 50, "runs": 10, "movements": 10, "scene_changes": [],
        "min_grid_distance": 0.15, "sweep_stride": 7, "width": 320, "height": 240, "size": [80, 60], "seed": 0,
        "strategies": ["entropy", "random", "sweep"], "filter": {}, "motion": {}, "channels": ["intensity"],
        "paper": False,
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


def test_product_defaults_are_the_commands_defaults() -> None:
    """The command's method options default to product_defaults() (the one place to change them)."""
    from services.cli import build_parser
    from services.evaluation.commands.active_cmd import _setup

    args = build_parser().parse_args(["eval", "active"])
    assert _setup(args, ()) == product_defaults()
    d = product_defaults().report()
    assert d["positions"] == 50 and d["runs"] == 10 and d["paper"] is False
    assert (d["virtual_headings"], d["features"], d["j"], d["particles"], d["n_actions"]) == (5, 20, 10, 150, 22)
    # the simulated service's map (config/sim.toml): both channels, 5 disparity features
    assert d["channels"] == ["intensity", "disparity"] and d["disparity_features"] == 5
    assert d["translations"] == 3  # and the views between the survey positions, as config/sim.toml
    assert d["filter"] == {"global_proposal_fraction": 0.5}
    assert d["motion"] == {"min_sigma_xy": 0.01, "min_sigma_theta": pytest.approx(math.radians(0.5))}
    assert d["pan_reliability"]["enabled"] is True  # lino_loc.pan_reliability, on for the product


def test_the_kernel_width_option(capsys: pytest.CaptureFixture[str]) -> None:
    """``--sigma-xy`` sets the sensor model's kernel width; a width that is not positive is a
    one-line error naming the option."""
    from services.cli import build_parser
    from services.evaluation.commands.active_cmd import _setup

    args = build_parser().parse_args(["eval", "active", "--sigma-xy", "0.2"])
    assert _setup(args, ()).sensor.sigma_xy == 0.2
    assert main(["eval", "active", *TINY, "--sigma-xy", "0"]) == 2
    err = capsys.readouterr().err
    assert "--sigma-xy" in err and "Traceback" not in err


def test_the_map_memory_budget_option(capsys: pytest.CaptureFixture[str]) -> None:
    """``--map-memory-budget`` reaches the setup and its report (absent by default, so default
    reports stay as they were); a budget that is not positive is a one-line error."""
    from services.cli import build_parser
    from services.evaluation.commands.active_cmd import _setup

    args = build_parser().parse_args(["eval", "active", "--map-memory-budget", "2048"])
    setup = _setup(args, ())
    assert setup.map_memory_budget_mb == 2048.0 and setup.report()["map_memory_budget_mb"] == 2048.0
    assert "map_memory_budget_mb" not in product_defaults().report()
    assert main(["eval", "active", *TINY, "--map-memory-budget", "0"]) == 2
    err = capsys.readouterr().err
    assert "--map-memory-budget" in err and "Traceback" not in err


def test_paper_setup_is_section_6_1() -> None:
    """--paper: intensity alone, no virtual headings, 5 features, no preprocessing, the
    nearest-neighbour sensor model with J = 10, 150 particles, 22 pans, survey 75 cm / 15 deg."""
    r = paper_setup(world="lab", positions=7).report()
    want = {"step": 0.75, "heading_step_deg": 15.0, "virtual_headings": 1, "features": 5, "preprocess": "none",
            "channels": ["intensity"], "j": 10, "particles": 150, "n_actions": 22, "eval_particles": 150,
            "world": "lab", "positions": 7, "paper": True}
    assert {k: r[k] for k in want} == want
    assert "sensor_model" not in r  # the nearest-neighbour model (the report names only the other)
    assert "pan_reliability" not in r  # the paper's H(u), undiscounted
    with pytest.raises(ValueError, match="features"):
        paper_setup(features=7)


def test_paper_on_the_command_line(capsys: pytest.CaptureFixture[str]) -> None:
    """``--paper`` builds paper_setup(); an option it fixes is accepted with the paper's value
    and is an error in one line (exit 2) with another; the options it leaves free still apply."""
    from services.cli import build_parser
    from services.evaluation.commands.active_cmd import _setup

    parse = build_parser().parse_args
    args = parse(["eval", "active", "--paper", "--positions", "3", "--features", "5", "--seed", "4",
                  "--eval-particles", "100"])
    got = _setup(args, ())
    assert got.paper and got.positions == 3 and got.seed == 4 and got.active.max_particles == 100
    assert got == dataclasses.replace(paper_setup(positions=3, seed=4),
                                      active=paper_setup().active.model_copy(update={"max_particles": 100}))
    for bad in (["--virtual-headings", "5"], ["--features", "7"], ["--channels", "intensity,disparity"],
                ["--sensor-model", "interpolated"], ["--step", "1.0"], ["--particles", "60"],
                ["--pan-reliability", "on"]):
        assert main(["eval", "active", "--paper", *bad]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and "--paper fixes" in err


@pytest.mark.slow
def test_paper_runs_the_papers_map(capsys: pytest.CaptureFixture[str]) -> None:
    """One position, one run, one movement of `eval active --paper` (the paper's full office
    survey: 1056 images, no virtual headings)."""
    assert main(["eval", "active", "--json", "--paper", "--positions", "1", "--runs", "1", "--movements", "1",
                 "--workers", "1"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["setup"]["paper"] is True and res["map_entries"] == res["map_images"] == 1056
    assert all(len(r["success_ci95"]) == 2 for r in res["strategies"].values())


def test_virtual_translations_fill_the_survey_cells(capsys: pytest.CaptureFixture[str]) -> None:
    """``--translations 3``: every survey image also gives the views of its cell's 25 cm lattice
    (free positions), so the map holds more entries than images x virtual headings, in both
    channels; success is still judged on the survey's own grid. An even refinement is a
    one-line error."""
    assert main(["eval", "active", "--json", *TINY, "--movements", "1", "--virtual-headings", "1",
                 "--translations", "3", "--channels", "intensity,disparity"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["setup"]["translations"] == 3 and res["setup"]["channels"] == ["intensity", "disparity"]
    assert res["map_images"] < res["map_entries"] <= 9 * res["map_images"]
    for bad, text in ((["--translations", "2", "--channels", "intensity"], "odd"),
                      (["--translations", "-1"], "odd")):
        assert main(["eval", "active", *TINY, *bad]) == 2
        err = capsys.readouterr().err
        assert text in err and "Traceback" not in err


def test_the_strategies_option_runs_the_lattice_strategy(capsys: pytest.CaptureFixture[str]) -> None:
    """``--strategies lattice,random``: the first strategy is compared with the others, the
    lattice strategy's settings are reported; an unknown or repeated strategy is a one-line
    error."""
    assert main(["eval", "active", "--json", *TINY, "--translations", "3", "--channels", "intensity",
                 "--strategies", "lattice,random"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert list(res["strategies"]) == ["lattice", "random"]
    assert "lattice-random" in res["comparisons"]
    assert res["setup"]["lattice_gate"] == 0.5 and res["setup"]["view_match"]["radius"] == 0.5
    for bad in ("entropy,nope", "random,random", ","):
        assert main(["eval", "active", *TINY, "--strategies", bad]) == 2
        err = capsys.readouterr().err
        assert "--strategies" in err and "Traceback" not in err


def test_the_standing_options_reach_the_standing_match(capsys: pytest.CaptureFixture[str]) -> None:
    """``--standing-match``, ``--standing-subcell`` and ``--standing-views`` set the standing
    match's settings, reported in the result's setup (the views' choice is the service's
    default, on); ``--paper`` fixes them off."""
    from services.cli import build_parser
    from services.evaluation.commands.active_cmd import _setup

    parse = build_parser().parse_args
    default = _setup(parse(["eval", "active"]), ())
    assert default.standing_match.enabled and default.standing_match.subcell and default.standing_match.choose_views
    got = _setup(parse(["eval", "active", "--standing-views", "off", "--standing-subcell", "off"]), ())
    assert got.standing_match.enabled and not got.standing_match.choose_views and not got.standing_match.subcell
    assert got.report()["standing_match"]["choose_views"] is False
    assert not _setup(parse(["eval", "active", "--standing-match", "off"]), ()).standing_match.enabled
    assert main(["eval", "active", "--paper", "--standing-views", "on", "--positions", "1"]) == 2
    err = capsys.readouterr().err
    assert "--paper fixes --standing-views off" in err and "Traceback" not in err

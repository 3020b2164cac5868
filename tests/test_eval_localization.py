"""Localization evaluations on tiny inputs: leave-out with a known answer, global and tracking
machinery (lengths, bounds, files), the convergence time, and the CLI."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from lino_loc.dataset import CameraInfo, DatasetMeta, DatasetWriter
from lino_loc.localizer import LocalizerConfig
from services.cli import main as cli_main
from services.evaluation import global_loc, leave_out, tracking
from services.evaluation.frame_trace import COLUMNS
from services.evaluation.trajectories import read_tum
from services.evaluation.views import build_sim_maps

SMALL = {"width": 80, "height": 60, "size": (40, 30)}


# --------------------------------------------------------------------------- leave-out


def _line_dataset(root, n=21, spacing=0.1):
    """Frames along a straight line (x = k * spacing, heading 0.3): the image is a sinusoid whose
    phase is proportional to x (half a period over the whole line), so feature space is an arc
    ordered like x and the nearest map frame in feature space is the nearest in x."""
    cam = CameraInfo(width=32, height=24, fx=30, fy=30, cx=15.5, cy=11.5)
    u = np.arange(32)[None, :] * np.ones((24, 1))
    length = n * spacing
    with DatasetWriter(root, DatasetMeta(name="line", camera=cam)) as w:
        for k in range(n):
            x = k * spacing
            img = 128 + 100 * np.sin(2 * np.pi * u / 32 + np.pi * x / length)
            w.add(np.clip(img, 0, 255).astype(np.uint8), (x, 1.0, 0.3))
    return root


def test_leave_out_on_a_line_finds_the_neighbouring_frames(tmp_path) -> None:
    ds = _line_dataset(tmp_path / "line")
    res = leave_out.run(ds, every=2, features=2, j=2, size=(32, 24))
    assert res["frames_map"] == 10 and res["frames_test"] == 11 and res["J"] == 2
    # held out: x = 0, 0.2, ..., 2.0; map: 0.1, 0.3, ..., 1.9 -> the nearest map frame is 0.1 m away
    assert res["floor_m"]["mean"] == pytest.approx(0.1, abs=1e-9)
    assert res["top1_error_m"]["mean"] == pytest.approx(0.1, abs=1e-9)
    assert res["top1_error_m"]["std"] == pytest.approx(0.0, abs=1e-9)
    assert res["error_m"]["mean"] == pytest.approx(0.1, abs=1e-9)  # best of J can't beat the floor
    assert res["heading_error_deg"]["median"] == pytest.approx(0.0, abs=1e-9)
    assert res["random_m"]["mean"] > 0.5  # chance level is far worse


def test_leave_out_error_lies_between_floor_and_top1(tmp_path) -> None:
    ds = _line_dataset(tmp_path / "line", n=30, spacing=0.05)
    res = leave_out.run(ds, every=3, features=3, j=5, size=(32, 24))
    assert res["floor_m"]["mean"] <= res["error_m"]["mean"] + 1e-12 <= res["top1_error_m"]["mean"] + 2e-12
    assert set(res) >= {"J", "frames_map", "frames_test", "error_m", "top1_error_m", "heading_error_deg", "floor_m"}
    assert set(res["error_m"]) == {"mean", "median", "std"}
    assert set(res["heading_error_deg"]) == {"mean", "median"}


def test_leave_out_user_errors(tmp_path) -> None:
    from lino_loc.errors import LinoLocError

    ds = _line_dataset(tmp_path / "line", n=8)
    with pytest.raises(LinoLocError, match="--every"):
        leave_out.run(ds, every=1)
    with pytest.raises(LinoLocError, match="--features"):
        leave_out.run(ds, every=2, features=10)


def test_leave_out_cli_prints_one_json_object(tmp_path, capsys) -> None:
    ds = _line_dataset(tmp_path / "line")
    assert cli_main(["eval", "leave-out", str(ds), "--every", "2", "--features", "2", "--j", "3", "--json"]) == 0
    out = capsys.readouterr().out
    assert len(out.strip().splitlines()) == 1
    assert json.loads(out)["frames_test"] == 11
    assert cli_main(["eval", "leave-out", str(tmp_path / "nope"), "--json"]) == 2


# --------------------------------------------------------------------------- simulated runs


@pytest.fixture(scope="module")
def office_map():
    return build_sim_maps("office", 1.5, 45.0, 4, ("none",), cache=False, workers=1, **SMALL)["none"]


def test_global_eval_lists_have_one_value_per_update_and_are_bounded(office_map) -> None:
    setup = global_loc.GlobalSetup(starts=2, updates=4, particles=200, workers=1, step=1.5,
                                   heading_step_deg=45.0, **SMALL)
    res = global_loc.run(setup, LocalizerConfig(), appearance_map=office_map)
    assert res["starts"] == 2 and res["updates"] == 4 and res["particles"] == 200
    for key in ("mean_error_m", "median_error_m", "success", "tracking", "median_heading_error_deg"):
        assert len(res[key]) == 4, key
    assert all(0.0 <= v <= 1.0 for v in res["success"] + res["tracking"])
    diag = math.hypot(8.0 + 1.0, 2.5 + 1.0)  # mapped area plus the sensor model's margin
    assert all(0.0 <= v <= diag for v in res["mean_error_m"] + res["median_error_m"])
    assert res["map_entries"] == len(office_map)
    assert res["sensor_model"] == "nearest_neighbour"


def test_global_eval_with_the_interpolated_sensor_model(office_map) -> None:
    setup = global_loc.GlobalSetup(starts=2, updates=3, particles=200, workers=1, step=1.5,
                                   heading_step_deg=45.0, sensor_model="interpolated", **SMALL)
    res = global_loc.run(setup, LocalizerConfig(), appearance_map=office_map)
    assert res["sensor_model"] == "interpolated" and len(res["success"]) == 3
    assert all(0.0 <= v <= 1.0 for v in res["success"])


def test_tracking_eval_keys_and_trajectories(office_map, tmp_path) -> None:
    setup = tracking.TrackingSetup(world="office", step=1.5, heading_step_deg=45.0, features=4,
                                   preprocess=("none",), lights=("tube", "bulb"), scene_changes=("boxes",),
                                   duration=2.0, rate=2.0, particles=100, workers=1, **SMALL)
    res = tracking.run(setup, maps={"none": office_map}, trajectories=tmp_path / "traj")
    assert res["frames"] == 5 and res["scene_changes"] == ["boxes"]
    assert res["pause_probability"] == 0.0 and 0 <= res["standing_frames"] < 5
    for light in ("tube", "bulb"):
        r = res["conditions"][light]
        for key in ("ate_rmse_m", "mean_error_m", "max_error_m", "heading_rmse_deg", "converged_after_s"):
            assert key in r, key
        assert 0.0 <= r["mean_error_m"] <= r["max_error_m"]
        assert r["mean_error_m"] <= r["ate_rmse_m"] + 1e-12 <= r["max_error_m"] + 2e-12  # mean <= RMS <= max
        assert "without_recovery" in r
        for m in (r, r["global_start"], r["kidnap"]):
            assert 0.0 <= m["confident_wrong_fraction"] <= m["tracking_fraction"] + 1e-12 <= 1.0 + 1e-12
            assert 0.0 <= m["false_lost_fraction"] <= 1.0 - m["tracking_fraction"] + 1e-12
            assert m["lost_delay_s"]["episodes"] >= m["lost_delay_s"]["caught"] >= 0
        assert r["kidnap"]["carried_m"] >= 0.0
    rows = res["quality_table"]
    assert [q["band"][0] for q in rows] == [0.0, 0.2, 0.4, 0.6, 0.8]
    # every frame of every graded run: 2 lights x (known, uniform, kidnapped) + the light switch
    n_kidnap = len(tracking.kidnap_frames(np.zeros((5, 3)))[0])
    assert sum(q["frames"] for q in rows) == 2 * (5 + 5 + n_kidnap) + 5
    s_t, truth = read_tum(tmp_path / "traj" / "truth.tum")
    s_e, est = read_tum(tmp_path / "traj" / "tube.estimate.tum")
    np.testing.assert_allclose(s_t, [0.0, 0.5, 1.0, 1.5, 2.0], atol=1e-9)
    np.testing.assert_array_equal(s_t, s_e)
    # the written estimate gives back the reported error
    err = np.hypot(*(est[:, :2] - truth[:, :2]).T)
    assert err.mean() == pytest.approx(res["conditions"]["tube"]["mean_error_m"], abs=1e-5)
    sw = res["light_switch"]  # tube for frames 0-1, bulb for 2-4
    assert sw["lights"] == ["tube", "bulb"] and sw["switch_at_s"] == pytest.approx(1.0)
    assert 0.0 <= sw["lost_fraction_after"] <= 1.0 and sw["mean_error_after_m"] <= sw["max_error_after_m"]
    s_w, est_w = read_tum(tmp_path / "traj" / "switch-tube-bulb.estimate.tum")  # the switch run too
    np.testing.assert_array_equal(s_t, s_w)
    err_w = np.hypot(*(est_w[2:, :2] - truth[2:, :2]).T)
    assert err_w.mean() == pytest.approx(sw["mean_error_after_m"], abs=1e-5)

    # per-frame traces of every run, read back by the csv module
    traj = tmp_path / "traj"
    assert sorted(p.name for p in traj.glob("*.trace.csv")) == sorted(
        [f"{light}{kind}.trace.csv" for light in ("tube", "bulb") for kind in ("", "-uniform", "-kidnap")]
        + ["switch-tube-bulb.trace.csv"])
    with (traj / "tube.trace.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == COLUMNS and len(rows) == 5
    np.testing.assert_allclose([[float(r[k]) for k in ("x", "y", "theta")] for r in rows], est, atol=1e-6)
    np.testing.assert_allclose([[float(r[k]) for k in ("truth_x", "truth_y", "truth_theta")] for r in rows],
                               truth, atol=1e-6)  # the TUM file has 6 decimals
    assert np.mean([float(r["error_m"]) for r in rows]) == pytest.approx(
        res["conditions"]["tube"]["mean_error_m"], abs=1e-9)
    assert all(r["state"] in ("global", "tracking", "lost") for r in rows)
    assert all(0.0 <= float(r["quality"]) <= 1.0 and float(r["heading_error_rad"]) <= math.pi for r in rows)
    assert all(r["rho_disparity"] == "" for r in rows)  # an intensity-only map: the column stays empty
    with (traj / "bulb-kidnap.trace.csv").open(newline="") as f:
        assert len(list(csv.DictReader(f))) == n_kidnap


def test_kidnap_frames_jump_to_the_farthest_pose_of_the_last_quarter() -> None:
    truth = np.zeros((16, 3))
    truth[:, 0] = [0, 1, 2, 3, 4, 5, 6, 7, 6, 5, 7, 20, 7, 7, 1, 0]
    frames, k = tracking.kidnap_frames(truth)
    assert k == 8 and list(frames[:8]) == list(range(8))
    # frames 10-13 are the candidates; frame 11 (x = 20) is the farthest from frame 7 (x = 7)
    assert list(frames[8:]) == list(range(11, 16))


def test_light_switch_metrics_on_a_known_run() -> None:
    stamps = np.arange(8) * 0.5
    truth = np.zeros((8, 3))
    est = np.zeros((8, 3))
    est[:, 0] = [0.1, 0.1, 0.1, 0.1, 0.5, 0.3, 0.2, 0.2]  # error grows after the switch at frame 4
    states = ["tracking"] * 4 + ["lost", "lost", "tracking", "tracking"]
    m = tracking.switch_metrics(stamps, est, truth, states, 4)
    assert m["switch_at_s"] == 2.0
    assert m["mean_error_before_m"] == pytest.approx(0.1)
    assert m["mean_error_after_m"] == pytest.approx(0.3) and m["max_error_after_m"] == pytest.approx(0.5)
    assert m["lost_fraction_before"] == 0.0 and m["lost_fraction_after"] == 0.5
    assert m["last_lost_after_switch_s"] == pytest.approx(0.5)  # frame 5, 0.5 s after the switch
    quiet = tracking.switch_metrics(stamps, est, truth, ["tracking"] * 8, 4)
    assert quiet["lost_fraction_after"] == 0.0 and quiet["last_lost_after_switch_s"] == 0.0


def test_tracking_map_settings_reach_the_map_build(monkeypatch, office_map, capsys) -> None:
    """`eval tracking --step --heading-step --virtual-headings --translations
    --disparity-features` build the map they name (the simulated service's); bad values are one-line errors."""
    from services.cli import main

    seen: dict = {}

    def fake_build(world, step, heading_step_deg, features, preprocesses, **kw):
        seen.update(world=world, step=step, heading=heading_step_deg, **kw)
        raise SystemExit(0)

    monkeypatch.setattr(tracking, "build_sim_maps", fake_build)
    with pytest.raises(SystemExit):
        main(["eval", "tracking", "--world", "office", "--step", "0.75", "--heading-step", "15",
              "--virtual-headings", "5", "--translations", "3", "--disparity-features", "5"])
    assert (seen["step"], seen["heading"], seen["virtual_headings"], seen["translations"],
            seen["disparity_features"], seen["disparity"]) == (0.75, 15.0, 5, 3, 5, True)
    for bad, needle in ((["--translations", "2"], "--translations must be odd"),
                        (["--step", "0"], "--step and --heading-step must be positive"),
                        (["--disparity-features", "0"], "--disparity-features must be positive"),
                        (["--pauses", "1.5"], "--pauses must be a probability in [0, 1] (got 1.5)")):
        assert main(["eval", "tracking", *bad]) == 2
        assert needle in capsys.readouterr().err


def test_tracking_pauses_reach_the_drive_planner(monkeypatch, office_map) -> None:
    """``pause_probability`` (``--pauses``) is the drive planner's: the evaluated robot stops at
    the goals it reaches, as the simulated robot does."""
    seen: dict = {}

    def fake_plan(world, cfg, seed):
        seen["planner"] = cfg.planner
        raise SystemExit(0)

    monkeypatch.setattr(tracking, "plan_drive", fake_plan)
    with pytest.raises(SystemExit):
        tracking.run(tracking.TrackingSetup(world="office", pause_probability=0.3, lights=("tube",)),
                     maps={"none": office_map})
    assert seen["planner"].pause_probability == 0.3


def test_switch_lights_argument_errors(capsys) -> None:
    from services.cli import main

    for bad, needle in (("tube", "expected two lights"), ("tube,sodium", "sodium not in --lights")):
        assert main(["eval", "tracking", "--lights", "tube,bulb", "--switch-lights", bad]) == 2
        assert needle in capsys.readouterr().err


def test_converged_after_needs_the_error_to_stay_low() -> None:
    t = np.arange(10.0)
    err = np.array([3, 2, 0.1, 0.2, 2, 0.3, 0.2, 0.1, 0.1, 0.2])
    assert tracking.converged_after(t, err, 0.5, 3.0) == 5.0  # 2-3 is too short, 5-9 holds
    assert tracking.converged_after(t, err, 0.5, 100.0) == 5.0  # held to the end of the run
    assert tracking.converged_after(t, np.full(10, 1.0), 0.5, 1.0) is None


def test_tracking_cli_with_a_map_file(office_map, tmp_path, capsys) -> None:
    """`eval tracking --map FILE` localizes against that map file (its features, camera and
    working size) and reports its sessions."""

    path = office_map.save(tmp_path / "tube.npz")
    code = cli_main(["eval", "tracking", "--world", "office", "--map", str(path), "--duration", "2", "--rate", "2",
                     "--particles", "100", "--lights", "bulb", "--switch-lights", "none", "--no-global",
                     "--no-kidnap", "--no-recovery-comparison", "--workers", "1", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    res = json.loads(out)
    assert res["map_entries"] == len(office_map) and res["features"] == 4
    assert [s["basis"] for s in res["map"]["sessions"]] == ["built"]
    assert res["conditions"]["bulb"]["mean_error_m"] >= 0.0

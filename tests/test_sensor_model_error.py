"""`lino-loc eval sensor-model` (Fig. 5): eq. 10 on hand-made neighbour sets, the J split of the
disjunctive model (eq. 8), the test path, and the JSON of a tiny run (coarse lab grid, small
renders, few test poses). The full experiment's figures are in docs/evaluations.md."""

from __future__ import annotations

import contextlib
import io
import json
import math

import numpy as np
import pytest

from drivers.sim.world import grid_poses, load_world
from lino_loc.fusion import FusionConfig
from lino_loc.metrics import sensor_model_error
from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig
from services.cli import main
from services.evaluation.sensor_model_error import (
    SensorModelSetup,
    default_path_box,
    errors_eq10,
    errors_eq10_pose,
    evaluate_condition,
    fused_points,
    grid_limit,
    path_poses,
    summary,
)

TINY = ["--step", "1.5", "--heading-step", "60", "--features", "5", "--width", "128", "--height", "96",
        "--map-width", "32", "--map-height", "24", "--spacing", "2.5", "--workers", "1", "--no-cache",
        "--compare", "histeq"]


# --------------------------------------------------------------------------- eq. 10
def test_eq10_on_hand_made_neighbours() -> None:
    truth = np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 3.0]])
    nb = np.array(
        [
            [[3.0, 1.0, 0.0], [1.0, 1.5, math.pi], [0.0, 0.0, 0.0]],  # nearest position: 0.5 m
            [[0.0, 0.0, -3.0], [3.0, 4.0, 3.0], [0.3, 0.4, 3.0]],  # the truth's own position
        ]
    )
    e = errors_eq10(truth, nb)
    np.testing.assert_allclose(e, [0.5, 0.0])
    assert e[0] == sensor_model_error(truth[0], nb[0])
    # (x, y, theta) variant: the heading counts (wrapped), so (1, 1.5, pi) is no longer nearest
    ep = errors_eq10_pose(truth, nb)
    np.testing.assert_allclose(ep[0], math.sqrt(2.0))  # (0, 0, 0): sqrt(1 + 1 + 0)
    np.testing.assert_allclose(ep[1], 2.0 * math.pi - 6.0)  # wrap(-3 - 3) = 2 pi - 6
    assert np.all(ep >= e)


def test_summary_is_population_mean_and_std() -> None:
    s = summary(np.array([0.0, 1.0, 2.0, 3.0]))
    assert s == {"mean_m": 1.5, "std_m": pytest.approx(math.sqrt(1.25)), "median_m": 1.5}


# --------------------------------------------------------------------------- J split (eq. 8)
def test_j_split_5_plus_5_gives_the_10_map_points_of_both_channels() -> None:
    rng = np.random.default_rng(3)
    n = 200
    poses = np.column_stack([rng.uniform(0, 9, n), rng.uniform(0, 5, n), rng.uniform(-np.pi, np.pi, n)])
    fi, fd = rng.standard_normal((n, 6)), rng.standard_normal((n, 4))
    mi = NearestNeighbourSensorModel(poses, fi, SensorModelConfig(j=10))
    md = NearestNeighbourSensorModel(poses, fd, SensorModelConfig(j=10), bounds=mi.bounds)
    yi, yd = rng.standard_normal((7, 6)), rng.standard_normal((7, 4))
    pts, w = fused_points(mi, md, yi, yd, FusionConfig(j_intensity=5, j_disparity=5))
    assert pts.shape == (7, 10, 3) and w.shape == (7, 10)
    np.testing.assert_allclose(w.sum(1), 1.0)
    for k in range(7):
        near_i = np.argsort(((fi - yi[k]) ** 2).sum(1))[:5]
        near_d = np.argsort(((fd - yd[k]) ** 2).sum(1))[:5]
        np.testing.assert_array_equal(pts[k, :5], poses[near_i])
        np.testing.assert_array_equal(pts[k, 5:], poses[near_d])
    # another split: 3 + 7 is still 10 points
    pts37, _ = fused_points(mi, md, yi, yd, FusionConfig(j_intensity=3, j_disparity=7))
    assert pts37.shape == (7, 10, 3)


def test_disparity_entries_the_channel_did_not_observe_are_never_its_points() -> None:
    """As in the Localizer: the disparity model searches only the entries it observed."""
    rng = np.random.default_rng(5)
    n = 300
    poses = np.column_stack([rng.uniform(0, 9, n), rng.uniform(0, 5, n), rng.uniform(-np.pi, np.pi, n)])
    fi, fd = rng.standard_normal((n, 6)), rng.standard_normal((n, 4))
    blank = rng.random(n) < 0.2
    fd[blank] = 0.0  # no stereo match: the EM projection's prior mean
    truths = poses[:9] + np.array([0.1, 0.1, 0.0])
    yi, yd = fi[:9] + 0.01, 0.01 * rng.standard_normal((9, 4))  # disparity views near the mean
    setup = SensorModelSetup(j=10, j_intensity=5, j_disparity=5)
    res = evaluate_condition(truths, poses, yi, fi, yd, fd, setup, map_rows_d=~blank)
    md = NearestNeighbourSensorModel(poses[~blank], fd[~blank], SensorModelConfig(j=10))
    idx, _ = md.neighbours(yd)
    want = errors_eq10(truths, poses[~blank][idx])
    np.testing.assert_allclose(res["disparity"]["errors_m"], np.round(want, 4))
    everything = evaluate_condition(truths, poses, yi, fi, yd, fd, setup)  # the blanks are searched
    assert everything["disparity"]["errors_m"] != res["disparity"]["errors_m"]


def test_a_view_without_disparity_is_fused_from_intensity_alone() -> None:
    """As in the Localizer: a test view with no valid disparity block has no disparity channel."""
    rng = np.random.default_rng(6)
    n = 300
    poses = np.column_stack([rng.uniform(0, 9, n), rng.uniform(0, 5, n), rng.uniform(-np.pi, np.pi, n)])
    fi, fd = rng.standard_normal((n, 6)), rng.standard_normal((n, 4))
    truths = poses[:8] + np.array([0.2, -0.1, 0.05])
    yi, yd = fi[:8] + 0.3 * rng.standard_normal((8, 6)), fd[:8] + 0.01
    seen = np.array([True, False, True, True, False, True, True, True])
    setup = SensorModelSetup(j=10, j_intensity=5, j_disparity=5)
    res = evaluate_condition(truths, poses, yi, fi, yd, fd, setup, observed_d=seen)
    full = evaluate_condition(truths, poses, yi, fi, yd, fd, setup)
    f, i = np.array(res["fused"]["errors_m"]), np.array(res["intensity"]["errors_m"])
    np.testing.assert_array_equal(f[~seen], i[~seen])  # intensity alone, J = j
    np.testing.assert_array_equal(f[seen], np.array(full["fused"]["errors_m"])[seen])
    assert res["fused"]["views_without_disparity"] == 2
    assert res["disparity"]["views"] == 6 and len(res["disparity"]["errors_m"]) == 6
    np.testing.assert_array_equal(res["disparity"]["errors_m"], np.array(full["disparity"]["errors_m"])[seen])
    none = evaluate_condition(truths, poses, yi, fi, yd, fd, setup, observed_d=np.zeros(8, dtype=bool))
    assert none["disparity"]["mean_m"] is None and none["fused"]["errors_m"] == res["intensity"]["errors_m"]


# --------------------------------------------------------------------------- the path
def test_path_is_regular_off_grid_free_and_headed_along() -> None:
    world = load_world("lab")
    grid = grid_poses(world, 0.5, math.radians(10))
    p = path_poses(world, 0.3, default_path_box(world), SensorModelSetup().path_exponent, avoid=grid)
    assert len(p) >= 50
    step = np.hypot(*np.diff(p[:, :2], axis=0).T)
    assert np.all(step <= 0.3 + 1e-9) and np.all(step > 0.25)  # chords of 0.3 m arcs
    assert np.all(world.is_free(p[:, 0], p[:, 1], 0.25))
    assert grid_limit(p, grid).min() > 0.075  # never on a surveyed position
    mid = 0.5 * (p[2:, :2] - p[:-2, :2])  # central difference: direction of travel
    along = np.arctan2(mid[:, 1], mid[:, 0])
    assert np.max(np.abs(np.angle(np.exp(1j * (along - p[1:-1, 2]))))) < math.radians(10)


# --------------------------------------------------------------------------- the command
@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, object]:
    out_dir = tmp_path_factory.mktemp("plot")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        status = main(["eval", "sensor-model", "--json", "--plot", str(out_dir), *TINY])
    assert status == 0
    lines = [ln for ln in buf.getvalue().splitlines() if ln.strip()]
    assert len(lines) == 1  # exactly one JSON object on stdout
    return json.loads(lines[0]), out_dir


def test_json_keys_shapes_and_conditions(tiny: tuple[dict, object]) -> None:
    res, out_dir = tiny
    assert set(res["conditions"]) == {"tube", "bulb", "natural"}
    m = res["positions"]
    assert m >= 5 and len(res["path"]["poses"]) == m and len(res["path"]["arc_m"]) == m
    assert res["J"] == {"intensity": 10, "fused": [5, 5]}
    for light, r in res["conditions"].items():
        for key in ("intensity", "fused"):
            block = r[key]
            assert block["mean_m"] >= 0 and block["std_m"] >= 0
            errs = np.asarray(block["errors_m"])
            assert errs.shape == (m,)
            assert block["mean_m"] == pytest.approx(errs.mean(), abs=1e-3)
            assert block["std_m"] == pytest.approx(errs.std(), abs=1e-3)
            # map points are surveyed positions: no model beats the grid
            assert block["mean_m"] >= res["grid_limit_m"]["mean_m"] - 1e-3
        assert 0.0 <= res["disparity_density"][light] <= 1.0
    assert set(res["by_preprocess"]) == {"none", "histeq"}
    assert res["map"]["preprocess"] == "none"
    assert (out_dir / "fig5_sensor_model.png").stat().st_size > 1000


def test_fused_error_is_the_min_over_both_channels_parts(tiny: tuple[dict, object]) -> None:
    res, _ = tiny
    for r in res["conditions"].values():
        fused = np.asarray(r["fused"]["errors_m"])
        part_i = np.asarray(r["intensity_j_split"]["errors_m"])
        part_d = np.asarray(r["disparity_j_split"]["errors_m"])
        np.testing.assert_allclose(fused, np.minimum(part_i, part_d), atol=1e-4)
        # the intensity model's 10 neighbours include its 5 nearest
        assert np.all(np.asarray(r["intensity"]["errors_m"]) <= part_i + 1e-4)


def test_tiny_run_on_the_corridor_derives_its_path_from_the_free_space() -> None:
    buf = io.StringIO()
    args = ["eval", "sensor-model", "--world", "corridor", "--json", *TINY, "--step", "1.0", "--heading-step", "90",
            "--lights", "tube,bulb", "--compare", ""]
    with contextlib.redirect_stdout(buf):
        assert main(args) == 0
    res = json.loads(buf.getvalue())
    world = load_world("corridor")
    assert res["world"] == "corridor" and set(res["conditions"]) == {"tube", "bulb"}
    assert res["path"]["box_from"] == "free space"
    poses = np.asarray(res["path"]["poses"])
    assert len(poses) >= 8 and np.all(world.is_free(poses[:, 0], poses[:, 1], 0.35))
    xmin, xmax, _, _ = world.mapped_area
    assert poses[:, 0].max() - poses[:, 0].min() > 0.8 * (xmax - xmin)  # the corridor's length
    for r in res["conditions"].values():
        assert r["intensity"]["mean_m"] >= res["grid_limit_m"]["mean_m"] - 1e-3


def test_path_box_given_is_the_old_lab_loop() -> None:
    world = load_world("lab")
    old = (0.35, 8.65, 1.15, 3.75)
    p = path_poses(world, 0.3, old, 4.0)
    assert p[:, 0].min() >= old[0] - 1e-9 and p[:, 0].max() <= old[1] + 1e-9
    assert p[:, 1].min() >= old[2] - 1e-9 and p[:, 1].max() <= old[3] + 1e-9
    assert default_path_box(world) != old  # the default is derived, not this constant


@pytest.mark.parametrize("extra", [["--j", "1"], ["--lights", "moonlight"], ["--spacing", "0"],
                                   ["--path-box", "1,2,3"], ["--path-box", "2,1,0,1"], ["--path-box", "a,b,c,d"]])
def test_bad_values_exit_2_with_one_line(extra: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "sensor-model", "--json", *TINY, *extra]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert len([ln for ln in captured.err.splitlines() if "error" in ln]) == 1


def test_unknown_preprocessing_is_a_usage_error() -> None:
    with pytest.raises(SystemExit) as exc:
        main(["eval", "sensor-model", "--json", *TINY, "--preprocess", "sharpen"])
    assert exc.value.code == 2

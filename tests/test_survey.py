"""Surveys: grid rows, skipped colliding poses, dataset folder contents, the CLI command."""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from drivers.sim.renderer import CameraModel
from drivers.sim.survey import condition_name, run_survey, survey_poses
from drivers.sim.world import World, WorldSpec
from lino_loc.appearance_map import build_map
from lino_loc.dataset import Dataset
from lino_loc.disparity import StereoConfig, compute_disparity
from lino_loc.errors import LinoLocError
from services.commands import survey_cmd


def _world(with_crate: bool = True) -> World:
    """A 5 x 3 m room, mapped area 1..4 x 0.5..2.5; a 0.8 m crate sits on the grid point (2, 1.5)."""
    tex = {"w": {"kind": "tiles", "albedo": 0.6, "period": 0.3}, "f": {"kind": "carpet", "albedo": 0.3},
           "c": {"kind": "paint", "albedo": 0.8}, "b": {"kind": "cardboard", "albedo": 0.5}}
    walls = [{"start": a, "end": b, "texture": "w"} for a, b in
             (([0, 0], [5, 0]), ([5, 0], [5, 3]), ([5, 3], [0, 3]), ([0, 3], [0, 0]))]
    furniture = [{"id": "crate", "pose": [2.0, 1.5, 0],
                  "boxes": [{"size": [0.8, 0.8], "zmin": 0, "zmax": 0.5, "texture": "b"}]}] if with_crate else []
    spec = {
        "name": "tiny", "room": {"xmin": 0, "xmax": 5, "ymin": 0, "ymax": 3},
        "mapped_area": {"xmin": 1, "xmax": 4, "ymin": 0.5, "ymax": 2.5}, "ceiling_height": 2.5,
        "floor_texture": "f", "ceiling_texture": "c", "textures": tex, "walls": walls, "furniture": furniture,
        "lighting": {"tube": {"ambient": 1.0, "lights": [{"type": "tube", "start": [1, 1.5, 2.45], "end": [4, 1.5, 2.45], "power": 3}]},
                     "bulb": {"ambient": 0.2, "lights": [{"type": "point", "position": [4.5, 2.5, 2.0], "power": 3}]}},
        "scene_changes": {"people": {"add": [{"id": "p", "pose": [3.0, 1.5, 0],
                                               "boxes": [{"size": [0.3, 0.4], "zmax": 1.7, "texture": "b"}]}]}},
    }
    return World(WorldSpec.model_validate(spec), source="<tiny>")


CAM = CameraModel(width=40, height=30)
SMALL_STEREO = StereoConfig(num_disparities=16, block_size=5)  # a matcher that fits 40 x 30 images


def test_grid_skips_colliding_positions() -> None:
    free_world = _world(with_crate=False)
    poses, skipped = survey_poses(free_world, 0.5, math.radians(90))
    assert skipped == 0 and len(poses) == 7 * 5 * 4
    poses, skipped = survey_poses(_world(), 0.5, math.radians(90))
    # the crate (0.8 x 0.8 at (2, 1.5)) plus the 0.25 m robot radius blocks the 3 x 3 grid points around it
    assert skipped == 9 and len(poses) == (35 - 9) * 4
    assert not np.any((np.abs(poses[:, 0] - 2.0) < 0.6) & (np.abs(poses[:, 1] - 1.5) < 0.6))


def test_survey_writes_dataset(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    res = run_survey(_world(), out, step=1.0, heading_step_rad=math.radians(120), camera=CAM, seed=3,
                     stereo_config=SMALL_STEREO)
    assert res.rows == (4 * 3 - 1) * 3  # 4 x 3 positions, the crate blocks (2, 1.5)
    poses, _ = survey_poses(_world(), 1.0, math.radians(120))
    assert res.rows == len(poses)
    ds = Dataset.open(out)
    assert len(ds) == len(poses)
    meta = json.loads((out / "dataset.json").read_text())
    assert meta["conditions"] == ["tube"] and meta["camera"]["baseline_m"] == pytest.approx(0.075)
    assert meta["camera"]["width"] == 40 and "world=tiny" in meta["source"]
    with open(out / "poses.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {"image", "x", "y", "theta", "right", "disparity", "condition"} <= set(rows[0])
    assert "depth" not in rows[0] and meta["disparity_source"] == "stereo-matcher"
    got = np.array([[float(r["x"]), float(r["y"]), float(r["theta"])] for r in rows])
    np.testing.assert_allclose(got, poses)
    assert (out / rows[0]["right"]).is_file() and (out / rows[0]["disparity"]).is_file()
    # the disparity column is the matcher's on the stored pair, to the 1/16 px of the PNG
    # (whose 0 means "no value", so a matched disparity 0 is stored as none)
    want = compute_disparity(ds.image(0), ds.right(0), SMALL_STEREO)
    got_d = ds.disparity(0)
    pos = np.nan_to_num(want) > 0
    np.testing.assert_array_equal(np.isfinite(got_d), pos)
    np.testing.assert_allclose(got_d[pos], want[pos], atol=1 / 32)
    # same seed, same survey
    res2 = run_survey(_world(), tmp_path / "ds2", step=1.0, heading_step_rad=math.radians(120), camera=CAM, seed=3,
                      stereo_config=SMALL_STEREO)
    assert res2.rows == res.rows
    assert (out / rows[-1]["image"]).read_bytes() == (tmp_path / "ds2" / rows[-1]["image"]).read_bytes()


def test_other_lighting_same_poses_and_scene_changes(tmp_path: Path) -> None:
    a = run_survey(_world(), tmp_path / "a", step=1.0, heading_step_rad=math.radians(180), camera=CAM, stereo=False)
    b = run_survey(_world(), tmp_path / "b", step=1.0, heading_step_rad=math.radians(180), camera=CAM,
                   lighting="bulb", stereo=False)
    pa = (tmp_path / "a" / "poses.csv").read_text().splitlines()
    pb = (tmp_path / "b" / "poses.csv").read_text().splitlines()
    assert a.rows == b.rows
    assert [r.split(",")[1:4] for r in pa] == [r.split(",")[1:4] for r in pb]
    assert "right" not in pa[0].split(",")
    assert b.condition == "bulb"
    c = run_survey(_world(), tmp_path / "c", step=1.0, heading_step_rad=math.radians(180), camera=CAM,
                   scene_changes=["people"], stereo=False)
    assert c.condition == condition_name("tube", ["people"]) == "tube+people"
    assert c.rows < a.rows  # the person stands on a grid point


def test_existing_folder_needs_overwrite(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    run_survey(_world(), out, step=2.0, heading_step_rad=math.pi, camera=CAM, stereo=False)
    with pytest.raises(LinoLocError):
        run_survey(_world(), out, step=2.0, heading_step_rad=math.pi, camera=CAM, stereo=False)
    run_survey(_world(), out, step=2.0, heading_step_rad=math.pi, camera=CAM, stereo=False, overwrite=True)


def test_stereo_survey_is_sparse_and_its_map_says_so(tmp_path: Path) -> None:
    """A stereo survey's disparity is the matcher's, sparse as a stereo camera's; the
    renderer's exact dense depth only on request, and the map's channel names its source."""
    cam = CameraModel(width=96, height=72)
    sparse = run_survey(_world(False), tmp_path / "s", step=1.0, heading_step_rad=math.radians(90), camera=cam)
    ds = Dataset.open(sparse.out)
    assert ds.has_disparity and ds.has_right and not ds.has_depth
    valid = np.mean([np.isfinite(ds.disparity(i)).mean() for i in range(len(ds))])
    assert 0.02 < valid < 0.9  # some pixels matched, many not: no stereo camera is dense
    m = build_map(ds, n_features=3, size=(24, 18), channels=("intensity", "disparity"))
    assert m.channels["disparity"].params["source"] == "stereo-matcher"
    dense = run_survey(_world(False), tmp_path / "d", step=1.0, heading_step_rad=math.radians(90), camera=cam,
                       dense_depth=True)
    dd = Dataset.open(dense.out)
    assert dd.has_depth and not dd.has_disparity and dd.meta.camera.baseline_m == pytest.approx(0.075)
    assert np.isfinite(dd.depth(0)).mean() > 0.99
    m = build_map(dd, n_features=3, size=(24, 18), channels=("intensity", "disparity"))
    assert m.channels["disparity"].params["source"] == "dense-depth"
    assert m.channels["disparity"].params["units"] == "disparity_px"


def test_stereo_too_small_for_the_matcher_is_a_one_line_error(tmp_path: Path) -> None:
    with pytest.raises(LinoLocError, match="too small for the stereo matcher"):
        run_survey(_world(), tmp_path / "x", step=2.0, heading_step_rad=math.pi, camera=CAM)
    assert not (tmp_path / "x").exists()


def _cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    survey_cmd.register(parser.add_subparsers())
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_survey_office(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "office"
    status = _cli(["survey", "--world", "office", "--step", "4", "--heading-step", "180", "--out", str(out),
                   "--width", "32", "--height", "24", "--lighting", "bulb", "--no-stereo", "--json"])
    assert status == 0
    summary = json.loads(capsys.readouterr().out)
    # office mapped area 8 x 2.5 m: x in {0, 4, 8}, y in {0}, 2 headings
    assert summary["rows"] == 3 * 1 * 2 and summary["condition"] == "bulb"
    ds = Dataset.open(out)
    assert len(ds) == 6 and ds.image(0).shape == (24, 32)


def test_cli_bad_input(tmp_path: Path) -> None:
    with pytest.raises(LinoLocError, match="unknown lighting"):
        _cli(["survey", "--world", "office", "--out", str(tmp_path / "x"), "--lighting", "disco"])
    with pytest.raises(LinoLocError, match="not found"):
        _cli(["survey", "--world", "atlantis", "--out", str(tmp_path / "y")])
    with pytest.raises(LinoLocError, match="positive"):
        _cli(["survey", "--out", str(tmp_path / "z"), "--step", "0"])

"""Translated datasets (lino_loc/translated_dataset.py, `lino-loc dataset translate`): the rows
written, read back by the dataset reader, built into a two-channel map, resumed after a kill."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_survey import _world  # the tiny room of the survey tests

from drivers.sim.renderer import CameraModel
from drivers.sim.survey import run_survey
from lino_loc.appearance_map import build_map
from lino_loc.dataset import JOURNAL_FILE, Dataset, DatasetMeta, DatasetWriter, require_valid
from lino_loc.disparity import StereoConfig
from lino_loc.errors import LinoLocError
from lino_loc.translated_dataset import survey_spacing, translate_dataset
from services.cli import main

CAM = CameraModel(width=64, height=48)
STEREO = StereoConfig(num_disparities=16, block_size=5)


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny room surveyed every 1 m and 120 deg with stereo (8 positions x 3 headings)."""
    out = tmp_path_factory.mktemp("survey") / "ds"
    run_survey(_world(with_crate=False), out, step=1.0, heading_step_rad=math.radians(120), camera=CAM, seed=1,
               stereo=True, stereo_config=STEREO)
    return out


def test_survey_spacing_is_the_grid_step() -> None:
    g = np.array([[x, y, t] for x in (0.0, 0.75, 1.5) for y in (0.0, 0.75) for t in (0.0, 1.0)])
    assert survey_spacing(g) == pytest.approx(0.75)
    with pytest.raises(LinoLocError, match="two distinct positions"):
        survey_spacing(np.zeros((4, 3)))


def test_every_row_is_seen_from_its_cells_lattice_with_its_disparity(survey: Path, tmp_path: Path) -> None:
    src = Dataset.open(survey)
    report = translate_dataset(src, tmp_path / "t3", refinement=3)
    assert report.step == pytest.approx(1.0) and report.refinement == 3 and report.resumed == 0
    assert report.rows_in == len(src) and report.rows_out == 9 * len(src)
    out = Dataset.open(tmp_path / "t3")
    require_valid(out)  # the dataset reader's own checks, files decoded at the camera's size
    assert len(out) == 9 * len(src) and out.has_disparity and not out.has_right
    assert out.meta.camera == src.meta.camera and out.meta.name == f"{src.meta.name}-t3"
    for i in (0, len(src) - 1):
        rows = slice(9 * i, 9 * i + 9)
        assert np.array_equal(out.image(9 * i), src.image(i))  # the real view first
        d_src, d_out = src.disparity(i), out.disparity(9 * i)
        assert np.array_equal(np.isnan(d_src), np.isnan(d_out))
        assert np.allclose(d_src[np.isfinite(d_src)], d_out[np.isfinite(d_out)], atol=1.0 / src.meta.disparity_scale)
        poses = out.poses[rows]
        assert np.allclose(poses[:, 2], src.poses[i, 2])  # same heading
        off = poses[:, :2] - src.poses[i, :2]
        assert np.allclose(np.sort(np.round(off / (1.0 / 3), 6), axis=0)[[0, -1]], [[-1, -1], [1, 1]])
        assert out.conditions[9 * i] == src.conditions[i]
    # a two-channel map builds from it (PCA with missing data over the moved disparity)
    amap = build_map(out, n_features=4, size=(16, 12), channels=("intensity", "disparity"), disparity_features=3)
    assert len(amap) == len(out) and set(amap.channels) == {"intensity", "disparity"}


def test_an_interrupted_translation_continues_where_it_stopped(survey: Path, tmp_path: Path) -> None:
    src = Dataset.open(survey)
    whole = translate_dataset(src, tmp_path / "whole", refinement=3)

    class Stop(Exception):
        pass

    def stop_after_two(done: int, total: int) -> None:
        if done == 2:
            raise Stop

    with pytest.raises(Stop):
        translate_dataset(src, tmp_path / "part", refinement=3, progress=stop_after_two)
    assert not (tmp_path / "part" / "dataset.json").exists() and (tmp_path / "part" / JOURNAL_FILE).is_file()
    again = translate_dataset(src, tmp_path / "part", refinement=3)
    assert again.resumed == 18 and again.rows_out == whole.rows_out and again.fallbacks == whole.fallbacks
    a, b = Dataset.open(tmp_path / "whole"), Dataset.open(tmp_path / "part")
    assert np.array_equal(a.poses, b.poses)
    assert all(np.array_equal(a.image(k), b.image(k)) for k in range(0, len(a), 5))


def test_workers_write_the_same_rows_as_one_process(survey: Path, tmp_path: Path) -> None:
    src = Dataset.open(survey)
    one = translate_dataset(src, tmp_path / "one", refinement=3, workers=1)
    two = translate_dataset(src, tmp_path / "two", refinement=3, workers=2)
    assert (one.rows_out, one.fallbacks) == (two.rows_out, two.fallbacks)
    a, b = Dataset.open(tmp_path / "one"), Dataset.open(tmp_path / "two")
    assert np.array_equal(a.poses, b.poses) and a.conditions == b.conditions
    for k in range(len(a)):
        assert np.array_equal(a.image(k), b.image(k))
        assert np.array_equal(a.disparity(k), b.disparity(k), equal_nan=True)


def _stat(pid: int) -> list[str]:
    """The fields of /proc/PID/stat after the command's name (state, parent pid, ...); [] when gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return []


def _children(pid: int) -> set[int]:
    pids = (int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit())
    return {c for c in pids if _stat(c)[1:2] == [str(pid)]}


def _alive(pid: int) -> bool:
    state = _stat(pid)[:1]
    return bool(state) and state != ["Z"]


def test_kill_9_keeps_the_rows_written(survey: Path, tmp_path: Path) -> None:
    """The command killed by SIGKILL mid-run, its two warping processes with it: the journal
    keeps every row and the workers exit; run again, the folder holds the same rows as an
    uninterrupted run."""
    out = tmp_path / "killed"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    cmd = [sys.executable, "-m", "services.cli", "dataset", "translate", str(survey), "--out", str(out),
           "--refinement", "5", "--json", "--workers", "2"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    journal = out / JOURNAL_FILE
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and (not journal.is_file() or journal.read_text().count("\n") < 30):
        time.sleep(0.02)
    workers = _children(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert len(workers) == 2
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.05)
    assert not any(_alive(w) for w in workers)  # no orphaned worker keeps warping
    rows_before = journal.read_text().count('"row"')
    assert rows_before >= 29 and not (out / "dataset.json").exists()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    summary = json.loads(done.stdout)
    assert summary["resumed"] >= rows_before - 1 and summary["rows_out"] == 25 * len(Dataset.open(survey))
    whole = translate_dataset(Dataset.open(survey), tmp_path / "whole5", refinement=5)
    assert np.array_equal(Dataset.open(out).poses, Dataset.open(tmp_path / "whole5").poses)
    assert whole.rows_out == summary["rows_out"]


def test_bad_requests_get_one_line(survey: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    nodisp = tmp_path / "nodisp"
    meta = DatasetMeta(name="n", camera=Dataset.open(survey).meta.camera)
    with DatasetWriter(nodisp, meta) as w:
        w.add(np.zeros((48, 64), np.uint8), (0.0, 0.0, 0.0))
        w.add(np.zeros((48, 64), np.uint8), (1.0, 0.0, 0.0))
    for args, text in (([str(survey), "--out", str(tmp_path / "a"), "--refinement", "2"], "odd"),
                       ([str(nodisp), "--out", str(tmp_path / "b")], "no disparity column"),
                       ([str(survey), "--out", str(tmp_path / "c"), "--step", "-1"], "step must be positive"),
                       ([str(survey), "--out", str(tmp_path / "d"), "--workers", "0"], "workers must be at least 1")):
        assert main(["dataset", "translate", *args]) == 2
        err = capsys.readouterr().err
        assert text in err and "Traceback" not in err and len(err.strip().splitlines()) == 1

"""Stereo metrics on hand-made arrays, ground-truth loaders, the `eval stereo` command, and the
regression check of the product's matcher on the real Middlebury "Motorcycle" pair."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lino_loc.errors import LinoLocError
from lino_loc.stereo_metrics import load_disparity_truth, stereo_metrics
from services.evaluation.commands.stereo_cmd import register_eval, run_stereo

MIDDLEBURY = (
    Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "middlebury_motorcycle"
)

# Measured 2026-11-21 with the StereoConfig defaults and --max-disparity 60 (= 64 disparities):
# density 0.769, bad1 0.061, bad2 0.044, rmse 3.55 px. The test allows a clear margin.
MB_DENSITY_MIN = 0.769 - 0.05
MB_BAD1_MAX = 0.061 + 0.03
MB_BAD2_MAX = 0.044 + 0.03
MB_RMSE_MAX = 3.55 + 1.0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lino-loc")
    sub = p.add_subparsers(dest="command")
    ev = sub.add_parser("eval").add_subparsers(dest="evaluation")
    register_eval(ev)
    return p


def test_metrics_hand_made():
    n = np.nan
    truth = np.array([[10.0, 10.0, 10.0, 10.0], [20.0, 20.0, np.inf, n]])
    disp = np.array([[10.5, 11.5, 12.5, n], [20.0, n, 5.0, 7.0]])
    m = stereo_metrics(disp, truth)
    # known GT: 6 pixels; valid among them: 4 (10.5, 11.5, 12.5, 20.0)
    assert m.n_known == 6 and m.n_evaluated == 4 and m.n_valid == 6 and m.n_pixels == 8
    assert m.density == pytest.approx(4 / 6)
    assert m.density_all == pytest.approx(6 / 8)
    # errors 0.5, 1.5, 2.5, 0 -> > 1: 2 of 4, > 2: 1 of 4
    assert m.bad1 == pytest.approx(0.5)
    assert m.bad2 == pytest.approx(0.25)
    assert m.rmse_px == pytest.approx(np.sqrt((0.25 + 2.25 + 6.25 + 0) / 4))
    # exactly 1 or 2 px off is not bad
    m = stereo_metrics(np.array([[11.0, 12.0]]), np.array([[10.0, 10.0]]))
    assert m.bad1 == 0.5 and m.bad2 == 0.0
    # nothing valid: density 0, rates undefined
    m = stereo_metrics(np.full((2, 2), np.nan), np.ones((2, 2)))
    assert m.density == 0.0 and m.bad1 is None and m.rmse_px is None
    with pytest.raises(LinoLocError):
        stereo_metrics(np.ones((2, 2)), np.ones((2, 3)))


def test_truth_loaders(tmp_path):
    gt = np.array([[1.5, np.inf], [np.nan, 30.0]], dtype=np.float32)
    np.savez(tmp_path / "a.npz", gt)
    np.savez(tmp_path / "named.npz", disparity=gt)
    np.save(tmp_path / "b.npy", gt)
    for name in ("a.npz", "named.npz", "b.npy"):
        t = load_disparity_truth(tmp_path / name)
        assert t.dtype == np.float32
        assert t[0, 0] == 1.5 and t[1, 1] == 30.0 and np.isnan(t[0, 1]) and np.isnan(t[1, 0])
    png16 = np.array([[0, 300], [1000, 65535]], dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "g16.png"), png16)
    t = load_disparity_truth(tmp_path / "g16.png")
    assert np.isnan(t[0, 0]) and t[0, 1] == 300.0 and t[1, 1] == 65535.0
    t = load_disparity_truth(tmp_path / "g16.png", png_scale=16.0)
    assert t[0, 1] == pytest.approx(18.75)
    cv2.imwrite(str(tmp_path / "g8.png"), np.array([[0, 7]], dtype=np.uint8))
    t = load_disparity_truth(tmp_path / "g8.png")
    assert np.isnan(t[0, 0]) and t[0, 1] == 7.0


@pytest.mark.parametrize(
    "name, content",
    [
        ("bad.npz", b"not a zip"),
        ("bad.npy", b"garbage"),
        ("bad.png", b"\x89PNG broken"),
        ("gt.txt", b"1 2"),
    ],
)
def test_bad_truth_files_name_the_file(tmp_path, name, content):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(LinoLocError, match=name):
        load_disparity_truth(path)


def test_truth_must_be_2d(tmp_path):
    np.save(tmp_path / "v.npy", np.zeros(5))
    with pytest.raises(LinoLocError, match="v.npy"):
        load_disparity_truth(tmp_path / "v.npy")
    with pytest.raises(LinoLocError, match="missing.npz"):
        load_disparity_truth(tmp_path / "missing.npz")


def _synthetic_files(tmp_path: Path, d: float = 12.0) -> tuple[str, str, str]:
    rng = np.random.default_rng(5)
    h, w = 120, 200
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 40)), (0, 0), 1.5)
    tex = ((tex - tex.min()) / (tex.max() - tex.min()) * 255).astype(np.uint8)
    left = tex[:, 20 : 20 + w]
    right = tex[:, 20 + int(d) : 20 + int(d) + w]
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    gt = np.full((h, w), d, np.float32)
    gt[:, :5] = np.inf
    np.save(tmp_path / "gt.npy", gt)
    return str(tmp_path / "l.png"), str(tmp_path / "r.png"), str(tmp_path / "gt.npy")


def test_eval_stereo_command_json(tmp_path, capsys):
    left, right, gt = _synthetic_files(tmp_path)
    args = _parser().parse_args(
        ["eval", "stereo", left, right, "--truth", gt, "--max-disparity", "30", "--json"]
    )
    assert args.func is run_stereo
    assert args.func(args) == 0
    out = capsys.readouterr().out
    report = json.loads(out)  # exactly one JSON object
    assert {"density", "bad1", "bad2", "rmse_px"} <= report.keys()
    assert report["config"]["num_disparities"] == 32
    assert report["density"] > 0.5
    assert report["bad1"] < 0.01 and report["rmse_px"] < 0.5
    assert report["n_known"] == 120 * 195


def test_eval_stereo_command_text_and_bad_files(tmp_path, capsys):
    left, right, gt = _synthetic_files(tmp_path)
    args = _parser().parse_args(["eval", "stereo", left, right, "--truth", gt])
    assert args.func(args) == 0
    assert "bad2" in capsys.readouterr().out
    (tmp_path / "broken.png").write_bytes(b"nope")
    args = _parser().parse_args(
        ["eval", "stereo", str(tmp_path / "broken.png"), right, "--truth", gt]
    )
    with pytest.raises(LinoLocError, match="broken.png"):
        args.func(args)
    np.save(tmp_path / "small.npy", np.ones((10, 10), np.float32))
    args = _parser().parse_args(
        ["eval", "stereo", left, right, "--truth", str(tmp_path / "small.npy")]
    )
    with pytest.raises(LinoLocError, match="small.npy"):
        args.func(args)


@pytest.mark.skipif(not MIDDLEBURY.is_dir(), reason="shared Middlebury data not present")
def test_middlebury_motorcycle_regression(capsys):
    argv = [
        "eval",
        "stereo",
        str(MIDDLEBURY / "motorcycle_left.png"),
        str(MIDDLEBURY / "motorcycle_right.png"),
        "--truth",
        str(MIDDLEBURY / "motorcycle_disp.npz"),
        "--max-disparity",
        "60",
        "--json",
    ]
    args = _parser().parse_args(argv)
    assert args.func(args) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["truth_max_disparity"] <= r["config"]["num_disparities"] - 1
    assert r["density"] >= MB_DENSITY_MIN, r
    assert r["bad1"] <= MB_BAD1_MAX, r
    assert r["bad2"] <= MB_BAD2_MAX, r
    assert r["rmse_px"] <= MB_RMSE_MAX, r

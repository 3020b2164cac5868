"""`lino-loc eval global --map` and `eval tracking --map`: a given map file evaluated on the same
test views as the rendered survey's map."""

from __future__ import annotations

import json

import pytest

from lino_loc.appearance_map import AppearanceMap
from services.cli import main


@pytest.fixture(scope="module")
def small_map(tmp_path_factory: pytest.TempPathFactory) -> str:
    tmp = tmp_path_factory.mktemp("eval-map")
    ds, m = tmp / "ds", tmp / "m.npz"
    assert main(["survey", "--world", "office", "--step", "2.0", "--heading-step", "90", "--width", "80",
                 "--height", "60", "--no-stereo", "--out", str(ds)]) == 0
    assert main(["map", "build", str(ds), "--out", str(m), "--features", "3"]) == 0
    return str(m)


def _json(capsys: pytest.CaptureFixture[str]) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_global_evaluates_the_given_map(small_map, capsys):
    n = len(AppearanceMap.load(small_map))
    assert main(["eval", "global", "--map", small_map, "--starts", "1", "--updates", "2", "--workers", "1",
                 "--json"]) == 0
    res = _json(capsys)
    assert res["map"]["file"] == small_map and res["map_entries"] == n and res["features"] == 3
    assert len(res["mean_error_m"]) == 2


def test_tracking_evaluates_the_given_map(small_map, capsys):
    n = len(AppearanceMap.load(small_map))
    assert main(["eval", "tracking", "--world", "office", "--map", small_map, "--duration", "2", "--lights", "tube",
                 "--switch-lights", "none", "--changes", "none", "--no-global", "--no-recovery-comparison",
                 "--no-kidnap", "--channels", "intensity", "--workers", "1", "--json"]) == 0
    res = _json(capsys)
    assert res["map"]["file"] == small_map and res["map_entries"] == n and res["features"] == 3
    assert res["conditions"]["tube"]["ate_rmse_m"] >= 0.0


def test_a_map_without_the_asked_channel_or_file_is_one_line(small_map, tmp_path, capsys):
    assert main(["eval", "global", "--map", small_map, "--channels", "intensity,disparity", "--starts", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no disparity channel" in err[0]
    assert main(["eval", "tracking", "--map", str(tmp_path / "none.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none.npz" in err[0]

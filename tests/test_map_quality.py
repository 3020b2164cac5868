"""`lino-loc map check` (lino_loc.map_quality): findings on synthetic maps with known holes
and a known ambiguous area; the CLI's report, JSON and PNG."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import services.cli as cli
from lino_loc.appearance_map import AppearanceMap, ChannelMap
from lino_loc.dataset import CameraInfo
from lino_loc.map_quality import QualityThresholds, check_map, heading_sector
from lino_loc.pca import PCA

CAM = CameraInfo(width=16, height=12, fx=10.0, fy=10.0, cx=8.0, cy=6.0)
SIZE = (8, 6)


def _grid_poses() -> np.ndarray:
    """Positions every 0.5 m over 0..5 x 0..2 m, headings every 30 deg."""
    xs, ys, ts = np.arange(0, 5.01, 0.5), np.arange(0, 2.01, 0.5), np.radians(np.arange(0, 360, 30))
    return np.array([(x, y, t) for x in xs for y in ys for t in ts])


def _features(poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Features varying smoothly with the pose (a nearest-neighbour model's ideal): the
    nearest view in feature space is a neighbour in pose."""
    x, y, t = poses.T
    f = np.stack([2 * x, 2 * y, 3 * np.cos(t), 3 * np.sin(t)], axis=1)
    return (f + 0.01 * rng.standard_normal(f.shape)).astype(np.float32)


def _map(poses: np.ndarray, feats: np.ndarray) -> AppearanceMap:
    D = SIZE[0] * SIZE[1]
    comps = np.linalg.qr(np.random.default_rng(1).standard_normal((D, feats.shape[1])))[0].T.astype(np.float32)
    pca = PCA(mean=np.zeros(D, np.float32), components=comps,
              explained_variance=np.ones(feats.shape[1], np.float32))
    ch = ChannelMap(name="intensity", preprocess="none", size=SIZE, pca=pca, features=feats)
    return AppearanceMap(poses=poses, channels={"intensity": ch}, camera=CAM, name="synthetic")


@pytest.fixture
def holed_map() -> AppearanceMap:
    """The grid without the east-facing views at x = 2.5 and 3.0 (cells 2.25 < x < 3.25) and
    without any view at (1.0, 1.0)."""
    rng = np.random.default_rng(0)
    p = _grid_poses()
    east = (heading_sector(p[:, 2], 8) == 0) & np.isin(np.round(p[:, 0], 2), (2.5, 3.0))
    gone = np.isclose(p[:, 0], 1.0) & np.isclose(p[:, 1], 1.0)
    p = p[~east & ~gone]
    return _map(p, _features(p, rng))


def test_known_holes_are_found(holed_map: AppearanceMap) -> None:
    q = check_map(holed_map)
    assert q.cell_m == pytest.approx(0.5)
    holes = [f for f in q.findings if f.kind == "heading_hole"]
    assert len(holes) == 1
    h = holes[0]
    assert h.sector == "east" and h.x == (2.25, 3.25) and h.y == (-0.25, 2.25) and h.cells == 10
    assert "no views facing east in 2.25 < x < 3.25" in h.message
    pos = [f for f in q.findings if f.kind == "position_hole"]
    assert len(pos) == 1 and pos[0].x == (0.75, 1.25) and pos[0].y == (0.75, 1.25)
    assert q.heading_holes == 10 and q.position_holes == 1
    # smooth features: nothing ambiguous
    assert q.ambiguous_fraction == 0.0
    assert not [f for f in q.findings if f.kind == "ambiguous"]


def test_full_grid_has_no_findings() -> None:
    p = _grid_poses()
    q = check_map(_map(p, _features(p, np.random.default_rng(2))))
    assert q.findings == [] and q.coverage_fraction == 1.0


def test_ambiguous_area_is_found() -> None:
    """Views in 4.0 <= x <= 5.0 given the features of views at x - 4 (a copy of the west
    end): their nearest other-position view is 4 m away."""
    rng = np.random.default_rng(3)
    p = _grid_poses()
    q_pose = p.copy()
    east_end = p[:, 0] >= 4.0 - 1e-9
    q_pose[east_end, 0] -= 4.0
    feats = _features(q_pose, rng)
    q = check_map(_map(p, feats))
    amb = [f for f in q.findings if f.kind == "ambiguous"]
    assert amb, q.findings
    assert any(f.x[0] <= 4.0 and f.x[1] >= 5.0 for f in amb)
    assert all(f.x[0] >= -0.25 for f in amb)
    assert q.ambiguous_fraction > 0.2


def test_thresholds_change_the_findings(holed_map: AppearanceMap) -> None:
    q = check_map(holed_map, thresholds=QualityThresholds(min_hole_cells=11))
    assert not [f for f in q.findings if f.kind == "heading_hole"]


@pytest.fixture(autouse=False)
def map_cli(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("services.commands.map",))


def test_cli_report_json_png(holed_map: AppearanceMap, tmp_path: Path, map_cli: None,
                             capsys: pytest.CaptureFixture[str]) -> None:
    path = holed_map.save(tmp_path / "holed.npz")
    code = cli.main(["map", "check", str(path), "--out", str(tmp_path / "rep")])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "- no views facing east in 2.25 < x < 3.25" in out
    rep = json.loads((tmp_path / "rep" / "map_check.json").read_text())
    assert rep["heading_holes"] == 10
    pytest.importorskip("matplotlib")
    png = (tmp_path / "rep" / "map_check.png").read_bytes()
    assert png.startswith(b"\x89PNG")


def test_cli_bad_map_is_one_line(tmp_path: Path, map_cli: None, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a map")
    code = cli.main(["map", "check", str(bad)])
    _, err = capsys.readouterr()
    assert code == 2 and len(err.strip().splitlines()) == 1 and "bad.npz" in err


def test_cell_of_a_map_of_two_sessions_is_the_sparser_spacing() -> None:
    """A 0.5 m survey extended by a 0.75 m one: cells of 0.75 m, no false holes."""
    from lino_loc.appearance_map import SessionInfo

    rng = np.random.default_rng(4)
    a = _grid_poses()
    xs, ys, ts = np.arange(0, 5.01, 0.75), np.arange(0, 2.01, 0.75), np.radians(np.arange(0, 360, 30))
    b = np.array([(x, y, t) for x in xs for y in ys for t in ts])
    p = np.vstack([a, b])
    amap = _map(p, _features(p, rng))
    amap.sessions = [SessionInfo(name="tube", first_entry=0, n_entries=len(a)),
                     SessionInfo(name="bulb", first_entry=len(a), n_entries=len(b), basis="projected")]
    q = check_map(amap)
    assert q.cell_m == pytest.approx(0.75)
    assert q.position_holes == 0 and q.heading_holes == 0

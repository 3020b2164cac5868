"""Dataset folders (docs/datasets.md): writer/reader round trip and validation messages."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lino_loc.dataset import (
    MAX_EXTENT_M,
    CameraInfo,
    Dataset,
    DatasetMeta,
    DatasetWriter,
    dataset_problems,
    decode_scaled_u16,
    encode_scaled_u16,
    extent_problem,
    pose_problem,
    require_valid,
)
from lino_loc.errors import LinoLocError

W, H = 16, 12


def _meta(**kw) -> DatasetMeta:
    cam = CameraInfo(width=W, height=H, fx=20.0, fy=20.0, cx=8.0, cy=6.0, baseline_m=0.075)
    return DatasetMeta(name="tiny", camera=cam, source="test", **kw)


def _write(root: Path, n: int = 4, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    with DatasetWriter(root, _meta()) as w:
        for i in range(n):
            w.add(rng.integers(0, 256, (H, W), dtype=np.uint8), (0.5 * i, -0.25 * i, 0.1 * i), condition="tube")
    return root


def _one_line_error(fn, *needles: str) -> str:
    with pytest.raises(LinoLocError) as info:
        fn()
    msg = str(info.value)
    assert "\n" not in msg
    for needle in needles:
        assert needle in msg, f"{needle!r} not in {msg!r}"
    return msg


def test_round_trip_all_columns(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    root = tmp_path / "ds"
    imgs, rights, depths, disps, poses = [], [], [], [], []
    with DatasetWriter(root, _meta()) as w:
        for i in range(3):
            img = rng.integers(0, 256, (H, W), dtype=np.uint8)
            right = rng.integers(0, 256, (H, W), dtype=np.uint8)
            depth = rng.uniform(0.3, 8.0, (H, W))
            depth[0, :3] = [np.nan, 0.0, -1.0]  # all three mean "no value"
            disp = rng.uniform(0.5, 60.0, (H, W))
            disp[1, 1] = np.nan
            pose = (1.0 + i, 2.0 - i, 0.3 * i - 3.0)
            kw = {"depth": depth, "disparity": disp, "right": right} if i != 1 else {}
            idx = w.add(img, pose, condition="bulb" if i == 2 else "tube", stamp=100.0 + i if i else None, **kw)
            assert idx == i
            imgs.append(img), rights.append(right), depths.append(depth), disps.append(disp), poses.append(pose)
    header = (root / "poses.csv").read_text().splitlines()[0]
    assert header == "image,x,y,theta,right,disparity,depth,condition,stamp"
    ds = Dataset.open(root)
    assert len(ds) == 3 and ds.has_depth and ds.has_disparity and ds.has_right
    np.testing.assert_array_equal(ds.poses, np.array(poses))
    assert ds.conditions == ["tube", "tube", "bulb"]
    assert ds.meta.conditions == ["tube", "bulb"]
    assert np.isnan(ds.stamps[0]) and ds.stamps[2] == 102.0
    for i in (0, 2):
        np.testing.assert_array_equal(ds.image(i), imgs[i])
        np.testing.assert_array_equal(ds.right(i), rights[i])
        d = ds.depth(i)
        assert d.dtype == np.float32 and np.isnan(d[0, :3]).all()
        ok = np.isfinite(depths[i]) & (depths[i] > 0)
        np.testing.assert_array_equal(np.isfinite(d), ok)
        # 16-bit quantisation: half a step of 1/depth_scale
        assert np.max(np.abs(d[ok] - depths[i][ok])) <= 0.5 / 1000 + 1e-6
        q = ds.disparity(i)
        assert np.isnan(q[1, 1]) and np.isfinite(q).sum() == H * W - 1
        ok = np.isfinite(q)
        assert np.max(np.abs(q[ok] - disps[i][ok])) <= 0.5 / 16 + 1e-6
        raw = cv2.imread(str(root / f"depth/{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw[0, 0] == 0
    assert ds.depth(1) is None and ds.disparity(1) is None and ds.right(1) is None
    tube = ds.where("tube")
    assert len(tube) == 2 and tube.conditions == ["tube", "tube"]
    np.testing.assert_array_equal(tube.image(1), imgs[1])
    sub = ds.subset([2, 0])
    np.testing.assert_array_equal(sub.poses, np.array([poses[2], poses[0]]))
    assert len(ds.where("natural")) == 0


def test_scaled_u16_codec_closed_form() -> None:
    v = np.array([np.nan, -2.0, 0.0, 0.01, 1.0, 65.535, 65.6, np.inf])
    raw = encode_scaled_u16(v, 1000)
    np.testing.assert_array_equal(raw, [0, 0, 0, 10, 1000, 65535, 0, 0])
    back = decode_scaled_u16(raw, 1000)
    assert np.isnan(back[[0, 1, 2, 6, 7]]).all()
    np.testing.assert_allclose(back[[3, 4, 5]], [0.01, 1.0, 65.535], rtol=1e-6)


def test_colour_image_read_as_grey(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    colour = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    with DatasetWriter(tmp_path / "c", _meta()) as w:
        w.add(colour, (0, 0, 0))
    got = Dataset.open(tmp_path / "c").image(0)
    assert got.shape == (H, W) and got.dtype == np.uint8
    # the PNG decoder's own colour -> grey conversion rounds differently by at most 1 level
    ref = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY).astype(int)
    assert np.max(np.abs(got.astype(int) - ref)) <= 1


def test_writer_refuses_non_empty_folder_and_overwrites(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds", n=5)
    _one_line_error(lambda: DatasetWriter(root, _meta()), str(root), "not empty")
    with DatasetWriter(root, _meta(), overwrite=True) as w:
        w.add(np.zeros((H, W), np.uint8), (0, 0, 0))
    ds = Dataset.open(root)
    assert len(ds) == 1
    assert sorted(p.name for p in (root / "images").iterdir()) == ["000000.png"]


def test_writer_checks_inputs(tmp_path: Path) -> None:
    w = DatasetWriter(tmp_path / "w", _meta())
    _one_line_error(lambda: w.add(np.zeros((H, W + 1), np.uint8), (0, 0, 0)), "camera is 16x12")
    _one_line_error(lambda: w.add(np.zeros((H, W), np.float32), (0, 0, 0)), "uint8")
    _one_line_error(lambda: w.add(np.zeros((H, W), np.uint8), (0, np.nan, 0)), "pose")
    _one_line_error(lambda: w.add(np.zeros((H, W), np.uint8), (0, 0, 0), depth=np.ones((2, 2))), "depth")


def test_failed_survey_is_not_a_dataset(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    with pytest.raises(RuntimeError):
        with DatasetWriter(root, _meta()) as w:
            w.add(np.zeros((H, W), np.uint8), (0, 0, 0))
            raise RuntimeError("renderer crashed")
    _one_line_error(lambda: Dataset.open(root), "dataset.json", "missing")


# ----------------------------------------------------------------- validation
def test_missing_folder_and_dataset_json(tmp_path: Path) -> None:
    _one_line_error(lambda: Dataset.open(tmp_path / "nope"), "nope")
    root = _write(tmp_path / "ds")
    (root / "dataset.json").unlink()
    _one_line_error(lambda: Dataset.open(root), "dataset.json", "missing")


def test_bad_json(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    (root / "dataset.json").write_text('{"version": 1, "name": ')
    _one_line_error(lambda: Dataset.open(root), "dataset.json", "bad JSON", "line 1")
    (root / "dataset.json").write_text("[1, 2]")
    _one_line_error(lambda: Dataset.open(root), "dataset.json", "object")


@pytest.mark.parametrize("version, needle", [(2, "newer"), (0, "unsupported"), ("1", "not an integer")])
def test_wrong_version(tmp_path: Path, version, needle: str) -> None:
    root = _write(tmp_path / "ds")
    meta = json.loads((root / "dataset.json").read_text())
    meta["version"] = version
    (root / "dataset.json").write_text(json.dumps(meta))
    _one_line_error(lambda: Dataset.open(root), "dataset.json", "version", needle)


def test_bad_meta_field(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    meta = json.loads((root / "dataset.json").read_text())
    meta["camera"]["fx"] = -3
    (root / "dataset.json").write_text(json.dumps(meta))
    _one_line_error(lambda: Dataset.open(root), "dataset.json", "camera.fx")
    del meta["camera"]
    (root / "dataset.json").write_text(json.dumps(meta))
    _one_line_error(lambda: Dataset.open(root), "dataset.json", "camera")


def _edit_csv(root: Path, fn) -> None:
    lines = (root / "poses.csv").read_text().splitlines()
    (root / "poses.csv").write_text("\n".join(fn(lines)) + "\n")


def test_missing_column(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")

    def drop_theta(lines):
        out = []
        for ln in lines:
            cells = ln.split(",")
            del cells[3]
            out.append(",".join(cells))
        return out

    _edit_csv(root, drop_theta)
    _one_line_error(lambda: Dataset.open(root), "poses.csv", "header", "missing column 'theta'")


def test_unknown_and_duplicate_columns(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    _edit_csv(root, lambda ls: [ls[0].replace("stamp", "stmp")] + ls[1:])
    _one_line_error(lambda: Dataset.open(root), "poses.csv", "unknown column 'stmp'")
    _edit_csv(root, lambda ls: [ls[0].replace("stmp", "x")] + ls[1:])
    _one_line_error(lambda: Dataset.open(root), "poses.csv", "duplicate column 'x'")


def test_non_numeric_x(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    _edit_csv(root, lambda ls: ls[:2] + [ls[2].replace(",0.5,", ",abc,", 1)] + ls[3:])
    _one_line_error(lambda: Dataset.open(root), "poses.csv", "line 3", "field 'x'", "abc")


def test_nan_theta(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")

    def nan_theta(lines):
        cells = lines[4].split(",")
        cells[3] = "nan"
        return lines[:4] + [",".join(cells)]

    _edit_csv(root, nan_theta)
    _one_line_error(lambda: Dataset.open(root), "poses.csv", "line 5", "field 'theta'", "not finite")


def test_wrong_field_count_and_empty(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    _edit_csv(root, lambda ls: ls[:2] + [ls[2] + ",extra"] + ls[3:])
    _one_line_error(lambda: Dataset.open(root), "poses.csv", "line 3", "fields")
    _edit_csv(root, lambda ls: ls[:1])
    _one_line_error(lambda: Dataset.open(root), "poses.csv", "no rows")


def test_missing_image_file(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    (root / "images" / "000002.png").unlink()
    _one_line_error(lambda: Dataset.open(root), "poses.csv", "line 4", "field 'image'", "000002.png")


def test_unreadable_image(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    (root / "images" / "000001.png").write_bytes(b"this is not a png")
    ds = Dataset.open(root)  # existence is checked up front; decoding when read
    _one_line_error(lambda: ds.image(1), "000001.png", "unreadable")
    np.testing.assert_equal(ds.image(0).shape, (H, W))


# ------------------------------------------------------------------ content checks


def _set_cell(root: Path, line: int, col: str, value: str) -> None:
    """Set column ``col`` of line ``line`` (1 = header) of poses.csv."""

    def edit(lines):
        header = lines[0].split(",")
        cells = lines[line - 1].split(",")
        cells[header.index(col)] = value
        return lines[: line - 1] + [",".join(cells)] + lines[line:]

    _edit_csv(root, edit)


def _one_problem(root: Path, *needles: str) -> str:
    problems = dataset_problems(Dataset.open(root), workers=1)
    assert len(problems) == 1, problems
    (msg,) = problems
    assert "\n" not in msg
    for needle in needles:
        assert needle in msg, f"{needle!r} not in {msg!r}"
    with pytest.raises(LinoLocError) as info:
        require_valid(Dataset.open(root))
    assert str(info.value) == msg
    return msg


def test_a_good_dataset_has_no_problems(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    rng = np.random.default_rng(1)
    with DatasetWriter(root, _meta()) as w:
        for i in range(70):  # more than one chunk of 64 rows: the thread pool runs
            w.add(rng.integers(0, 256, (H, W), dtype=np.uint8), (0.1 * i, 0.0, 0.0),
                  depth=rng.uniform(0.5, 3.0, (H, W)), right=rng.integers(0, 256, (H, W), dtype=np.uint8))
    ds = Dataset.open(root)
    seen = []
    assert dataset_problems(ds, progress=lambda d, n: seen.append((d, n))) == []
    assert seen[-1] == (70, 70) and len(seen) == 2
    assert dataset_problems(ds, workers=1) == []
    require_valid(ds)


def test_undecodable_image_is_named_with_its_row(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    (root / "images" / "000001.png").write_bytes(b"\x89PNG\r\n\x1a\n but truncated")
    _one_problem(root, str(root / "images" / "000001.png"), "poses.csv line 3", "field 'image'", "cannot be decoded")


def test_image_of_another_size(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    cv2.imwrite(str(root / "images" / "000002.png"), np.zeros((H + 4, W * 2), np.uint8))
    _one_problem(root, "000002.png", "line 4", "field 'image'", f"{2 * W}x{H + 4} pixels",
                 f"the camera in dataset.json is {W}x{H}")


def test_every_problem_is_one_line(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    rng = np.random.default_rng(2)
    with DatasetWriter(root, _meta()) as w:
        for i in range(3):
            w.add(rng.integers(0, 256, (H, W), dtype=np.uint8), (0.5 * i, 0.0, 0.0),
                  depth=rng.uniform(0.5, 3.0, (H, W)))
    cv2.imwrite(str(root / "depth" / "000000.png"), np.zeros((H, W), np.uint8))  # 8-bit depth
    (root / "images" / "000002.png").write_bytes(b"")
    _set_cell(root, 3, "y", "1e300")
    problems = dataset_problems(Dataset.open(root))
    assert len(problems) == 3, problems
    assert problems[0].startswith(f"{root / 'poses.csv'}: line 3, field 'y': 1e+300 is not a position in metres")
    assert problems[1].startswith(f"{root / 'depth' / '000000.png'}: poses.csv line 2, field 'depth': "
                                  "expected a 16-bit single-channel PNG, got uint8")
    assert problems[2].startswith(f"{root / 'images' / '000002.png'}: poses.csv line 4, field 'image': cannot")
    with pytest.raises(LinoLocError, match=r"\(and 2 more; see `lino-loc dataset check "):
        require_valid(Dataset.open(root))


def test_pose_of_1e300(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    _set_cell(root, 3, "x", "1e300")
    Dataset.open(root)  # finite: the structure is fine
    _one_problem(root, "poses.csv: line 3, field 'x': 1e+300 is not a position in metres (|x| > 1e+07)")


def test_survey_in_millimetres(tmp_path: Path) -> None:
    root = tmp_path / "mm"
    rng = np.random.default_rng(3)
    with DatasetWriter(root, _meta()) as w:
        for x, y in ((0.0, 0.0), (4.2, 0.0), (4.2, 3.1), (0.0, 3.1), (2.0, 1.0)):
            w.add(rng.integers(0, 256, (H, W), dtype=np.uint8), (1000 * x, 1000 * y, 0.0))
    _one_problem(root, "poses.csv: extent 4200 x 3100 m: are the poses in millimetres? poses are metres")


def test_headings_in_degrees(tmp_path: Path) -> None:
    root = _write(tmp_path / "ds")
    _set_cell(root, 5, "theta", "345")
    _one_problem(root, "line 5, field 'theta': 345 is not a heading in radians", "in degrees?")


def test_pose_and_extent_rules() -> None:
    assert pose_problem((1e7, -1e7, 8 * np.pi)) is None
    assert "field 'y'" in pose_problem((0.0, np.inf, 0.0))
    assert "not finite" in pose_problem((np.nan, 0.0, 0.0))
    assert extent_problem(np.array([[0.0, 0.0, 0.0], [MAX_EXTENT_M, 0.0, 0.0]])) is None
    assert "extent 1001 x 0 m" in extent_problem(np.array([[0.0, 0.0, 0.0], [MAX_EXTENT_M + 1, 0.0, 0.0]]))
    # UTM-like coordinates: large but a small survey
    assert extent_problem(np.array([[5e5, 5.2e6, 0.0], [5e5 + 30, 5.2e6 + 20, 0.0]])) is None

"""`lino-loc map build` / `map info`: exit codes, JSON output, one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import services.cli as cli
from lino_loc.dataset import CameraInfo, DatasetMeta, DatasetWriter


@pytest.fixture(autouse=True)
def only_map_commands(monkeypatch: pytest.MonkeyPatch) -> None:
    # run the real CLI (parser, error handling, exit codes) with just this command group,
    # so the test does not depend on the other command modules
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("services.commands.map",))


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    cam = CameraInfo(width=24, height=18, fx=20.0, fy=20.0, cx=12.0, cy=9.0)
    root = tmp_path / "ds"
    with DatasetWriter(root, DatasetMeta(name="cli", camera=cam)) as w:
        for i in range(12):
            w.add(rng.integers(0, 256, (18, 24), dtype=np.uint8), (0.5 * i, 0.0, 0.0), condition="tube")
    return root


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    try:
        code = cli.main(list(argv))
    except SystemExit as exc:  # argparse usage errors
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


def test_build_and_info(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out_map = tmp_path / "m.npz"
    code, out, err = _run(
        capsys, "map", "build", str(dataset), "--out", str(out_map), "--features", "5",
        "--preprocess", "gradient", "--size", "12x9", "--condition", "tube", "--json",
    )
    assert code == 0, err
    summary = json.loads(out)
    assert summary["images"] == 12 and summary["size"] == [12, 9] and out_map.is_file()

    code, out, err = _run(capsys, "map", "info", str(out_map), "--json")
    assert code == 0
    assert len(out.strip().splitlines()) == 1  # exactly one JSON object
    info = json.loads(out)
    assert info["n_images"] == 12 and info["condition"] == "tube"
    ch = info["channels"]["intensity"]
    assert ch["n_features"] == 5 and ch["preprocess"] == "gradient" and ch["size"] == [12, 9]

    code, out, _ = _run(capsys, "map", "info", str(out_map))
    assert code == 0 and "intensity: 5 features, preprocess gradient, 12x9" in out


def test_build_with_virtual_headings(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out_map = tmp_path / "v.npz"
    code, out, err = _run(capsys, "map", "build", str(dataset), "--out", str(out_map), "--features", "4",
                          "--size", "24x18", "--virtual-headings", "3", "--virtual-step", "4", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["images"] == 12 and summary["entries"] == 36
    code, out, _ = _run(capsys, "map", "info", str(out_map))
    assert code == 0 and "every image also turned by -4,0,4 deg" in out
    assert "entries    36 (12 images x 3 headings)" in out
    # a turn that leaves the field of view is refused in one line
    code, _, err = _run(capsys, "map", "build", str(dataset), "--out", str(tmp_path / "w.npz"),
                        "--size", "24x18", "--virtual-headings", "3", "--virtual-step", "40")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "virtual headings" in err
    code, _, err = _run(capsys, "map", "build", str(dataset), "--out", str(tmp_path / "w.npz"),
                        "--virtual-headings", "0")
    assert code == 2 and len(err.strip().splitlines()) == 1


def test_bad_map_files_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "notes.txt").write_text("not a map")
    for path in (tmp_path / "notes.txt", tmp_path / "missing.npz"):
        code, out, err = _run(capsys, "map", "info", str(path))
        assert code == 2 and out == ""
        assert len(err.strip().splitlines()) == 1 and str(path) in err and "Traceback" not in err


def test_malformed_dataset_exit_2(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (dataset / "poses.csv").write_text("image,x,y\nimages/000000.png,0,0\n")
    code, _, err = _run(capsys, "map", "build", str(dataset), "--out", str(tmp_path / "m.npz"))
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "poses.csv" in err and "theta" in err
    assert not (tmp_path / "m.npz").exists()


def test_bad_arguments_exit_2(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out_map = str(tmp_path / "m.npz")
    for extra in (["--size", "80by60"], ["--preprocess", "sharpen"], ["--features", "50"], ["--condition", "dusk"]):
        code, _, err = _run(capsys, "map", "build", str(dataset), "--out", out_map, *extra)
        assert code == 2, extra
        assert len(err.strip().splitlines()) == 1, err


def _set_x(dataset: Path, line: int, value: str) -> None:
    lines = (dataset / "poses.csv").read_text().splitlines()
    cells = lines[line - 1].split(",")
    cells[1] = value
    lines[line - 1] = ",".join(cells)
    (dataset / "poses.csv").write_text("\n".join(lines) + "\n")


def _refused(capsys: pytest.CaptureFixture[str], dataset: Path, out_map: Path, *needles: str) -> str:
    code, out, err = _run(capsys, "map", "build", str(dataset), "--out", str(out_map), "--features", "3")
    assert code == 2 and out == "" and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err
    for needle in needles:
        assert needle in err, (needle, err)
    assert not out_map.exists()
    return err


def test_build_refuses_what_dataset_check_refuses(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import cv2

    from lino_loc.dataset import Dataset, dataset_problems

    _set_x(dataset, 4, "1e300")
    _refused(capsys, dataset, tmp_path / "a.npz", "poses.csv: line 4, field 'x': 1e+300 is not a position in metres")
    _set_x(dataset, 4, "1.5")
    cv2.imwrite(str(dataset / "images" / "000005.png"), np.zeros((36, 48), np.uint8))
    (dataset / "images" / "000007.png").write_bytes(b"not a png")
    err = _refused(capsys, dataset, tmp_path / "b.npz", "000005.png: poses.csv line 7, field 'image': 48x36 pixels",
                   "(and 1 more; see `lino-loc dataset check")
    assert err.split("error: ", 1)[1].startswith(dataset_problems(Dataset.open(dataset))[0])


def test_build_refuses_a_survey_in_millimetres(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(1)
    cam = CameraInfo(width=24, height=18, fx=20.0, fy=20.0, cx=12.0, cy=9.0)
    root = tmp_path / "mm"
    with DatasetWriter(root, DatasetMeta(name="mm", camera=cam)) as w:
        for i in range(12):
            w.add(rng.integers(0, 256, (18, 24), dtype=np.uint8), (1000.0 * 0.4 * i, 1000.0 * 0.1 * (i % 3), 0.0))
    _refused(capsys, root, tmp_path / "m.npz", "extent 4400 x 200 m: are the poses in millimetres? poses are metres")


def test_dataset_check_lists_every_problem(dataset: Path, monkeypatch: pytest.MonkeyPatch,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    import cv2

    monkeypatch.setattr(cli, "COMMAND_MODULES", ("services.commands.dataset_cmd",))
    code, out, err = _run(capsys, "dataset", "check", "--json", str(dataset))
    assert code == 0 and err == "" and json.loads(out)["ok"] is True and json.loads(out)["problems"] == []
    _set_x(dataset, 2, "1e300")
    cv2.imwrite(str(dataset / "images" / "000005.png"), np.zeros((36, 48), np.uint8))
    (dataset / "images" / "000007.png").write_bytes(b"")
    code, out, err = _run(capsys, "dataset", "check", "--json", str(dataset))
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 3 and "Traceback" not in err
    assert "line 2, field 'x'" in lines[0] and "000005.png" in lines[1] and "000007.png" in lines[2]
    summary = json.loads(out)
    assert summary["ok"] is False and summary["problems"] == lines
    code, out, err = _run(capsys, "dataset", "check", str(dataset))
    assert code == 2 and err.strip().splitlines() == lines and "problems" not in json.loads(out)


def test_disparity_channel_info_names_its_source_and_the_em(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(1)
    cam = CameraInfo(width=24, height=18, fx=20.0, fy=20.0, cx=12.0, cy=9.0, baseline_m=0.075)
    root = tmp_path / "stereo"
    meta = DatasetMeta(name="st", camera=cam, disparity_source="stereo-matcher")
    with DatasetWriter(root, meta) as w:
        for i in range(16):
            disp = rng.uniform(2.0, 20.0, (18, 24))
            disp[rng.random((18, 24)) < 0.6] = np.nan  # sparse, as a stereo matcher's
            w.add(rng.integers(0, 256, (18, 24), dtype=np.uint8), (0.5 * i, 0.0, 0.0), disparity=disp)
    out_map = tmp_path / "d.npz"
    code, _, err = _run(capsys, "map", "build", str(root), "--out", str(out_map), "--features", "3",
                        "--size", "12x9", "--channels", "intensity,disparity")
    assert code == 0, err
    few = tmp_path / "few.npz"
    code, _, err = _run(capsys, "map", "build", str(root), "--out", str(few), "--features", "3",
                        "--disparity-features", "2", "--size", "12x9", "--channels", "intensity,disparity")
    assert code == 0, err
    code, out, _ = _run(capsys, "map", "info", str(few), "--json")
    assert {c: v["n_features"] for c, v in json.loads(out)["channels"].items()} == {"intensity": 3, "disparity": 2}
    code, out, _ = _run(capsys, "map", "info", str(out_map), "--json")
    params = json.loads(out)["channels"]["disparity"]["params"]
    assert params["source"] == "stereo-matcher" and params["em_converged"] is True
    assert 0 < params["em_iterations"] < 100
    code, out, _ = _run(capsys, "map", "info", str(out_map))
    assert code == 0 and "source stereo-matcher" in out
    assert f"EM {params['em_iterations']} iterations (converged)" in out
    # a map written before these parameters existed still loads; its info leaves them out
    with np.load(out_map, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    header = json.loads(bytes(arrays["header"]).decode())
    for key in ("source", "em_iterations", "em_converged"):
        header["channels"]["disparity"]["params"].pop(key)
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    old = tmp_path / "old.npz"
    np.savez(old, **arrays)
    code, out, err = _run(capsys, "map", "info", str(old))
    assert code == 0, err
    assert "disparity: 3 features" in out and "EM " not in out and "source" not in out


def test_build_checks_only_the_files_it_reads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`map build` decodes the images and, for the disparity channel, the disparity column
    before it builds; a broken right image (which no channel reads) does not stop it, a broken
    disparity file does, and `dataset check` still reports both."""
    rng = np.random.default_rng(2)
    cam = CameraInfo(width=24, height=18, fx=20.0, fy=20.0, cx=12.0, cy=9.0, baseline_m=0.075)
    root = tmp_path / "stereo"
    with DatasetWriter(root, DatasetMeta(name="st", camera=cam)) as w:
        for i in range(12):
            disp = rng.uniform(2.0, 20.0, (18, 24))
            disp[rng.random((18, 24)) < 0.5] = np.nan
            img = rng.integers(0, 256, (18, 24), dtype=np.uint8)
            w.add(img, (0.5 * i, 0.0, 0.0), disparity=disp, right=img)
    (root / "images_right" / "000003.png").write_bytes(b"not a png")
    code, _, err = _run(capsys, "map", "build", str(root), "--out", str(tmp_path / "a.npz"), "--features", "3",
                        "--size", "12x9", "--channels", "intensity,disparity")
    assert code == 0, err
    (root / "disparity" / "000004.png").write_bytes(b"not a png")
    code, out, err = _run(capsys, "map", "build", str(root), "--out", str(tmp_path / "b.npz"), "--features", "3",
                          "--size", "12x9", "--channels", "intensity,disparity")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "000004.png: poses.csv line 6, field 'disparity': cannot be decoded" in err
    assert "(and" not in err  # the right image is not one of its problems
    # intensity alone reads no disparity file
    code, _, err = _run(capsys, "map", "build", str(root), "--out", str(tmp_path / "c.npz"), "--features", "3",
                        "--size", "12x9")
    assert code == 0, err
    from lino_loc.dataset import Dataset, dataset_problems

    problems = dataset_problems(Dataset.open(root))
    assert [p.split("field ")[1].split(":")[0] for p in problems] == ["'right'", "'disparity'"]
    with pytest.raises(ValueError, match="not file columns"):
        dataset_problems(Dataset.open(root), columns=("images",))

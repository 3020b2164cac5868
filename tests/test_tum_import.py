"""TUM RGB-D import on a tiny synthetic sequence with known answers."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lino_loc.dataset import Dataset
from lino_loc.errors import LinoLocError
from lino_loc.tum_import import import_tum, planar_pose

# Camera-to-world rotation of a camera looking along world +y, level (x right, y down, z forward).
LOOK_ALONG_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _write_sequence(root: Path, with_associations: bool = True) -> None:
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    # Ground truth every 0.01 s from t=100.00 to 101.00: x goes 0 -> 2 m, heading +y, pitched down.
    pitch_down = Rotation.from_euler("x", -20, degrees=True)  # about the camera x axis
    rot = Rotation.from_matrix(LOOK_ALONG_Y) * pitch_down
    q = rot.as_quat()
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for k in range(101):
        t = 100.0 + 0.01 * k
        lines.append(f"{t:.4f} {2.0 * k / 100:.6f} 3.0 1.5 {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    assoc = []
    rgb_list, depth_list = [], []
    for t in (99.5, 100.25, 100.5, 101.5):  # first and last are outside the ground truth
        name = f"{t:.6f}.png"
        cv2.imwrite(str(root / "rgb" / name), np.full((6, 8, 3), 100, np.uint8))
        cv2.imwrite(str(root / "depth" / name), np.full((6, 8), 5000, np.uint16))
        assoc.append(f"{t:.6f} rgb/{name} {t:.6f} depth/{name}")
        rgb_list.append(f"{t:.6f} rgb/{name}")
        depth_list.append(f"{t + 0.005:.6f} depth/{name}")
    if with_associations:
        (root / "associations.txt").write_text("\n".join(assoc) + "\n")
    else:
        (root / "rgb.txt").write_text("# rgb\n" + "\n".join(rgb_list) + "\n")
        (root / "depth.txt").write_text("# depth\n" + "\n".join(depth_list) + "\n")


@pytest.mark.parametrize("with_associations", [True, False])
def test_import_known_poses(tmp_path, with_associations):
    seq = tmp_path / "seq"
    _write_sequence(seq, with_associations)
    report = import_tum(seq, tmp_path / "ds")
    assert report.frames == 2 and report.skipped_no_groundtruth == 2
    ds = Dataset.open(tmp_path / "ds")
    assert len(ds) == 2
    # Linear interpolation in position; the heading is +y (pi/2) whatever the pitch.
    assert np.allclose(ds.poses[:, 0], [0.5, 1.0], atol=1e-6)
    assert np.allclose(ds.poses[:, 1], 3.0)
    assert np.allclose(ds.poses[:, 2], np.pi / 2, atol=1e-6)
    assert ds.meta.depth_scale == 5000
    assert np.allclose(ds.depth(0), 1.0)  # 5000 / 5000 metres, scale kept
    assert ds.image(0).shape == (6, 8)


def test_planar_pose_heading_of_optical_axis():
    yaw = Rotation.from_euler("z", 0.7)
    p = planar_pose(np.array([1.0, 2.0, 3.0]), yaw * Rotation.from_matrix(LOOK_ALONG_Y))
    assert np.allclose(p, [1.0, 2.0, np.pi / 2 + 0.7])


def test_bad_groundtruth_is_one_line_error(tmp_path):
    seq = tmp_path / "seq"
    _write_sequence(seq)
    (seq / "groundtruth.txt").write_text("100.0 1 2 3 0 0 0\n")
    with pytest.raises(LinoLocError, match="groundtruth.txt"):
        import_tum(seq, tmp_path / "ds")


def test_refuses_non_empty_output(tmp_path):
    seq = tmp_path / "seq"
    _write_sequence(seq)
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "keep.txt").write_text("x")
    with pytest.raises(LinoLocError, match="not empty"):
        import_tum(seq, tmp_path / "ds")
    assert (tmp_path / "ds" / "keep.txt").exists()


def test_cli_import_refuses_a_frame_of_another_size(tmp_path, capsys, monkeypatch):
    import services.cli as cli

    monkeypatch.setattr(cli, "COMMAND_MODULES", ("services.commands.dataset_cmd",))
    seq = tmp_path / "seq"
    _write_sequence(seq)
    assert cli.main(["dataset", "import-tum", str(seq), "--out", str(tmp_path / "ok")]) == 0
    capsys.readouterr()
    cv2.imwrite(str(seq / "rgb" / "100.500000.png"), np.full((12, 16, 3), 100, np.uint8))
    assert cli.main(["dataset", "import-tum", str(seq), "--out", str(tmp_path / "odd")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "100.500000.png: poses.csv line 3, field 'image': 16x12 pixels" in err[0], err

"""Convert a TUM RGB-D sequence into a lino-loc dataset folder (docs/datasets.md).

A TUM sequence (Sturm et al., IROS 2012) holds ``rgb/`` and ``depth/`` PNGs, the lists
``rgb.txt`` / ``depth.txt`` and/or an ``associations.txt`` (``rgb_stamp rgb_path depth_stamp
depth_path``), and ``groundtruth.txt`` (``stamp tx ty tz qx qy qz qw``, world z up, the
camera's optical frame: z forward, x right, y down).

The lino-loc pose of a frame is planar: the camera position projected on the floor plane
(x, y of the world), and the heading of the optical axis projected onto that plane,
``theta = atan2(R[1, 2], R[0, 2])`` with R the camera-to-world rotation. Ground truth is
interpolated at the colour image's stamp (linear in position, slerp in rotation); frames
outside the ground truth's coverage, or in a gap of it, are skipped and counted.
Depth PNGs are copied unchanged: TUM depth is value / 5000 = metres, so the dataset's
``depth_scale`` is 5000 ("depth kept with its scale").
"""

from __future__ import annotations

import csv
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from lino_loc.dataset import CameraInfo, DatasetMeta
from lino_loc.errors import LinoLocError

#: Factory intrinsics of the TUM sequences (fx, fy, cx, cy), from the benchmark's page.
TUM_INTRINSICS: dict[str, tuple[float, float, float, float]] = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
TUM_DEPTH_SCALE = 5000.0
MAX_ASSOCIATION_GAP_S = 0.02
MAX_GROUNDTRUTH_GAP_S = 0.05


@dataclass(frozen=True)
class ImportReport:
    frames: int
    skipped_no_groundtruth: int
    skipped_no_depth: int


def _read_table(path: Path, min_columns: int) -> list[list[str]]:
    if not path.is_file():
        raise LinoLocError(f"{path}: file not found")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < min_columns:
            raise LinoLocError(f"{path}:{lineno}: expected {min_columns} columns, got {len(parts)}")
        rows.append(parts)
    return rows


def _floats(path: Path, row: list[str], n: int) -> list[float]:
    try:
        values = [float(v) for v in row[:n]]
    except ValueError:
        raise LinoLocError(f"{path}: not a number in row {' '.join(row)!r}") from None
    if not np.all(np.isfinite(values)):
        raise LinoLocError(f"{path}: non-finite value in row {' '.join(row)!r}")
    return values


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray, Rotation]:
    """Stamps (N,), positions (N,3) and rotations (camera to world) of a TUM trajectory file."""
    rows = _read_table(path, 8)
    if len(rows) < 2:
        raise LinoLocError(f"{path}: needs at least two ground-truth poses")
    data = np.array([_floats(path, r, 8) for r in rows])
    order = np.argsort(data[:, 0], kind="stable")
    data = data[order]
    return data[:, 0], data[:, 1:4], Rotation.from_quat(data[:, 4:8])


def read_pairs(seq: Path) -> list[tuple[float, str, str | None]]:
    """(rgb stamp, rgb path, depth path or None) from associations.txt, or rgb.txt + depth.txt."""
    assoc = seq / "associations.txt"
    if assoc.is_file():
        return [(float(r[0]), r[1], r[3]) for r in _read_table(assoc, 4)]
    rgb = _read_table(seq / "rgb.txt", 2)
    depth_file = seq / "depth.txt"
    if not depth_file.is_file():
        return [(float(r[0]), r[1], None) for r in rgb]
    depth = _read_table(depth_file, 2)
    d_stamps = np.array([float(r[0]) for r in depth])
    pairs: list[tuple[float, str, str | None]] = []
    for r in rgb:
        t = float(r[0])
        k = int(np.argmin(np.abs(d_stamps - t))) if len(d_stamps) else -1
        ok = k >= 0 and abs(d_stamps[k] - t) <= MAX_ASSOCIATION_GAP_S
        pairs.append((t, r[1], depth[k][1] if ok else None))
    return pairs


def planar_pose(position: np.ndarray, rotation: Rotation) -> np.ndarray:
    """(x, y, theta): camera position on the floor plane and optical-axis heading (world z up)."""
    axis = rotation.apply(np.array([0.0, 0.0, 1.0]))
    return np.array([position[0], position[1], np.arctan2(axis[1], axis[0])])


def import_tum(seq_dir: Path | str, out_dir: Path | str, camera: str = "freiburg1",
               overwrite: bool = False, name: str | None = None) -> ImportReport:
    """Convert the TUM sequence ``seq_dir`` into a dataset folder at ``out_dir``.

    LinoLocError if ``seq_dir`` is not a folder, ``camera`` is not one of
    ``TUM_INTRINSICS``, ``out_dir`` is a non-empty folder without ``overwrite`` (with it, the
    folder is removed first), no frame is listed or none lies within the ground truth, or a
    listed image is missing or unreadable.
    """
    seq = Path(seq_dir)
    out = Path(out_dir)
    _check_paths(seq, out, camera, overwrite)
    stamps, positions, rotations = read_groundtruth(seq / "groundtruth.txt")
    slerp = Slerp(stamps, rotations)
    pairs = read_pairs(seq)
    if not pairs:
        raise LinoLocError(f"{seq}: no frames listed")

    (out / "images").mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, str]] = []
    skipped_gt = skipped_depth = 0
    width = height = 0
    for t, rgb_rel, depth_rel in pairs:
        pose = _groundtruth_pose(t, stamps, positions, slerp)
        if pose is None:
            skipped_gt += 1
            continue
        src = seq / rgb_rel
        if not src.is_file():
            raise LinoLocError(f"{src}: image listed but missing")
        if not width:
            height, width = _image_size(src)
        row = _copy_frame(seq, out, t, pose, rgb_rel, depth_rel)
        if not row["depth"]:
            skipped_depth += 1
        rows.append(row)
    if not rows:
        raise LinoLocError(f"{seq}: no frame lies within the ground truth's time span")

    fx, fy, cx, cy = TUM_INTRINSICS[camera]
    meta = DatasetMeta(
        name=name or seq.name,
        camera=CameraInfo(width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy, baseline_m=None),
        depth_scale=TUM_DEPTH_SCALE,
        conditions=["tum"],
        source=f"TUM RGB-D sequence {seq.name} ({camera}), imported by lino-loc",
    )
    _write_dataset(out, rows, meta)
    return ImportReport(frames=len(rows), skipped_no_groundtruth=skipped_gt, skipped_no_depth=skipped_depth)


def _check_paths(seq: Path, out: Path, camera: str, overwrite: bool) -> None:
    """The checks of :func:`import_tum` before anything is read; removes a non-empty ``out``
    when ``overwrite``."""
    if not seq.is_dir():
        raise LinoLocError(f"{seq}: not a folder")
    if camera not in TUM_INTRINSICS:
        raise LinoLocError(f"camera {camera!r}: expected one of {', '.join(TUM_INTRINSICS)}")
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise LinoLocError(f"{out}: folder exists and is not empty (use --overwrite)")
        shutil.rmtree(out)


def _groundtruth_pose(t: float, stamps: np.ndarray, positions: np.ndarray, slerp: Slerp) -> np.ndarray | None:
    """The planar pose at stamp ``t``, interpolated between the ground-truth poses around it
    (linear in position, slerp in rotation); None outside the stamps' span or in a gap longer
    than ``MAX_GROUNDTRUTH_GAP_S``."""
    k = int(np.searchsorted(stamps, t))
    if k == 0 or k >= len(stamps) or stamps[k] - stamps[k - 1] > MAX_GROUNDTRUTH_GAP_S:
        return None
    a = (t - stamps[k - 1]) / (stamps[k] - stamps[k - 1])
    position = (1 - a) * positions[k - 1] + a * positions[k]
    return planar_pose(position, slerp([t])[0])


def _image_size(src: Path) -> tuple[int, int]:
    """(height, width) of the image ``src``; LinoLocError if it cannot be read."""
    first = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise LinoLocError(f"{src}: not a readable image")
    height, width = first.shape[:2]
    return height, width


def _copy_frame(seq: Path, out: Path, t: float, pose: np.ndarray, rgb_rel: str,
                depth_rel: str | None) -> dict[str, str]:
    """Copy one frame's colour image (and its depth PNG when listed and present) from ``seq``
    into ``out``; its row of poses.csv (``depth`` empty without depth)."""
    image_rel = f"images/{Path(rgb_rel).name}"
    shutil.copyfile(seq / rgb_rel, out / image_rel)
    row = {"image": image_rel, "x": repr(float(pose[0])), "y": repr(float(pose[1])), "theta": repr(float(pose[2])),
           "depth": "", "condition": "tum", "stamp": f"{t:.6f}"}
    if depth_rel is not None and (seq / depth_rel).is_file():
        (out / "depth").mkdir(exist_ok=True)
        row["depth"] = f"depth/{Path(depth_rel).name}"
        shutil.copyfile(seq / depth_rel, out / row["depth"])
    return row


def _write_dataset(out: Path, rows: list[dict[str, str]], meta: DatasetMeta) -> None:
    """Write ``poses.csv`` (the rows) and ``dataset.json`` (the meta) in ``out``."""
    with open(out / "poses.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["image", "x", "y", "theta", "depth", "condition", "stamp"])
        writer.writeheader()
        writer.writerows(rows)
    (out / "dataset.json").write_text(meta.model_dump_json(indent=2) + "\n")

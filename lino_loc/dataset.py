"""Dataset folders: a survey of images at known camera poses (a contract, see docs/datasets.md).

A dataset folder holds::

    DATASET/
      dataset.json     DatasetMeta: version, name, camera, disparity_scale, depth_scale,
                       conditions, source, disparity_source
      poses.csv        header row; columns image,x,y,theta and optionally
                       right, disparity, depth, condition, stamp
      images/          8-bit PNG or JPEG, grey or colour (read as grey)
      images_right/    optional right image of the stereo pair
      disparity/       optional 16-bit PNG: disparity [px] * disparity_scale, 0 = no value
      depth/           optional 16-bit PNG: depth [m] * depth_scale, 0 = no value

``x, y`` (metres) and ``theta`` (radians, CCW, REP-103) are the *camera* pose in the map
frame: the ``x_i`` of the appearance map (eq. 1 pairs each image ``z_i`` with ``x_i``).
Paths in ``poses.csv`` are relative to the folder. An empty ``right``/``disparity``/
``depth``/``condition``/``stamp`` cell means "none for this row".

Usage::

    from lino_loc.dataset import CameraInfo, DatasetMeta, DatasetWriter, Dataset

    meta = DatasetMeta(name="lab", camera=CameraInfo(width=320, height=240, fx=300,
                       fy=300, cx=160, cy=120, baseline_m=0.075))
    with DatasetWriter("out/lab", meta) as w:
        w.add(grey_u8, (1.0, 2.0, 0.5), condition="tube", depth=depth_m)
    ds = Dataset.open("out/lab")          # validates; LinoLocError on any problem
    img = ds.image(0)                     # uint8 grey
    tube = ds.where("tube")

:meth:`Dataset.open` checks everything that is cheap (schema, version, every cell of
``poses.csv``, that every referenced file exists) and raises :class:`LinoLocError` with one
line naming the file, row and field. Reading an unreadable image later raises the same.
:func:`dataset_problems` checks the content (every file decoded at the camera's size,
plausible poses in metres: :func:`pose_problem`, :func:`extent_problem`) and lists every
problem; :func:`require_valid` raises with the first. ``lino-loc dataset check`` and
``lino-loc map build`` use them.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import shutil
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from lino_loc.atomic_file import atomic_write
from lino_loc.errors import LinoLocError

DATASET_VERSION = 1
META_FILE = "dataset.json"
POSES_FILE = "poses.csv"
#: The crash-safe writer's journal (``DatasetWriter(..., journal=True)``): one JSON line per row.
JOURNAL_FILE = "poses.journal.jsonl"
REQUIRED_COLUMNS = ("image", "x", "y", "theta")
OPTIONAL_COLUMNS = ("right", "disparity", "depth", "condition", "stamp")
_FILE_COLUMNS = ("image", "right", "disparity", "depth")
_SUBDIRS = {"image": "images", "right": "images_right", "disparity": "disparity", "depth": "depth"}


class CameraInfo(BaseModel):
    """Pinhole intrinsics of the (left) camera, in pixels; ``baseline_m`` for a stereo pair."""

    model_config = ConfigDict(extra="forbid")

    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0, allow_inf_nan=False)
    fy: float = Field(gt=0, allow_inf_nan=False)
    cx: float = Field(allow_inf_nan=False)
    cy: float = Field(allow_inf_nan=False)
    baseline_m: float | None = Field(default=None, gt=0, allow_inf_nan=False)


class DatasetMeta(BaseModel):
    """Contents of ``dataset.json``."""

    model_config = ConfigDict(extra="forbid")

    version: int = DATASET_VERSION
    name: str
    camera: CameraInfo
    disparity_scale: float = Field(default=16, gt=0, allow_inf_nan=False)
    depth_scale: float = Field(default=1000, gt=0, allow_inf_nan=False)
    conditions: list[str] = []
    source: str = ""
    disparity_source: str = Field(
        default="",
        description="how the disparity column was made, e.g. 'stereo-matcher' (lino_loc.disparity."
        "compute_disparity on the right images) or 'device'; empty: not said",
    )


def _one_line_validation(exc: ValidationError) -> str:
    """The first pydantic error as ``field.sub: message`` (one line)."""
    err = exc.errors()[0]
    loc = ".".join(str(p) for p in err.get("loc", ())) or "(root)"
    extra = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return f"field '{loc}': {err.get('msg', 'invalid')}{extra}"


def _poses_header(path: Path) -> tuple[Any, list[str]]:
    """A CSV reader over the pose table ``path`` positioned after its header, and the header
    (cells stripped). LinoLocError if the file is missing, not UTF-8, empty or unparsable on
    line 1, lacks a required column, or repeats or adds an unknown column."""
    if not path.is_file():
        raise LinoLocError(f"{path}: missing")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise LinoLocError(f"{path}: not a UTF-8 text file") from None
    reader = csv.reader(io.StringIO(text))
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise LinoLocError(f"{path}: empty file (expected a header row)") from None
    except csv.Error as exc:
        raise LinoLocError(f"{path}: line 1: {exc}") from None
    for col in REQUIRED_COLUMNS:
        if col not in header:
            raise LinoLocError(f"{path}: header: missing column '{col}' (have {','.join(header)})")
    seen: set[str] = set()
    for col in header:
        if col in seen:
            raise LinoLocError(f"{path}: header: duplicate column '{col}'")
        if col not in REQUIRED_COLUMNS and col not in OPTIONAL_COLUMNS:
            raise LinoLocError(
                f"{path}: header: unknown column '{col}' (known: "
                f"{','.join(REQUIRED_COLUMNS + OPTIONAL_COLUMNS)})"
            )
        seen.add(col)
    return reader, header


def _finite_cell(cell: str, where: str, col: str) -> float:
    """The number in ``cell``; LinoLocError naming ``where`` and ``col`` if it is not a
    number or not finite."""
    try:
        v = float(cell)
    except ValueError:
        raise LinoLocError(f"{where}, field '{col}': not a number ({cell!r})") from None
    if not math.isfinite(v):
        raise LinoLocError(f"{where}, field '{col}': not finite ({cell!r})")
    return v


def _pose_row(
    cells: list[str], idx: dict[str, int], where: str, root: Path
) -> tuple[tuple[float, float, float], dict[str, str | None], str | None, float]:
    """One row of the pose table: (x, y, theta), the file of each of ``_FILE_COLUMNS``
    (relative to ``root``; None when the cell is empty or the column absent), the condition
    (None when empty) and the stamp (nan when empty). LinoLocError naming ``where`` for a
    field count that differs from the header's, a bad number, an empty image or a file not
    found."""
    if len(cells) != len(idx):
        raise LinoLocError(f"{where}: {len(cells)} fields, header has {len(idx)}")
    x, y, theta = (_finite_cell(cells[idx[col]].strip(), where, col) for col in ("x", "y", "theta"))
    files: dict[str, str | None] = {}
    for col in _FILE_COLUMNS:
        cell = cells[idx[col]].strip() if col in idx else ""
        if not cell:
            if col == "image":
                raise LinoLocError(f"{where}, field 'image': empty")
            files[col] = None
            continue
        if not os.path.isfile(root / cell):
            raise LinoLocError(f"{where}, field '{col}': file not found: {root / cell}")
        files[col] = cell
    cond = cells[idx["condition"]].strip() if "condition" in idx else ""
    st = cells[idx["stamp"]].strip() if "stamp" in idx else ""
    stamp = _finite_cell(st, where, "stamp") if st else math.nan
    return (x, y, theta), files, cond or None, stamp


def _atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename."""
    with atomic_write(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(text)


def encode_scaled_u16(values: np.ndarray, scale: float) -> np.ndarray:
    """float map -> uint16 ``round(v * scale)``; NaN, <= 0 and out-of-range values -> 0 (none)."""
    v = np.asarray(values, dtype=np.float64) * float(scale)
    ok = np.isfinite(v) & (v > 0) & (v < 65535.5)
    out = np.zeros(v.shape, dtype=np.uint16)
    out[ok] = np.rint(v[ok]).astype(np.uint16)
    return out


def decode_scaled_u16(raw: np.ndarray, scale: float) -> np.ndarray:
    """uint16 -> float32 ``raw / scale`` with 0 -> NaN (no value)."""
    out = raw.astype(np.float32) / np.float32(scale)
    out[raw == 0] = np.nan
    return out


class DatasetWriter:
    """Write a dataset folder row by row (context manager).

    Images are written as they are added (``images/000000.png`` ...); ``poses.csv`` and then
    ``dataset.json`` are written atomically on :meth:`close` (a folder without
    ``dataset.json`` is an unfinished survey, and :meth:`Dataset.open` refuses it). If the
    ``with`` block raises, nothing is finalised. Conditions used in :meth:`add` are appended
    to ``meta.conditions``.

    ``journal=True`` makes the writer crash-safe and resumable: each :meth:`add` appends its
    row (and the caller's ``extra`` JSON object) as one line to ``poses.journal.jsonl``,
    flushed and fsynced after the row's files are written, so a process killed at any point
    (``kill -9``) keeps every row added before. A writer opened with ``journal=True`` on a
    folder that has a journal continues it: the rows already there are kept (a torn last
    line, from a kill in the middle of writing it, is dropped), new rows take the next
    indices, and :attr:`extras` holds each row's ``extra``; the journal's camera must be
    ``meta``'s (LinoLocError naming the file otherwise). :meth:`close` writes ``poses.csv``
    and ``dataset.json`` from all rows, and leaves the journal (a later writer may add more).
    ``overwrite`` removes a journal too.
    """

    def __init__(
        self, root: Path | str, meta: DatasetMeta, overwrite: bool = False, *, journal: bool = False
    ) -> None:
        self.root = Path(root)
        self.meta = meta.model_copy(deep=True)
        self._rows: list[dict[str, str]] = []
        self.extras: list[dict[str, Any]] = []
        self._journal_fh: Any = None
        jpath = self.root / JOURNAL_FILE
        if journal and not overwrite and jpath.is_file():
            self._resume(jpath)
            self._closed = False
            return
        if self.root.exists():
            if not self.root.is_dir():
                raise LinoLocError(f"{self.root}: exists and is not a folder")
            if any(self.root.iterdir()):
                if not overwrite:
                    raise LinoLocError(
                        f"{self.root}: folder exists and is not empty (use overwrite to replace it)"
                    )
                for name in (META_FILE, POSES_FILE, JOURNAL_FILE):
                    (self.root / name).unlink(missing_ok=True)
                for sub in _SUBDIRS.values():
                    if (self.root / sub).is_dir():
                        shutil.rmtree(self.root / sub)
        self.root.mkdir(parents=True, exist_ok=True)
        self._closed = False
        if journal:
            self._journal_fh = open(jpath, "a", encoding="utf-8")  # noqa: SIM115 - closed in close()
            self._journal_line({"meta": self.meta.model_dump(mode="json")})

    def _journal_line(self, obj: dict[str, Any]) -> None:
        fh = self._journal_fh
        fh.write(json.dumps(obj, separators=(",", ":")) + "\n")
        fh.flush()
        os.fsync(fh.fileno())

    def _resume(self, jpath: Path) -> None:
        """Load the rows of the journal ``jpath`` and open it for appending (see the class)."""
        raw = jpath.read_bytes()
        *lines, tail = raw.split(b"\n")  # tail: what follows the last newline (a torn line)
        saved_meta: DatasetMeta | None = None
        for lineno, line in enumerate(lines, start=1):
            try:
                obj = json.loads(line)
            except (json.JSONDecodeError, UnicodeDecodeError):
                raise LinoLocError(f"{jpath}: line {lineno}: not JSON (the journal is damaged)") from None
            if not isinstance(obj, dict):
                raise LinoLocError(f"{jpath}: line {lineno}: not a JSON object")
            if "meta" in obj:
                try:
                    saved_meta = DatasetMeta.model_validate(obj["meta"])
                except ValidationError as exc:
                    raise LinoLocError(f"{jpath}: line {lineno}: {_one_line_validation(exc)}") from None
                continue
            row = obj.get("row")
            if not isinstance(row, dict) or not all(isinstance(v, str) for v in row.values()):
                raise LinoLocError(f"{jpath}: line {lineno}: 'row' must be an object of strings")
            missing = [c for c in REQUIRED_COLUMNS if c not in row]
            if missing:
                raise LinoLocError(f"{jpath}: line {lineno}: row lacks {','.join(missing)}")
            for col in _FILE_COLUMNS:
                if row.get(col) and not (self.root / row[col]).is_file():
                    raise LinoLocError(f"{jpath}: line {lineno}: file not found: {self.root / row[col]}")
            self._rows.append(row)
            extra = obj.get("extra")
            self.extras.append(extra if isinstance(extra, dict) else {})
            cond = row.get("condition") or ""
            if cond and cond not in self.meta.conditions:
                self.meta.conditions.append(cond)
        if saved_meta is None:
            raise LinoLocError(f"{jpath}: no meta line (not a dataset journal)")
        if saved_meta.camera != self.meta.camera:
            raise LinoLocError(
                f"{jpath}: the journal's camera ({saved_meta.camera.width}x{saved_meta.camera.height}, "
                f"fx {saved_meta.camera.fx:g}) is not this writer's ({self.meta.camera.width}x"
                f"{self.meta.camera.height}, fx {self.meta.camera.fx:g})"
            )
        if tail:
            with open(jpath, "r+b") as fh:
                fh.truncate(len(raw) - len(tail))
        self._journal_fh = open(jpath, "a", encoding="utf-8")  # noqa: SIM115 - closed in close()

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self._closed = True
            self._close_journal()

    def _close_journal(self) -> None:
        if self._journal_fh is not None:
            self._journal_fh.close()
            self._journal_fh = None

    def __len__(self) -> int:
        return len(self._rows)

    def _write_png(self, kind: str, index: int, array: np.ndarray) -> str:
        rel = f"{_SUBDIRS[kind]}/{index:06d}.png"
        path = self.root / rel
        path.parent.mkdir(exist_ok=True)
        if not cv2.imwrite(str(path), array):
            raise LinoLocError(f"{path}: could not write image")
        return rel

    def _check_image(self, what: str, image: np.ndarray) -> np.ndarray:
        img = np.asarray(image)
        if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)):
            raise LinoLocError(
                f"{self.root}: {what} must be uint8 HxW or HxWx3, got {img.dtype} {img.shape}"
            )
        self._check_size(what, img.shape[:2])
        return img

    def _check_size(self, what: str, shape: tuple[int, ...]) -> None:
        cam = self.meta.camera
        if tuple(shape) != (cam.height, cam.width):
            raise LinoLocError(
                f"{self.root}: {what} is {shape[1]}x{shape[0]}, camera is {cam.width}x{cam.height}"
            )

    def add(
        self,
        image: np.ndarray,
        pose: Sequence[float] | np.ndarray,
        condition: str | None = None,
        depth: np.ndarray | None = None,
        disparity: np.ndarray | None = None,
        right: np.ndarray | None = None,
        stamp: float | None = None,
        extra: dict[str, Any] | None = None,
    ) -> int:
        """Add one row; returns its index. ``depth`` in metres, ``disparity`` in pixels
        (float arrays, NaN or <= 0 = no value); ``right`` uint8 like ``image``. ``extra``: a
        JSON-serializable object kept with the row in the journal (``journal=True``) and in
        :attr:`extras`; not written to ``poses.csv``."""
        if self._closed:
            raise LinoLocError(f"{self.root}: writer is closed")
        p = np.asarray(pose, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise LinoLocError(f"{self.root}: pose must be 3 finite numbers (x, y, theta), got {pose!r}")
        if stamp is not None and not math.isfinite(float(stamp)):
            raise LinoLocError(f"{self.root}: stamp must be finite, got {stamp!r}")
        if condition is not None and ("," in condition or "\n" in condition or condition == ""):
            raise LinoLocError(f"{self.root}: bad condition name {condition!r}")
        index = len(self._rows)
        row: dict[str, str] = {}
        row["image"] = self._write_png("image", index, self._check_image("image", image))
        row["x"], row["y"], row["theta"] = (repr(float(v)) for v in p)
        if right is not None:
            row["right"] = self._write_png("right", index, self._check_image("right image", right))
        if disparity is not None:
            d = np.asarray(disparity)
            self._check_size("disparity", d.shape)
            row["disparity"] = self._write_png(
                "disparity", index, encode_scaled_u16(d, self.meta.disparity_scale)
            )
        if depth is not None:
            z = np.asarray(depth)
            self._check_size("depth", z.shape)
            row["depth"] = self._write_png("depth", index, encode_scaled_u16(z, self.meta.depth_scale))
        row["condition"] = condition or ""
        row["stamp"] = "" if stamp is None else repr(float(stamp))
        if condition is not None and condition not in self.meta.conditions:
            self.meta.conditions.append(condition)
        if self._journal_fh is not None:
            self._journal_line({"row": row, "extra": extra or {}})
        self._rows.append(row)
        self.extras.append(dict(extra or {}))
        return index

    def close(self) -> None:
        """Write ``poses.csv`` then ``dataset.json`` (both atomically)."""
        if self._closed:
            return
        self._closed = True
        columns = list(REQUIRED_COLUMNS)
        for opt in ("right", "disparity", "depth"):
            if any(opt in r for r in self._rows):
                columns.append(opt)
        columns += ["condition", "stamp"]
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(columns)
        for r in self._rows:
            w.writerow([r.get(c, "") for c in columns])
        _atomic_write_text(self.root / POSES_FILE, buf.getvalue())
        _atomic_write_text(self.root / META_FILE, self.meta.model_dump_json(indent=2) + "\n")
        self._close_journal()


class Dataset:
    """A validated dataset folder (open with :meth:`open`).

    Attributes: ``root``, ``meta`` (:class:`DatasetMeta`), ``poses`` (N, 3) float64 camera
    poses, ``conditions`` (list of str or None), ``stamps`` (N,) float64, NaN = none,
    ``lines`` the line of ``poses.csv`` of each row (for messages).
    """

    def __init__(
        self,
        root: Path,
        meta: DatasetMeta,
        poses: np.ndarray,
        files: dict[str, list[str | None]],
        conditions: list[str | None],
        stamps: np.ndarray,
        lines: list[int] | None = None,
    ) -> None:
        self.root = root
        self.meta = meta
        self.poses = poses
        self.conditions = conditions
        self.stamps = stamps
        self.lines = list(range(2, 2 + len(poses))) if lines is None else lines
        self._files = files
        self._present = frozenset(k for k, v in files.items() if any(f is not None for f in v))

    # ----------------------------------------------------------------- opening
    @classmethod
    def open(cls, root: Path | str) -> Dataset:
        """Open and validate a dataset folder; any problem -> one-line :class:`LinoLocError`."""
        root = Path(root)
        if not root.is_dir():
            raise LinoLocError(f"{root}: not a dataset folder (no such folder)")
        meta = cls._read_meta(root / META_FILE)
        poses, files, conditions, stamps, lines = cls._read_poses(root, root / POSES_FILE)
        return cls(root, meta, poses, files, conditions, stamps, lines)

    @staticmethod
    def _read_meta(path: Path) -> DatasetMeta:
        if not path.is_file():
            raise LinoLocError(f"{path}: missing (not a dataset folder, or an unfinished survey)")
        try:
            raw = json.loads(path.read_text(encoding="utf-8"))
        except UnicodeDecodeError:
            raise LinoLocError(f"{path}: not a JSON text file") from None
        except json.JSONDecodeError as exc:
            raise LinoLocError(f"{path}: bad JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
        if not isinstance(raw, dict):
            raise LinoLocError(f"{path}: expected a JSON object, got {type(raw).__name__}")
        version = raw.get("version")
        if not isinstance(version, int) or isinstance(version, bool):
            raise LinoLocError(f"{path}: field 'version': missing or not an integer ({version!r})")
        if version > DATASET_VERSION:
            raise LinoLocError(
                f"{path}: field 'version': dataset version {version} is newer than this lino-loc "
                f"reads ({DATASET_VERSION}); upgrade lino-loc"
            )
        if version != DATASET_VERSION:
            raise LinoLocError(f"{path}: field 'version': unsupported dataset version {version}")
        try:
            return DatasetMeta.model_validate(raw)
        except ValidationError as exc:
            raise LinoLocError(f"{path}: {_one_line_validation(exc)}") from None

    @staticmethod
    def _read_poses(
        root: Path, path: Path
    ) -> tuple[np.ndarray, dict[str, list[str | None]], list[str | None], np.ndarray, list[int]]:
        """The pose table ``path``: poses (N, 3), the files of each column of
        ``_FILE_COLUMNS`` (None where empty), the conditions, the stamps (nan where
        empty) and the line of ``poses.csv`` each row came from. Blank rows are skipped;
        LinoLocError (naming the line) for a bad header or row, a CSV syntax error, or no
        row at all."""
        reader, header = _poses_header(path)
        idx = {c: header.index(c) for c in header}
        poses: list[tuple[float, float, float]] = []
        files: dict[str, list[str | None]] = {c: [] for c in _FILE_COLUMNS}
        conditions: list[str | None] = []
        stamps: list[float] = []
        lines: list[int] = []
        line = 1
        try:
            for cells in reader:
                line = reader.line_num
                if not cells or all(not c.strip() for c in cells):
                    continue
                pose, row_files, cond, stamp = _pose_row(cells, idx, f"{path}: line {line}", root)
                poses.append(pose)
                for col in _FILE_COLUMNS:
                    files[col].append(row_files[col])
                conditions.append(cond)
                stamps.append(stamp)
                lines.append(line)
        except csv.Error as exc:
            raise LinoLocError(f"{path}: line {line + 1}: {exc}") from None
        if not poses:
            raise LinoLocError(f"{path}: no rows (an empty survey)")
        return (
            np.asarray(poses, dtype=np.float64).reshape(-1, 3),
            files,
            conditions,
            np.asarray(stamps, dtype=np.float64),
            lines,
        )

    # ----------------------------------------------------------------- access
    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def __repr__(self) -> str:
        return f"Dataset({str(self.root)!r}, name={self.meta.name!r}, n={len(self)})"

    @property
    def has_right(self) -> bool:
        return "right" in self._present

    @property
    def has_disparity(self) -> bool:
        return "disparity" in self._present

    @property
    def has_depth(self) -> bool:
        return "depth" in self._present

    def image_path(self, i: int) -> Path:
        """Path of image ``i`` (for bulk loaders)."""
        return self.root / str(self._files["image"][i])

    def file_path(self, kind: str, i: int) -> Path | None:
        """Path of row ``i``'s ``image``/``right``/``disparity``/``depth`` file, or None."""
        rel = self._files[kind][i]
        return None if rel is None else self.root / rel

    @staticmethod
    def read_grey(path: Path | str) -> np.ndarray:
        """Read an 8-bit image file as uint8 grey (colour converted); LinoLocError if unreadable."""
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise LinoLocError(f"{path}: unreadable image (not a PNG/JPEG, or corrupt)")
        if img.dtype != np.uint8:  # 16-bit grey PNG: OpenCV keeps the depth
            raise LinoLocError(f"{path}: expected an 8-bit image, got {img.dtype}")
        return img

    def _read_u16(self, path: Path) -> np.ndarray:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise LinoLocError(f"{path}: unreadable image (not a PNG, or corrupt)")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise LinoLocError(f"{path}: expected a 16-bit single-channel PNG, got {raw.dtype} {raw.shape}")
        return raw

    def image(self, i: int) -> np.ndarray:
        """Image ``i`` as uint8 grey (H, W)."""
        return self.read_grey(self.image_path(i))

    def right(self, i: int) -> np.ndarray | None:
        """Right image of the stereo pair as uint8 grey, or None."""
        p = self.file_path("right", i)
        return None if p is None else self.read_grey(p)

    def depth(self, i: int) -> np.ndarray | None:
        """Depth in metres (float32, NaN = no value), or None if the row has none."""
        p = self.file_path("depth", i)
        return None if p is None else decode_scaled_u16(self._read_u16(p), self.meta.depth_scale)

    def disparity(self, i: int) -> np.ndarray | None:
        """Disparity in pixels (float32, NaN = no value), or None if the row has none."""
        p = self.file_path("disparity", i)
        return None if p is None else decode_scaled_u16(self._read_u16(p), self.meta.disparity_scale)

    def subset(self, indices: Sequence[int] | np.ndarray) -> Dataset:
        """A view on the rows ``indices`` (same folder and meta; no files are copied)."""
        ix = np.asarray(indices)
        if ix.dtype == bool:
            ix = np.flatnonzero(ix)
        ix = ix.astype(np.int64).reshape(-1)
        lst = [int(k) for k in ix]
        return Dataset(
            self.root,
            self.meta,
            self.poses[ix].copy(),
            {k: [v[j] for j in lst] for k, v in self._files.items()},
            [self.conditions[j] for j in lst],
            self.stamps[ix].copy(),
            [self.lines[j] for j in lst],
        )

    def where(self, condition: str | None) -> Dataset:
        """Rows recorded under ``condition`` (may be empty)."""
        return self.subset([i for i, c in enumerate(self.conditions) if c == condition])


# --------------------------------------------------------------------------- content checks
#: A survey wider than this in x or y (metres) is refused: the buildings lino-loc maps are
#: tens of metres across, and the filter's work and memory grow with the mapped area (a
#: survey in millimetres, 1000x too wide, made ``lino-loc run`` take several GB). A campus
#: larger than 1 km is several maps.
MAX_EXTENT_M = 1000.0
#: |x| or |y| above this (metres) is not a position: 10 000 km, so that projected
#: coordinates (UTM northings up to 1e7 m) stay valid while 1e300 does not.
MAX_ABS_POSITION_M = 1.0e7
#: |theta| above this (radians, four turns either way) is not a heading in radians; a
#: survey in degrees (0..350) is far beyond it.
MAX_ABS_THETA_RAD = 8.0 * math.pi

#: What each file column is decoded with and must decode to: (OpenCV flags, dtype, allowed
#: channel counts with 0 = a 2-D array, what it is). Images keep their depth and colours but,
#: as :meth:`Dataset.read_grey` does, follow a JPEG's EXIF orientation (which
#: ``IMREAD_UNCHANGED`` ignores), so the size checked is the size read.
_IMAGE_FLAGS = cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR
_FILE_KINDS: dict[str, tuple[int, type, tuple[int, ...], str]] = {
    "image": (_IMAGE_FLAGS, np.uint8, (0, 1, 3), "an 8-bit image"),
    "right": (_IMAGE_FLAGS, np.uint8, (0, 1, 3), "an 8-bit image"),
    "disparity": (cv2.IMREAD_UNCHANGED, np.uint16, (0,), "a 16-bit single-channel PNG"),
    "depth": (cv2.IMREAD_UNCHANGED, np.uint16, (0,), "a 16-bit single-channel PNG"),
}


def pose_problem(pose: Sequence[float] | np.ndarray) -> str | None:
    """Why the camera pose ``(x, y, theta)`` is not plausible in metres and radians
    (``"field 'x': 1e+300 is not a position in metres (|x| > 1e+07)"``), or None. The
    limits are :data:`MAX_ABS_POSITION_M` and :data:`MAX_ABS_THETA_RAD`; NaN and inf fail."""
    for col, v, limit, unit in (
        ("x", pose[0], MAX_ABS_POSITION_M, "a position in metres"),
        ("y", pose[1], MAX_ABS_POSITION_M, "a position in metres"),
        ("theta", pose[2], MAX_ABS_THETA_RAD, "a heading in radians"),
    ):
        v = float(v)
        if not math.isfinite(v):
            return f"field '{col}': not finite ({v!r})"
        if abs(v) > limit:
            hint = ": are the headings in degrees? theta is radians" if col == "theta" else ""
            return f"field '{col}': {v:g} is not {unit} (|{col}| > {limit:g}){hint}"
    return None


def extent_problem(poses: np.ndarray) -> str | None:
    """Why the positions of ``poses`` (N, 3) span an implausible area, or None: an extent
    (max - min) above :data:`MAX_EXTENT_M` in x or y, with a question about the units
    (``"extent 4200 x 3100 m: are the poses in millimetres? poses are metres ..."``). Rows
    that are not finite are ignored (:func:`pose_problem` reports them)."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)[:, :2]
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) == 0:
        return None
    ex, ey = (float(v) for v in p.max(axis=0) - p.min(axis=0))
    if max(ex, ey) <= MAX_EXTENT_M:
        return None
    return (
        f"extent {ex:.0f} x {ey:.0f} m: are the poses in millimetres? poses are metres "
        f"(a survey at most {MAX_EXTENT_M:.0f} m across)"
    )


def _file_problem(path: Path, kind: str, camera: CameraInfo) -> str | None:
    """Why the file ``path`` of column ``kind`` is not what the dataset says (undecodable,
    another pixel type, another size than ``camera``), or None. Decodes it in full."""
    flags, dtype, channels, what = _FILE_KINDS[kind]
    try:
        raw = cv2.imread(str(path), flags)
    except cv2.error:  # pragma: no cover - OpenCV reports most bad files as None
        raw = None
    if raw is None:
        return f"cannot be decoded (not {what}, or corrupt)"
    nch = 0 if raw.ndim == 2 else raw.shape[2]
    if raw.dtype != dtype or nch not in channels:
        return f"expected {what}, got {raw.dtype} {'x'.join(str(v) for v in raw.shape)}"
    h, w = raw.shape[:2]
    if (w, h) != (camera.width, camera.height):
        return f"{w}x{h} pixels, the camera in {META_FILE} is {camera.width}x{camera.height}"
    return None


def _row_file_problems(ds: Dataset, i: int, columns: Sequence[str] = _FILE_COLUMNS) -> list[str]:
    """The problems of row ``i``'s files in ``columns``, one line each naming the file and the row."""
    out = []
    for kind in columns:
        path = ds.file_path(kind, i)
        if path is None:
            continue
        msg = _file_problem(path, kind, ds.meta.camera)
        if msg is not None:
            out.append(f"{path}: {POSES_FILE} line {ds.lines[i]}, field '{kind}': {msg}")
    return out


def dataset_problems(
    ds: Dataset,
    *,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    columns: Sequence[str] = _FILE_COLUMNS,
) -> list[str]:
    """Every content problem of the opened dataset ``ds``, one line each; [] if none.

    What :meth:`Dataset.open` does not check because it is not cheap: every pose is
    plausible (:func:`pose_problem`), the survey's extent is (:func:`extent_problem`), and
    every image, right image, disparity and depth file decodes (``_FILE_KINDS``) to the
    pixel type its column needs and to the camera's size. Files are decoded by a thread
    pool (OpenCV releases the GIL; default 4 threads, at most 2 per core; ``workers`` <= 1:
    none). ``progress(done, total)`` is called as rows are checked. Lines name the file, the
    line of ``poses.csv`` and the field. ``lino-loc dataset check`` and ``lino-loc map
    build`` both use this (through :func:`require_valid`). ``columns``: the file columns to
    decode (default all of ``image``, ``right``, ``disparity``, ``depth``; ``map build``
    decodes only those it reads); ValueError for a name that is not a file column.
    """
    unknown = [c for c in columns if c not in _FILE_COLUMNS]
    if unknown:
        raise ValueError(f"not file columns of a dataset: {unknown} (expected some of {list(_FILE_COLUMNS)})")
    table = ds.root / POSES_FILE
    problems = []
    plausible = np.ones(len(ds), dtype=bool)
    for i, pose in enumerate(ds.poses):
        msg = pose_problem(pose)
        if msg is not None:
            problems.append(f"{table}: line {ds.lines[i]}, {msg}")
            plausible[i] = False
    msg = extent_problem(ds.poses[plausible])
    if msg is not None:
        problems.append(f"{table}: {msg}")
    n = len(ds)
    bounds = [(lo, min(lo + 64, n)) for lo in range(0, n, 64)]

    def work(lo: int, hi: int) -> list[str]:
        return [line for i in range(lo, hi) for line in _row_file_problems(ds, i, columns)]

    nw = workers if workers is not None else min(4, 2 * (os.cpu_count() or 1))
    pool = ThreadPoolExecutor(max_workers=nw) if nw > 1 and len(bounds) > 1 else None
    try:
        results = pool.map(work, *zip(*bounds, strict=True)) if pool else (work(lo, hi) for lo, hi in bounds)
        for (_, hi), lines in zip(bounds, results, strict=True):
            problems.extend(lines)
            if progress:
                progress(hi, n)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    return problems


def require_valid(
    ds: Dataset,
    *,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    columns: Sequence[str] = _FILE_COLUMNS,
) -> None:
    """Raise :class:`LinoLocError` with the first of :func:`dataset_problems` (over the file
    ``columns``) and how many more there are, if there is any; the refusal ``lino-loc map
    build`` shares with ``lino-loc dataset check``."""
    problems = dataset_problems(ds, workers=workers, progress=progress, columns=columns)
    if problems:
        more = (
            f" (and {len(problems) - 1} more; see `lino-loc dataset check {ds.root}`)"
            if len(problems) > 1 else ""
        )
        raise LinoLocError(problems[0] + more)

"""Appearance maps: PCA features of images at known camera poses (eq. 1), and the map file.

An :class:`AppearanceMap` holds the N camera poses ``x_i`` of a survey and, per sensing
*channel*, the projection ``W`` (mean + components) and the N feature vectors
``y_i = W (z_i - mean)`` (eq. 1). The ``intensity`` channel is the paper's image channel
(preprocessing ``none`` / ``histeq`` / ``gradient``, see :mod:`lino_loc.preprocessing`); the
``disparity`` channel (paper, section 5) holds a PCA fitted by EM with missing data
(:mod:`lino_loc.pca_missing`) and projects sparse maps from their valid pixels alone.

Channels plug in through :class:`ChannelKind` (see :func:`register_channel_kind`): a kind
says how an observation becomes features (``project``) and how its projection model is
written to and read back from the map file (``to_arrays`` / ``from_arrays``). Both built-in
kinds are registered below; the disparity kind imports ``lino_loc.pca_missing`` and
``lino_loc.disparity`` only when used.

Working image size. Images are preprocessed at full resolution and then area-averaged to
80 x 60 by default (``DEFAULT_SIZE``): D = 4800 pixels keeps the lab survey's data matrix
(4000 x 4800 float32 = 77 MB) and the PCA cheap; the 4:3 shape matches the 320 x 240
simulated camera; a 4x area average suppresses sensor noise and the high spatial
frequencies that change fastest with small camera motions (the nearest-neighbour sensor
model wants features that vary smoothly with pose, sections 3 and 6.1); and the paper's
few (5-20) leading components only carry coarse structure anyway. Projecting a frame then
costs d x D = 96 000 multiply-adds. The size is stored in the map and used at query time.

Map file (a contract; docs/datasets.md describes it for users). One uncompressed ``.npz``
(``np.savez``, read back with ``allow_pickle=False``), loadable without the dataset:

- ``header``: UTF-8 JSON (a uint8 array) validated as :class:`MapHeader`: magic
  ``"lino-loc-map"``, ``format_version`` (1), ``sha256`` over all other arrays, creation
  time, source dataset, camera, and per channel its preprocessing, working size (w, h),
  number of features, PCA method, parameters and the names of its arrays;
- ``poses`` (N, 3) float64 camera poses;
- per channel ``<name>/features`` (N, d) and the model arrays (``<name>/mean``,
  ``<name>/components``, ``<name>/explained_variance``, and for disparity ``<name>/W`` and
  ``<name>/observed_count``).

The checksum is SHA-256 over every non-header array in name order (name, dtype, shape and
raw bytes). :meth:`AppearanceMap.load` turns every way a file can be wrong (missing, empty,
truncated, not an archive, a foreign archive, a newer format, a bad header, missing or
inconsistent arrays, a checksum mismatch, and content that no map holds: non-finite or
implausible poses or extent by the dataset's rules, non-finite or huge features and
projections, see :func:`_check_content`) into a one-line :class:`LinoLocError` naming the
file and the problem.

Usage::

    from lino_loc.dataset import Dataset
    from lino_loc.appearance_map import AppearanceMap, build_map
    amap = build_map(Dataset.open("lab"), n_features=20, preprocess="histeq")
    amap.save("lab.map.npz")
    amap = AppearanceMap.load("lab.map.npz")
    y = amap.channels["intensity"].project(grey_u8)     # (20,), eq. 1
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import math
import os
import tempfile
import time
import zipfile
import zlib
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from lino_loc import __version__
from lino_loc.atomic_file import atomic_write
from lino_loc.dataset import (
    MAX_ABS_POSITION_M,
    MAX_ABS_THETA_RAD,
    POSES_FILE,
    CameraInfo,
    Dataset,
    extent_problem,
    pose_problem,
)
from lino_loc.errors import LinoLocError
from lino_loc.pca import PCA, PCA_METHODS, PcaMethod, RowChunks, fit_pca, fit_pca_streamed
from lino_loc.preprocessing import PREPROCESS_METHODS, Preprocess, preprocess, to_vector
from lino_loc.row_file import RowFile
from lino_loc.survey_vectors import vectors_of_files
from lino_loc.virtual_views import VirtualHeadings, augment_poses, augment_vectors, crop_columns

log = logging.getLogger(__name__)

MAP_MAGIC = "lino-loc-map"
MAP_FORMAT_VERSION = 1
DEFAULT_SIZE: tuple[int, int] = (80, 60)
DEFAULT_FEATURES = 20
HEADER_KEY = "header"
POSES_KEY = "poses"
_ZIP_MAGIC = b"PK\x03\x04"

ProgressFn = Callable[[int, int], None]


# --------------------------------------------------------------------------- header models
ParamValue = float | int | str | bool | None


class ChannelHeader(BaseModel):
    """What the header says about one channel."""

    model_config = ConfigDict(extra="forbid")

    kind: str
    preprocess: str
    size: tuple[int, int] = Field(description="working image size (width, height)")
    n_features: int = Field(gt=0)
    method: str
    params: dict[str, ParamValue] = {}
    arrays: list[str]


class SessionInfo(BaseModel):
    """One survey session of a map (e.g. one lighting): its entries are rows ``first_entry``
    .. ``first_entry + n_entries - 1`` of the map. ``basis`` says how the session entered
    the map: ``built`` (the PCA was fitted on it), ``projected`` (projected onto the basis
    as it was), ``refitted`` (the basis was updated incrementally with it,
    :mod:`lino_loc.incremental_pca`, and every earlier entry re-projected).
    ``residual_fraction``: the mean share of the session's centred image energy outside
    the intensity basis when it was added (before a refit), None for ``built``."""

    model_config = ConfigDict(extra="forbid")

    name: str
    condition: str | None = None
    source: str = ""
    first_entry: int = Field(ge=0)
    n_entries: int = Field(ge=1)
    added: str = ""
    basis: Literal["built", "projected", "refitted"] = "built"
    residual_fraction: float | None = Field(default=None, ge=0, le=1)


class MapHeader(BaseModel):
    """The JSON header of a map file (dict-able with ``model_dump``). ``sessions`` is empty
    for a map of one survey (maps written before sessions existed): see
    :meth:`AppearanceMap.session_list`."""

    model_config = ConfigDict(extra="forbid")

    magic: Literal["lino-loc-map"] = MAP_MAGIC
    format_version: int = MAP_FORMAT_VERSION
    created: str
    lino_loc_version: str = __version__
    name: str = ""
    source: str = ""
    condition: str | None = None
    n_images: int = Field(ge=1)
    camera: CameraInfo
    channels: dict[str, ChannelHeader]
    sessions: list[SessionInfo] = []
    sha256: str = ""


# --------------------------------------------------------------------------- channels
@dataclass
class ChannelMap:
    """One sensing channel of the map: projection model + the features of every map image.

    ``pca`` is PCA-like (``mean`` (D,), ``components`` (d, D), ``explained_variance`` (d,)):
    a :class:`lino_loc.pca.PCA` for intensity, a ``MissingDataPCA`` for disparity.
    """

    name: str
    preprocess: str
    size: tuple[int, int]
    pca: Any
    features: np.ndarray
    method: str = "randomized"
    params: dict[str, ParamValue] = field(default_factory=dict)

    @property
    def n_features(self) -> int:
        return int(self.features.shape[1])

    @property
    def kind(self) -> ChannelKind:
        return get_channel_kind(self.name)

    def project(self, observation: np.ndarray) -> np.ndarray:
        """Features (d,) of one observation (eq. 1): an image for intensity, a disparity map
        (float pixels, NaN = none) for disparity."""
        return self.kind.project(self, observation)

    def observed_rows(self) -> NDArray[np.bool_]:
        """Which map entries this channel observed (N,): every entry for intensity; for
        disparity the entries whose image had at least one valid block. EM-PCA with missing
        data gives an image with no valid pixel zero features (``MissingDataPCA.project``),
        the prior mean: no observation, just as a query with none is dropped (NaN features,
        see ``_disparity_project``). Such entries all share the same features and would
        otherwise tie in a J-nearest search."""
        f = np.asarray(self.features)
        if self.name != "disparity":
            return np.ones(f.shape[0], dtype=bool)
        return np.asarray(np.any(f != 0, axis=1), dtype=bool)


@dataclass(frozen=True)
class ChannelKind:
    """How a channel turns observations into features and how its model is stored.

    - ``project(channel, observation) -> (d,)`` features;
    - ``to_arrays(channel) -> (arrays, params)``: the model's arrays (names without the
      ``<channel>/`` prefix) and JSON-able parameters to keep in the header;
    - ``from_arrays(arrays, params) -> model``: the inverse, used by :meth:`AppearanceMap.load`.
    """

    name: str
    project: Callable[[ChannelMap, np.ndarray], np.ndarray]
    to_arrays: Callable[[ChannelMap], tuple[dict[str, np.ndarray], dict[str, ParamValue]]]
    from_arrays: Callable[[Mapping[str, np.ndarray], Mapping[str, ParamValue]], Any]


_KINDS: dict[str, ChannelKind] = {}


def register_channel_kind(kind: ChannelKind) -> None:
    """Register (or replace) a channel kind by name."""
    _KINDS[kind.name] = kind


def get_channel_kind(name: str) -> ChannelKind:
    """The registered channel kind called name; LinoLocError naming the known kinds otherwise."""
    try:
        return _KINDS[name]
    except KeyError:
        raise LinoLocError(f"unknown map channel {name!r} (known: {', '.join(sorted(_KINDS))})") from None


# ---- intensity
def channel_margin(ch: ChannelMap | ChannelHeader) -> int:
    """Columns cropped on each side of the working image before projection (virtual headings,
    :mod:`lino_loc.virtual_views`; 0 for a map without them)."""
    return int(ch.params.get("margin", 0) or 0)


def channel_dim(ch: ChannelMap | ChannelHeader) -> int:
    """Length of the vector the channel's PCA projects: (w - 2 margin) * h."""
    w, h = ch.size
    return (int(w) - 2 * channel_margin(ch)) * int(h)


def _intensity_project(ch: ChannelMap, image: np.ndarray) -> np.ndarray:
    z = to_vector(preprocess(image, ch.preprocess), ch.size)  # type: ignore[arg-type]
    return ch.pca.project(crop_columns(z, ch.size, channel_margin(ch)))


def _pca_to_arrays(ch: ChannelMap) -> tuple[dict[str, np.ndarray], dict[str, ParamValue]]:
    p = ch.pca
    return {
        "mean": np.asarray(p.mean),
        "components": np.asarray(p.components),
        "explained_variance": np.asarray(p.explained_variance),
    }, {}


def _pca_from_arrays(a: Mapping[str, np.ndarray], params: Mapping[str, ParamValue]) -> PCA:
    return PCA(mean=a["mean"], components=a["components"], explained_variance=a["explained_variance"])


register_channel_kind(ChannelKind("intensity", _intensity_project, _pca_to_arrays, _pca_from_arrays))


# ---- disparity (paper, section 5): EM-PCA with missing data; modules imported on use
def _disparity_project(ch: ChannelMap, disparity: np.ndarray) -> np.ndarray:
    from lino_loc.disparity import downsample_sparse

    frac = float(ch.params.get("min_valid_fraction", 0.25) or 0.0)
    z = crop_columns(downsample_sparse(disparity, ch.size, min_valid_fraction=frac).reshape(-1), ch.size,
                     channel_margin(ch))
    if not np.isfinite(z).any():
        # No block with enough stereo matches: the channel observed nothing this frame. NaN
        # features say so (the Localizer drops the channel) instead of the prior mean 0,
        # which would look like a real observation.
        return np.full(ch.features.shape[1], np.nan, dtype=np.float32)
    return np.asarray(ch.pca.project(z), dtype=np.float32)


def _missing_to_arrays(ch: ChannelMap) -> tuple[dict[str, np.ndarray], dict[str, ParamValue]]:
    p = ch.pca
    arrays, _ = _pca_to_arrays(ch)
    arrays["W"] = np.asarray(p.W)
    arrays["observed_count"] = np.asarray(p.observed_count)
    return arrays, {"sigma2": float(p.sigma2), "em_iterations": int(p.n_iter), "em_converged": bool(p.converged)}


def _missing_from_arrays(a: Mapping[str, np.ndarray], params: Mapping[str, ParamValue]) -> Any:
    from lino_loc.pca_missing import MissingDataPCA

    return MissingDataPCA(
        mean=a["mean"],
        components=a["components"],
        explained_variance=a["explained_variance"],
        W=a["W"],
        sigma2=float(params["sigma2"]),  # type: ignore[arg-type]
        observed_count=a["observed_count"],
        n_iter=int(params.get("em_iterations", 0) or 0),
        converged=bool(params.get("em_converged", False)),
    )


register_channel_kind(ChannelKind("disparity", _disparity_project, _missing_to_arrays, _missing_from_arrays))


# --------------------------------------------------------------------------- the map
def _checksum(arrays: Mapping[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        if name == HEADER_KEY:
            continue
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode("utf-8") + b"\0" + a.dtype.str.encode() + b"\0" + repr(a.shape).encode() + b"\0")
        h.update(memoryview(a).cast("B") if a.size else b"")
    return h.hexdigest()


def _check_sessions(path: Path, sessions: Sequence[SessionInfo], n: int) -> None:
    """LinoLocError naming ``path`` unless ``sessions`` (if any) tile the n entries in order."""
    if not sessions:
        return
    at = 0
    for k, sess in enumerate(sessions):
        if sess.first_entry != at:
            raise LinoLocError(f"{path}: corrupt map file: session {k} ({sess.name!r}) starts at entry "
                               f"{sess.first_entry}, expected {at}")
        at += sess.n_entries
    if at != n:
        raise LinoLocError(f"{path}: corrupt map file: the sessions hold {at} entries but the map has {n}")


_ZIP_LOCAL_HEADER = 30  # bytes of a zip local file header before its name and extra field


def _mapped_arrays(path: Path, npz: Any) -> dict[str, np.ndarray]:
    """Every non-header array of the open map archive ``npz`` (``np.load`` of ``path``) as a
    read-only ``np.memmap`` into ``path``: ``np.savez`` stores each ``.npy`` uncompressed
    (``ZIP_STORED``), so its data lie contiguously in the file at the member's offset (the
    local header's fixed 30 bytes, its name and extra field, then the ``.npy`` header). A
    compressed member (an archive written by ``np.savez_compressed``) or an array of another
    layout is read into memory as without ``mmap``. A member that ends beyond the file is a
    ValueError (the caller reports a truncated file)."""
    import struct

    arrays: dict[str, np.ndarray] = {}
    zf: zipfile.ZipFile = npz.zip
    with open(path, "rb") as fh:
        for key in npz.files:
            if key == HEADER_KEY:
                continue
            info = zf.getinfo(key + ".npy") if key + ".npy" in zf.namelist() else zf.getinfo(key)
            if info.compress_type != zipfile.ZIP_STORED:
                arrays[key] = npz[key]
                continue
            fh.seek(info.header_offset)
            local = fh.read(_ZIP_LOCAL_HEADER)
            if len(local) != _ZIP_LOCAL_HEADER or local[:4] != _ZIP_MAGIC:
                raise ValueError(f"member {key!r}: bad local header")
            name_len, extra_len = struct.unpack("<HH", local[26:30])
            fh.seek(info.header_offset + _ZIP_LOCAL_HEADER + name_len + extra_len)
            version = np.lib.format.read_magic(fh)
            if version not in ((1, 0), (2, 0)):  # np.save writes 1.0, 2.0 for huge headers
                arrays[key] = npz[key]
                continue
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read_header(fh)
            if dtype.hasobject:
                raise ValueError(f"member {key!r}: object arrays are not map arrays")
            offset = fh.tell()
            nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
            if offset + nbytes > os.fstat(fh.fileno()).st_size:
                raise ValueError(f"member {key!r} ends beyond the end of the file")
            if nbytes == 0:
                arrays[key] = np.zeros(shape, dtype=dtype)
            else:
                # a plain ndarray view (it keeps the map open): no np.memmap subclass semantics
                arrays[key] = np.asarray(np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape,
                                                   order="F" if fortran else "C"))
    return arrays


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat().replace("+00:00", "Z")


#: Largest magnitude a map's features and projection arrays may hold. They are projections
#: of preprocessed images (values in [0, 1], or gradients in multiples of their mean) or of
#: disparities in pixels, over at most a few million pixels: far below 1e9. Beyond it the
#: squared feature distances of the sensor model overflow float32.
MAX_ABS_MAP_VALUE = 1.0e9


def _array_problem(a: np.ndarray, limit: float, nonnegative: bool = False) -> str | None:
    """Why ``a`` is not finite with ``|v| <= limit`` (and ``v >= 0`` if ``nonnegative``), as
    ``"holds nan (row 3)"``, or None. Two passes without temporaries (min and max, which
    propagate NaN); the offending row is looked up only when there is one."""
    if a.size == 0 or a.dtype.kind not in "fiu":
        return None if a.size == 0 else f"has dtype {a.dtype}, expected numbers"
    lo, hi = float(a.min()), float(a.max())
    if math.isfinite(lo) and math.isfinite(hi) and max(-lo, hi) <= limit and not (nonnegative and lo < 0):
        return None
    flat = a.reshape(len(a), -1) if a.ndim > 1 else a.reshape(-1, 1)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(flat) | ~(np.abs(flat) <= limit) | ((flat < 0) if nonnegative else False)
    row = int(np.flatnonzero(bad.any(axis=1))[0])
    v = float(flat[row][bad[row]][0])
    rule = "negative" if math.isfinite(v) and abs(v) <= limit else f"beyond +-{limit:g}"
    return f"holds {v:g} (row {row}): {'not finite' if not math.isfinite(v) else rule}"


def _check_content(path: Path, header: MapHeader, arrays: Mapping[str, np.ndarray]) -> None:
    """LinoLocError naming ``path`` and what is wrong if the map's content is implausible:
    a camera pose that :func:`lino_loc.dataset.pose_problem` refuses, an extent that
    :func:`lino_loc.dataset.extent_problem` refuses (the rules a dataset passes), a feature or
    projection value not finite or beyond :data:`MAX_ABS_MAP_VALUE` (a variance beyond its
    square, or negative), a negative count, or a header parameter that is not finite. The
    checksum only says that the file is as it was written; this says that what was written
    is a map. Shapes are checked before (``_from_parts``)."""
    def bad(msg: str) -> LinoLocError:
        return LinoLocError(f"{path}: implausible map content: {msg}")

    poses = arrays[POSES_KEY]
    msg = _array_problem(poses, math.inf)
    if msg is not None:
        raise bad(f"'{POSES_KEY}' {msg}")
    lim = np.array([MAX_ABS_POSITION_M, MAX_ABS_POSITION_M, MAX_ABS_THETA_RAD])
    rows = np.flatnonzero((np.abs(poses) > lim).any(axis=1))
    if len(rows):
        raise bad(f"'{POSES_KEY}' row {int(rows[0])}: {pose_problem(poses[rows[0]])}")
    msg = extent_problem(poses)
    if msg is not None:
        raise bad(f"'{POSES_KEY}': {msg}")
    for name, ch in header.channels.items():
        for k in ch.arrays:
            a = arrays[f"{name}/{k}"]
            if a.dtype.kind in "iu":
                msg = _array_problem(a, math.inf, nonnegative=True)
            elif k == "explained_variance":
                msg = _array_problem(a, MAX_ABS_MAP_VALUE**2, nonnegative=True)
            else:
                msg = _array_problem(a, MAX_ABS_MAP_VALUE)
            if msg is not None:
                raise bad(f"'{name}/{k}' {msg}")
        for k, v in ch.params.items():
            if isinstance(v, float) and not math.isfinite(v):
                raise bad(f"channel {name!r}: header parameter {k!r} is {v}")


@dataclass
class AppearanceMap:
    """Poses + channels (see module docstring). ``meta`` is the file header as a model."""

    poses: np.ndarray
    channels: dict[str, ChannelMap]
    camera: CameraInfo
    source: str = ""
    name: str = ""
    condition: str | None = None
    created: str = field(default_factory=_utc_now)
    path: Path | None = None
    sessions: list[SessionInfo] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def session_list(self) -> list[SessionInfo]:
        """The map's sessions: the header's, or for a map of one survey (``sessions`` empty,
        every map before ``lino-loc map extend``) that survey as one ``built`` session."""
        if self.sessions:
            return list(self.sessions)
        return [SessionInfo(name=self.condition or self.name or "survey", condition=self.condition,
                            source=self.source, first_entry=0, n_entries=max(len(self), 1), added=self.created)]

    @property
    def preprocess(self) -> str:
        """Preprocessing of the intensity channel."""
        return self.channels["intensity"].preprocess if "intensity" in self.channels else ""

    @property
    def size(self) -> tuple[int, int]:
        """Working image size (w, h) of the intensity channel."""
        ch = self.channels.get("intensity") or next(iter(self.channels.values()))
        return ch.size

    def _arrays_and_header(self) -> tuple[dict[str, np.ndarray], MapHeader]:
        arrays: dict[str, np.ndarray] = {POSES_KEY: np.ascontiguousarray(self.poses, dtype=np.float64)}
        chans: dict[str, ChannelHeader] = {}
        n = arrays[POSES_KEY].shape[0]
        for name, ch in self.channels.items():
            if "/" in name or not name:
                raise LinoLocError(f"map: bad channel name {name!r}")
            model_arrays, extra = get_channel_kind(name).to_arrays(ch)
            feats = np.ascontiguousarray(ch.features)
            if feats.ndim != 2 or feats.shape[0] != n:
                raise LinoLocError(f"map: channel {name!r} has features {feats.shape}, expected ({n}, d)")
            model_arrays = {"features": feats, **model_arrays}
            for k, v in model_arrays.items():
                arrays[f"{name}/{k}"] = np.ascontiguousarray(v)
            chans[name] = ChannelHeader(
                kind=name,
                preprocess=ch.preprocess,
                size=(int(ch.size[0]), int(ch.size[1])),
                n_features=int(feats.shape[1]),
                method=ch.method,
                params={**ch.params, **extra},
                arrays=sorted(model_arrays),
            )
        header = MapHeader(
            created=self.created,
            name=self.name,
            source=self.source,
            condition=self.condition,
            n_images=max(n, 1),
            camera=self.camera,
            channels=chans,
            sessions=self.sessions,
            sha256=_checksum(arrays),
        )
        return arrays, header

    @property
    def meta(self) -> MapHeader:
        """The header this map would be saved with (checksum included)."""
        return self._arrays_and_header()[1]

    def save(self, path: Path | str) -> Path:
        """Write the map file atomically (temporary file + rename). Returns the path."""
        path = Path(path)
        arrays, header = self._arrays_and_header()
        # a map of one survey is written without the ``sessions`` key, as before sessions existed
        hdr_json = header.model_dump_json(exclude={"sessions"} if not header.sessions else None)
        hdr = np.frombuffer(hdr_json.encode("utf-8"), dtype=np.uint8)
        parent = path.parent if str(path.parent) else Path(".")
        if not parent.is_dir():
            raise LinoLocError(f"{path}: folder {parent} does not exist")
        with atomic_write(path, "wb") as fh:
            np.savez(fh, **{HEADER_KEY: hdr}, **arrays)
        self.path = path
        return path

    @classmethod
    def load(cls, path: Path | str, mmap: bool = False) -> AppearanceMap:
        """Read and verify a map file; any problem -> one-line :class:`LinoLocError`.

        ``mmap``: the arrays are read-only memory maps of the file instead of copies in memory
        (:func:`_mapped_arrays`; the file is the same format, every map file written so far
        can be mapped). The checks are the same (the checksum reads every byte once, through
        the page cache); the pages are the file's, shared with other processes that map it
        and given back by the kernel under memory pressure, and no copy is made while
        loading (figures: docs/scale.md). A map file replaced while mapped (``atomic_write``
        renames over it) leaves the mapping on the old file."""
        path = Path(path)
        if not path.exists():
            raise LinoLocError(f"{path}: no such map file")
        if not path.is_file():
            raise LinoLocError(f"{path}: not a map file (a folder?)")
        with open(path, "rb") as fh:
            start = fh.read(8)
        if not start:
            raise LinoLocError(f"{path}: empty file, not a lino-loc map")
        if not start.startswith(_ZIP_MAGIC):
            what = "a PNG image" if start.startswith(b"\x89PNG") else "an .npy array" if start.startswith(b"\x93NUMPY") else "not an .npz archive"
            raise LinoLocError(f"{path}: not a lino-loc map file ({what})")
        try:
            with np.load(path, allow_pickle=False) as npz:
                names = set(npz.files)
                if HEADER_KEY not in names:
                    raise LinoLocError(f"{path}: not a lino-loc map file (an .npz archive without a map header)")
                header_raw = npz[HEADER_KEY]
                header = cls._parse_header(path, header_raw)
                if mmap:
                    arrays = _mapped_arrays(path, npz)
                else:
                    arrays = {k: npz[k] for k in npz.files if k != HEADER_KEY}
        except LinoLocError:
            raise
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as exc:
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise LinoLocError(f"{path}: truncated or corrupt map file ({msg})") from None
        if _checksum(arrays) != header.sha256:
            raise LinoLocError(f"{path}: checksum mismatch (the file is corrupt or was modified)")
        return cls._from_parts(path, header, arrays)

    @staticmethod
    def _parse_header(path: Path, raw: np.ndarray) -> MapHeader:
        if raw.dtype != np.uint8 or raw.ndim != 1:
            raise LinoLocError(f"{path}: not a lino-loc map file (header is not JSON bytes)")
        try:
            obj = json.loads(raw.tobytes().decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise LinoLocError(f"{path}: not a lino-loc map file (header is not JSON)") from None
        if not isinstance(obj, dict) or obj.get("magic") != MAP_MAGIC:
            raise LinoLocError(f"{path}: not a lino-loc map file (wrong magic)")
        version = obj.get("format_version")
        if not isinstance(version, int) or isinstance(version, bool):
            raise LinoLocError(f"{path}: bad map header: format_version {version!r} is not an integer")
        if version > MAP_FORMAT_VERSION:
            raise LinoLocError(
                f"{path}: map format version {version} is newer than this lino-loc reads "
                f"({MAP_FORMAT_VERSION}); upgrade lino-loc"
            )
        if version != MAP_FORMAT_VERSION:
            raise LinoLocError(f"{path}: unsupported map format version {version}")
        try:
            return MapHeader.model_validate(obj)
        except ValidationError as exc:
            err = exc.errors()[0]
            loc = ".".join(str(p) for p in err.get("loc", ()))
            raise LinoLocError(f"{path}: bad map header: field '{loc}': {err.get('msg')}") from None

    @classmethod
    def _from_parts(cls, path: Path, header: MapHeader, arrays: dict[str, np.ndarray]) -> AppearanceMap:
        def bad(msg: str) -> LinoLocError:
            return LinoLocError(f"{path}: corrupt map file: {msg}")

        poses = arrays.get(POSES_KEY)
        if poses is None or poses.ndim != 2 or poses.shape[1] != 3 or poses.dtype.kind != "f":
            raise bad("missing or malformed 'poses' array")
        n = poses.shape[0]
        if n != header.n_images:
            raise bad(f"{n} poses but the header says {header.n_images} images")
        channels: dict[str, ChannelMap] = {}
        for name, ch in header.channels.items():
            kind = get_channel_kind(ch.kind)
            own: dict[str, np.ndarray] = {}
            for k in ch.arrays:
                a = arrays.get(f"{name}/{k}")
                if a is None:
                    raise bad(f"channel {name!r}: missing array {k!r}")
                own[k] = a
            for k in ("features", "mean", "components"):
                if k not in own:
                    raise bad(f"channel {name!r}: missing array {k!r}")
            w, h = ch.size
            d, D = ch.n_features, channel_dim(ch)
            feats, mean, comps = own["features"], own["mean"], own["components"]
            if feats.shape != (n, d) or mean.shape != (D,) or comps.shape != (d, D):
                raise bad(
                    f"channel {name!r}: shapes features {feats.shape}, mean {mean.shape}, "
                    f"components {comps.shape} do not match {n} images, {d} features, {D} pixels"
                )
            try:
                model = kind.from_arrays(own, ch.params)
            except (KeyError, TypeError, ValueError) as exc:
                raise bad(f"channel {name!r}: {exc}") from None
            channels[name] = ChannelMap(
                name=name,
                preprocess=ch.preprocess,
                size=(int(w), int(h)),
                pca=model,
                features=feats,
                method=ch.method,
                params={k: v for k, v in ch.params.items()},
            )
        _check_content(path, header, arrays)
        _check_sessions(path, header.sessions, n)
        return cls(
            poses=poses,
            channels=channels,
            camera=header.camera,
            source=header.source,
            name=header.name,
            condition=header.condition,
            created=header.created,
            path=path,
            sessions=list(header.sessions),
        )

    def info(self) -> dict[str, Any]:
        """A JSON-ready summary of what the map holds (for ``lino-loc map info``)."""
        header = self.meta
        p = np.asarray(self.poses, dtype=np.float64)
        chans: dict[str, Any] = {}
        for name, ch in self.channels.items():
            ev = np.asarray(ch.pca.explained_variance, dtype=np.float64)
            total = ch.params.get("total_variance")
            entry: dict[str, Any] = {
                "preprocess": ch.preprocess,
                "size": [int(ch.size[0]), int(ch.size[1])],
                "n_features": ch.n_features,
                "method": ch.method,
                "explained_variance": [float(v) for v in ev],
                "params": dict(header.channels[name].params),
            }
            if isinstance(total, int | float) and total > 0:
                entry["variance_fraction"] = float(ev.sum() / total)
            chans[name] = entry
        return {
            "file": None if self.path is None else str(self.path),
            "format_version": header.format_version,
            "name": self.name,
            "source": self.source,
            "condition": self.condition,
            "created": self.created,
            "lino_loc_version": header.lino_loc_version,
            "n_images": len(self),
            "camera": self.camera.model_dump(),
            "extent": {
                "x": [float(p[:, 0].min()), float(p[:, 0].max())],
                "y": [float(p[:, 1].min()), float(p[:, 1].max())],
            },
            "channels": chans,
            "sessions": [sess.model_dump() for sess in self.session_list()],
            "sha256": header.sha256,
        }


# --------------------------------------------------------------------------- building
def load_vectors(
    dataset: Dataset,
    method: Preprocess,
    size: tuple[int, int],
    *,
    workers: int | None = None,
    progress: ProgressFn | None = None,
    chunk: int = 64,
) -> np.ndarray:
    """Read, preprocess and area-average every image of ``dataset`` -> (N, w*h) float32.

    Files are decoded straight to grey (``cv2.IMREAD_GRAYSCALE``) by a thread pool
    (OpenCV releases the GIL; default 4 threads, at most 2 per core), in chunks written
    into one preallocated matrix (PNG decoding is most of the cost; see docs/results.md,
    'Map build'). An image of another size than the dataset's camera is a LinoLocError
    naming the file (area averaging would hide it). ``workers`` <= 1 or a single chunk: no pool. ``progress(done, total)`` is
    called after every chunk. An exception in a worker cancels the chunks not yet started
    and is re-raised.
    """
    n = len(dataset)
    w, h = int(size[0]), int(size[1])
    X = np.empty((n, w * h), dtype=np.float32)
    paths = [dataset.image_path(i) for i in range(n)]
    cam = dataset.meta.camera

    def work(lo: int, hi: int) -> int:
        X[lo:hi] = vectors_of_files(paths[lo:hi], method, (w, h), (cam.width, cam.height))
        return hi - lo

    _in_chunks(n, work, workers=workers, progress=progress, chunk=chunk)
    return X


def load_vectors_to_file(
    dataset: Dataset,
    method: Preprocess,
    size: tuple[int, int],
    scratch_dir: Path | str | None = None,
    *,
    virtual: VirtualHeadings | None = None,
    workers: int | None = None,
    progress: ProgressFn | None = None,
    chunk: int = 64,
    chunk_rows: int | None = None,
) -> RowFile:
    """:func:`load_vectors` into a :class:`lino_loc.row_file.RowFile` in ``scratch_dir``
    (the caller closes it), with ``virtual`` each image's V turned views
    (:func:`lino_loc.virtual_views.augment_vectors`, image-major as in memory): memory holds
    only the chunks being decoded. ``chunk_rows``: rows per chunk when read back."""
    n = len(dataset)
    w, h = int(size[0]), int(size[1])
    paths = [dataset.image_path(i) for i in range(n)]
    cam = dataset.meta.camera
    v = 1 if virtual is None else len(virtual.offsets)
    dim = w * h if virtual is None else (w - 2 * virtual.margin) * h
    rows = RowFile(n * v, dim, scratch_dir, chunk_rows)

    def work(lo: int, hi: int) -> int:
        X = vectors_of_files(paths[lo:hi], method, (w, h), (cam.width, cam.height))
        if virtual is not None:
            X = augment_vectors(X, (w, h), virtual.K, virtual.offsets, virtual.margin)
        rows.write(lo * v, X)
        return hi - lo

    try:
        _in_chunks(n, work, workers=workers, progress=progress, chunk=chunk)
    except BaseException:
        rows.close()
        raise
    return rows


def _in_chunks(
    n: int,
    work: Callable[[int, int], int],
    *,
    workers: int | None,
    progress: ProgressFn | None,
    chunk: int = 64,
) -> None:
    """Run ``work(lo, hi)`` (which returns the rows it did) over ``range(n)`` in chunks of
    ``chunk`` rows, on a thread pool (default 4 threads, at most 2 per core; ``workers`` <= 1
    or a single chunk: none). ``progress(done, n)`` after every chunk, in order. An exception
    in a worker cancels the chunks not yet started and is re-raised."""
    bounds = [(lo, min(lo + chunk, n)) for lo in range(0, n, chunk)]
    nw = workers if workers is not None else min(4, 2 * (os.cpu_count() or 1))
    done = 0
    if nw <= 1 or len(bounds) <= 1:
        for lo, hi in bounds:
            done += work(lo, hi)
            if progress:
                progress(done, n)
        return
    with ThreadPoolExecutor(max_workers=nw) as pool:
        futures = [pool.submit(work, lo, hi) for lo, hi in bounds]
        try:
            for f in futures:
                done += f.result()
                if progress:
                    progress(done, n)
        except BaseException:
            for f in futures:
                f.cancel()
            raise


def _project_rows(pca: PCA, X: np.ndarray | RowChunks, block: int = 1024) -> tuple[np.ndarray, float]:
    """Features of every row (eq. 1), and the total variance sum_j var(x_j), in row blocks
    (no full centred copy of X); X in memory or read in chunks (:class:`lino_loc.row_file.RowFile`)."""
    n = X.shape[0]
    Y = np.empty((n, pca.components.shape[0]), dtype=np.float32)
    ss = 0.0
    chunks = ((lo, X[lo : lo + block]) for lo in range(0, n, block)) if isinstance(X, np.ndarray) else X.chunks()
    for lo, rows in chunks:
        Xc = rows - pca.mean
        Y[lo : lo + len(rows)] = Xc @ pca.components.T
        ss += float(np.einsum("ij,ij->", Xc, Xc, dtype=np.float64))
    return Y, ss / n


project_rows = _project_rows  # public name (services.evaluation.views uses the private one)


def virtual_setup(
    camera: CameraInfo, size: tuple[int, int], offsets: Sequence[float] | None
) -> VirtualHeadings | None:
    """The virtual headings (:mod:`lino_loc.virtual_views`) of a map of ``camera`` at the
    working ``size``, or None for the plain map (no offsets, or only 0)."""
    if offsets is None or len(offsets) == 0 or (len(offsets) == 1 and float(offsets[0]) == 0.0):
        return None
    return VirtualHeadings.for_camera(camera.fx, camera.fy, camera.cx, camera.cy, (camera.width, camera.height),
                                      size, offsets)


def intensity_channel_from_vectors(
    X: np.ndarray,
    preprocess: Preprocess,
    size: tuple[int, int],
    n_features: int,
    *,
    virtual: VirtualHeadings | None = None,
    method: PcaMethod = "randomized",
    seed: int = 0,
) -> ChannelMap:
    """The intensity channel from working-size vectors ``X`` (N, w*h): with ``virtual`` (see
    :func:`virtual_setup`) each image first becomes its V turned, cropped views (rows
    image-major, poses by :func:`lino_loc.virtual_views.augment_poses`); then PCA (eq. 1) and
    the features of every row."""
    if virtual is not None:
        X = augment_vectors(X, size, virtual.K, virtual.offsets, virtual.margin)
    pca = fit_pca(X, n_features, method=method, seed=seed)
    Y, total = _project_rows(pca, X)
    return ChannelMap(
        name="intensity",
        preprocess=preprocess,
        size=(int(size[0]), int(size[1])),
        pca=pca,
        features=Y,
        method=method,
        params={"total_variance": total, "seed": seed, **(virtual.params() if virtual else {})},
    )


#: Largest data matrix (N x D float32, virtual views included) the local map build keeps in
#: memory, in MiB; a larger survey is streamed from a scratch file in chunks of rows
#: (:mod:`lino_loc.row_file`, :func:`lino_loc.pca.fit_pca_streamed`). 1 GiB: a survey of up
#: to about 55 000 views at the default 80 x 60 stays in memory, a floor's 100 000 views
#: stream, so that a build fits a robot-class computer of 4 GB next to the running service
#: (peak memory and the cost of streaming: docs/scale.md).
DEFAULT_MEMORY_BUDGET_MB = 1024.0

def _phase(name: str, seconds: float) -> None:
    """Log how long a phase of the local build took (``extra``: ``phase``, ``seconds``)."""
    log.info("map build: %s %.2f s", name, seconds, extra={"phase": name, "seconds": seconds})


Engine = Literal["local", "dask"]
ENGINES: tuple[str, ...] = ("local", "dask")


def _entry_values(size: tuple[int, int], virtual: VirtualHeadings | None) -> int:
    """Values of one map entry's vector at ``size`` (cropped by the virtual headings' margin)."""
    w, h = int(size[0]), int(size[1])
    return w * h if virtual is None else (w - 2 * virtual.margin) * h


def data_matrix_mb(n_rows: int, size: tuple[int, int], virtual: VirtualHeadings | None = None) -> float:
    """MiB of a channel's float32 data matrix for n_rows images at ``size`` (each image's V
    virtual headings with ``virtual``)."""
    V = 1 if virtual is None else len(virtual.offsets)
    return n_rows * V * _entry_values(size, virtual) * 4 / 2**20


def build_intensity_channel(
    dataset: Dataset,
    n_features: int = DEFAULT_FEATURES,
    preprocess: Preprocess = "none",
    size: tuple[int, int] = DEFAULT_SIZE,
    progress: ProgressFn | None = None,
    *,
    method: PcaMethod = "randomized",
    seed: int = 0,
    workers: int | None = None,
    virtual: VirtualHeadings | None = None,
    memory_budget_mb: float = DEFAULT_MEMORY_BUDGET_MB,
    scratch_dir: Path | str | None = None,
    chunk_rows: int | None = None,
) -> ChannelMap:
    """The intensity channel: preprocess, area-average, PCA (eq. 1), features of every image
    (of every virtual view with ``virtual``).

    A data matrix (:func:`data_matrix_mb`) above ``memory_budget_mb`` is streamed: written to
    a scratch file in ``scratch_dir`` (default the system's temporary folder) and read back in
    chunks of ``chunk_rows`` rows (default 64 MiB) by :func:`lino_loc.pca.fit_pca_streamed`
    and the projection; the same map up to float32 rounding. Only ``randomized`` streams:
    ``gram`` and ``svd`` over the budget are a LinoLocError."""
    mb = data_matrix_mb(len(dataset), size, virtual)
    t0 = time.perf_counter()
    if mb <= memory_budget_mb:
        X = load_vectors(dataset, preprocess, size, workers=workers, progress=progress)
        t1 = time.perf_counter()
        _phase("load", t1 - t0)
        ch = intensity_channel_from_vectors(X, preprocess, size, n_features, virtual=virtual, method=method,
                                            seed=seed)
        _phase("pca+features", time.perf_counter() - t1)
        return ch
    if method != "randomized":
        raise LinoLocError(f"{dataset.root}: PCA method {method!r} needs the whole data matrix in memory "
                           f"({mb:.0f} MiB, over the memory budget of {memory_budget_mb:.0f} MiB): use "
                           f"randomized, which streams, or raise the memory budget")
    log.info("map build: data matrix %.0f MiB over the memory budget of %.0f MiB: streaming from %s",
             mb, memory_budget_mb, scratch_dir or tempfile.gettempdir())
    with load_vectors_to_file(dataset, preprocess, size, scratch_dir, virtual=virtual, workers=workers,
                              progress=progress, chunk_rows=chunk_rows) as rows:
        t1 = time.perf_counter()
        _phase("load", t1 - t0)
        pca = fit_pca_streamed(rows, n_features, seed=seed)
        t2 = time.perf_counter()
        _phase("pca", t2 - t1)
        Y, total = _project_rows(pca, rows)
        _phase("features", time.perf_counter() - t2)
    return ChannelMap(
        name="intensity",
        preprocess=preprocess,
        size=(int(size[0]), int(size[1])),
        pca=pca,
        features=Y,
        method=method,
        params={"total_variance": total, "seed": seed, **(virtual.params() if virtual else {})},
    )


#: ``source`` of a disparity channel built from a dataset's dense ``depth`` column.
DENSE_DEPTH_SOURCE = "dense-depth"


def disparity_source(dataset: Dataset) -> tuple[str, str]:
    """(source, units) of the disparity channel ``dataset`` gives: its ``disparity`` column
    (source: ``dataset.json``'s ``disparity_source``, e.g. ``stereo-matcher``, or
    ``disparity`` when not said; units disparity_px), else its ``depth`` column
    (``dense-depth``; f*B/Z in disparity_px with a baseline, inverse depth without).
    LinoLocError naming the folder if it has neither."""
    if dataset.has_disparity:
        return dataset.meta.disparity_source or "disparity", "disparity_px"
    if dataset.has_depth:
        return DENSE_DEPTH_SOURCE, "disparity_px" if dataset.meta.camera.baseline_m else "inverse_depth_per_m"
    raise LinoLocError(f"{dataset.root}: no disparity or depth in this dataset: cannot build a disparity channel")


def map_file_columns(dataset: Dataset, channels: Sequence[str]) -> tuple[str, ...]:
    """The dataset's file columns :func:`build_map` reads for ``channels``: ``image``, and
    for the disparity channel the ``disparity`` column, else ``depth`` (:func:`disparity_source`).
    What ``lino-loc map build`` checks before it builds (the right images are not read)."""
    cols: tuple[str, ...] = ("image",)
    if "disparity" in channels:
        cols += ("disparity",) if dataset.has_disparity else ("depth",) if dataset.has_depth else ()
    return cols


def _disparity_rows(dataset: Dataset, size: tuple[int, int], min_valid_fraction: float,
                    progress: ProgressFn | None, workers: int | None = None, chunk: int = 64) -> np.ndarray:
    """(N, w*h) float32 NaN-aware area averages of every row's disparity (NaN = no value):
    the ``disparity`` column if the dataset has one, else disparity from ``depth``. Decoded
    by a thread pool in chunks of ``chunk`` rows as :func:`load_vectors` does (``workers``)."""
    from lino_loc.disparity import depth_to_disparity, depth_to_inverse_depth, downsample_sparse

    n = len(dataset)
    w, h = size
    cam = dataset.meta.camera
    X = np.full((n, w * h), np.nan, dtype=np.float32)
    from_column = dataset.has_disparity

    def row(i: int) -> np.ndarray | None:
        if from_column:
            return dataset.disparity(i)
        depth = dataset.depth(i)
        if depth is None:
            return None
        return depth_to_disparity(depth, cam.fx, cam.baseline_m) if cam.baseline_m else depth_to_inverse_depth(depth)

    def work(lo: int, hi: int) -> int:
        for i in range(lo, hi):
            disp = row(i)
            if disp is not None:
                X[i] = downsample_sparse(disp, (w, h), min_valid_fraction=min_valid_fraction).reshape(-1)
        return hi - lo

    _in_chunks(n, work, workers=workers, progress=progress, chunk=chunk)
    return X


#: The iteration limit of the disparity channel's EM (:func:`lino_loc.pca_missing.fit_pca_missing`):
#: a fit stopped at the limit is not the model's answer, and a map must carry the converged one.
#: Chosen with margin over the iterations the tuned worlds' maps need (docs/results.md, "The
#: disparity EM's iteration limit").
DISPARITY_EM_MAX_ITER = 300


def build_disparity_channel(
    dataset: Dataset,
    n_features: int = DEFAULT_FEATURES,
    size: tuple[int, int] = DEFAULT_SIZE,
    progress: ProgressFn | None = None,
    *,
    min_valid_fraction: float = 0.25,
    seed: int = 0,
    max_iter: int = DISPARITY_EM_MAX_ITER,
    virtual: VirtualHeadings | None = None,
    workers: int | None = None,
    memory_budget_mb: float = DEFAULT_MEMORY_BUDGET_MB,
) -> ChannelMap:
    """The disparity channel (section 5): sparse disparity per image (the ``disparity``
    column, or ``depth`` by f*B/Z, or inverse depth without a baseline: see
    :func:`disparity_source`, kept in the channel's ``source`` parameter), NaN-aware
    area-average, then :func:`disparity_channel_from_vectors`."""
    w, h = int(size[0]), int(size[1])
    source, units = disparity_source(dataset)
    X = _disparity_rows(dataset, (w, h), min_valid_fraction, progress, workers)
    return disparity_channel_from_vectors(X, (w, h), n_features, units=units, source=source,
                                          min_valid_fraction=min_valid_fraction, seed=seed, max_iter=max_iter,
                                          virtual=virtual, memory_budget_mb=memory_budget_mb)


#: The disparity EM's memory per value of the rows it fits, in float32 copies: the rows
#: themselves, the EM's data with 0 where missing and its mask, and the temporaries of its
#: steps (measured on the office's translated map: docs/scale.md, "The disparity channel
#: within the memory budget").
DISPARITY_FIT_COPIES = 6.0


def disparity_fit_rows(n_rows: int, row_mb: float, memory_budget_mb: float, n_features: int) -> int:
    """How many of ``n_rows`` source rows, each ``row_mb`` MiB of the EM's float32 data (after
    virtual headings: :func:`data_matrix_mb` of one row), the disparity EM fits within
    ``memory_budget_mb`` (:data:`DISPARITY_FIT_COPIES` copies of them): all if they fit, never
    fewer than ``n_features + 1``."""
    return int(min(n_rows, max(memory_budget_mb // (row_mb * DISPARITY_FIT_COPIES), n_features + 1)))


def _disparity_views(X: np.ndarray, size: tuple[int, int], virtual: VirtualHeadings | None) -> np.ndarray:
    """The disparity rows ``X`` as the map's entries: each row's V virtual headings with ``virtual``."""
    if virtual is None:
        return X
    return augment_vectors(X, size, virtual.K, virtual.offsets, virtual.margin, disparity=True)


def _project_disparity(
    model: Any, X: np.ndarray, size: tuple[int, int], virtual: VirtualHeadings | None
) -> tuple[np.ndarray, int]:
    """Features (N*V, d) float32 of the entries of the disparity rows ``X`` (their V virtual
    headings with ``virtual``), made a block of rows at a time; and the number of valid values."""
    V = 1 if virtual is None else len(virtual.offsets)
    Y = np.empty((X.shape[0] * V, model.n_components), dtype=np.float32)
    valid = 0
    block = max(1, 2048 // V)
    for lo in range(0, X.shape[0], block):
        rows = _disparity_views(X[lo : lo + block], size, virtual)
        Y[lo * V : lo * V + rows.shape[0]] = model.project(rows)
        valid += int(np.isfinite(rows).sum())
    return Y, valid


def disparity_channel_from_vectors(
    X: np.ndarray,
    size: tuple[int, int],
    n_features: int,
    *,
    units: str = "disparity_px",
    source: str = "stereo-matcher",
    min_valid_fraction: float = 0.25,
    seed: int = 0,
    max_iter: int = DISPARITY_EM_MAX_ITER,
    virtual: VirtualHeadings | None = None,
    memory_budget_mb: float = DEFAULT_MEMORY_BUDGET_MB,
) -> ChannelMap:
    """The disparity channel from working-size sparse vectors ``X`` (N, w*h), NaN = no value
    (``min_valid_fraction`` is the one they were area-averaged with, kept for the queries;
    ``source`` says where the disparity came from, :func:`disparity_source`): with
    ``virtual`` each image first becomes its V turned views; then PCA with missing data by
    EM (:func:`lino_loc.pca_missing.fit_pca_missing`) and every row's features from its valid
    pixels alone.

    The EM fits every row when they fit ``memory_budget_mb`` (:func:`disparity_fit_rows`),
    else a random sample of the rows (``seed``; each with all its virtual headings) as large
    as the budget allows: an estimate of the same model from fewer samples. Every row is
    then projected, a block of rows at a time. ``fit_rows`` in the channel's parameters says
    how many of the map's entries the model was fitted on."""
    from lino_loc.pca_missing import fit_pca_missing

    w, h = int(size[0]), int(size[1])
    V = 1 if virtual is None else len(virtual.offsets)
    n = X.shape[0]
    k = disparity_fit_rows(n, data_matrix_mb(1, (w, h), virtual), memory_budget_mb, n_features)
    fit_idx = slice(None) if k >= n else np.sort(np.random.default_rng(seed).choice(n, k, replace=False))
    if k < n:
        log.info("map build: the disparity EM fits %d of %d images (memory budget %.0f MiB)", k, n, memory_budget_mb)
    model = fit_pca_missing(_disparity_views(X[fit_idx], (w, h), virtual), n_features, seed=seed,
                            max_iter=max_iter, dtype=np.float32)
    Y, valid = _project_disparity(model, X, (w, h), virtual)
    return ChannelMap(
        name="disparity",
        preprocess="none",
        size=(w, h),
        pca=model,
        features=Y,
        method="em-missing",
        params={
            "min_valid_fraction": float(min_valid_fraction),
            "units": units,
            "source": source,
            "seed": seed,
            "valid_fraction": valid / max(Y.shape[0] * _entry_values((w, h), virtual), 1),
            "fit_rows": k * V,
            **(virtual.params() if virtual else {}),
        },
    )


def build_map(
    dataset: Dataset,
    n_features: int = DEFAULT_FEATURES,
    preprocess: Preprocess = "none",
    size: tuple[int, int] = DEFAULT_SIZE,
    condition: str | None = None,
    progress: ProgressFn | None = None,
    *,
    method: PcaMethod = "randomized",
    channels: Sequence[str] = ("intensity",),
    seed: int = 0,
    workers: int | None = None,
    virtual_offsets: Sequence[float] | None = None,
    disparity_features: int | None = None,
    engine: Engine = "local",
    memory_budget_mb: float = DEFAULT_MEMORY_BUDGET_MB,
    scratch_dir: Path | str | None = None,
    chunk_rows: int | None = None,
) -> AppearanceMap:
    """Build an appearance map from a dataset (eq. 1 for every image).

    ``engine="local"``: in this process; a data matrix over ``memory_budget_mb`` is streamed
    through a scratch file in ``scratch_dir`` (:func:`build_intensity_channel`).
    ``engine="dask"``: the intensity channel's image loading, preprocessing, PCA and
    projection run as Dask tasks on the current Dask scheduler (a ``distributed.Client``
    the caller set up, :func:`lino_loc.pca_dask.intensity_pca_dask`; ``chunk_rows``
    images per task); only ``method="randomized"``. The disparity channel's EM-PCA runs in
    this process with either engine (:mod:`lino_loc.pca_dask` says why).

    ``disparity_features``: the disparity channel's number of features (default
    ``n_features``); its EM-PCA's cost grows with the square of it.

    ``virtual_offsets`` (radians, e.g. ``lino_loc.virtual_views.offsets(radians(3), 5)``):
    every image also gives the views turned by these heading offsets
    (:mod:`lino_loc.virtual_views`); the map then has one entry per (image, offset).

    ``condition`` keeps only the rows recorded under that condition (e.g. ``tube``, the
    mapping light). ``channels``: ``("intensity",)`` or ``("intensity", "disparity")``.
    ``progress(done, total)`` is called while images are read.
    """
    w, h = _checked_map_settings(preprocess, method, size, dataset.meta.camera)
    virtual = virtual_setup(dataset.meta.camera, (w, h), virtual_offsets)  # checked before any image is read
    ds = _map_rows(dataset, condition, n_features, (w, h))
    _check_poses(ds)
    _check_channels(channels)
    intensity = _intensity_by_engine(engine, ds, n_features, preprocess, (w, h), progress, method=method, seed=seed,
                                     workers=workers, virtual=virtual, memory_budget_mb=memory_budget_mb,
                                     scratch_dir=scratch_dir, chunk_rows=chunk_rows)
    chans: dict[str, ChannelMap] = {"intensity": intensity}
    if "disparity" in channels:
        chans["disparity"] = build_disparity_channel(ds, disparity_features or n_features, (w, h), progress, seed=seed,
                                                     virtual=virtual, workers=workers, memory_budget_mb=memory_budget_mb)
    return AppearanceMap(
        poses=ds.poses.copy() if virtual is None else augment_poses(ds.poses, virtual.offsets),
        channels=chans,
        camera=ds.meta.camera,
        source=ds.meta.source or str(ds.root),
        name=ds.meta.name,
        condition=condition,
    )


def _check_channels(channels: Sequence[str]) -> None:
    """LinoLocError unless ``channels`` is intensity, optionally with disparity."""
    unknown = [c for c in channels if c not in ("intensity", "disparity")]
    if unknown or "intensity" not in channels:
        raise LinoLocError(f"map channels must include 'intensity' and may add 'disparity', got {list(channels)}")

def _intensity_by_engine(
    engine: str,
    ds: Dataset,
    n_features: int,
    preprocess: Preprocess,
    size: tuple[int, int],
    progress: ProgressFn | None,
    *,
    method: PcaMethod,
    seed: int,
    workers: int | None,
    virtual: VirtualHeadings | None,
    memory_budget_mb: float,
    scratch_dir: Path | str | None,
    chunk_rows: int | None,
) -> ChannelMap:
    """The intensity channel built by ``engine`` (see :func:`build_map`); LinoLocError for an
    unknown engine or a PCA method the dask engine does not compute."""
    if engine == "local":
        return build_intensity_channel(ds, n_features, preprocess, size, progress, method=method, seed=seed,
                                       workers=workers, virtual=virtual, memory_budget_mb=memory_budget_mb,
                                       scratch_dir=scratch_dir, chunk_rows=chunk_rows)
    if engine != "dask":
        raise LinoLocError(f"map build: unknown engine {engine!r} (choose from {', '.join(ENGINES)})")
    if method != "randomized":
        raise LinoLocError(f"map build: the dask engine computes the randomized PCA only, got method {method!r}")
    from lino_loc.pca_dask import intensity_pca_dask

    pca, Y, total = intensity_pca_dask(ds, n_features, preprocess, size, seed=seed, virtual=virtual,
                                       chunk_rows=chunk_rows)
    return ChannelMap(name="intensity", preprocess=preprocess, size=size, pca=pca, features=Y, method=method,
                      params={"total_variance": total, "seed": seed, **(virtual.params() if virtual else {})})


def _checked_map_settings(
    preprocess: str, method: str, size: tuple[int, int], cam: CameraInfo
) -> tuple[int, int]:
    """The map size (w, h) as ints; LinoLocError for an unknown preprocessing or PCA method,
    or a size not positive or larger than the camera's image."""
    if preprocess not in PREPROCESS_METHODS:
        raise LinoLocError(f"preprocess: unknown method {preprocess!r} (choose from {', '.join(PREPROCESS_METHODS)})")
    if method not in PCA_METHODS:
        raise LinoLocError(f"PCA method: unknown {method!r} (choose from {', '.join(PCA_METHODS)})")
    w, h = int(size[0]), int(size[1])
    if not (0 < w <= cam.width and 0 < h <= cam.height):
        raise LinoLocError(f"map size {w}x{h} must be positive and at most the camera's {cam.width}x{cam.height}")
    return w, h


def _check_poses(ds: Dataset) -> None:
    """LinoLocError naming ``poses.csv`` and the line if a pose of ``ds`` is implausible
    (:func:`lino_loc.dataset.pose_problem`) or their extent is
    (:func:`lino_loc.dataset.extent_problem`): what a map's load would refuse."""
    table = ds.root / POSES_FILE
    for i, pose in enumerate(ds.poses):
        msg = pose_problem(pose)
        if msg is not None:
            raise LinoLocError(f"{table}: line {ds.lines[i]}, {msg}")
    msg = extent_problem(ds.poses)
    if msg is not None:
        raise LinoLocError(f"{table}: {msg}")


def _map_rows(dataset: Dataset, condition: str | None, n_features: int, size: tuple[int, int]) -> Dataset:
    """The rows of ``dataset`` recorded under ``condition`` (all rows for None).

    LinoLocError if no row has that condition, or if ``n_features`` is not in
    [1, min(n - 1, w h)] for the n rows kept and the map size (w, h).
    """
    w, h = size
    ds = dataset
    if condition is not None:
        ds = dataset.where(condition)
        if len(ds) == 0:
            have = sorted({c for c in dataset.conditions if c is not None})
            raise LinoLocError(f"{dataset.root}: no rows with condition {condition!r} (have: {', '.join(have) or 'none'})")
    n = len(ds)
    if n_features < 1 or n_features > min(n - 1, w * h):
        raise LinoLocError(
            f"{dataset.root}: {n_features} features asked but {n} images of {w}x{h} allow at most {max(min(n - 1, w * h), 0)}"
        )
    return ds

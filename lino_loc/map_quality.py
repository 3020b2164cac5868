"""Map quality before deployment: coverage, ambiguity and leave-out error of an appearance map.

The plan (floor) is cut into square cells of ``cell_m`` metres (default: the map's own
position spacing, the median distance from a map position to its nearest other one; for a
map of several sessions the largest of theirs, so that a sparser session's grid leaves no
false holes) and
headings into ``sectors`` sectors (default 8 of 45 deg, named east, north-east, north, ...:
heading 0 = +x = east, CCW, REP-103). Three measures, per map entry and per cell:

- **coverage**: which heading sectors a cell's entries face. A *heading hole* is a sector no
  entry of an occupied cell faces (grouped into 8-connected areas per sector); a *position
  hole* is an empty cell enclosed by occupied ones (``scipy.ndimage.binary_fill_holes``:
  furniture, or a missed stop);
- **ambiguity**: for every entry, its nearest entry *at another position* (more than
  ``SAME_POSITION_M`` away; entries of one image at virtual headings share a position) in the
  intensity channel's feature space, the space the sensor model searches (eq. 1). The entry
  is *ambiguous* when that neighbour is more than ``ambiguous_m`` away in position: a view
  there looks more like a view elsewhere than like its neighbours;
- **leave-out error** (with a dataset): each dataset image projected onto the map's basis,
  its nearest map entry at another position (the entries at its own position left out, so
  for the map's own survey this is a leave-one-out of the nearest-neighbour model; the
  basis was fitted with the image, which makes it slightly optimistic), and that entry's
  position error. ``floor_m`` is the error no nearest-neighbour answer can beat once the
  own position is left out (the distance to the nearest other map position).

:func:`check_map` returns a :class:`MapQuality` with per-cell grids (for the plot) and
:class:`Finding` lines a user should act on. The thresholds (:class:`QualityThresholds`)
were chosen on the office, the lab and the corridor together (docs/mapping.md, "Checking a
map"; the figures in docs/results.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from lino_loc.appearance_map import AppearanceMap, channel_margin, load_vectors
from lino_loc.dataset import Dataset
from lino_loc.errors import LinoLocError
from lino_loc.virtual_views import crop_columns

SAME_POSITION_M = 1e-3
SECTOR_NAMES_8 = ("east", "north-east", "north", "north-west", "west", "south-west", "south", "south-east")


class QualityThresholds(BaseModel):
    """What ``map check`` reports (chosen on the three simulated worlds together)."""

    model_config = ConfigDict(extra="forbid")

    cell_m: float | None = Field(default=None, gt=0, description="cell size; None: the map's position spacing")
    sectors: int = Field(default=8, ge=2, le=36, description="heading sectors")
    ambiguous_m: float = Field(default=1.0, gt=0, description="an entry is ambiguous when its nearest "
                               "other-position entry in feature space is farther than this")
    ambiguous_share: float = Field(default=0.5, ge=0, le=1, description="finding: cells with more "
                                   "ambiguous entries than this share")
    leave_out_m: float = Field(default=2.0, gt=0, description="finding: cells whose mean leave-out "
                               "error exceeds this")
    min_hole_cells: int = Field(default=1, ge=1, description="smallest hole (cells) a finding reports")
    min_area_cells: int = Field(default=2, ge=1, description="smallest ambiguous or leave-out area (cells) "
                                "a finding reports (single cells are noise)")


class Finding(BaseModel):
    """One thing a user should act on: ``kind`` (heading_hole, position_hole, ambiguous,
    leave_out), the area (metres, half-open cell bounds), the cells, and the line to print."""

    kind: str
    x: tuple[float, float]
    y: tuple[float, float]
    cells: int
    sector: str | None = None
    value: float | None = None
    message: str


class MapQuality(BaseModel):
    """The report. Grids are indexed [iy][ix] over cells whose lower-left corner is
    ``origin + (ix, iy) * cell_m``."""

    model_config = ConfigDict(arbitrary_types_allowed=True)

    entries: int
    positions: int
    cell_m: float
    origin: tuple[float, float]
    shape: tuple[int, int] = Field(description="(ny, nx)")
    sectors: list[str]
    occupied_cells: int
    coverage_fraction: float = Field(description="(occupied cell, sector) pairs faced by an entry")
    heading_holes: int = Field(description="(occupied cell, sector) pairs no entry faces")
    position_holes: int
    ambiguous_fraction: float
    leave_out: dict[str, float] | None = None
    thresholds: QualityThresholds
    findings: list[Finding]
    sector_count: list[list[int]] = Field(description="sectors faced per cell (0 = empty cell)")
    position_hole_grid: list[list[bool]]
    ambiguous_share_grid: list[list[float | None]]
    leave_out_grid: list[list[float | None]] | None = None


def sector_names(n: int) -> list[str]:
    """Names of ``n`` heading sectors centred on 0, 2 pi / n, ... (compass names for 8)."""
    if n == 8:
        return list(SECTOR_NAMES_8)
    return [f"{360.0 * k / n:.0f} deg" for k in range(n)]


def heading_sector(theta: np.ndarray, n: int) -> np.ndarray:
    """Sector index in [0, n) of headings (radians), sector k centred on 2 pi k / n."""
    return np.mod(np.round(np.asarray(theta) / (2 * math.pi / n)).astype(np.int64), n)


def position_spacing(xy: np.ndarray) -> float:
    """Median distance from each distinct position to its nearest other one (0.5 m when there
    is a single position)."""
    from scipy.spatial import cKDTree

    pts = np.unique(np.round(xy, 3), axis=0)
    if len(pts) < 2:
        return 0.5
    d, _ = cKDTree(pts).query(pts, k=2)
    return float(np.median(d[:, 1]))


def _position_ids(xy: np.ndarray) -> np.ndarray:
    """An id per row, equal for rows within SAME_POSITION_M (rounded to the millimetre)."""
    _, ids = np.unique(np.round(xy / SAME_POSITION_M).astype(np.int64), axis=0, return_inverse=True)
    return ids.reshape(-1)


def nearest_other_position(
    query: np.ndarray, query_xy: np.ndarray, feats: np.ndarray, xy: np.ndarray, block: int = 256
) -> np.ndarray:
    """Index into ``feats`` (N, d) of the nearest row (squared Euclidean distance, ties by
    index) among those more than SAME_POSITION_M from the query's position, for every row of
    ``query`` (M, d) at ``query_xy`` (M, 2). -1 when every row is at the query's position."""
    F = np.asarray(feats, dtype=np.float64)
    fn = np.einsum("ij,ij->i", F, F)
    out = np.empty(len(query), dtype=np.int64)
    for lo in range(0, len(query), block):
        q = np.asarray(query[lo : lo + block], dtype=np.float64)
        d2 = fn[None, :] - 2.0 * q @ F.T
        same = np.hypot(query_xy[lo : lo + block, None, 0] - xy[None, :, 0],
                        query_xy[lo : lo + block, None, 1] - xy[None, :, 1]) <= SAME_POSITION_M
        d2[same] = np.inf
        idx = np.argmin(d2, axis=1)
        idx[~np.isfinite(d2[np.arange(len(q)), idx])] = -1
        out[lo : lo + block] = idx
    return out


class _Grid:
    def __init__(self, xy: np.ndarray, cell: float) -> None:
        self.cell = cell
        lo = xy.min(axis=0) - cell / 2
        self.origin = (float(lo[0]), float(lo[1]))
        ij = np.floor((xy - lo) / cell).astype(np.int64)
        self.nx, self.ny = int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1

    def index(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ix, iy, inside) of positions."""
        ij = np.floor((xy - np.array(self.origin)) / self.cell).astype(np.int64)
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < self.nx) & (ij[:, 1] >= 0) & (ij[:, 1] < self.ny)
        return ij[:, 0], ij[:, 1], inside

    def bounds(self, cells: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
        """x and y bounds (metres) of a set of cells given as (iy, ix) rows."""
        iy, ix = cells[:, 0], cells[:, 1]
        x0, y0 = self.origin
        c = self.cell
        return ((round(x0 + c * ix.min(), 2), round(x0 + c * (ix.max() + 1), 2)),
                (round(y0 + c * iy.min(), 2), round(y0 + c * (iy.max() + 1), 2)))


def _areas(mask: np.ndarray, min_cells: int, bridge: np.ndarray | None = None) -> list[np.ndarray]:
    """8-connected areas of a boolean (ny, nx) mask with at least ``min_cells`` of its cells,
    as arrays of (iy, ix) of the mask's cells, largest first. Cells of ``bridge`` (unknown
    cells, e.g. without a held-out view) connect areas without counting in them."""
    conn = mask if bridge is None else mask | bridge
    labels, n = ndimage.label(conn, structure=np.ones((3, 3), dtype=bool))
    areas = [np.argwhere((labels == k) & mask) for k in range(1, n + 1)]
    areas = [a for a in areas if len(a) >= min_cells]
    return sorted(areas, key=lambda a: (-len(a), a[0, 0], a[0, 1]))


def _where(x: tuple[float, float], y: tuple[float, float]) -> str:
    return f"{x[0]:.2f} < x < {x[1]:.2f}, {y[0]:.2f} < y < {y[1]:.2f}"


def check_map(
    amap: AppearanceMap,
    dataset: Dataset | None = None,
    thresholds: QualityThresholds | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> MapQuality:
    """The quality report of ``amap`` (module docstring); with ``dataset`` also the leave-out
    error of its images. LinoLocError if the map has no intensity channel or the dataset's
    camera differs from the map's."""
    th = thresholds or QualityThresholds()
    if "intensity" not in amap.channels:
        raise LinoLocError("map check: the map has no intensity channel")
    poses = np.asarray(amap.poses, dtype=np.float64)
    xy = poses[:, :2]
    cell = th.cell_m or max(position_spacing(xy[sess.first_entry : sess.first_entry + sess.n_entries])
                            for sess in amap.session_list())
    grid = _Grid(xy, cell)
    ix, iy, _ = grid.index(xy)
    names = sector_names(th.sectors)
    sec = heading_sector(poses[:, 2], th.sectors)
    faced = np.zeros((grid.ny, grid.nx, th.sectors), dtype=bool)
    faced[iy, ix, sec] = True
    occupied = faced.any(axis=2)
    findings, holes = _coverage_findings(grid, faced, names, th)
    amb, share, amb_findings = _ambiguity(amap, grid, th)
    findings += amb_findings
    leave: dict[str, float] | None = None
    leave_grid: list[list[float | None]] | None = None
    if dataset is not None:
        err_cells, leave = _leave_out(amap, dataset, grid, progress)
        leave_grid = _rounded(err_cells)
        findings += _leave_out_findings(grid, err_cells, occupied, th)
    n_pairs = int(occupied.sum()) * th.sectors
    return MapQuality(
        entries=len(amap),
        positions=int(_position_ids(xy).max()) + 1,
        cell_m=round(float(cell), 4),
        origin=grid.origin,
        shape=(grid.ny, grid.nx),
        sectors=names,
        occupied_cells=int(occupied.sum()),
        coverage_fraction=float(faced[occupied].sum() / max(n_pairs, 1)),
        heading_holes=int(n_pairs - faced[occupied].sum()),
        position_holes=int(holes.sum()),
        ambiguous_fraction=float(amb.mean()),
        leave_out=leave,
        thresholds=th,
        findings=findings,
        sector_count=faced.sum(axis=2).astype(int).tolist(),
        position_hole_grid=holes.tolist(),
        ambiguous_share_grid=_rounded(share),
        leave_out_grid=leave_grid,
    )


def _rounded(grid: np.ndarray) -> list[list[float | None]]:
    return [[None if math.isnan(v) else round(float(v), 4) for v in row] for row in grid]


def _coverage_findings(
    grid: _Grid, faced: np.ndarray, names: list[str], th: QualityThresholds
) -> tuple[list[Finding], np.ndarray]:
    """Heading holes per sector and enclosed empty cells (the mask of the latter too)."""
    occupied = faced.any(axis=2)
    findings: list[Finding] = []
    for k, name in enumerate(names):
        for area in _areas(occupied & ~faced[:, :, k], th.min_hole_cells):
            bx, by = grid.bounds(area)
            findings.append(Finding(kind="heading_hole", x=bx, y=by, cells=len(area), sector=name,
                                    message=f"no views facing {name} in {_where(bx, by)} ({len(area)} cells "
                                            f"of {grid.cell:.2f} m): survey these headings"))
    holes = ndimage.binary_fill_holes(occupied) & ~occupied
    for area in _areas(holes, th.min_hole_cells):
        bx, by = grid.bounds(area)
        findings.append(Finding(kind="position_hole", x=bx, y=by, cells=len(area),
                                message=f"no views at all in {_where(bx, by)} ({len(area)} cells), inside "
                                        "the mapped area: furniture there? if not, survey it"))
    return findings, holes


def _ambiguity(amap: AppearanceMap, grid: _Grid, th: QualityThresholds
               ) -> tuple[np.ndarray, np.ndarray, list[Finding]]:
    """Per entry whether it is ambiguous, the per-cell share of ambiguous entries (NaN: no
    entry), and the findings for areas above ``ambiguous_share``."""
    xy = np.asarray(amap.poses[:, :2], dtype=np.float64)
    iy_ix = grid.index(xy)
    ix, iy = iy_ix[0], iy_ix[1]
    feats = np.asarray(amap.channels["intensity"].features, dtype=np.float64)
    nn = nearest_other_position(feats, xy, feats, xy)
    dist = np.where(nn >= 0, np.hypot(*(xy[np.maximum(nn, 0)] - xy).T), 0.0)
    amb = dist > th.ambiguous_m
    count = np.zeros((grid.ny, grid.nx))
    n_amb = np.zeros((grid.ny, grid.nx))
    np.add.at(count, (iy, ix), 1.0)
    np.add.at(n_amb, (iy, ix), amb.astype(float))
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(count > 0, n_amb / np.maximum(count, 1), np.nan)
    findings = []
    for area in _areas(np.nan_to_num(share, nan=0.0) > th.ambiguous_share, th.min_area_cells):
        bx, by = grid.bounds(area)
        n = float(count[area[:, 0], area[:, 1]].sum())
        s = float(n_amb[area[:, 0], area[:, 1]].sum() / n)
        findings.append(Finding(kind="ambiguous", x=bx, y=by, cells=len(area), value=s,
                                message=f"views in {_where(bx, by)} look like views more than "
                                        f"{th.ambiguous_m:g} m away ({100 * s:.0f} % of its {int(n)} entries): "
                                        "expect global localization to hesitate here; add views or landmarks, "
                                        "or use the disparity channel"))
    return amb, share, findings


def _leave_out_findings(grid: _Grid, err_cells: np.ndarray, occupied: np.ndarray,
                        th: QualityThresholds) -> list[Finding]:
    findings = []
    for area in _areas(np.nan_to_num(err_cells, nan=0.0) > th.leave_out_m, th.min_area_cells,
                       bridge=np.isnan(err_cells) & occupied):
        bx, by = grid.bounds(area)
        e = float(np.nanmean(err_cells[area[:, 0], area[:, 1]]))
        findings.append(Finding(kind="leave_out", x=bx, y=by, cells=len(area), value=e,
                                message=f"held-out views in {_where(bx, by)} are placed {e:.2f} m off on "
                                        f"average (over {th.leave_out_m:g} m): the map does not know this area "
                                        "as the dataset sees it (survey it more densely, or extend the map with "
                                        "this session if its light differs)"))
    return findings


def _leave_out(
    amap: AppearanceMap, dataset: Dataset, grid: _Grid, progress: Callable[[int, int], None] | None
) -> tuple[np.ndarray, dict[str, float]]:
    """Per-cell mean leave-out error (NaN: no dataset row there) and the overall figures."""
    ch = amap.channels["intensity"]
    cam, mcam = dataset.meta.camera, amap.camera
    if (cam.width, cam.height) != (mcam.width, mcam.height):
        raise LinoLocError(f"{dataset.root}: camera {cam.width}x{cam.height}, the map's is "
                           f"{mcam.width}x{mcam.height}")
    X = load_vectors(dataset, ch.preprocess, ch.size, progress=progress)  # type: ignore[arg-type]
    margin = channel_margin(ch)
    if margin:
        X = np.stack([crop_columns(x, ch.size, margin) for x in X])
    Y = ch.pca.project(X)
    xy = np.asarray(amap.poses[:, :2], dtype=np.float64)
    qxy = np.asarray(dataset.poses[:, :2], dtype=np.float64)
    nn = nearest_other_position(Y, qxy, ch.features, xy)
    ok = nn >= 0
    err = np.full(len(Y), np.nan)
    err[ok] = np.hypot(*(xy[nn[ok]] - qxy[ok]).T)
    # floor: distance to the nearest map position other than the row's own
    from scipy.spatial import cKDTree

    upts = np.unique(np.round(xy, 3), axis=0)
    d, _ = cKDTree(upts).query(qxy, k=min(2, len(upts)))
    d = d.reshape(len(qxy), -1)
    floor = np.where(d[:, 0] <= SAME_POSITION_M, d[:, -1], d[:, 0])
    ix, iy, inside = grid.index(qxy)
    s = np.zeros((grid.ny, grid.nx))
    c = np.zeros((grid.ny, grid.nx))
    m = inside & ok
    np.add.at(s, (iy[m], ix[m]), err[m])
    np.add.at(c, (iy[m], ix[m]), 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        cells = np.where(c > 0, s / np.maximum(c, 1), np.nan)
    e = err[ok]
    return cells, {
        "rows": int(len(Y)),
        "mean_m": float(e.mean()) if len(e) else float("nan"),
        "median_m": float(np.median(e)) if len(e) else float("nan"),
        "wrong_1m_fraction": float((e > 1.0).mean()) if len(e) else float("nan"),
        "floor_mean_m": float(floor.mean()),
    }

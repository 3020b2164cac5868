"""A survey dataset seen from between its positions: its virtual translations as a new dataset.

Every row of a dataset folder (:mod:`lino_loc.dataset`) with its sparse stereo disparity is
seen from the lattice of spacing ``step / refinement`` inside its survey cell, at the same
heading (:func:`lino_loc.virtual_translations.translate_survey`: the grey image warped with the
disparity's depth, the disparity map moved with it). The result is an ordinary dataset folder:
the real row first, then its translations, each with its moved disparity, condition and
camera; ``lino-loc map build`` turns it into a map like any survey, both channels included.

Only the disparity a robot's survey has is used, never a ``depth`` column (dense depth exists
in simulation alone). Rows without disparity keep their own view at every lattice position
(the map stays a product grid of positions x headings).

The writer journals every row (``DatasetWriter(journal=True)``), each with its source row,
lattice offset and its source's fallback count: a translation killed at any point continues
where it stopped when run again, without reading or warping the sources already complete.

Usage::

    report = translate_dataset(Dataset.open("survey"), "survey-t3", refinement=3)
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from lino_loc.dataset import Dataset, DatasetWriter
from lino_loc.errors import LinoLocError
from lino_loc.virtual_translations import (
    as_uint8,
    heading_neighbours,
    lattice_offsets,
    translate_survey,
)

ProgressFn = Callable[[int, int], None]


def survey_spacing(poses: NDArray[np.float64]) -> float:
    """The survey's position spacing (m): the median, over its distinct floor positions
    (rounded to 1 mm), of the distance to the nearest other one. LinoLocError with fewer than
    two distinct positions."""
    xy = np.unique(np.round(np.asarray(poses, dtype=np.float64)[:, :2], 3), axis=0)
    if xy.shape[0] < 2:
        raise LinoLocError("the survey has fewer than two distinct positions: give the step")
    dist, _ = cKDTree(xy).query(xy, k=2)
    return float(np.median(dist[:, 1]))


@dataclass(frozen=True)
class TranslationReport:
    """What :func:`translate_dataset` wrote: the source rows, the rows of the new dataset, the
    views that fell back to their survey view, the survey step and refinement used, and how
    many rows an earlier, interrupted run had already written."""

    rows_in: int
    rows_out: int
    fallbacks: int
    step: float
    refinement: int
    resumed: int


def _resume_state(extras: list[dict]) -> tuple[set[tuple[int, int]], int, int]:
    """From an interrupted run's journalled rows (their ``extra``): the (source, offset) pairs
    written, the first source to warp again (rows are written in source order, so every source
    before the last one journalled is complete) and the fallbacks of the complete sources."""
    done = {(int(e.get("source", -1)), int(e.get("offset", -1))) for e in extras}
    first = max((src for src, _ in done), default=0)
    fallbacks = sum(int(e.get("fallbacks", 0)) for e in extras
                    if e.get("offset") == 0 and int(e.get("source", -1)) < first)
    return done, first, fallbacks


def translate_dataset(
    dataset: Dataset,
    out: Path | str,
    refinement: int,
    step: float | None = None,
    keep: Callable[[NDArray[np.float64]], NDArray[np.bool_]] | None = None,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
    workers: int = 1,
) -> TranslationReport:
    """Write ``dataset`` seen from the lattice of its cells to the folder ``out`` (see the
    module docstring). ``refinement``: odd m >= 1 (m^2 lattice positions per cell); ``step``:
    the survey's spacing (default :func:`survey_spacing`); ``keep(xy)`` (M, 2) -> bool (M,)
    drops lattice positions (e.g. outside a floor plan's free space; default: all kept).
    ``progress(done, total)`` per source row. An ``out`` holding an interrupted run's journal
    is continued (unless ``overwrite``). ``workers`` > 1 warps the rows in that many forked
    processes (where the platform can fork); the rows are written in order and are the same
    bytes as with one."""
    lattice_offsets(1.0, refinement)  # the refinement's check, before anything is written
    if workers < 1:
        raise LinoLocError(f"workers must be at least 1 (got {workers})")
    cam = dataset.meta.camera
    if not dataset.has_disparity:
        raise LinoLocError(f"{dataset.root}: no disparity column; virtual translations need the survey's "
                           "stereo disparity (lino-loc survey --stereo)")
    if not cam.baseline_m:
        raise LinoLocError(f"{dataset.root}: dataset.json: camera.baseline_m is not set; the disparity "
                           "cannot be turned into depth")
    spacing = survey_spacing(dataset.poses) if step is None else float(step)
    if not spacing > 0.0:
        raise LinoLocError(f"the survey step must be positive (got {step})")
    intrinsics = (cam.fx, cam.fy, cam.cx, cam.cy)
    meta = dataset.meta.model_copy(update={
        "name": f"{dataset.meta.name}-t{refinement}",
        "source": f"virtual translations of {dataset.meta.source or dataset.root} "
                  f"(step {spacing:g} m, refinement {refinement})",
        "conditions": [],
    })
    n = len(dataset)
    job = _Job(dataset, intrinsics, float(cam.baseline_m), spacing, int(refinement), keep,
               heading_neighbours(dataset.poses, labels=dataset.conditions))  # views under one light only
    with DatasetWriter(out, meta, overwrite=overwrite, journal=True) as writer:
        done, first, fallbacks = _resume_state(writer.extras)
        resumed = len(writer)
        if progress and first:
            progress(first, n)
        for i, row in _moved_rows(job, range(first, n), workers):
            fallbacks += row.fallbacks
            cond = dataset.conditions[i] or None
            for k, (image, d, pose) in enumerate(zip(row.images, row.disparities, row.poses, strict=True)):
                if (i, k) in done:
                    continue
                writer.add(image, pose, condition=cond, disparity=d,
                           extra={"source": i, "offset": k, "fallbacks": row.fallbacks})
            if progress:
                progress(i + 1, n)
        rows_out = len(writer)
    return TranslationReport(rows_in=n, rows_out=rows_out, fallbacks=fallbacks, step=spacing,
                             refinement=int(refinement), resumed=resumed)


@dataclass(frozen=True)
class _Job:
    """What warping one source row needs: the dataset, its camera, the lattice and each row's
    heading neighbours."""

    dataset: Dataset
    intrinsics: tuple[float, float, float, float]
    baseline_m: float
    step: float
    refinement: int
    keep: Callable[[NDArray[np.float64]], NDArray[np.bool_]] | None
    near: list[tuple[int, ...]]


@dataclass(frozen=True)
class _Row:
    """One source row seen from its lattice: uint8 views, their disparities and poses."""

    images: NDArray[np.uint8]
    disparities: NDArray[np.float32]
    poses: NDArray[np.float64]
    fallbacks: int


def _moved_row(job: _Job, i: int) -> _Row:
    """Source row ``i`` seen from the lattice of its cell, its holes filled from its heading
    neighbours (:func:`lino_loc.virtual_translations.translate_survey`)."""
    ds = job.dataset
    others = [(ds.image(k), _disparity(ds, k), ds.poses[k]) for k in job.near[i]]
    moved = translate_survey(ds.image(i)[None], _disparity(ds, i)[None], ds.poses[i][None], job.intrinsics,
                             job.baseline_m, job.step, job.refinement, keep=job.keep, neighbours=[others])
    return _Row(np.stack([as_uint8(im) for im in moved.images]), moved.disparities, moved.poses, moved.fallbacks)


_WORKER_JOB: _Job | None = None  # set in each forked worker by _set_worker_job


def _set_worker_job(job: _Job) -> None:
    global _WORKER_JOB  # noqa: PLW0603 - one job per worker process
    _WORKER_JOB = job


def _worker_row(i: int) -> _Row:
    assert _WORKER_JOB is not None
    return _moved_row(_WORKER_JOB, i)


def _moved_rows(job: _Job, rows: range, workers: int) -> Iterator[tuple[int, _Row]]:
    """(row, its lattice views) in row order: in this process, or in ``workers`` forked processes
    with at most two rows per worker in flight (the parent writes while they warp, and the
    views waiting to be written stay bounded). The job reaches the workers by fork, not by
    pickling (``keep`` may be a closure)."""
    if workers == 1 or len(rows) < 2 or "fork" not in mp.get_all_start_methods():
        for i in rows:
            yield i, _moved_row(job, i)
        return
    with mp.get_context("fork").Pool(workers, initializer=_set_worker_job, initargs=(job,)) as pool:
        pending: deque[tuple[int, Any]] = deque()
        todo = iter(rows)
        for i in itertools.islice(todo, 2 * workers):
            pending.append((i, pool.apply_async(_worker_row, (i,))))
        while pending:
            i, result = pending.popleft()
            row = result.get()
            nxt = next(todo, None)
            if nxt is not None:
                pending.append((nxt, pool.apply_async(_worker_row, (nxt,))))
            yield i, row


def _disparity(dataset: Dataset, i: int) -> np.ndarray:
    """Row ``i``'s sparse disparity, all NaN (no value) where the row has none."""
    disp = dataset.disparity(i)
    if disp is None:
        return np.full(dataset.image(i).shape, np.nan, dtype=np.float32)
    return disp

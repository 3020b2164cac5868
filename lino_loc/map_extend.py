"""Add a survey session (another light, moved furniture) to an appearance map without a rebuild.

:func:`extend_map` appends the images of a dataset to a map as a new *session*
(:class:`lino_loc.appearance_map.SessionInfo`, kept in the map header; the sensor model
searches every entry of every session alike, so a map with a tube and a bulb session matches
a bulb view against bulb entries). The new images are preprocessed and area-averaged as the
map's were (its working size, preprocessing and virtual headings) and then, for the
intensity channel:

- **projected** onto the map's basis (eq. 1 with the existing mean and components) when the
  basis represents them: their mean *residual fraction* (share of centred image energy
  outside the basis, :func:`lino_loc.incremental_pca.residual_fraction`) is at most
  ``refit_ratio`` times the map's own (``1 - sum(explained variance) / total variance`` of
  the images it was fitted on);
- **refitted** otherwise: the basis is updated incrementally with the new images
  (:func:`lino_loc.incremental_pca.update_pca`, Ross et al. 2008, in blocks of 2 d images),
  the earlier entries are
  re-projected from what the map keeps of them (``y' = W' (mean + W^T y - mean')``: exact for
  everything the old basis held), and the new images projected onto the new basis.

``refit`` forces either (``"always"`` / ``"never"``; ``"auto"`` decides as above). The
disparity channel (EM-PCA with missing data) is never refitted: its new rows are projected
onto its basis from their valid pixels (a dataset without disparity or depth cannot extend a
map that has that channel). The map's working size, features, camera (the dataset's must
equal the map's) and header fields stay; ``n_images`` becomes the new number of entries.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from lino_loc.appearance_map import (
    AppearanceMap,
    ChannelMap,
    SessionInfo,
    _disparity_rows,
    _project_disparity,
    _utc_now,
    load_vectors,
    virtual_setup,
)
from lino_loc.dataset import Dataset
from lino_loc.errors import LinoLocError
from lino_loc.incremental_pca import residual_fraction, update_pca
from lino_loc.pca import PCA
from lino_loc.virtual_views import VirtualHeadings, augment_poses, augment_vectors

RefitMode = Literal["auto", "always", "never"]
#: ``auto`` refits when the new images' mean residual fraction exceeds this many times the
#: map's own (its survey's). Chosen on the office, lab and corridor bulb sessions
#: (docs/mapping.md, "Keeping a map fresh").
DEFAULT_REFIT_RATIO = 1.2

ProgressFn = Callable[[int, int], None]


@dataclass(frozen=True)
class ExtendReport:
    """What :func:`extend_map` did: the session added, whether the basis was refitted, the
    new images' mean residual fraction before (``residual_before``: against the map's
    basis) and after (``residual_after``: against the basis they were projected on), and
    the map's own residual fraction (``map_residual``, NaN when the map does not record its
    total variance)."""

    session: SessionInfo
    refitted: bool
    residual_before: float
    residual_after: float
    map_residual: float
    entries_before: int
    entries_after: int


def _virtual(amap: AppearanceMap, ch: ChannelMap) -> VirtualHeadings | None:
    text = ch.params.get("virtual_offsets_deg")
    if not text:
        return None
    offs = [math.radians(float(v)) for v in str(text).split(",") if v.strip()]
    return virtual_setup(amap.camera, ch.size, offs)


def map_residual_fraction(ch: ChannelMap) -> float:
    """The map's own residual fraction: 1 - captured / total variance of the images its
    basis was fitted on (NaN when the header has no ``total_variance``)."""
    total = ch.params.get("total_variance")
    if not isinstance(total, int | float) or not total > 0:
        return float("nan")
    return float(max(0.0, 1.0 - float(np.sum(ch.pca.explained_variance, dtype=np.float64)) / float(total)))


def _total_variance(mean_a: np.ndarray, tv_a: float, n_a: int, X: np.ndarray) -> float:
    """Total variance of old rows (mean ``mean_a``, total variance ``tv_a``, ``n_a`` rows)
    and the rows of X together (the parallel-variance formula)."""
    m = X.shape[0]
    mu_b = X.mean(axis=0, dtype=np.float64)
    tv_b = float(np.mean(np.sum((X - mu_b) ** 2, axis=1, dtype=np.float64)))
    n = n_a + m
    shift = float(np.sum((mu_b - np.asarray(mean_a, dtype=np.float64)) ** 2))
    return (n_a * tv_a + m * tv_b + n_a * m / n * shift) / n


def extend_map(
    amap: AppearanceMap,
    dataset: Dataset | Sequence[Dataset],
    *,
    condition: str | None = None,
    name: str | None = None,
    refit: RefitMode = "auto",
    refit_ratio: float = DEFAULT_REFIT_RATIO,
    progress: ProgressFn | None = None,
    workers: int | None = None,
) -> tuple[AppearanceMap, ExtendReport]:
    """A new map: ``amap`` plus the rows of ``dataset`` (a dataset, or several, e.g. the
    parts the daemon's map refresh wrote, taken in order; their rows of ``condition`` if
    given) as one session named ``name`` (default: the condition, else the first dataset's
    name). ``amap`` is not modified. LinoLocError when the cameras differ, no row is left, the map lacks an
    intensity channel, or the dataset lacks what a channel of the map needs."""
    _check_args(amap, refit, refit_ratio)
    sets = _session_rows(amap, [dataset] if isinstance(dataset, Dataset) else list(dataset), condition)
    ds = sets[0]
    conds = sorted({c for d in sets for c in d.conditions if c is not None})
    cond = condition or (conds[0] if len(conds) == 1 else None)
    ch = amap.channels["intensity"]
    virtual = _virtual(amap, ch)
    X = np.vstack([load_vectors(d, ch.preprocess, ch.size, workers=workers, progress=progress)  # type: ignore[arg-type]
                   for d in sets])
    if virtual is not None:
        X = augment_vectors(X, ch.size, virtual.K, virtual.offsets, virtual.margin)
    n_old, n_new = len(amap), X.shape[0]
    before = float(residual_fraction(ch.pca, X).mean())
    own = map_residual_fraction(ch)
    if refit == "auto":
        # a map without its total variance: compare with the new images' residual alone
        do_refit = before > refit_ratio * own if math.isfinite(own) else False
    else:
        do_refit = refit == "always"
    if do_refit:
        pca, old_feats, params = _refit(ch, n_old, X)
    else:
        pca, old_feats, params = ch.pca, np.asarray(ch.features, dtype=np.float32), dict(ch.params)
    new_feats = pca.project(X)
    after = float(residual_fraction(pca, X).mean())
    channels = {"intensity": replace(ch, pca=pca, features=np.vstack([old_feats, new_feats]), params=params)}
    if "disparity" in amap.channels:
        channels["disparity"] = _extend_disparity(amap.channels["disparity"], sets, virtual, n_new, progress,
                                                  workers)
    rows = np.vstack([d.poses for d in sets])
    sess = SessionInfo(
        name=name or cond or ds.meta.name or os.path.basename(str(ds.root)), condition=cond,
        source=ds.meta.source or str(ds.root), first_entry=n_old, n_entries=n_new, added=_utc_now(),
        basis="refitted" if do_refit else "projected", residual_fraction=min(1.0, max(0.0, before)),
    )
    out = replace(amap, poses=np.vstack([np.asarray(amap.poses, dtype=np.float64),
                                         rows if virtual is None else augment_poses(rows, virtual.offsets)]),
                  channels=channels, path=None, sessions=[*amap.session_list(), sess])
    return out, ExtendReport(session=sess, refitted=do_refit, residual_before=before, residual_after=after,
                             map_residual=own, entries_before=n_old, entries_after=len(out))


def _check_args(amap: AppearanceMap, refit: str, refit_ratio: float) -> None:
    if refit not in ("auto", "always", "never"):
        raise LinoLocError(f"refit: expected auto, always or never, got {refit!r}")
    if not refit_ratio > 0:
        raise LinoLocError(f"refit ratio must be positive, got {refit_ratio}")
    if "intensity" not in amap.channels:
        raise LinoLocError("map extend: the map has no intensity channel")


def _session_rows(amap: AppearanceMap, sets: list[Dataset], condition: str | None) -> list[Dataset]:
    """The datasets of the new session, each with its rows of ``condition`` (those left
    empty dropped); LinoLocError for none, a camera other than the map's, or no row left."""
    if not sets:
        raise LinoLocError("map extend: no dataset given")
    mcam = amap.camera
    for d in sets:
        cam = d.meta.camera
        if (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) != (mcam.width, mcam.height, mcam.fx,
                                                                       mcam.fy, mcam.cx, mcam.cy):
            raise LinoLocError(f"{d.root}: camera {cam.model_dump()} differs from the map's {mcam.model_dump()}")
    if condition is None:
        return sets
    kept = [d.where(condition) for d in sets]
    if not any(len(d) for d in kept):
        have = sorted({c for d in sets for c in d.conditions if c is not None})
        raise LinoLocError(f"{sets[0].root}: no rows with condition {condition!r} (have: {', '.join(have) or 'none'})")
    return [d for d in kept if len(d)]


def _refit(ch: ChannelMap, n_old: int, X: np.ndarray) -> tuple[PCA, np.ndarray, dict]:
    """The basis updated with the new rows X (blocks of 2 d), the old entries re-projected
    from what the map keeps of them (exact within the old span), and the header parameters
    with the total variance of old and new rows together."""
    old = ch.pca
    new_pca = update_pca(old, n_old, X, block=2 * old.n_components)
    M = new_pca.components.astype(np.float64) @ old.components.astype(np.float64).T  # (d', d)
    shift = new_pca.components.astype(np.float64) @ (old.mean.astype(np.float64) - new_pca.mean.astype(np.float64))
    old_feats = (np.asarray(ch.features, dtype=np.float64) @ M.T + shift).astype(np.float32)
    params = dict(ch.params)
    tv = params.get("total_variance")
    if isinstance(tv, int | float):
        params["total_variance"] = _total_variance(old.mean, float(tv), n_old, X)
    return new_pca, old_feats, params


def _extend_disparity(
    ch: ChannelMap, sets: Sequence[Dataset], virtual: VirtualHeadings | None, n_new: int,
    progress: ProgressFn | None, workers: int | None,
) -> ChannelMap:
    """The disparity channel with the new rows projected onto its basis (never refitted)."""
    for ds in sets:
        if not (ds.has_disparity or ds.has_depth):
            raise LinoLocError(f"{ds.root}: the map has a disparity channel but this dataset has no disparity "
                               "or depth")
    frac = float(ch.params.get("min_valid_fraction", 0.25) or 0.0)
    X = np.vstack([_disparity_rows(ds, ch.size, frac, progress, workers) for ds in sets])
    Y, _ = _project_disparity(ch.pca, X, ch.size, virtual)  # the entries' views a block of rows at a time
    if Y.shape[0] != n_new:
        raise LinoLocError(f"{sets[0].root}: {Y.shape[0]} disparity rows for {n_new} image rows")
    return replace(ch, features=np.vstack([np.asarray(ch.features, dtype=np.float32), Y]))

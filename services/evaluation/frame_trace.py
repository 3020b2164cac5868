"""Per-frame traces of the tracking evaluation's runs: why a run went wrong, frame by frame.

A trace is a CSV file (RFC 4180, a header line, one row per frame) with the fixed columns of
:data:`COLUMNS`:

- ``stamp`` (s); the true pose ``truth_x, truth_y, truth_theta`` and the estimate
  ``x, y, theta`` (m, rad, map frame); ``error_m`` (position) and ``heading_error_rad``
  (absolute, wrapped to [0, pi]);
- what the service publishes with the pose (``lino_loc.pose_estimate.Estimate``): ``state``,
  ``quality``, ``doubt``, ``cluster_weight``, ``ess``, ``log_likelihood``;
- the self-checks behind the state: the intensity channel's ``novelty`` (the
  appearance-change detector's input, ``lino_loc.appearance_change``), the view fit's ``verdict`` and, per channel, its learnt hit rate
  ``rho_<channel>``, its recent fit ``fit_<channel>`` and whether it is ``informative``
  (``lino_loc.view_fit``), and the adaptive fusion weights ``weight_<channel>``
  (``lino_loc.fusion_weights``; empty with the fixed weights of eq. 8).

An empty cell means "not defined for this frame" (a channel the map lacks, a likelihood
before the first image). Any CSV reader reads it (pandas, numpy, a spreadsheet).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from lino_loc.errors import LinoLocError
from lino_loc.localizer import Localizer
from lino_loc.metrics import heading_errors, position_errors
from lino_loc.pose_estimate import Estimate

CHANNELS = ("intensity", "disparity")

COLUMNS: tuple[str, ...] = (
    "stamp", "truth_x", "truth_y", "truth_theta", "x", "y", "theta", "error_m", "heading_error_rad",
    "state", "quality", "doubt", "cluster_weight", "ess", "log_likelihood", "novelty", "verdict",
    *(f"{k}_{c}" for c in CHANNELS for k in ("rho", "fit", "informative")),
    *(f"weight_{c}" for c in CHANNELS),
)


def _num(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def frame_row(loc: Localizer, est: Estimate) -> dict[str, Any]:
    """The filter's diagnostics after one update (every column but the truth and errors)."""
    fit = loc.filter.view_fit
    row: dict[str, Any] = {
        "stamp": est.stamp, "x": float(est.pose[0]), "y": float(est.pose[1]), "theta": float(est.pose[2]),
        "state": est.state, "quality": float(est.quality), "doubt": float(est.doubt),
        "cluster_weight": float(est.cluster_weight), "ess": float(est.ess),
        "log_likelihood": _num(est.log_likelihood), "novelty": _num(loc.last_novelty),
        "verdict": fit.verdict() if fit.channels else None,
    }
    for name, ch in fit.channels.items():
        if name in CHANNELS:
            row.update({f"rho_{name}": ch.rho, f"fit_{name}": ch.fit, f"informative_{name}": int(ch.informative)})
    for name, w in (loc.fusion_weights or {}).items():
        row[f"weight_{name}"] = float(w)
    return row


def write_trace(path: Path | str, rows: list[dict[str, Any]], truth: ArrayLike) -> Path:
    """Write the rows of :func:`frame_row` of one run with the true poses ``truth`` (K, 3) of
    its frames as a CSV trace (see the module docstring). Returns the path."""
    path = Path(path)
    t = np.asarray(truth, dtype=np.float64).reshape(-1, 3)
    if t.shape[0] != len(rows):
        raise LinoLocError(f"{path}: {len(rows)} frames but {t.shape[0]} true poses")
    est = np.array([[r["x"], r["y"], r["theta"]] for r in rows], dtype=np.float64).reshape(-1, 3)
    err = position_errors(est, t)
    herr = heading_errors(est, t)
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS, restval="")
        w.writeheader()
        for r, (tx, ty, tth), e, h in zip(rows, t, err, herr, strict=True):
            full = {**r, "truth_x": tx, "truth_y": ty, "truth_theta": tth, "error_m": e, "heading_error_rad": h}
            w.writerow({k: ("" if v is None else v) for k, v in full.items()})
    return path

"""Trajectories in the TUM format (readable by the ``evo`` tool: ``evo_ape tum truth.txt est.txt``).

One pose per line, ``stamp tx ty tz qx qy qz qw`` (Sturm et al., IROS 2012): the stamp in
seconds, the position in metres and the orientation as a unit quaternion (x, y, z, w).
Planar poses (x, y, theta) are written with ``tz = 0`` and the rotation about the world z
axis, ``q = (0, 0, sin(theta / 2), cos(theta / 2))``; :func:`read_tum` reads any TUM file back
to planar poses (heading = yaw of the quaternion, i.e. the x axis projected onto the floor).
Lines starting with ``#`` are comments.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lino_loc.errors import LinoLocError

FloatArray = NDArray[np.float64]


def write_tum(path: Path | str, stamps: ArrayLike, poses: ArrayLike, comment: str | None = None) -> Path:
    """Write planar poses (K, 3) with stamps (K,) as a TUM trajectory file. Returns the path."""
    path = Path(path)
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if t.shape[0] != p.shape[0]:
        raise LinoLocError(f"{path}: {t.shape[0]} stamps but {p.shape[0]} poses")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
        raise LinoLocError(f"{path}: stamps or poses contain NaN or infinite values")
    half = 0.5 * p[:, 2]
    lines = [] if comment is None else [f"# {line}" for line in comment.splitlines()]
    lines.append("# timestamp tx ty tz qx qy qz qw")
    for s, (x, y, _), qz, qw in zip(t, p, np.sin(half), np.cos(half), strict=True):
        lines.append(f"{s:.6f} {x:.6f} {y:.6f} 0.000000 0.000000 0.000000 {qz:.9f} {qw:.9f}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def read_tum(path: Path | str) -> tuple[FloatArray, FloatArray]:
    """Read a TUM trajectory -> (stamps (K,), planar poses (K, 3): x, y, yaw)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise LinoLocError(f"{path}: cannot read ({exc.strerror})") from None
    rows = []
    for n, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise LinoLocError(f"{path}: line {n}: expected 8 values (stamp tx ty tz qx qy qz qw), got {len(parts)}")
        try:
            rows.append([float(v) for v in parts])
        except ValueError:
            raise LinoLocError(f"{path}: line {n}: not a number") from None
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    qx, qy, qz, qw = a[:, 4], a[:, 5], a[:, 6], a[:, 7]
    yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return a[:, 0].copy(), np.column_stack([a[:, 1], a[:, 2], yaw])


def trajectory_names(condition: str) -> tuple[str, str]:
    """File names of the estimated and the true trajectory of one condition."""
    safe = "".join(c if c.isalnum() or c in "-_+" else "_" for c in condition)
    return f"{safe}.estimate.tum", f"{safe}.truth.tum"

"""Pictures of a run: PNGs of a recording or a replay's output (matplotlib, the ``eval`` extra).

:func:`read_run` takes from a recording's parts (or a replay's ``OUT.mcap``, the same layout)
the poses of ``/pose/estimate`` (stamp, x, y, theta, state, quality, the 3 x 3 covariance), the
true poses of ``/truth`` (simulation), and from the session's metadata the map's survey poses
(the ``poses`` array of the map file ``map_path``, when that file is here) and the simulated
world (``devices.camera.sim.world`` of the recorded configuration, when its camera is
simulated). :func:`plot_run` writes:

- ``trajectory.png``: the estimate over the map (the survey poses as grey dots, the world's
  walls as black lines when it names a world), the truth beside it when the recording has it,
  the start and end marked;
- ``timeline.png``: over time since the first pose, the position error ``|p - p_true|`` and the
  estimate's own 1-sigma ``sqrt(sigma_xx + sigma_yy)`` (when truth exists: the truth is
  interpolated linearly at each pose's stamp, the heading along its unwrapped angle, poses
  outside the truth's span left out), the heading error, the state (global, tracking, lost)
  and the quality (0-1; missing where the pose has none).

Errors (one line, :class:`lino_loc.errors.LinoLocError`): a missing file, a file that is not
MCAP, a recording without ``/pose/estimate`` or without a pose, ``out`` an existing file,
matplotlib missing (the ``eval`` extra).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lino_loc.errors import LinoLocError
from lino_loc.poses import wrap_angle
from services.recording.recording_reader import Recording, read_recording

POSE_TOPIC = "/pose/estimate"
STATES = ("global", "tracking", "lost")
#: Figure size (inches) and resolution of the PNGs.
FIGSIZE = (8.0, 6.0)
DPI = 110


@dataclass
class Run:
    """What is drawn. ``poses``: (N, 3) x, y, theta at ``stamps``; ``truth``: (M, 4) stamp, x,
    y, theta; ``survey``: (K, 3) or None; ``walls``: ((x0, y0), (x1, y1)) per wall; ``boxes``:
    the furniture's footprints, (4, 2) corners each."""

    stamps: np.ndarray
    poses: np.ndarray
    states: list[str]
    quality: np.ndarray
    cov: np.ndarray
    truth: np.ndarray
    survey: np.ndarray | None = None
    walls: list[tuple[tuple[float, float], tuple[float, float]]] = field(default_factory=list)
    boxes: list[np.ndarray] = field(default_factory=list)
    world: str | None = None
    truncated: str | None = None


def read_run(paths: list[Path]) -> Run:
    """The run of a recording's parts (module docstring)."""
    rec = Recording(paths)
    rows: list[tuple[float, float, float, float]] = []
    states: list[str] = []
    quality: list[float] = []
    covs: list[list[float]] = []
    truth: list[tuple[float, float, float, float]] = []
    for m in read_recording(paths, rec):
        if m.topic == POSE_TOPIC:
            p = json.loads(m.data)
            rows.append((float(p["stamp"]), p["pose"]["x"], p["pose"]["y"], p["pose"]["theta"]))
            states.append(str(p.get("state", "")))
            q = p.get("quality")
            quality.append(math.nan if q is None else float(q))
            covs.append(list(p["covariance"]))
        elif m.topic == "/truth":
            t = json.loads(m.data)
            truth.append((float(t["stamp"]), t["pose"]["x"], t["pose"]["y"], t["pose"]["theta"]))
    if POSE_TOPIC not in rec.topics:
        have = ", ".join(sorted(rec.topics)) or "none"
        raise LinoLocError(f"{paths[0]}: no {POSE_TOPIC} channel: not a lino-loc recording or "
                           f"replay (channels: {have})")
    if not rows:
        raise LinoLocError(f"{paths[0]}: no pose on {POSE_TOPIC}: nothing to plot")
    a = np.asarray(rows, dtype=np.float64)
    run = Run(stamps=a[:, 0], poses=a[:, 1:], states=states, quality=np.asarray(quality),
              cov=np.asarray(covs, dtype=np.float64).reshape(-1, 3, 3),
              truth=np.asarray(truth, dtype=np.float64).reshape(-1, 4), truncated=rec.truncated)
    run.survey = _survey(rec.metadata)
    run.world, run.walls, run.boxes = _world(rec.metadata)
    return run


def _survey(meta: dict[str, Any]) -> np.ndarray | None:
    """The map file's survey poses, or None (no map named, not here, unreadable)."""
    from lino_loc.appearance_map import POSES_KEY

    path = meta.get("map_path")
    if not isinstance(path, str) or not Path(path).is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as npz:
            poses = np.asarray(npz[POSES_KEY], dtype=np.float64)
    except (OSError, KeyError, ValueError):
        return None
    return poses if poses.ndim == 2 and poses.shape[1] == 3 else None


def _world(meta: dict[str, Any]) -> tuple[str | None, list[Any], list[np.ndarray]]:
    """(world name, its walls, its furniture's footprints) of a recording of the simulated
    camera (the world without scene changes), else (None, [], [])."""
    cfg = meta.get("config")
    try:
        cfg = json.loads(cfg) if isinstance(cfg, str) else cfg
        camera = cfg["devices"]["camera"]
        if camera.get("kind") != "sim":
            return None, [], []
        name = str(camera["sim"]["world"])
    except (TypeError, KeyError, ValueError):
        return None, [], []
    from drivers.sim.world import load_world

    try:
        world = load_world(name)
    except LinoLocError:
        return name, [], []
    geometry = world.geometry()
    return (world.name, [(tuple(w.start), tuple(w.end)) for w in geometry.walls],
            [b.corners() for b in geometry.boxes])


def truth_at(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """(mask of the poses inside the truth's span, the truth (x, y, theta) at those stamps)."""
    if run.truth.shape[0] < 2:
        return np.zeros(len(run.stamps), dtype=bool), np.zeros((0, 3))
    t = run.truth
    order = np.argsort(t[:, 0], kind="stable")
    t = t[order]
    inside = (run.stamps >= t[0, 0]) & (run.stamps <= t[-1, 0])
    s = run.stamps[inside]
    th = np.interp(s, t[:, 0], np.unwrap(t[:, 3]))
    return inside, np.column_stack([np.interp(s, t[:, 0], t[:, 1]), np.interp(s, t[:, 0], t[:, 2]),
                                    wrap_angle(th)])


def plot_run(paths: list[Path] | list[str], out: Path | str) -> list[Path]:
    """Write the PNGs of the module docstring into the folder ``out``; returns their paths."""
    from services.evaluation.plotting import pyplot

    plt = pyplot()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise LinoLocError(f"--out {out}: a file, not a folder")
    run = read_run([Path(p) for p in paths])
    out.mkdir(parents=True, exist_ok=True)
    written = [_trajectory(plt, run, out / "trajectory.png"), _timeline(plt, run, out / "timeline.png")]
    return written


def _trajectory(plt: Any, run: Run, path: Path) -> Path:
    fig, ax = plt.subplots(figsize=FIGSIZE)
    for (x0, y0), (x1, y1) in run.walls:
        ax.plot([x0, x1], [y0, y1], color="black", lw=2, solid_capstyle="butt")
    for corners in run.boxes:
        ax.fill(corners[:, 0], corners[:, 1], color="0.85", ec="0.6", lw=0.5)
    if run.survey is not None:
        ax.scatter(run.survey[:, 0], run.survey[:, 1], s=4, color="0.7", label=f"survey ({len(run.survey)} poses)")
    if run.truth.shape[0]:
        ax.plot(run.truth[:, 1], run.truth[:, 2], color="tab:green", lw=1.5, label="truth")
    p = run.poses
    ax.plot(p[:, 0], p[:, 1], color="tab:blue", lw=1.0, marker=".", ms=3, label="estimate")
    ax.plot(p[0, 0], p[0, 1], "o", color="tab:blue", ms=7, mfc="none", label="start")
    ax.plot(p[-1, 0], p[-1, 1], "s", color="tab:blue", ms=7, mfc="none", label="end")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x in map (m)")
    ax.set_ylabel("y in map (m)")
    where = f" in the {run.world} world" if run.world else ""
    ax.set_title(f"trajectory{where}: {len(p)} poses over {run.stamps[-1] - run.stamps[0]:.1f} s")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def _timeline(plt: Any, run: Run, path: Path) -> Path:
    inside, true = truth_at(run)
    panels = 4 if inside.any() else 2
    fig, axes = plt.subplots(panels, 1, figsize=(FIGSIZE[0], 2.0 * panels), sharex=True)
    t = run.stamps - run.stamps[0]
    sigma = np.sqrt(np.maximum(run.cov[:, 0, 0] + run.cov[:, 1, 1], 0.0))
    k = 0
    if inside.any():
        err = np.hypot(run.poses[inside, 0] - true[:, 0], run.poses[inside, 1] - true[:, 1])
        axes[0].plot(t[inside], err, color="tab:red", lw=1, label="position error")
        axes[0].plot(t, sigma, color="0.5", lw=1, ls="--", label="estimated 1-sigma")
        axes[0].set_ylabel("m")
        axes[0].set_title(f"error: median {np.median(err):.3f} m, max {err.max():.3f} m")
        axes[0].legend(loc="upper right", fontsize=8)
        axes[1].plot(t[inside], np.degrees(np.abs(wrap_angle(run.poses[inside, 2] - true[:, 2]))),
                     color="tab:purple", lw=1)
        axes[1].set_ylabel("heading error (deg)")
        k = 2
    codes = np.array([STATES.index(s) if s in STATES else -1 for s in run.states])
    axes[k].step(t, codes, where="post", color="tab:blue")
    axes[k].set_yticks(range(len(STATES)), STATES)
    axes[k].set_ylim(-0.5, len(STATES) - 0.5)
    axes[k].set_ylabel("state")
    axes[k + 1].plot(t, run.quality, color="tab:orange", lw=1)
    axes[k + 1].set_ylim(-0.05, 1.05)
    axes[k + 1].set_ylabel("quality")
    axes[k + 1].set_xlabel("time since the first pose (s)")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path

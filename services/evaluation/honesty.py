"""Does the filter's state tell the truth? Metrics of a run's states against its errors.

A run is a sequence of frames k = 0..K-1 with stamps t_k (s), position errors e_k (m, the
estimate against the truth) and states s_k (``global`` / ``tracking`` / ``lost``), and
optionally the estimate's ``quality`` q_k in [0, 1].

- :func:`confident_wrong_fraction`: the share of frames with s_k = ``tracking`` and
  e_k > ``wrong_m`` (:data:`WRONG_M`, 1 m): the state says "I know where I am" while the
  estimate is more than a metre off.
- :func:`false_lost_fraction`: the share of frames with s_k = ``lost`` and e_k <=
  ``right_m`` (:data:`RIGHT_M`, 0.5 m: the tracking criterion of the paper's section 7): the
  state says "I do not know where I am" while the estimate is right, the false alarm that
  makes a client stop the robot for nothing; :func:`lost_when_wrong`, its counterpart: of
  the frames with e_k > ``wrong_m``, the share in state ``lost`` (the rest are ``tracking``,
  confident-wrong, or ``global``, not confirmed).
- :func:`wrong_episodes`: the episodes of error above ``wrong_m``. An episode is a maximal
  run of frames with e_k > wrong_m, where runs separated by a dip (frames with e_k <=
  wrong_m) lasting less than ``merge_s`` (:data:`MERGE_S`, 2 s, from the last wrong frame
  before the dip to the first wrong frame after it) are merged into one: an error that
  hovers about 1 m is one episode, not many. A kidnapping (the robot carried elsewhere) is
  such an episode.
- :func:`lost_delays`: per episode, how long the state said ``tracking`` while wrong. Each
  stretch of consecutive ``tracking`` frames inside the episode (from the episode's first
  frame when it starts while tracking, as a kidnapping does; or from a confirmation while
  wrong, as when a search settles on the wrong place) is CAUGHT when a frame of the same
  episode after it is not ``tracking`` (``lost`` or ``global``), its delay the time from the
  stretch's first frame to that frame; a stretch that lasts to the episode's end is NOT
  CAUGHT, its delay the time from its first to the episode's last frame (the true delay is at
  least that). The episode's delay is its stretches' largest, caught when all of them are;
  an episode never ``tracking`` is caught at 0.
- :func:`lost_delay_summary`: ``episodes``, ``caught`` (episodes whose state left
  ``tracking``), ``caught_within_s_share`` (share of the episodes caught within ``within_s``,
  :data:`WITHIN_S` = 5 s, delay <= within_s; 1.0 when there is no episode), ``median_s`` and
  ``max_s`` of the delays (uncaught ones counted with their duration; None without episodes).
- :func:`state_changes_per_min`: how often the state changes (frames whose state differs from
  the previous frame's, per minute of the run): a state that flickers between ``tracking``
  and ``lost`` every few frames tells a client little, whatever the error.
- :func:`quality_table`: the error by band of quality ([0, 0.2), [0.2, 0.4), ..., [0.8, 1.0]
  by default): frames, mean and median error, share of frames with error above wrong_m, and
  the share of frames ``tracking``. A calibrated quality has errors falling from band to band.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

WRONG_M = 1.0  # an estimate this far off (m) is wrong
RIGHT_M = 0.5  # an estimate this close (m) is right (the paper's section 7: error below 50 cm)
MERGE_S = 2.0  # dips below WRONG_M shorter than this (s) do not end an episode
WITHIN_S = 5.0  # an episode is caught in time when the state leaves tracking within this (s)
QUALITY_EDGES = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)


def _arrays(stamps: ArrayLike, errors: ArrayLike, states: Sequence[str]) -> tuple[np.ndarray, ...]:
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    tracking = np.array([s == "tracking" for s in states], dtype=bool)
    if not (t.shape == e.shape == tracking.shape):
        raise ValueError(f"stamps, errors and states differ in length: {t.size}, {e.size}, {tracking.size}")
    return t, e, tracking


def confident_wrong_fraction(errors: ArrayLike, states: Sequence[str], wrong_m: float = WRONG_M) -> float:
    """Share of the frames whose state is ``tracking`` while the error exceeds ``wrong_m``
    (0 for an empty run)."""
    e, tracking = _errors_in(errors, states, "tracking")
    if e.size == 0:
        return 0.0
    return float(np.mean(tracking & (e > wrong_m)))


def _errors_in(errors: ArrayLike, states: Sequence[str], state: str) -> tuple[np.ndarray, np.ndarray]:
    """The errors as an array and which frames are in ``state``; their lengths must agree."""
    e, mask = np.asarray(errors, dtype=np.float64).reshape(-1), np.array([s == state for s in states], dtype=bool)
    if mask.size != e.size:
        raise ValueError(f"errors and states differ in length: {e.size}, {mask.size}")
    return e, mask


def false_lost_fraction(errors: ArrayLike, states: Sequence[str], right_m: float = RIGHT_M) -> float:
    """The share of frames in state ``lost`` with a position error of at most ``right_m``."""
    e, lost = _errors_in(errors, states, "lost")
    return float(np.mean(lost & (e <= right_m))) if e.size else 0.0


def lost_when_wrong(errors: ArrayLike, states: Sequence[str], wrong_m: float = WRONG_M) -> float | None:
    """The share of the frames with a position error above ``wrong_m`` whose state is
    ``lost``; None when no frame is that wrong."""
    e, lost = _errors_in(errors, states, "lost")
    wrong = e > wrong_m
    return float(lost[wrong].mean()) if wrong.any() else None


def wrong_episodes(
    stamps: ArrayLike, errors: ArrayLike, wrong_m: float = WRONG_M, merge_s: float = MERGE_S
) -> list[tuple[int, int]]:
    """The episodes of error above ``wrong_m`` as (first, last) frame indices, inclusive, runs
    separated by dips shorter than ``merge_s`` merged (see the module docstring)."""
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    wrong = np.asarray(errors, dtype=np.float64).reshape(-1) > wrong_m
    idx = np.flatnonzero(wrong)
    episodes: list[tuple[int, int]] = []
    for k in idx:
        if episodes and (k == episodes[-1][1] + 1 or t[k] - t[episodes[-1][1]] < merge_s):
            episodes[-1] = (episodes[-1][0], int(k))
        else:
            episodes.append((int(k), int(k)))
    return episodes


def lost_delays(
    stamps: ArrayLike, errors: ArrayLike, states: Sequence[str], wrong_m: float = WRONG_M,
    merge_s: float = MERGE_S,
) -> list[tuple[float, bool]]:
    """(delay s, caught) per episode of :func:`wrong_episodes`: its ``tracking`` stretches'
    largest delay, caught when every stretch is (see the module docstring)."""
    t, e, tracking = _arrays(stamps, errors, states)
    return [_episode_delay(t[a : b + 1], tracking[a : b + 1]) for a, b in wrong_episodes(t, e, wrong_m, merge_s)]


def _episode_delay(t: np.ndarray, tracking: np.ndarray) -> tuple[float, bool]:
    """One episode's (delay, caught) from its frames' stamps and tracking flags."""
    flags = tracking.astype(np.int8)
    edges = np.diff(np.concatenate(([0], flags, [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)  # ends: first frame after
    delay, caught = 0.0, True
    for a, b in zip(starts, ends, strict=True):
        ok = bool(b < t.size)
        delay = max(delay, float(t[b] - t[a]) if ok else float(t[-1] - t[a]))
        caught = caught and ok
    return delay, caught


def lost_delay_summary(
    stamps: ArrayLike, errors: ArrayLike, states: Sequence[str], wrong_m: float = WRONG_M,
    merge_s: float = MERGE_S, within_s: float = WITHIN_S,
) -> dict[str, Any]:
    """The episodes' delays summarised (see the module docstring for the keys)."""
    delays = lost_delays(stamps, errors, states, wrong_m, merge_s)
    d = np.array([x for x, _ in delays])
    in_time = [ok and x <= within_s for x, ok in delays]
    return {
        "episodes": len(delays),
        "caught": int(sum(ok for _, ok in delays)),
        "caught_within_s": float(within_s),
        "caught_within_s_share": float(np.mean(in_time)) if delays else 1.0,
        "median_s": float(np.median(d)) if delays else None,
        "max_s": float(d.max()) if delays else None,
    }


def state_changes_per_min(stamps: ArrayLike, states: Sequence[str]) -> float:
    """Frames whose state differs from the previous frame's, per minute from the first to the
    last stamp (0 for fewer than two frames or a zero span)."""
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    if len(states) != t.size:
        raise ValueError(f"stamps and states differ in length: {t.size}, {len(states)}")
    span = float(t[-1] - t[0]) if t.size >= 2 else 0.0
    if span <= 0.0:
        return 0.0
    changes = sum(a != b for a, b in zip(states[:-1], states[1:], strict=True))
    return 60.0 * changes / span


def honesty_metrics(stamps: ArrayLike, errors: ArrayLike, states: Sequence[str]) -> dict[str, Any]:
    """``tracking_fraction`` (the share of frames ``tracking``: what honesty costs),
    ``confident_wrong_fraction``, ``false_lost_fraction``, ``lost_when_wrong``, ``lost_delay_s`` (:func:`lost_delay_summary`) and
    ``state_changes_per_min`` (:func:`state_changes_per_min`) of one run."""
    return {
        "tracking_fraction": float(np.mean([s == "tracking" for s in states])) if len(states) else 0.0,
        "confident_wrong_fraction": confident_wrong_fraction(errors, states),
        "false_lost_fraction": false_lost_fraction(errors, states),
        "lost_when_wrong": lost_when_wrong(errors, states),
        "lost_delay_s": lost_delay_summary(stamps, errors, states),
        "state_changes_per_min": state_changes_per_min(stamps, states),
    }


def quality_table(
    quality: ArrayLike, errors: ArrayLike, states: Sequence[str] | None = None,
    edges: Sequence[float] = QUALITY_EDGES, wrong_m: float = WRONG_M,
) -> list[dict[str, Any]]:
    """One row per band [edges[i], edges[i+1]) (the last band closed): ``band`` [lo, hi],
    ``frames``, ``mean_error_m``, ``median_error_m``, ``wrong_fraction`` (error above
    ``wrong_m``) and ``tracking_fraction`` (None without ``states``); the error keys are None
    for an empty band. Frames with a non-finite quality are left out."""
    q = np.asarray(quality, dtype=np.float64).reshape(-1)
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if q.shape != e.shape:
        raise ValueError(f"quality and errors differ in length: {q.size}, {e.size}")
    tr = None if states is None else np.array([s == "tracking" for s in states], dtype=bool)
    rows = []
    for i in range(len(edges) - 1):
        lo, hi = float(edges[i]), float(edges[i + 1])
        sel = np.isfinite(q) & (q >= lo) & ((q <= hi) if i == len(edges) - 2 else (q < hi))
        n = int(sel.sum())
        rows.append({
            "band": [lo, hi],
            "frames": n,
            "mean_error_m": float(e[sel].mean()) if n else None,
            "median_error_m": float(np.median(e[sel])) if n else None,
            "wrong_fraction": float(np.mean(e[sel] > wrong_m)) if n else None,
            "tracking_fraction": float(np.mean(tr[sel])) if n and tr is not None else None,
        })
    return rows

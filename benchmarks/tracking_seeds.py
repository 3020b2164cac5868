"""The tracking evaluation's honesty bounds over several worlds AND seeds, in one table.

One seed per world hid runs above the bounds (docs/results.md): the filter's path depends on
the last bits of its likelihoods, so a bound is a claim about the distribution of runs, not
about one. This runs ``lino-loc eval tracking`` (:func:`services.evaluation.tracking.run`, the
same setup, maps and frames as the command; no without-recovery comparison) for every
(world, seed), in worker processes, and prints one JSON object:

- ``runs``: per world, seed and run (known start, uniform start, kidnap per light, and the
  light switch) the mean error, ``confident_wrong_fraction``, the episodes of error above 1 m
  and how many left ``tracking`` within 5 s, the share of frames ``tracking``, and for the
  uniform starts the time to converge (error) and to the first ``tracking`` frame, and how
  often the state changed (``state_changes_per_min``) and the share of frames ``lost`` while
  the estimate was within 0.5 m (``false_lost_fraction``) and of the frames more than 1 m off
  (``lost_when_wrong``);
- ``summary``: over all runs, the episodes caught within 5 s, the runs whose
  confident-wrong fraction exceeds 2 %, the uniform starts that converged, the mean
  ``tracking`` share, false-lost share and state changes per minute by kind of run;
- ``quality_by_world``: per world, the evaluation's quality table (error by band of the
  published ``quality``, over the graded runs) pooled over the seeds: frames, and the
  frame-weighted mean error, wrong share (error above 1 m) and ``tracking`` share per band
  (medians do not pool, so none is given).

A progress line per finished (world, seed) goes to stderr.

Usage::

    OPENBLAS_NUM_THREADS=1 python benchmarks/tracking_seeds.py --worlds lab,office,corridor \\
        --seeds 0,1,2 [--config default --config C.toml] [--jobs 2] > out.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

WRONG_SHARE = 0.02  # the confident-wrong bound of the evaluation


def _row(world: str, seed: int, name: str, res: dict[str, Any]) -> dict[str, Any]:
    d = res["lost_delay_s"]
    return {
        "world": world, "seed": seed, "run": name,
        "mean_error_m": res.get("mean_error_m", res.get("mean_error_after_m")),
        "confident_wrong_fraction": res["confident_wrong_fraction"],
        "false_lost_fraction": res["false_lost_fraction"],
        "lost_when_wrong": res["lost_when_wrong"],
        "tracking_fraction": res["tracking_fraction"],
        "state_changes_per_min": res["state_changes_per_min"],
        "episodes": d["episodes"],
        "caught_within_5s": round(d["caught_within_s_share"] * d["episodes"]),
    }


def one(args: tuple[str, int, tuple[str, ...], dict[str, Any]]) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Every run of ``eval tracking`` on one world and seed, per configuration ("default": the
    defaults), as rows, and the quality table per configuration. The frames are rendered once
    for all the configurations (the evaluation's own ``render_frames``, remembered in this
    process)."""
    world, seed, configs, map_settings = args
    import functools

    import services.evaluation.tracking as tracking
    from services.config import load_config

    render = tracking.render_frames
    frames: dict[Any, Any] = {}

    @functools.wraps(render)
    def remembered(spec: Any, truth: Any, **kw: Any) -> Any:
        if spec not in frames:
            frames[spec] = render(spec, truth, **kw)
        return frames[spec]

    tracking.render_frames = remembered
    rows = []
    tables = {}
    for config in configs:
        cfg = None if config == "default" else load_config(config).localizer
        res = tracking.run(tracking.TrackingSetup(world=world, seed=seed, channels=tracking.DEFAULT_CHANNELS,
                                                  workers=1, compare_recovery=False, **map_settings), cfg)
        rows += [{**r, "config": config} for r in _rows(world, seed, res)]
        tables[config] = res["quality_table"]
    return rows, tables


def pool_quality(tables: list[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Quality tables of several runs (:func:`services.evaluation.honesty.quality_table`, same
    bands) as one: per band the frames summed and the mean error, wrong share and ``tracking``
    share weighted by each table's frames; None for a band with no frames."""
    if not tables:
        return []
    bands = [r["band"] for r in tables[0]]
    if any([r["band"] for r in t] != bands for t in tables):
        raise ValueError("quality tables with different bands do not pool")
    out = []
    for i, band in enumerate(bands):
        rows = [t[i] for t in tables if t[i]["frames"]]
        out.append({"band": band, "frames": sum(r["frames"] for r in rows),
                    **{k: _weighted(rows, k) for k in ("mean_error_m", "wrong_fraction", "tracking_fraction")}})
    return out


def _weighted(rows: list[dict[str, Any]], key: str) -> float | None:
    """The frame-weighted mean of ``key`` over the rows that have it; None if none has."""
    vals = [(r[key], r["frames"]) for r in rows if r[key] is not None]
    w = sum(f for _, f in vals)
    return sum(v * f for v, f in vals) / w if w else None


def _rows(world: str, seed: int, res: dict[str, Any]) -> list[dict[str, Any]]:
    rows = []
    for light, c in res["conditions"].items():
        rows.append(_row(world, seed, f"{light}/known", c))
        g = {**c["global_start"], "mean_error_m": c["global_mean_error_m"]}
        rows.append({**_row(world, seed, f"{light}/uniform", g), "converged_after_s": c["converged_after_s"],
                     "first_tracking_s": c["converged_state_after_s"]})
        k = c["kidnap"]
        rows.append(_row(world, seed, f"{light}/kidnap", {**k, "mean_error_m": k["mean_error_after_m"]}))
    if "light_switch" in res:
        rows.append(_row(world, seed, "switch", res["light_switch"]))
    return rows


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ep = sum(r["episodes"] for r in rows)
    caught = sum(r["caught_within_5s"] for r in rows)
    uniform = [r for r in rows if r["run"].endswith("/uniform")]
    kinds = ("known", "uniform", "kidnap", "switch")
    return {
        "episodes": ep,
        "caught_within_5s": caught,
        "caught_within_5s_share": caught / ep if ep else 1.0,
        "runs": len(rows),
        "runs_over_2pc_confident_wrong": [
            f"{r['world']} seed {r['seed']} {r['run']}: {100 * r['confident_wrong_fraction']:.2f} %"
            for r in rows if r["confident_wrong_fraction"] > WRONG_SHARE],
        "max_confident_wrong_fraction": max(r["confident_wrong_fraction"] for r in rows),
        "uniform_converged": sum(r["converged_after_s"] is not None for r in uniform),
        "uniform_runs": len(uniform),
        "state_changes_per_min_by_kind": {
            k: sum(r["state_changes_per_min"] for r in rows if r["run"].endswith(k)) /
            max(1, sum(r["run"].endswith(k) for r in rows)) for k in kinds},
        **{f"{key}_by_kind": {
            k: sum(r[key] for r in rows if r["run"].endswith(k)) /
            max(1, sum(r["run"].endswith(k) for r in rows)) for k in kinds}
           for key in ("tracking_fraction", "false_lost_fraction")},
        "lost_when_wrong_by_kind": {k: _mean([r["lost_when_wrong"] for r in rows if r["run"].endswith(k)])
                                    for k in kinds},
    }


def _mean(values: list[float | None]) -> float | None:
    """The mean of the values that are not None; None if all are."""
    v = [x for x in values if x is not None]
    return sum(v) / len(v) if v else None


def main() -> None:
    from lino_loc.errors import LinoLocError
    from services.evaluation.commands.localization_cmd import (
        add_tracking_map_arguments,
        tracking_map_settings,
    )

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", default="lab,office,corridor")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--config", action="append", help="take the [localizer] settings from this "
                   "configuration file ('default': the defaults); repeat to compare configurations on "
                   "the same frames (default: the defaults alone)")
    p.add_argument("--jobs", type=int, default=2)
    add_tracking_map_arguments(p)  # eval tracking's own (config/sim.toml's map: --step 0.75 --heading-step 15
    # --virtual-headings 5 --translations 3 --disparity-features 5)
    a = p.parse_args()
    configs = tuple(a.config or ["default"])
    try:
        map_settings = tracking_map_settings(a)
    except LinoLocError as e:
        p.error(str(e))
    jobs = [(w, int(s), configs, map_settings) for w in a.worlds.split(",") for s in a.seeds.split(",")]
    rows: list[dict[str, Any]] = []
    tables: dict[tuple[str, str], list[list[dict[str, Any]]]] = {}
    t0 = time.monotonic()
    with ProcessPoolExecutor(a.jobs) as ex:
        for i, (r, q) in enumerate(ex.map(one, jobs), 1):
            rows += r
            w, s, _, _ = jobs[i - 1]
            for c, t in q.items():
                tables.setdefault((c, w), []).append(t)
            print(f"[{time.monotonic() - t0:6.0f} s] {i}/{len(jobs)} done: {w} seed {s}",
                  file=sys.stderr, flush=True)
    worlds = a.worlds.split(",")
    out = {c: {"summary": summary([r for r in rows if r["config"] == c]),
               "quality_by_world": {w: pool_quality(tables.get((c, w), [])) for w in worlds}}
           for c in configs}
    print(json.dumps({"map": map_settings, "configs": out, "runs": rows}, indent=1))


if __name__ == "__main__":
    main()

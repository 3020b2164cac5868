"""How much the choice of the first camera movement can gain: the success after it for every pan.

For ``lino-loc eval active``'s test positions (the product's defaults: the same map, positions,
test views, first pans and filter seeds as ``eval active --seed S``) and runs ``r < R``, the
robot takes its first view at the run's first pan ``a0``. Then, for EVERY other candidate pan
``a``, a filter started from the same seed takes the views ``a0`` and ``a`` (the standing match
acting as in the evaluation), and the section 6.1 success after that first movement is
recorded; ``F - 1`` further filter seeds repeat it, so each pan's success is a rate over ``F``
filters. Reported, over positions x runs (success after one movement):

- ``random``: the mean over the other pans, what a uniformly random choice expects;
- ``entropy``: at the entropy strategy's choice (``eval active``'s: the filter's H(u), or the
  standing match's spread values once the belief is gathered, discounted by the per-pan
  reliability);
- ``sweep``: at the sweep's (``a0`` + stride);
- ``oracle``: a chooser that knew the outcomes, honestly scored: each run's pan of highest
  success over half of the filter seeds, scored over the other half (both halves, averaged),
  so that the maximum's selection bias over noisy rates does not inflate it;
- ``choice_matters``: the share of runs whose pans' success rates differ;
- ``seed_variance`` and ``pan_variance``: the variance of a single outcome within a pan (over
  filter seeds) and within a run (over pans and seeds): how much of the outcome the pan decides;
- ``corr_h``: the mean correlation, over the runs where the choice matters, between H(u) and
  the pans' success (negative: a lower expected entropy goes with success);
- ``entropy_minus_random``, ``entropy_minus_sweep``: the paired differences and their standard
  errors over the test positions.

It measures the room a first-movement chooser has, and how much of it the entropy strategy
takes. Prints one JSON object.

Usage::

    OPENBLAS_NUM_THREADS=1 python benchmarks/first_look_headroom.py --world office [--seed 0] \
        [--runs 2] [--filters 4] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _position(args: tuple[int, np.ndarray, np.ndarray, np.ndarray | None, int, int]) -> list[dict[str, Any]]:
    """Every run at one test position: the success table (filters, pans) after the first
    movement, the entropy strategy's and the sweep's choices and H(u)."""
    from lino_loc.metrics import success
    from services.evaluation import active

    pos, truth, feats, dfeats, runs, filters = args
    setup = active._ctx["setup"]
    n_a = setup.active.actions().size
    rows = []
    for run in range(runs):
        a0 = int(np.random.default_rng((setup.seed, pos, run, 1)).integers(n_a))
        first = active.Look.start(active.new_filter(pos, run))
        first.take(a0, feats, dfeats)
        values = first.entropy_values([])
        table = np.full((filters, n_a), np.nan)
        for a in range(n_a):
            if a == a0:
                continue
            for f in range(filters):
                look = active.Look.start(active.new_filter(pos, run, None if f == 0 else 100 + f))
                look.take(a0, feats, dfeats)
                look.take(a, feats, dfeats)
                est = look.pf.estimate().pose
                table[f, a] = float(success(est[None], truth[None], active._ctx["map_poses"])[0])
        rows.append({"pos": pos, "a0": a0, "entropy": first.entropy_choice(a0, []), "sweep": (a0 + setup.sweep_stride) % n_a,
                     "h": values.expected_entropy, "table": table})
    return rows


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The report (module docstring) of the runs' success tables."""
    tables = np.stack([r["table"] for r in rows])  # (runs, F, A), NaN at a0
    rate = np.mean(tables, axis=1)  # (runs, A), NaN at a0
    half = tables.shape[1] // 2
    oracle = []
    for pick_on, score_on in ((slice(0, half), slice(half, None)), (slice(half, None), slice(0, half))):
        choose = np.nan_to_num(np.mean(tables[:, pick_on], axis=1), nan=-1.0)
        best = np.argmax(choose, axis=1)
        oracle.append(float(np.mean(np.mean(tables[:, score_on], axis=1)[np.arange(len(rows)), best])))
    differs = np.nanmax(rate, axis=1) > np.nanmin(rate, axis=1)
    corr = [np.corrcoef(r["h"][np.isfinite(rate[i])], rate[i][np.isfinite(rate[i])])[0, 1]
            for i, r in enumerate(rows) if differs[i] and np.std(r["h"][np.isfinite(rate[i])]) > 0]
    at = np.arange(len(rows))
    pos = np.array([r.get("pos", i) for i, r in enumerate(rows)])
    entropy = rate[at, [r["entropy"] for r in rows]]
    others = {"random": np.nanmean(rate, axis=1), "sweep": rate[at, [r["sweep"] for r in rows]]}
    return {
        "random": round(float(np.mean(np.nanmean(rate, axis=1))), 4),
        "entropy": round(float(np.mean(rate[at, [r["entropy"] for r in rows]])), 4),
        "sweep": round(float(np.mean(rate[at, [r["sweep"] for r in rows]])), 4),
        "oracle": round(float(np.mean(oracle)), 4) if half else None,
        "choice_matters": round(float(np.mean(differs)), 4),
        "seed_variance": round(float(np.mean(np.var(tables, axis=1)[np.isfinite(rate)])), 4),
        "pan_variance": round(float(np.mean([np.nanvar(t) for t in tables])), 4),
        "corr_h": round(float(np.mean(corr)), 3) if corr else None,
        **{f"entropy_minus_{k}": paired(entropy - v, pos) for k, v in others.items()},
    }


def paired(diff: np.ndarray, pos: np.ndarray) -> dict[str, float]:
    """A paired difference's mean and standard error over test positions (each position's runs
    averaged first: positions are the independent units)."""
    per = np.array([diff[pos == p].mean() for p in np.unique(pos)])
    se = float(per.std(ddof=1) / np.sqrt(per.size)) if per.size > 1 else float("nan")
    return {"difference": round(float(diff.mean()), 4), "se": round(se, 4)}


def main() -> None:
    from drivers.sim.world import load_world
    from services.evaluation import active
    from services.evaluation.active_setup import product_defaults
    from services.evaluation.machine import machine

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--world", default="office")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--positions", type=int, default=50)
    p.add_argument("--runs", type=int, default=2, help="runs per position (eval active's first runs)")
    p.add_argument("--filters", type=int, default=4, help="filter seeds per pan (at least 2 for the oracle)")
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args()
    for name in ("positions", "runs", "filters", "workers"):
        if getattr(a, name) < 1:
            p.error(f"--{name} must be at least 1 (got {getattr(a, name)})")
    t0 = time.perf_counter()
    setup = product_defaults(world=a.world, seed=a.seed, workers=a.workers, positions=a.positions, runs=a.runs,
                             movements=1, strategies=("entropy",))
    world = load_world(a.world)
    grid = active.grid_poses(world, setup.judged_step, math.radians(setup.heading_step_deg))
    pca, map_features, entries, margin, disp = active.render_map(setup, None)
    truths = active.place_test_positions(world, setup, grid)
    pans = setup.active.actions()
    feats, dfeats = active.render_tests(setup, pca, margin, truths, pans, (), None, None if disp is None else disp[0])
    jobs = [(i, truths[i], feats[i], None if dfeats is None else dfeats[i], a.runs, a.filters)
            for i in range(truths.shape[0])]
    with ProcessPoolExecutor(a.workers, initializer=active.init_worker,
                             initargs=(setup, entries, map_features, grid, None if disp is None else disp[1])) as pool:
        rows = [r for part in pool.map(_position, jobs) for r in part]
    print(json.dumps({"benchmark": "first_look_headroom", "world": a.world, "seed": a.seed,
                      "positions": int(truths.shape[0]), "runs": a.runs, "filters": a.filters,
                      "success_after_one_movement": summarize(rows), "machine": machine(),
                      "seconds": round(time.perf_counter() - t0, 1)}))


if __name__ == "__main__":
    main()

"""The precision section 6.1's success criterion asks for, against what appearance gives.

For each world, at the test positions of ``lino-loc eval active`` (the product's map and test
placement, seed ``--seed``):

1. the success rate of the truth plus a Gaussian position error of sigma per axis, and the
   sigma at which it falls to 95 % and 85 % (the criterion's demand, whatever the method);
2. the fine-lattice appearance oracle (:func:`services.evaluation.criterion_precision.appearance_oracle`):
   the test views of the sweep's first ``--views`` pans matched against real renders on a
   lattice within ``--radius`` of the truth, at the true heading; success after
   1 .. views views and the median / 90th-percentile position error, in the map's PCA features
   and in pixels, for lattices of spacing step / m aligned with the survey grid (m = 1: the
   survey's positions). Its success bounds any sensor model that synthesizes views between
   survey poses on such a lattice, with the truth's neighbourhood and heading given.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_criterion_precision.py --worlds office,lab,corridor,reading_room \
        --positions 40 --json out.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from drivers.sim.world import grid_poses, load_world
from services.evaluation import active, active_stats
from services.evaluation.active_setup import product_defaults
from services.evaluation.criterion_precision import (
    SIGMAS,
    appearance_oracle,
    precision_for,
    success_under_noise,
)
from services.evaluation.machine import machine


def world_report(name: str, args: argparse.Namespace) -> dict[str, Any]:
    t0 = time.perf_counter()
    world = load_world(name)
    setup = product_defaults(world=name, positions=args.positions, runs=1, movements=3, seed=args.seed,
                             workers=args.workers, channels=("intensity",))
    grid = grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    many = active.place_test_positions(world, product_defaults(world=name, positions=args.noise_positions,
                                                               seed=args.seed), grid)
    rates = success_under_noise(many, grid, SIGMAS, draws=args.draws, seed=args.seed)
    pca, _, _, margin, _ = active.render_map(setup, None)
    truths = active.place_test_positions(world, setup, grid)
    oracle = appearance_oracle(setup, world, grid, pca, margin, truths, views=args.views, radius=args.radius,
                               refinements=tuple(int(m) for m in args.refinements.split(",")))
    report: dict[str, Any] = {
        "criterion": {"sigmas": list(SIGMAS), "success": [round(float(r), 4) for r in rates],
                      "sigma_for_95": precision_for(SIGMAS, rates, 0.95),
                      "sigma_for_85": precision_for(SIGMAS, rates, 0.85),
                      "positions": int(many.shape[0]), "draws": args.draws},
        "oracle": {},
    }
    counts = active_stats.resample_counts(truths.shape[0], 1)
    for dist, by_m in oracle.items():
        report["oracle"][dist] = {}
        for m, by_k in by_m.items():
            rep: dict[str, Any] = {"spacing": round(setup.step / int(m), 4)}
            for k, v in by_k.items():
                s, e = v["success"], v["error"]
                lo, hi = active_stats.interval(s[:, None].astype(float), counts)
                rep[k] = {"success": round(float(s.mean()), 4), "interval": [round(float(lo), 4), round(float(hi), 4)],
                          "error_median": round(float(np.median(e)), 3),
                          "error_p90": round(float(np.quantile(e, 0.9)), 3)}
            report["oracle"][dist][m] = rep
    report["seconds"] = round(time.perf_counter() - t0, 1)
    return report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", default="office")
    ap.add_argument("--positions", type=int, default=40, help="test positions of the oracle")
    ap.add_argument("--noise-positions", type=int, default=2000, help="test positions of the criterion's curve")
    ap.add_argument("--draws", type=int, default=50)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--radius", type=float, default=0.6, help="candidates within this of the truth (m)")
    ap.add_argument("--refinements", default="1,3,9",
                    help="lattices of spacing step / m; odd m keep every lattice point off the survey cells' borders")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    out: dict[str, Any] = {"machine": machine(),
                           "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                           "worlds": {}}
    for name in args.worlds.split(","):
        rep = world_report(name, args)
        out["worlds"][name] = rep
        c = rep["criterion"]
        print(f"{name}: criterion sigma for 95 % {c['sigma_for_95']}, for 85 % {c['sigma_for_85']}; "
              f"success by sigma {dict(zip(c['sigmas'], c['success'], strict=True))}", flush=True)
        for dist, by_m in rep["oracle"].items():
            for r in by_m.values():
                row = ", ".join(f"{k} {r[k]['success']:.1%} [{r[k]['interval'][0]:.0%}-{r[k]['interval'][1]:.0%}] "
                                f"(median {r[k]['error_median']} m, p90 {r[k]['error_p90']} m)"
                                for k in r if k != "spacing")
                print(f"  oracle, {dist}, lattice {r['spacing']} m, success after 1..k views: {row}", flush=True)
        print(f"  {rep['seconds']} s", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""`lino-loc eval illumination`: Table 1 of the paper on the simulated lab."""

from __future__ import annotations

import argparse
import json

from services.evaluation.illumination import IlluminationSetup, run
from services.progress import Progress

PAPER = {"plain": (3.85, 4.64, 4.24), "histeq": (1.50, 1.84, 1.67), "gradient": (1.11, 1.37, 1.24),
         "disparity": (0.68, 0.79, 0.73)}


def _table(result: dict) -> str:
    lights = [k for k in next(iter(result["ratios"].values())) if k != "average"]
    head = f"{'features':<10}" + "".join(f"{light:>10}" for light in lights) + f"{'average':>10}   paper (bulb, natural, avg)"
    lines = [f"Table 1 on the simulated {result['world']}: {result['poses']} poses, {result['pairs']} pairs, "
             f"{result['features']} features", head, "-" * len(head)]
    for name, r in result["ratios"].items():
        paper = PAPER.get(name)
        lines.append(f"{name:<10}" + "".join(f"{r[light]:>10.2f}" for light in lights) + f"{r['average']:>10.2f}"
                     + (f"   {paper[0]:.2f}, {paper[1]:.2f}, {paper[2]:.2f}" if paper else ""))
    return "\n".join(lines)


def _run(args: argparse.Namespace) -> int:
    setup = IlluminationSetup(world=args.world, step=args.step, heading_step_deg=args.heading_step,
                              features=args.features, width=args.width, height=args.height,
                              disparity=not args.no_disparity, seed=args.seed, workers=args.workers)
    bar = Progress("render")
    result = run(setup, progress=lambda light, d, n: bar.update(d, n, label=f"render {light}"))
    bar.close()
    print(json.dumps(result) if args.json else _table(result))
    return 0


def register_eval(eval_sub: argparse._SubParsersAction) -> None:
    p = eval_sub.add_parser("illumination", help="Table 1: feature change under other light vs. 50 cm translation")
    p.add_argument("--world", default="lab")
    p.add_argument("--step", type=float, default=0.5, help="grid step in metres (b is one step from a)")
    p.add_argument("--heading-step", type=float, default=10.0, help="heading step in degrees")
    p.add_argument("--features", type=int, default=20, help="PCA features per channel")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--no-disparity", action="store_true", help="intensity rows only")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None, help="rendering processes (default: all cores)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run)

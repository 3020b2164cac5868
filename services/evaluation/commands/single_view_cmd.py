"""`lino-loc eval single-view`: how often one image alone localizes the robot."""

from __future__ import annotations

import argparse
import json

from services.evaluation.single_view import SingleViewSetup, run
from services.progress import Progress


def _run(args: argparse.Namespace) -> int:
    setup = SingleViewSetup(world=args.world, features=args.features, preprocess=args.preprocess,
                            views=args.views, j=args.j, seed=args.seed, workers=args.workers,
                            virtual_headings=args.virtual_headings)
    bar = Progress("render test views")
    result = run(setup, progress=bar.update)
    bar.close()
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{result['views']} off-grid views of the {result['world']} against {result['map_entries']} map entries "
              f"({result['features']} features, {result['preprocess']}):\n"
              f"  nearest entry at the right place (section 6.1): {result['top1_success']:.1%}"
              f" (same position and heading cell: {result['top1_success_pose']:.1%})\n"
              f"  right place among the J={result['J']} nearest:      {result['success_within_J']:.1%}\n"
              f"  a random entry at the right place (chance):     {result['chance_success']:.1%}")
    return 0


def register_eval(eval_sub: argparse._SubParsersAction) -> None:
    p = eval_sub.add_parser("single-view", help="single-image ambiguity: nearest map image at the right place?")
    p.add_argument("--world", default="office")
    p.add_argument("--features", type=int, default=5)
    p.add_argument("--preprocess", default="none", choices=("none", "histeq", "gradient"))
    p.add_argument("--views", type=int, default=300, help="test views off the map grid")
    p.add_argument("--j", type=int, default=10)
    p.add_argument("--virtual-headings", type=int, default=1, choices=range(1, 32), metavar="N",
                   help="map entries per image, turned 3 deg apart (lino_loc.virtual_views); default 1: the images alone")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run)

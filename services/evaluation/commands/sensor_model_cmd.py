"""`lino-loc eval sensor-model`: Fig. 5 of the paper, the sensor-model error (eq. 10) along a
path through a simulated world (default: the lab) under tube, bulb and natural light, intensity only (J = 10)
against intensity + disparity with disjunctive fusion (eq. 8, J = 5 + 5)."""

from __future__ import annotations

import argparse
import json
import logging

from lino_loc.errors import LinoLocError
from lino_loc.preprocessing import PREPROCESS_METHODS
from services.evaluation.plotting import pyplot
from services.evaluation.sensor_model_error import SensorModelSetup, plot, run
from services.evaluation.tracking import DEFAULT_PREPROCESS
from services.progress import Progress

log = logging.getLogger(__name__)


def _cell(block: dict) -> str:
    """``mean +- std`` of one block, right-aligned; "-" for a block without any view."""
    if block["mean_m"] is None:
        return f"{'-':>22}"
    return f"{block['mean_m']:>13.3f} +- {block['std_m']:.3f}"


def _table(result: dict) -> str:
    j = result["J"]
    lines = [
        f"Fig. 5 on the simulated {result['world']}: map of {result['map']['poses']} poses under tube "
        f"({result['features']} features, intensity preprocessing {result['map']['preprocess']}), "
        f"{result['positions']} test poses along {result['path']['length_m']:.1f} m; "
        f"grid limit {result['grid_limit_m']['mean_m']:.2f} m",
        f"{'light':<10}{'intensity J=' + str(j['intensity']):>22}{'fused J={}+{}'.format(*j['fused']):>22}"
        f"{'disparity J=' + str(j['intensity']):>22}{'density':>10}",
    ]
    lines.append("-" * len(lines[-1]))
    for light, r in result["conditions"].items():
        cells = "".join(_cell(r[k]) for k in ("intensity", "fused", "disparity"))
        lines.append(f"{light:<10}{cells}{result['disparity_density'][light]:>10.3f}")
    others = [p for p in result["by_preprocess"] if p != result["map"]["preprocess"]]
    for p in others:
        lines.append(f"\nintensity preprocessing {p}:")
        for light, r in result["by_preprocess"][p].items():
            lines.append(f"{light:<10}" + "".join(_cell(r[k]) for k in ("intensity", "fused", "disparity")))
    return "\n".join(lines)


def _path_box(text: str) -> tuple[float, float, float, float]:
    """``--path-box XMIN,XMAX,YMIN,YMAX`` as four floats; LinoLocError naming the value."""
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        v = ()
    if len(v) != 4 or not (v[0] < v[1] and v[2] < v[3]):
        raise LinoLocError(f"--path-box: want XMIN,XMAX,YMIN,YMAX with XMIN < XMAX and YMIN < YMAX, got {text!r}")
    return v[0], v[1], v[2], v[3]


def _run(args: argparse.Namespace) -> int:
    if args.plot:
        pyplot()  # fails now, in one line naming the extra, rather than after the run
    if args.j < 2:
        raise LinoLocError(f"--j must be at least 2 (it is split between the two channels), got {args.j}")
    if args.spacing <= 0:
        raise LinoLocError(f"--spacing must be positive, got {args.spacing}")
    lights = tuple(x.strip() for x in args.lights.split(",") if x.strip())
    if not lights:
        raise LinoLocError("--lights: give at least one lighting setup")
    compare = tuple(x.strip() for x in args.compare.split(",") if x.strip() and x.strip() != args.preprocess)
    j_i = args.j - args.j // 2
    box = _path_box(args.path_box) if args.path_box else None
    setup = SensorModelSetup(world=args.world, step=args.step, heading_step_deg=args.heading_step,
                             features=args.features, preprocess=args.preprocess, compare_preprocess=compare,
                             lights=lights, j=args.j, j_intensity=j_i, j_disparity=args.j - j_i,
                             spacing=args.spacing, path_box=box, width=args.width, height=args.height,
                             size=(args.map_width, args.map_height), seed=args.seed, workers=args.workers,
                             cache=not args.no_cache)
    bar = Progress("sensor-model")
    result = run(setup, progress=lambda label, d, n: bar.update(d, n, label=label))
    bar.close()
    if args.plot:
        for f in plot(result, args.plot):
            log.info("wrote %s", f)
    print(json.dumps(result) if args.json else _table(result))
    return 0


def register_eval(eval_sub: argparse._SubParsersAction) -> None:
    p = eval_sub.add_parser(
        "sensor-model",
        help="Fig. 5: sensor-model error (eq. 10) along a path, intensity vs. intensity + disparity",
        description="Fig. 5 of the paper on a simulated world (default: the lab): the error e of eq. 10 "
        "(metres) of the sensor model's J map points along a path under tube, bulb and natural light, for "
        "intensity only (J) and intensity + disparity with disjunctive fusion (eq. 8, J/2 + J/2). The path is "
        "a closed loop derived from the world's free space (seeded by --seed) unless --path-box gives its box.",
    )
    p.add_argument("--world", default="lab")
    p.add_argument("--step", type=float, default=0.5, help="map grid step, metres")
    p.add_argument("--heading-step", type=float, default=10.0, help="map heading step, degrees")
    p.add_argument("--features", type=int, default=20, help="PCA features per channel")
    p.add_argument("--preprocess", default=DEFAULT_PREPROCESS, choices=PREPROCESS_METHODS,
                   help="intensity preprocessing of the main result (default: the product's)")
    p.add_argument("--compare", default="histeq,gradient",
                   help="other intensity preprocessings also reported under by_preprocess ('' = none)")
    p.add_argument("--lights", default="tube,bulb,natural", help="lighting setups of the test path")
    p.add_argument("--j", type=int, default=10,
                   help="J of the intensity-only model; the fused model takes J/2 + J/2 (default 10: 5 + 5)")
    p.add_argument("--spacing", type=float, default=0.3, help="distance between test poses along the path, m")
    p.add_argument("--path-box", metavar="XMIN,XMAX,YMIN,YMAX", default=None,
                   help="the test loop's box, metres (default: the longest free loop of the world's free space; "
                   "the lab's loop before it was derived: 0.35,8.65,1.15,3.75)")
    p.add_argument("--width", type=int, default=320, help="rendered image width")
    p.add_argument("--height", type=int, default=240, help="rendered image height")
    p.add_argument("--map-width", type=int, default=80, help="working (map) image width")
    p.add_argument("--map-height", type=int, default=60, help="working (map) image height")
    p.add_argument("--seed", type=int, default=0, help="seed of the survey's noise (test views: seed + 1000) and of the test loop's lattice")
    p.add_argument("--workers", type=int, default=None, help="rendering processes (default: all cores)")
    p.add_argument("--no-cache", action="store_true", help="do not read or write cached survey maps")
    p.add_argument("--plot", metavar="DIR", default=None, help="write fig5_sensor_model.png into DIR")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run)

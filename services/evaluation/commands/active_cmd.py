"""`lino-loc eval active`: the paper's active-localization experiment (section 6.1, Fig. 3, 4)."""

from __future__ import annotations

import argparse
import json
import logging
import math

from lino_loc.errors import LinoLocError
from lino_loc.interpolated_appearance import InterpolationConfig
from services.evaluation.active import plot, run
from services.evaluation.active_setup import (
    STRATEGIES,
    ActiveSetup,
    paper_active_vision,
    paper_sensor_model,
)
from services.evaluation.commands.localization_cmd import parse_channels
from services.evaluation.plotting import pyplot
from services.progress import Progress

log = logging.getLogger(__name__)


def _table(result: dict) -> str:
    lines = [
        f"Active localization in the simulated {result['setup']['world']}: {result['positions']} positions x "
        f"{result['runs']} runs, {result['map_images']} map images ({result['map_entries']} map entries with "
        f"virtual headings), {result['setup']['particles']} particles, "
        f"{result['setup']['n_actions']} pans"
    ]
    blocks = [("as mapped", result["strategies"], result["success_by_grid_distance"])]
    if "scene_changes" in result:
        blocks.append(("scene changes " + "+".join(result["scene_changes"]["names"]),
                       result["scene_changes"]["strategies"], result["scene_changes"]["success_by_grid_distance"]))
    for title, strategies, bands in blocks:
        n = len(next(iter(strategies.values()))["success"])
        lines.append(f"\n{title}: success % position / pose cell (mean error m) after k movements")
        lines.append(f"{'k':<10}" + "".join(f"{k:>14}" for k in range(n)))
        for s, r in strategies.items():
            lines.append(f"{s:<10}" + "".join(
                f"{100 * r['success'][k]:>5.0f}/{100 * r['success_pose'][k]:<3.0f}({r['mean_error_m'][k]:4.2f})"
                for k in range(n)))
        for band, b in bands.items():
            lines.append(f"  test positions {band} m from a map position ({b['positions']}): success % " + ", ".join(
                f"{s} " + "/".join(f"{100 * v:.0f}" for v in b[s][:4]) for s in strategies if s in b)
                + " after 0/1/2/3 movements")
    for name, diag in result.get("diagnostics", {}).items():
        lines.append(f"\ndiagnostics ({name}): " + ", ".join(
            f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in diag.items()))
    if result.get("entropy_eval_ms_median") is not None:
        lines.append(f"\nH(u) evaluation: median {result['entropy_eval_ms_median']:.1f} ms CPU")
    return "\n".join(lines)


def _run(args: argparse.Namespace) -> int:
    if args.plot:
        pyplot()  # fails now, in one line naming the extra, rather than after the run
    changes: tuple[str, ...] = ()
    if args.scene_changes:
        changes = tuple(c.strip() for c in args.scene_changes.split(",") if c.strip())
        if changes == ("all",):
            from drivers.sim.world import load_world

            changes = load_world(args.world).scene_change_names
    for name, value in (("--positions", args.positions), ("--runs", args.runs), ("--movements", args.movements),
                        ("--particles", args.particles), ("--actions", args.actions), ("--eval-particles", args.eval_particles),
                        ("--virtual-headings", args.virtual_headings)):
        if value < 1:
            raise LinoLocError(f"{name} must be at least 1 (got {value})")
    if not args.residual_scale > 0.0:
        raise LinoLocError(f"--residual-scale must be positive (got {args.residual_scale})")
    setup = ActiveSetup(world=args.world, positions=args.positions, runs=args.runs, movements=args.movements,
                        particles=args.particles, scene_changes=changes,
                        seed=args.seed, workers=args.workers, features=args.features,
                        sensor=paper_sensor_model(j=args.j), sensor_model=args.sensor_model,
                        interpolation=InterpolationConfig(residual_scale=args.residual_scale),
                        active=paper_active_vision(n_actions=args.actions, max_particles=args.eval_particles,
                                                   predicted_neighbours=args.predicted),
                        step=args.step, heading_step_deg=args.heading_step, inject=args.inject,
                        ideal=args.ideal, virtual_headings=args.virtual_headings,
                        virtual_step_deg=args.virtual_step, preprocess=args.preprocess,
                        filter={"global_proposal_fraction": args.global_proposal},
                        motion={"min_sigma_xy": args.floor_xy, "min_sigma_theta": math.radians(args.floor_theta)},
                        channels=parse_channels(args.channels))
    bar = Progress("active")
    result, extras = run(setup, progress=lambda label, d, n: bar.update(d, n, label=label))
    bar.close()
    if args.plot:
        for f in plot(result, extras, args.plot):
            log.info("wrote %s", f)
    print(json.dumps(result) if args.json else _table(result))
    return 0


def register_eval(eval_sub: argparse._SubParsersAction) -> None:
    p = eval_sub.add_parser(
        "active",
        help="Fig. 3: localization error and success against camera movements (entropy, random, sweep)",
        description="The paper's active-localization experiment in the simulated office: map every 75 cm "
        "and 15 deg, 5 features, J = 10, 150 particles, 22 pans, uniform initial belief, test positions "
        f"off the grid; strategies {', '.join(STRATEGIES)}.",
    )
    p.add_argument("--world", default="office")
    p.add_argument("--positions", type=int, default=20, help="test positions (default 20)")
    p.add_argument("--runs", type=int, default=10, help="runs per position (default 10)")
    p.add_argument("--movements", type=int, default=10, help="camera movements per run (default 10)")
    p.add_argument("--particles", type=int, default=150, help="particles of the filter")
    p.add_argument("--eval-particles", type=int, default=150, help="particles used to evaluate H(u)")
    p.add_argument("--predicted", choices=("all", "leave_one_out"), default="all",
                   help="sensor model of a predicted observation (see lino_loc.active_vision)")
    p.add_argument("--inject", type=float, default=0.0,
                   help="investigation: after each update replace this fraction of the particles by draws "
                   "from the image's sensor model (default 0: the filter as the service runs it)")
    p.add_argument("--global-proposal", type=float, default=0.5,
                   help="FilterConfig.global_proposal_fraction: share of the particles drawn from the first "
                   "image's sensor model (0: the plain APF from the uniform set)")
    p.add_argument("--floor-xy", type=float, default=0.01,
                   help="MotionModelConfig.min_sigma_xy: process-noise floor per update, metres")
    p.add_argument("--floor-theta", type=float, default=0.5,
                   help="MotionModelConfig.min_sigma_theta: process-noise floor per update, degrees")
    p.add_argument("--ideal", action="store_true",
                   help="also compute the sensor model's upper bound (dense-grid posterior, no particles) and "
                   "the map oracle (the map position whose stored views best match the views taken)")
    p.add_argument("--step", type=float, default=0.75, help="map grid step, metres")
    p.add_argument("--heading-step", type=float, default=15.0, help="map heading step, degrees")
    p.add_argument("--actions", type=int, default=22, help="candidate pan angles")
    p.add_argument("--virtual-headings", type=int, default=5,
                   help="views per map image, turned by multiples of --virtual-step (lino_loc.virtual_views); "
                   "1 = the paper's plain map (default 5)")
    p.add_argument("--virtual-step", type=float, default=3.0, help="degrees between virtual headings (default 3)")
    p.add_argument("--features", type=int, default=5)
    p.add_argument("--preprocess", choices=("none", "histeq", "gradient"), default="none",
                   help="image preprocessing before PCA (default none: section 6.1 names none)")
    p.add_argument("--j", type=int, default=10, help="nearest neighbours of the sensor model")
    p.add_argument("--sensor-model", choices=("nearest_neighbour", "interpolated"), default="nearest_neighbour",
                   help="p(y | x): the J nearest map entries (default, section 3) or the map's appearance "
                   "interpolated between survey poses (lino_loc.interpolated_appearance)")
    p.add_argument("--residual-scale", type=float, default=1.0,
                   help="interpolated sensor model: scale of the leave-one-out residuals (default 1)")
    p.add_argument("--scene-changes", default="",
                   help="also run with these scene changes of the world (comma-separated, or 'all')")
    p.add_argument("--channels", default="intensity",
                   help="the map's channels: intensity, or intensity,disparity (the filter fuses both, eq. 8; "
                   "the views are chosen with the intensity channel's predictions)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--plot", metavar="DIR", default=None, help="write Fig. 3 and Fig. 4 PNGs here")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run)

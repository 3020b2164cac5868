"""`lino-loc survey`: render a survey of a simulated world into a dataset folder.

    lino-loc survey --world office --step 0.75 --heading-step 15 --out DATASET
                    [--lighting tube|bulb|natural] [--scene-changes a,b]
                    [--width 320 --height 240] [--seed N] [--no-stereo] [--dense-depth]
                    [--overwrite] [--json]

Poses: every ``--step`` metres over the world's mapped area and every ``--heading-step``
DEGREES (defaults: the world file's ``survey`` grid, e.g. the floor's 0.5 m and 10 deg, the
lab's spacing, 116,964 views; else 0.75 m and 15 deg), skipping poses where the robot (radius ``--radius``) would touch furniture or
walls; the same poses under every lighting. With stereo (the default) every row has the
right image and the sparse disparity of the product's block matcher, as on the robot; the
renderer's exact dense depth instead only with ``--dense-depth``. See :mod:`drivers.sim.survey`.

With ``--robot`` the survey is made by the robot itself (the simulated one when none is
attached): :mod:`services.commands.robot_survey_cmd`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

from drivers.sim.renderer import CameraModel
from drivers.sim.survey import run_survey
from drivers.sim.world import load_world
from lino_loc.errors import LinoLocError
from services.commands.robot_survey_cmd import add_robot_arguments
from services.progress import Progress

#: Survey grid of a world whose file names none (``survey``): the office's of the paper.
DEFAULT_STEP_M = 0.75
DEFAULT_HEADING_STEP_DEG = 15.0


def _changes(text: str) -> tuple[str, ...]:
    return tuple(c.strip() for c in text.split(",") if c.strip())


def _run(args: argparse.Namespace) -> int:
    if args.robot:
        from services.commands.robot_survey_cmd import run_robot_survey

        if args.heading_step is None:
            args.heading_step = DEFAULT_HEADING_STEP_DEG

        return run_robot_survey(args)
    if args.width < 8 or args.height < 8:
        raise LinoLocError("--width and --height must be at least 8 pixels")
    world = load_world(args.world)
    grid = world.spec.survey
    if args.step is None:
        args.step = grid.step if grid is not None else DEFAULT_STEP_M
    if args.heading_step is None:
        args.heading_step = grid.heading_step_deg if grid is not None else DEFAULT_HEADING_STEP_DEG
    if args.step <= 0 or args.heading_step <= 0:
        raise LinoLocError("--step and --heading-step must be positive")
    camera = CameraModel(width=args.width, height=args.height)
    bar = Progress(f"survey {world.name}/{args.lighting}")
    try:
        result = run_survey(
            world, args.out, step=args.step, heading_step_rad=math.radians(args.heading_step),
            lighting=args.lighting, scene_changes=args.scene_changes, camera=camera, seed=args.seed,
            stereo=not args.no_stereo, overwrite=args.overwrite, radius=args.radius, progress=bar.update,
            dense_depth=args.dense_depth,
        )
    finally:
        bar.close()
    summary = {
        "dataset": str(result.out),
        "world": world.name,
        "rows": result.rows,
        "skipped_positions": result.skipped_positions,
        "condition": result.condition,
        "seconds": round(result.seconds, 3),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {result.out}: {result.rows} images ({result.condition}), "
              f"{result.skipped_positions} grid positions blocked, {result.seconds:.1f} s", file=sys.stderr)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "survey",
        help="survey a building into a dataset folder: rendered (simulated worlds) or with the robot (--robot)",
        description="Render the camera views on a grid of poses of a simulated world and write a "
                    "dataset folder (images, poses, condition; with stereo the right images and the "
                    "block matcher's sparse disparity; the renderer's dense depth instead with --dense-depth).",
    )
    p.add_argument("--world", default="office", help="world name (config/worlds/NAME.json) or path")
    p.add_argument("--step", type=float, default=None,
                   help=f"grid step in metres (default: the world file's survey grid, else {DEFAULT_STEP_M})")
    p.add_argument("--heading-step", type=float, default=None,
                   help="heading step in DEGREES (default: the world file's survey grid, else "
                        f"{DEFAULT_HEADING_STEP_DEG:g})")
    p.add_argument("--out", required=True, help="dataset folder to write")
    p.add_argument("--lighting", default="tube", help="lighting setup: tube (mapping), bulb, natural")
    p.add_argument("--scene-changes", type=_changes, default=(), help="comma-separated scene change sets")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--seed", type=int, default=0, help="sensor-noise seed")
    p.add_argument("--radius", type=float, default=0.25, help="robot radius for the collision check (m)")
    p.add_argument("--no-stereo", action="store_true",
                   help="do not render/store the right image (and so no disparity)")
    p.add_argument("--dense-depth", action="store_true",
                   help="store the renderer's exact dense depth instead of the matcher's sparse disparity "
                        "(no stereo camera gives it; a map's disparity channel built from it says source "
                        "dense-depth)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    p.add_argument("--json", action="store_true", help="print one JSON summary on stdout")
    add_robot_arguments(p)
    p.set_defaults(func=_run)

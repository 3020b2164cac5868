"""`lino-loc plot FILE [FILE ...] --out DIR [--json]`.

PNGs of a recording or a replay's output (:mod:`services.run_plots`): ``trajectory.png`` (the
estimate over the map's survey poses and, in simulation, the world's walls, against the truth
where the recording has it) and ``timeline.png`` (the error when there is truth, the state and
the quality over time). Several FILEs are the parts of one rotated recording, in order.

Exit status 2 with one line for a missing file, a file that is not MCAP, a recording without
a pose, DIR an existing file, or without the ``eval`` extra (matplotlib) or the ``viz`` extra.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lino_loc.errors import LinoLocError


def run_plot(args: argparse.Namespace) -> int:
    from services.evaluation.plotting import pyplot
    from services.recording.channels import require_viz

    require_viz("lino-loc plot")
    pyplot()
    from services.run_plots import plot_run

    files = [Path(f) for f in args.files]
    for f in files:
        if not f.is_file():
            raise LinoLocError(f"{f}: no such file")
    written = plot_run(files, Path(args.out))
    if args.json:
        print(json.dumps({"png": [str(p) for p in written]}))
    else:
        print("wrote " + ", ".join(str(p) for p in written))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plot", help="PNGs of a recording or a replay: trajectory over the map, error, state, quality",
        description="Draw a recording or a replay's output: DIR/trajectory.png (over the map's survey "
        "poses and the simulated world's walls, against the truth) and DIR/timeline.png (error, "
        "state, quality over time).")
    p.add_argument("files", nargs="+", metavar="FILE", help="the recording (its parts in order) or a replay's OUT.mcap")
    p.add_argument("--out", required=True, metavar="DIR", help="the folder for the PNGs (created)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=run_plot)

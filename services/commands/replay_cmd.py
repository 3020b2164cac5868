"""`lino-loc replay FILE [FILE ...] [--config F] [--seed S] [--out OUT] [--recompose] [--json]`.

Runs the Localizer on a recording's inputs as fast as it can
(:mod:`services.replay`): with the recorded configuration and seed it gives the
service's poses; ``--config`` and ``--seed`` try another setting on the same inputs. Several
FILEs are the parts of one rotated recording, in order. Writes OUT (MCAP, default
``FILE-replay.mcap`` next to the first FILE) and the TUM trajectory OUT with the suffix
``.tum`` (for evo), and prints one line: poses, the difference to the recorded poses, the speed
as a multiple of real time (``--json``: one JSON object).

Exit status 2 with one line for a missing file, a file that is not MCAP, a recording without
the camera or the Localizer's input channel, a bad configuration, or without the ``viz`` extra.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

from lino_loc.errors import LinoLocError


def run_replay(args: argparse.Namespace) -> int:
    from services.recording.channels import require_viz

    require_viz("lino-loc replay")
    from services.config import load_config
    from services.replay import replay

    files = [Path(f) for f in args.files]
    for f in files:
        if not f.is_file():
            raise LinoLocError(f"{f}: no such file")
    config = load_config(args.config) if args.config else None
    out = Path(args.out) if args.out else files[0].with_name(files[0].stem + "-replay.mcap")
    if out.suffix != ".mcap":
        raise LinoLocError(f"--out {args.out}: the file name must end in .mcap")
    if out.resolve() in {f.resolve() for f in files}:
        raise LinoLocError(f"--out {args.out}: would overwrite the recording")
    r = replay(files, config=config, seed=args.seed, out=out, recompose=args.recompose)
    summary = {k: v for k, v in asdict(r).items() if k != "poses"}
    summary.update(poses=len(r.poses), speed_x_realtime=round(r.speed, 2), out=str(out),
                   tum=str(out.with_suffix(".tum")))
    if args.json:
        print(json.dumps(summary))
    else:
        s = r.service
        vs = ("no recorded poses" if s is None else
              f"{s['identical']}/{s['service_poses']} recorded poses identical, position difference "
              f"median {s['median_m']:.3g} m, max {s['max_m']:.3g} m" if s["matched"] else
              "no recorded pose at a replayed stamp")
        print(f"{len(r.poses)} poses ({r.updates} frames, {r.predicts} dead-reckoning steps, "
              f"{r.errors} failed), seed {r.seed}, {r.speed:.1f}x real time; {vs}; wrote {out} "
              f"and {out.with_suffix('.tum')}" + (f"; {r.truncated}" if r.truncated else ""))
    if r.missing_frames or r.missing_inputs:
        print(f"lino-loc replay: warning: {r.missing_inputs} Localizer inputs and {r.missing_frames} "
              "frames missing from the recording (dropped by the recorder): poses differ from the "
              "service's after them", file=sys.stderr)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="run the Localizer on a recording (lino-loc run --record) as fast as it can",
        description="Replay a recording's inputs through the Localizer: the service's poses with "
        "its configuration and seed, or another configuration on the same inputs. Writes OUT "
        "(MCAP) and, beside it, OUT.tum (the TUM trajectory, for evo).",
    )
    p.add_argument("files", nargs="+", metavar="FILE", help="the recording (its parts in order)")
    p.add_argument("--config", metavar="F", help="replay with this configuration (default: the recorded one)")
    p.add_argument("--seed", type=int, metavar="S", help="the filter's seed (default: the recorded one)")
    p.add_argument("--out", metavar="OUT.mcap",
                   help="output MCAP (default FILE-replay.mcap); the TUM trajectory beside it, OUT.tum")
    p.add_argument("--recompose", action="store_true",
                   help="compose the odometry actions and pans again from the raw streams")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=run_replay)

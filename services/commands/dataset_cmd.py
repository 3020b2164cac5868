"""`lino-loc dataset ...`: import and check dataset folders (the format: :mod:`lino_loc.dataset`).

- ``lino-loc dataset check DATASET [--json]``: the structure (:meth:`Dataset.open`), then the
  content (:func:`lino_loc.dataset.dataset_problems`: plausible poses and extent, every file
  decoded at the camera's size). Every problem is one line on stderr naming the file, the
  line of ``poses.csv`` and the field; exit 2 if any. The summary goes to stdout (with
  ``ok``, and with ``--json`` the list ``problems`` too).
- ``lino-loc dataset import-tum SEQUENCE --out DATASET``: the converted folder passes the
  same checks, or the command fails with the first problem.
- ``lino-loc dataset translate DATASET --out DATASET2 [--refinement 3] [--step S] [--workers N]``: every row
  also seen from the lattice every ``step / refinement`` inside its survey cell, by virtual
  translations with its own stereo disparity (:mod:`lino_loc.translated_dataset`); an
  interrupted run continues when started again. ``lino-loc map build DATASET2`` makes the map.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from lino_loc.dataset import Dataset, dataset_problems, require_valid
from lino_loc.translated_dataset import translate_dataset
from lino_loc.tum_import import TUM_INTRINSICS, import_tum
from services.progress import Progress


def _import_tum(args: argparse.Namespace) -> int:
    report = import_tum(args.sequence, args.out, camera=args.camera, overwrite=args.overwrite)
    bar = Progress("dataset check")
    try:  # the result must pass the same validation as any dataset
        require_valid(Dataset.open(args.out), progress=bar.update)
    finally:
        bar.close()
    print(
        f"wrote {args.out}: {report.frames} frames "
        f"(skipped {report.skipped_no_groundtruth} outside the ground truth, "
        f"{report.skipped_no_depth} without depth)",
        file=sys.stderr,
    )
    return 0


def _check(args: argparse.Namespace) -> int:
    ds = Dataset.open(args.dataset)
    bar = Progress("dataset check")
    try:
        problems = dataset_problems(ds, progress=bar.update)
    finally:
        bar.close()
    for line in problems:
        print(line, file=sys.stderr)
    summary = {
        "ok": not problems,
        "name": ds.meta.name,
        "frames": len(ds),
        "conditions": sorted({c for c in ds.conditions if c}),
        "camera": ds.meta.camera.model_dump(),
        "depth": ds.has_depth,
        "disparity": ds.has_disparity,
    }
    if args.json:
        summary["problems"] = problems
    print(json.dumps(summary, indent=None if args.json else 2))
    return 2 if problems else 0


def _translate(args: argparse.Namespace) -> int:
    bar = Progress("dataset translate")
    try:
        report = translate_dataset(Dataset.open(args.dataset), args.out, args.refinement, step=args.step,
                                   overwrite=args.overwrite, progress=bar.update, workers=args.workers)
    finally:
        bar.close()
    summary = {"out": str(args.out), "rows_in": report.rows_in, "rows_out": report.rows_out,
               "fallbacks": report.fallbacks, "step": report.step, "refinement": report.refinement,
               "resumed": report.resumed}
    print(json.dumps(summary, indent=None if args.json else 2))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("dataset", help="import or check a dataset folder")
    dsub = parser.add_subparsers(dest="dataset_command", metavar="ACTION", parser_class=type(parser))
    dsub.required = True
    p = dsub.add_parser("import-tum", help="convert a TUM RGB-D sequence into a dataset folder")
    p.add_argument("sequence", help="TUM sequence folder (groundtruth.txt, associations.txt or rgb.txt/depth.txt)")
    p.add_argument("--out", required=True, help="dataset folder to write")
    p.add_argument("--camera", default="freiburg1", choices=sorted(TUM_INTRINSICS), help="intrinsics to record")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    p.set_defaults(func=_import_tum)
    p = dsub.add_parser("check", help="validate a dataset folder and summarise it")
    p.add_argument("dataset")
    p.add_argument("--json", action="store_true", help="one JSON object on one line")
    p.set_defaults(func=_check)
    p = dsub.add_parser("translate", help="add virtual translations between the survey positions (both channels)")
    p.add_argument("dataset", help="survey dataset folder with stereo disparity")
    p.add_argument("--out", required=True, help="dataset folder to write (an interrupted run there continues)")
    p.add_argument("--refinement", type=int, default=3,
                   help="odd m: views every step / m inside each survey cell (default %(default)s)")
    p.add_argument("--step", type=float, default=None,
                   help="the survey's spacing, metres (default: the median distance between neighbouring positions)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="processes warping the rows (default: the CPUs, %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    p.add_argument("--json", action="store_true", help="one JSON object on one line")
    p.set_defaults(func=_translate)

"""`lino-loc dataset ...`: import and check dataset folders (the format: :mod:`lino_loc.dataset`)."""

from __future__ import annotations

import argparse
import json
import sys

from lino_loc.dataset import Dataset
from lino_loc.tum_import import TUM_INTRINSICS, import_tum


def _import_tum(args: argparse.Namespace) -> int:
    report = import_tum(args.sequence, args.out, camera=args.camera, overwrite=args.overwrite)
    Dataset.open(args.out)  # the result must pass the same validation as any dataset
    print(
        f"wrote {args.out}: {report.frames} frames "
        f"(skipped {report.skipped_no_groundtruth} outside the ground truth, "
        f"{report.skipped_no_depth} without depth)",
        file=sys.stderr,
    )
    return 0


def _check(args: argparse.Namespace) -> int:
    ds = Dataset.open(args.dataset)
    summary = {
        "name": ds.meta.name,
        "frames": len(ds),
        "conditions": sorted({c for c in ds.conditions if c}),
        "camera": ds.meta.camera.model_dump(),
        "depth": ds.has_depth,
        "disparity": ds.has_disparity,
    }
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

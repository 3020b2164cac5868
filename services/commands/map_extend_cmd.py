"""`lino-loc map extend`: add a survey session to a map without a rebuild.

    lino-loc map extend MAP DATASET [DATASET ...] --out MAP2 [--condition C] [--name NAME]
                        [--refit auto|always|never] [--refit-ratio R] [--json]

The datasets' images (those of ``--condition`` if given; several datasets, e.g. the parts
the daemon's ``[map_refresh]`` wrote, make one session) become a new session of the map
(``lino_loc.map_extend``): projected onto the map's basis, or with ``auto`` (the default)
the basis refitted incrementally first when the images are poorly represented by it (their
mean residual fraction above ``--refit-ratio`` times the map's own). The dataset is checked
as ``map build`` checks it. ``lino-loc map info MAP2`` lists the sessions. A bad map,
dataset or option is one line on stderr, exit 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from lino_loc.appearance_map import AppearanceMap, map_file_columns
from lino_loc.dataset import Dataset, require_valid
from lino_loc.errors import LinoLocError
from lino_loc.map_extend import DEFAULT_REFIT_RATIO, extend_map
from services.progress import Progress


def _extend(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    out = Path(args.out)
    if out.resolve() == Path(args.map).resolve():
        raise LinoLocError(f"{out}: --out must differ from the map it extends")
    amap = AppearanceMap.load(args.map)
    sets = [Dataset.open(d) for d in args.dataset]
    for ds in sets:
        bar = Progress("dataset check")
        try:
            require_valid(ds, progress=bar.update, columns=map_file_columns(ds, tuple(amap.channels)))
        finally:
            bar.close()
    bar = Progress("map extend")
    try:
        new, rep = extend_map(amap, sets, condition=args.condition, name=args.name, refit=args.refit,
                              refit_ratio=args.refit_ratio, progress=bar.update)
    finally:
        bar.close()
    path = new.save(out)
    elapsed = time.perf_counter() - t0
    summary = {
        "map": str(path),
        "session": rep.session.name,
        "basis": rep.session.basis,
        "entries_before": rep.entries_before,
        "entries": rep.entries_after,
        "residual_before": round(rep.residual_before, 5),
        "residual_after": round(rep.residual_after, 5),
        "map_residual": None if rep.map_residual != rep.map_residual else round(rep.map_residual, 5),
        "sessions": [s.name for s in new.session_list()],
        "seconds": round(elapsed, 3),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        how = "basis refitted incrementally" if rep.refitted else "projected onto the map's basis"
        print(f"wrote {path}: session {rep.session.name!r} ({rep.entries_after - rep.entries_before} entries, {how}; "
              f"residual {100 * rep.residual_before:.1f} % -> {100 * rep.residual_after:.1f} %, the map's own "
              f"{100 * rep.map_residual:.1f} %), {rep.entries_after} entries in {len(summary['sessions'])} sessions, "
              f"{elapsed:.1f} s", file=sys.stderr)
    return 0


def _ratio(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = 0.0
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def register(msub: argparse._SubParsersAction) -> None:
    """Add ``extend`` to the ``lino-loc map`` actions."""
    p = msub.add_parser("extend", help="add a survey session (another light, ...) to a map without a rebuild")
    p.add_argument("map", help="map file to extend (not modified)")
    p.add_argument("dataset", nargs="+", help="dataset folder(s) of the new session")
    p.add_argument("--out", required=True, help="map file to write (.npz)")
    p.add_argument("--condition", default=None, help="use only the dataset's rows of this condition")
    p.add_argument("--name", default=None, help="session name (default: the condition, else the dataset's name)")
    p.add_argument("--refit", choices=("auto", "always", "never"), default="auto",
                   help="refit the basis incrementally: auto (when the new images are poorly represented), "
                        "always, never (default %(default)s)")
    p.add_argument("--refit-ratio", type=_ratio, default=DEFAULT_REFIT_RATIO, metavar="R",
                   help="auto refits when the new images' residual exceeds R times the map's own "
                        "(default %(default)s)")
    p.add_argument("--json", action="store_true", help="print one JSON summary object on stdout")
    p.set_defaults(func=_extend)

"""`lino-loc map check`: a map's quality report before deployment.

    lino-loc map check MAP [--dataset DATASET] [--out DIR] [--cell M] [--json]

Prints the coverage (cells x heading sectors, with the holes), the ambiguity (share of map
entries whose nearest view at another position in feature space is more than 1 m away), the
leave-out error of the dataset's images when ``--dataset`` is given, then one line per
finding (``lino_loc.map_quality``). With ``--out DIR`` it writes ``DIR/map_check.json`` and
``DIR/map_check.png`` (the plan coloured by these; without matplotlib, the ``eval`` extra,
one line says so and the JSON is still written). Exit status 0, also with findings (they
are advice); 2 for a bad map, dataset or folder (one line).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lino_loc.appearance_map import AppearanceMap
from lino_loc.dataset import Dataset
from lino_loc.errors import LinoLocError
from lino_loc.map_quality import MapQuality, QualityThresholds, check_map
from services.map_check_plot import matplotlib_missing, plot_quality
from services.progress import Progress


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = 0.0
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number of metres, got {text!r}")
    return v


def summary_lines(q: MapQuality) -> list[str]:
    """The report as text lines (summary, then one line per finding)."""
    lines = [
        f"entries    {q.entries} at {q.positions} positions; cells of {q.cell_m:.2f} m, {q.occupied_cells} with views",
        f"coverage   {100 * q.coverage_fraction:.1f} % of (cell, heading sector) pairs faced "
        f"({len(q.sectors)} sectors); {q.heading_holes} heading holes, {q.position_holes} enclosed empty cells",
        f"ambiguity  {100 * q.ambiguous_fraction:.1f} % of entries: nearest view at another position in feature "
        f"space more than {q.thresholds.ambiguous_m:g} m away",
    ]
    if q.leave_out is not None:
        lo = q.leave_out
        lines.append(f"leave-out  {int(lo['rows'])} dataset images: error mean {lo['mean_m']:.2f} m, median "
                     f"{lo['median_m']:.2f} m, {100 * lo['wrong_1m_fraction']:.1f} % over 1 m "
                     f"(floor {lo['floor_mean_m']:.2f} m)")
    lines.append(f"findings   {len(q.findings)}" + (":" if q.findings else " (nothing to act on)"))
    lines += [f"- {f.message}" for f in q.findings]
    return lines


def _check(args: argparse.Namespace) -> int:
    amap = AppearanceMap.load(args.map)
    ds = Dataset.open(args.dataset) if args.dataset else None
    out = Path(args.out) if args.out else None
    if out is not None:
        if out.exists() and not out.is_dir():
            raise LinoLocError(f"{out}: exists and is not a folder")
        out.mkdir(parents=True, exist_ok=True)
    bar = Progress("leave-out") if ds is not None else None
    try:
        q = check_map(amap, ds, QualityThresholds(cell_m=args.cell), progress=bar.update if bar else None)
    finally:
        if bar:
            bar.close()
    if out is not None:
        (out / "map_check.json").write_text(q.model_dump_json(indent=1) + "\n", encoding="utf-8")
        if matplotlib_missing():
            print("map check: no PNG: matplotlib is missing (install the 'eval' extra: pip install 'lino-loc[eval]')",
                  file=sys.stderr)
        else:
            plot_quality(q, out / "map_check.png", title=f"map check: {args.map}")
    if args.json:
        print(q.model_dump_json())
    else:
        print("\n".join(summary_lines(q)))
    return 0


def register(msub: argparse._SubParsersAction) -> None:
    """Add ``check`` to the ``lino-loc map`` actions."""
    p = msub.add_parser("check", help="a map's quality report: coverage, ambiguity, leave-out error, findings")
    p.add_argument("map", help="map file")
    p.add_argument("--dataset", default=None, help="dataset folder whose images are held out against the map")
    p.add_argument("--out", default=None, metavar="DIR", help="write map_check.json and map_check.png here")
    p.add_argument("--cell", type=_positive, default=None, metavar="M",
                   help="cell size in metres (default: the map's position spacing)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.set_defaults(func=_check)

"""`lino-loc map build` and `lino-loc map info`: appearance maps (eq. 1).

    lino-loc map build DATASET --out MAP [--features 20] [--preprocess none|histeq|gradient]
                       [--size 80x60] [--condition tube] [--method randomized|gram|svd]
                       [--channels intensity[,disparity]]
                       [--virtual-headings N [--virtual-step DEG]] [--json]
                       [--engine local|dask [--scheduler ADDRESS | --workers 2] [--chunk-rows N]]
                       [--memory-budget MB] [--scratch DIR]
    lino-loc map info MAP [--json]

A malformed dataset folder or a bad map file is a user error: one line on stderr, exit 2.
``map build`` refuses what ``lino-loc dataset check`` refuses (the same
:func:`lino_loc.dataset.require_valid`, run before any PCA; with ``--engine dask`` the images
are checked by the workers as they decode them) in the files it reads
(:func:`lino_loc.appearance_map.map_file_columns`: the images, and the disparity or depth
column for the disparity channel; not the right images): the first problem, and how many
more there are.

``--engine dask`` runs the intensity channel's loading, preprocessing, PCA and projection on
a Dask cluster (:mod:`lino_loc.pca_dask`): a LocalCluster of ``--workers`` processes, or the
running cluster at ``--scheduler`` (:mod:`services.dask_cluster`); needs the ``cluster``
extra. The local engine streams a data matrix larger than ``--memory-budget`` MiB through a
scratch file in ``--scratch`` (default: the output map's folder). The disparity channel's EM
fits as many views as its working set allows within the same budget, chosen at random, and
gives every view its features (:func:`lino_loc.appearance_map.disparity_fit_rows`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from lino_loc.appearance_map import (
    DEFAULT_FEATURES,
    DEFAULT_MEMORY_BUDGET_MB,
    DEFAULT_SIZE,
    ENGINES,
    AppearanceMap,
    build_map,
    map_file_columns,
)
from lino_loc.dataset import Dataset, require_valid
from lino_loc.errors import LinoLocError
from lino_loc.pca import PCA_METHODS
from lino_loc.preprocessing import PREPROCESS_METHODS
from lino_loc.virtual_views import offsets
from services.commands import map_check_cmd, map_extend_cmd
from services.progress import Progress

log = logging.getLogger("lino_loc.map")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 80x60, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return w, h


def _channels(text: str) -> tuple[str, ...]:
    chans = tuple(c.strip() for c in text.split(",") if c.strip())
    if "intensity" not in chans or any(c not in ("intensity", "disparity") for c in chans):
        raise argparse.ArgumentTypeError(f"channels: 'intensity' or 'intensity,disparity', got {text!r}")
    return chans


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return v


def _build(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    if args.scheduler is not None and args.engine != "dask":
        raise LinoLocError("--scheduler needs --engine dask")
    ds = Dataset.open(args.dataset)
    virtual = None if args.virtual_headings == 1 else offsets(math.radians(args.virtual_step), args.virtual_headings)
    # With the dask engine the workers check every image as they decode it (the first bad file
    # stops the build with its name): a local pass decoding every image first would cost as
    # much as the local build itself. The poses, and the disparity channel's files (read
    # here), are checked here either way.
    columns = map_file_columns(ds, args.channels)
    if args.engine == "dask":
        columns = tuple(c for c in columns if c != "image")
    bar = Progress("dataset check")
    try:
        require_valid(ds, progress=bar.update, columns=columns)
    finally:
        bar.close()
    if args.engine == "dask":
        from services.dask_cluster import dask_client

        cluster = dask_client(args.scheduler, workers=args.workers)
    else:
        cluster = contextlib.nullcontext()
    bar = Progress("map build")
    try:
        with cluster:
            amap = _build_map(ds, args, virtual, bar)
    finally:
        bar.close()
    return _finish(amap, args, t0)


def _scratch(args: argparse.Namespace) -> Path | None:
    """--scratch, else the output map's folder if it exists (None: the system's temporary folder)."""
    if args.scratch is not None:
        return Path(args.scratch)
    folder = Path(args.out).resolve().parent
    return folder if folder.is_dir() else None


def _build_map(ds: Dataset, args: argparse.Namespace, virtual: Sequence[float] | None, bar: Progress) -> AppearanceMap:
    return build_map(
        ds,
        n_features=args.features,
        preprocess=args.preprocess,
        size=args.size,
        condition=args.condition,
        progress=bar.update,
        method=args.method,
        channels=args.channels,
        virtual_offsets=virtual,
        disparity_features=args.disparity_features,
        engine=args.engine,
        memory_budget_mb=args.memory_budget,
        scratch_dir=_scratch(args),
        chunk_rows=args.chunk_rows,
    )


def _finish(amap: AppearanceMap, args: argparse.Namespace, t0: float) -> int:
    path = amap.save(args.out)
    elapsed = time.perf_counter() - t0
    summary = {
        "map": str(path),
        "images": len(amap) // args.virtual_headings,
        "entries": len(amap),
        "features": args.features,
        "preprocess": args.preprocess,
        "size": list(args.size),
        "channels": sorted(amap.channels),
        "seconds": round(elapsed, 3),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"wrote {path}: {len(amap)} entries ({len(amap) // args.virtual_headings} images x "
            f"{args.virtual_headings} headings), {args.features} features, "
            f"{args.preprocess}, {args.size[0]}x{args.size[1]}, channels "
            f"{','.join(sorted(amap.channels))} in {elapsed:.1f} s",
            file=sys.stderr,
        )
    return 0


def _entries(info: dict) -> str:
    """``images N,`` or, for a map with virtual headings, ``entries N (M images x V headings),``."""
    virt = info["channels"].get("intensity", {}).get("params", {}).get("virtual_offsets_deg")
    if not virt:
        return f"images     {info['n_images']},"
    v = len(str(virt).split(","))
    return f"entries    {info['n_images']} ({info['n_images'] // v} images x {v} headings),"


def _em_summary(params: dict) -> str:
    """``, source stereo-matcher, 25.8% valid, EM 31 iterations (converged)`` for a channel
    fitted by EM-PCA; the parts a map does not record (older maps) are left out."""
    parts = []
    if params.get("source"):
        parts.append(f"source {params['source']}")
    if isinstance(params.get("valid_fraction"), int | float):
        parts.append(f"{100 * params['valid_fraction']:.1f}% valid")
    if isinstance(params.get("em_iterations"), int) and params["em_iterations"] > 0:
        state = "converged" if params.get("em_converged") else "NOT converged"
        parts.append(f"EM {params['em_iterations']} iterations ({state})")
    return "".join(f", {p}" for p in parts)


def _info(args: argparse.Namespace) -> int:
    info = AppearanceMap.load(args.map).info()
    if args.json:
        print(json.dumps(info))
        return 0
    cam = info["camera"]
    lines = [
        f"map        {info['file']}",
        f"format     lino-loc-map v{info['format_version']} (lino-loc {info['lino_loc_version']}), created {info['created']}",
        f"dataset    {info['name']} ({info['source']})" + (f", condition {info['condition']}" if info["condition"] else ""),
        f"{_entries(info)} x {info['extent']['x'][0]:.2f}..{info['extent']['x'][1]:.2f} m, "
        f"y {info['extent']['y'][0]:.2f}..{info['extent']['y'][1]:.2f} m",
        f"camera     {cam['width']}x{cam['height']} fx {cam['fx']:.1f} fy {cam['fy']:.1f}"
        + (f" baseline {cam['baseline_m']} m" if cam.get("baseline_m") else ""),
    ]
    for name, ch in info["channels"].items():
        virt = ch["params"].get("virtual_offsets_deg")
        if virt:
            lines.append(f"virtual    {name}: every image also turned by {virt} deg "
                         f"({ch['params'].get('margin')} columns cropped each side)")
        frac = f", {100 * ch['variance_fraction']:.1f}% of the variance" if "variance_fraction" in ch else ""
        lines.append(
            f"channel    {name}: {ch['n_features']} features, preprocess {ch['preprocess']}, "
            f"{ch['size'][0]}x{ch['size'][1]}, {ch['method']}{frac}{_em_summary(ch['params'])}"
        )
    sessions = info.get("sessions", [])
    if len(sessions) > 1:
        for sess in sessions:
            lines.append(f"session    {sess['name']}: entries {sess['first_entry']}..{sess['first_entry'] + sess['n_entries'] - 1}"
                         f" ({sess['n_entries']}), condition {sess['condition'] or '-'}, {sess['basis']}"
                         + (f", added {sess['added']}" if sess.get("added") else ""))
    lines.append(f"sha256     {info['sha256']}")
    print("\n".join(lines))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("map", help="build or inspect an appearance map")
    msub = parser.add_subparsers(dest="map_command", metavar="ACTION", parser_class=type(parser))
    msub.required = True

    p = msub.add_parser("build", help="build an appearance map file from a dataset folder")
    p.add_argument("dataset", help="dataset folder (made by lino-loc survey or lino-loc dataset import)")
    p.add_argument("--out", required=True, help="map file to write (.npz)")
    p.add_argument("--features", type=int, default=DEFAULT_FEATURES, help="PCA features per image (default %(default)s)")
    p.add_argument("--disparity-features", type=_positive_int, default=None, metavar="N",
                   help="the disparity channel's features (default: --features; its EM costs grow with the square)")
    p.add_argument("--preprocess", choices=PREPROCESS_METHODS, default="none", help="image preprocessing (default %(default)s)")
    p.add_argument(
        "--size", type=_size, default=DEFAULT_SIZE, metavar="WxH",
        help=f"working image size after area averaging (default {DEFAULT_SIZE[0]}x{DEFAULT_SIZE[1]})",
    )
    p.add_argument("--condition", default=None, help="use only the rows of this condition (e.g. tube)")
    p.add_argument("--method", choices=PCA_METHODS, default="randomized", help="PCA algorithm (default %(default)s)")
    p.add_argument(
        "--channels", type=_channels, default=("intensity",), metavar="LIST",
        help="intensity or intensity,disparity (default intensity)",
    )
    p.add_argument(
        "--virtual-headings", type=_positive_int, default=1, metavar="N",
        help="map entries per image: the image turned by N headings --virtual-step apart, centred on the "
        "image's own (lino_loc.virtual_views; 5 with a 15 deg survey gives a map every 3 deg). Default 1: "
        "the images alone",
    )
    p.add_argument("--virtual-step", type=float, default=3.0, metavar="DEG",
                   help="degrees between virtual headings (default %(default)s)")
    p.add_argument("--engine", choices=ENGINES, default="local",
                   help="local (this process) or dask (a Dask cluster: needs lino-loc[cluster]); default %(default)s")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="with --engine dask: a running Dask scheduler (e.g. tcp://10.0.0.5:8786); default a LocalCluster")
    p.add_argument("--workers", type=_positive_int, default=2, metavar="N",
                   help="with --engine dask and no --scheduler: the LocalCluster's worker processes (default %(default)s)")
    p.add_argument("--chunk-rows", type=_positive_int, default=None, metavar="N",
                   help="images per Dask task, or rows per chunk when the local build streams (default: 64 MiB of rows)")
    p.add_argument("--memory-budget", type=float, default=DEFAULT_MEMORY_BUDGET_MB, metavar="MB",
                   help="local engine: a larger data matrix (images x pixels float32, MiB) is streamed from a "
                   "scratch file in chunks; the disparity EM is fitted on a random sample of the views that fits "
                   "it (default %(default)g)")
    p.add_argument("--scratch", default=None, metavar="DIR",
                   help="folder of the streamed build's scratch file (default: the --out map's folder)")
    p.add_argument("--json", action="store_true", help="print one JSON summary object on stdout")
    p.set_defaults(func=_build)

    p = msub.add_parser("info", help="print what a map file holds")
    p.add_argument("map", help="map file")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=_info)

    map_check_cmd.register(msub)
    map_extend_cmd.register(msub)

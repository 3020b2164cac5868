"""`lino-loc eval stereo LEFT RIGHT --truth GT`: the product's stereo matcher against ground truth.

Computes the sparse disparity map of a rectified pair with the product's block-matching
settings (``lino_loc.disparity.StereoConfig`` defaults; ``--max-disparity`` only widens or
narrows ``num_disparities``) and reports, against the ground truth:

- ``density``: valid pixels / pixels with known ground truth (``density_all``: / all pixels);
- ``bad1``, ``bad2``: share of the valid pixels with known ground truth off by > 1 / > 2 px;
- ``rmse_px``: RMS error over those pixels, pixels.

``--json`` prints exactly one JSON object on stdout. Bad files exit with status 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time

import numpy as np

from lino_loc.disparity import StereoConfig, compute_disparity
from lino_loc.errors import LinoLocError
from lino_loc.stereo_metrics import load_disparity_truth, load_grey, stereo_metrics

log = logging.getLogger("lino_loc.eval.stereo")

DENSITY_DEFINITION = "valid disparity pixels / pixels with known ground truth"


def register_eval(eval_sub: argparse._SubParsersAction) -> None:
    """Add ``stereo`` to the ``lino-loc eval`` sub-command group."""
    p = eval_sub.add_parser(
        "stereo",
        help="density and bad-pixel rates of the stereo matcher against ground truth",
        description=__doc__.split("\n\n")[1] if __doc__ else None,
    )
    p.add_argument("left", metavar="LEFT", help="rectified left image (8-bit)")
    p.add_argument("right", metavar="RIGHT", help="rectified right image (8-bit)")
    p.add_argument(
        "--truth",
        required=True,
        metavar="GT",
        help="ground-truth disparity of the left image: .npz/.npy (float, non-finite = unknown) "
        "or PNG (value = disparity in pixels, 0 = unknown)",
    )
    p.add_argument(
        "--max-disparity",
        type=float,
        default=None,
        metavar="N",
        help="largest disparity to search, pixels (sets num_disparities; default: the product's)",
    )
    p.add_argument(
        "--png-scale",
        type=float,
        default=1.0,
        metavar="S",
        help="PNG ground truth holds disparity x S (default 1)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=run_stereo)


def evaluate_stereo(
    left: str, right: str, truth: str, max_disparity: float | None = None, png_scale: float = 1.0
) -> dict:
    """Run the matcher on a pair and return the report (the JSON object of the command)."""
    lim = load_grey(left, "left image")
    rim = load_grey(right, "right image")
    if lim.shape != rim.shape:
        raise LinoLocError(
            f"{right}: size {rim.shape[::-1]} differs from the left image {lim.shape[::-1]}"
        )
    gt = load_disparity_truth(truth, png_scale=png_scale)
    if gt.shape != lim.shape:
        raise LinoLocError(
            f"{truth}: ground truth size {gt.shape[::-1]} differs from the images {lim.shape[::-1]}"
        )
    config = StereoConfig()
    if max_disparity is not None:
        config = config.covering(max_disparity)
    gt_max = float(np.nanmax(gt)) if np.isfinite(gt).any() else math.nan
    if gt_max > config.max_disparity:
        log.warning(
            "ground truth reaches %.1f px but the search stops at %d px: use --max-disparity",
            gt_max,
            config.max_disparity,
        )
    t0 = time.perf_counter()
    disp = compute_disparity(lim, rim, config)
    ms = 1e3 * (time.perf_counter() - t0)
    m = stereo_metrics(disp, gt)
    report = {
        "density": m.density,
        "bad1": m.bad1,
        "bad2": m.bad2,
        "rmse_px": m.rmse_px,
        "density_all": m.density_all,
        "density_definition": DENSITY_DEFINITION,
        "bad_definition": "share of valid pixels with known ground truth off by more than 1 (bad1) or 2 (bad2) px",
        "n_pixels": m.n_pixels,
        "n_known": m.n_known,
        "n_valid": m.n_valid,
        "n_evaluated": m.n_evaluated,
        "truth_max_disparity": None if math.isnan(gt_max) else gt_max,
        "image_size": [int(lim.shape[1]), int(lim.shape[0])],
        "matcher_ms": round(ms, 2),
        "config": config.model_dump(),
        "left": str(left),
        "right": str(right),
        "truth": str(truth),
    }
    return report


def run_stereo(args: argparse.Namespace) -> int:
    report = evaluate_stereo(
        args.left, args.right, args.truth, args.max_disparity, getattr(args, "png_scale", 1.0)
    )
    if args.json:
        print(json.dumps(report))
        return 0

    def fmt(v: float | None, spec: str) -> str:
        return "n/a" if v is None else format(v, spec)

    c = report["config"]
    print(
        f"stereo matcher on {report['image_size'][0]}x{report['image_size'][1]}: "
        f"StereoBM block {c['block_size']}, disparities {c['min_disparity']}..{c['min_disparity'] + c['num_disparities'] - 1}, "
        f"{report['matcher_ms']:.1f} ms"
    )
    print(
        f"  density  {fmt(report['density'], '.3f')}   ({DENSITY_DEFINITION}; of all pixels {report['density_all']:.3f})"
    )
    print(f"  bad1     {fmt(report['bad1'], '.3f')}   (valid pixels off by > 1 px)")
    print(f"  bad2     {fmt(report['bad2'], '.3f')}   (valid pixels off by > 2 px)")
    print(f"  rmse_px  {fmt(report['rmse_px'], '.3f')}")
    return 0

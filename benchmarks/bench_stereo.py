"""What the host's stereo matching costs per frame, and what each matcher delivers.

    python benchmarks/bench_stereo.py [--world office] [--lighting tube] [--frames 40] [--repeats 5]

The simulated camera (drivers/sim/camera.py) and the evaluations compute the disparity of
every 320 x 240 pair on the host with :func:`lino_loc.disparity.compute_disparity`; the map's
disparity channel uses it at 80 x 60. This compares, on ``frames`` rendered pairs of the
world's survey grid (seeded), the matchers of ``StereoConfig``:

- ``bm``: StereoBM at 320 x 240, the product's default;
- ``bm/2``: StereoBM on the pair area-averaged to 160 x 120 (32 disparities, the same depth
  range);
- ``sgbm`` and ``sgbm/2``: semi-global matching at the same two sizes.

Per matcher: the median time of one ``compute_disparity`` call (the configurations
interleaved frame by frame, ``repeats`` passes, one thread), the density (valid fraction at
the matched size, and at 80 x 60 after :func:`lino_loc.disparity.downsample_sparse` with the
map's ``min_valid_fraction`` 0.25), and the error at 80 x 60 against the renderer's exact
disparity (``fx * baseline / Z`` area-averaged to 80 x 60): median absolute error and the
share of cells more than 1 px (320-pixel units) off. One JSON object with the machine.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from drivers.sim.renderer import CameraModel, Renderer  # noqa: E402
from drivers.sim.world import grid_poses, load_world  # noqa: E402
from lino_loc.disparity import STEREO_PRESETS as MATCHERS  # noqa: E402
from lino_loc.disparity import compute_disparity, downsample_sparse  # noqa: E402

SIZE = (80, 60)
MIN_VALID = 0.25


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="office")
    ap.add_argument("--lighting", default="tube")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    world = load_world(args.world)
    cam = CameraModel(width=320, height=240)
    fx = cam.intrinsics()[0]
    r = Renderer(world, camera=cam, lighting=args.lighting)
    poses = grid_poses(world, 0.5, math.radians(30))
    sel = poses[np.random.default_rng(0).permutation(len(poses))[: args.frames]]
    views = [r.render(*p, stereo=True, rng=np.random.default_rng((0, k))) for k, p in enumerate(sel)]
    truths = [downsample_sparse((fx * cam.baseline_m / v.depth).astype(np.float32), SIZE, 0.5) for v in views]
    times: dict[str, list[float]] = {m: [] for m in MATCHERS}
    for _ in range(args.repeats):
        for v in views:
            for name, cfg in MATCHERS.items():
                t = time.perf_counter()
                compute_disparity(v.left, v.right, cfg)
                times[name].append(time.perf_counter() - t)
    out: dict[str, object] = {}
    for name, cfg in MATCHERS.items():
        dens, dens_small, err, bad = [], [], [], []
        for v, truth in zip(views, truths, strict=True):
            d = compute_disparity(v.left, v.right, cfg)
            small = downsample_sparse(d, SIZE, MIN_VALID)
            dens.append(float(np.isfinite(d).mean()))
            dens_small.append(float(np.isfinite(small).mean()))
            ok = np.isfinite(small) & np.isfinite(truth)
            e = np.abs(small[ok] - truth[ok])
            err.extend(e.tolist())
            bad.append(float((e > 1.0).mean()) if e.size else float("nan"))
        out[name] = {
            "matched_size": [320 // cfg.downscale, 240 // cfg.downscale],
            "ms_median": round(1e3 * statistics.median(times[name]), 2),
            "density": round(statistics.fmean(dens), 3),
            "density_80x60": round(statistics.fmean(dens_small), 3),
            "median_abs_error_px": round(float(np.median(err)), 3) if err else None,
            "bad1_80x60": round(statistics.fmean([b for b in bad if b == b]), 3),
        }
    print(json.dumps({
        "benchmark": "stereo", "world": args.world, "lighting": args.lighting, "frames": len(views),
        "repeats": args.repeats, "matchers": out,
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count(), "load_avg_1m": round(os.getloadavg()[0], 2)},
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())

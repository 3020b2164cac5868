"""Renderer speed: stereo pairs (left + right + depth) per second on ONE core.

    python benchmarks/bench_render.py [--world office] [--lighting tube] [--width 320 --height 240]
                                      [--frames 60] [--repeats 5]

Prints one JSON object: the median (and min/max) over ``repeats`` runs of ``frames`` renders
each at poses spread over the world's survey grid (noise on, stereo on), the one-off bake
time, and the machine (platform, processor, os.cpu_count). Threads of the numeric libraries
are limited to one before numpy is imported and the process is pinned to one core.
``median_per_s`` is wall-clock; ``median_per_cpu_s`` divides by the process CPU time, which
is the fairer figure when other jobs share the core (see ``load_average_1min``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from drivers.sim.renderer import CameraModel, Renderer  # noqa: E402
from drivers.sim.world import grid_poses, load_world  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="office")
    ap.add_argument("--lighting", default="tube")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--mono", action="store_true", help="left image + depth only")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    except (AttributeError, OSError):
        pass
    world = load_world(args.world)
    t0 = time.perf_counter()
    r = Renderer(world, camera=CameraModel(width=args.width, height=args.height), lighting=args.lighting)
    bake_s = time.perf_counter() - t0
    poses = grid_poses(world, 0.5, math.radians(30))
    idx = np.random.default_rng(0).permutation(len(poses))[: args.frames]
    sel = poses[idx]
    r.render(*sel[0], stereo=not args.mono)  # warm-up: per-camera ray tables
    rates, cpu_rates = [], []
    for _ in range(args.repeats):
        t, c = time.perf_counter(), time.process_time()
        for p in sel:
            r.render(*p, stereo=not args.mono)
        rates.append(len(sel) / (time.perf_counter() - t))
        cpu_rates.append(len(sel) / (time.process_time() - c))
    out = {
        "benchmark": "render",
        "what": "left+depth per second" if args.mono else "stereo pairs (left+right+depth) per second",
        "world": args.world,
        "lighting": args.lighting,
        "image": [args.width, args.height],
        "frames_per_run": len(sel),
        "repeats": args.repeats,
        "median_per_s": round(statistics.median(rates), 2),
        "min_per_s": round(min(rates), 2),
        "max_per_s": round(max(rates), 2),
        "median_per_cpu_s": round(statistics.median(cpu_rates), 2),
        "target_per_s": 30,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "bake_s": round(bake_s, 3),
        "threads": 1,
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(),
            "cpu_count": os.cpu_count(),
            "numpy": np.__version__,
        },
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())

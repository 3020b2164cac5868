"""Benchmark: time and peak memory of the EM fit of PCA with missing data (lino_loc.pca_missing).

The lab survey of the paper's section 6.2: about 4000 disparity maps of 80 x 60 = 4800 pixels,
d = 20 features, with about 40 % of the pixels missing. Synthetic low-rank data plus noise,
missing completely at random. Prints one JSON object: median / min / max wall time of the fit
over the repeats, EM iterations, peak memory of the fit (tracemalloc: numpy buffers, excluding
the input array), the largest principal angle between the fitted and the true subspace, and
the cost of projecting one sparse map, and (for 80 x 60 maps) the per-frame cost the
disparity channel adds to an update: block matching of a 320 x 240 / 640 x 400 pair,
downsampling to 80 x 60, projection. Set OPENBLAS_NUM_THREADS to compare thread counts.

    .venv/bin/python benchmarks/bench_em_pca.py [--n 4000] [--dim 4800] [--d 20]
        [--missing 0.4] [--repeats 3] [--dtype float64|float32] [--max-iter 200]
        [--no-accelerate] [--data maps.npy]

``--data`` fits a saved (N, D) NaN-sparse matrix (e.g. rendered disparity maps) instead of
the synthetic data (no true subspace then: the angle is null). ``--no-accelerate`` runs
plain PX-EM without the SQUAREM extrapolation, for comparison.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
import tracemalloc

import cv2
import numpy as np
from scipy.linalg import subspace_angles

from lino_loc.disparity import StereoConfig, compute_disparity, downsample_sparse
from lino_loc.pca_missing import fit_pca_missing


def _per_frame_ms(model, rng: np.random.Generator, dim: int) -> dict:
    """Per-frame cost of the disparity channel: stereo matching of a grey pair with the
    product's StereoConfig, NaN-aware downsampling to the map size, projection (medians, ms)."""
    out: dict = {}
    if dim != 80 * 60:
        return out
    for w, h in ((320, 240), (640, 400)):
        tex = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 32)), (0, 0), 1.5)
        tex = ((tex - tex.min()) / (tex.max() - tex.min()) * 255).astype(np.uint8)
        left, right = tex[:, 16 : 16 + w], tex[:, 4 : 4 + w]  # disparity 12 px
        left[h // 4 : h // 2, w // 3 : w // 2] = 128  # a textureless patch
        t_bm, t_ds, t_pr = [], [], []
        for _ in range(30):
            t0 = time.perf_counter()
            disp = compute_disparity(left, right, StereoConfig())
            t1 = time.perf_counter()
            small = downsample_sparse(disp, (80, 60), 0.25)
            t2 = time.perf_counter()
            model.project(small.reshape(-1))
            t3 = time.perf_counter()
            t_bm.append(t1 - t0)
            t_ds.append(t2 - t1)
            t_pr.append(t3 - t2)
        out[f"{w}x{h}"] = {
            "stereo_bm": round(1e3 * statistics.median(t_bm), 3),
            "downsample_80x60": round(1e3 * statistics.median(t_ds), 3),
            "project": round(1e3 * statistics.median(t_pr), 3),
            "total": round(
                1e3 * (statistics.median(t_bm) + statistics.median(t_ds) + statistics.median(t_pr)),
                3,
            ),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4000)
    ap.add_argument("--dim", type=int, default=4800)
    ap.add_argument("--d", type=int, default=20)
    ap.add_argument("--missing", type=float, default=0.4)
    ap.add_argument("--noise", type=float, default=0.3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dtype", choices=["float64", "float32"], default="float64")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-iter", type=int, default=200)
    ap.add_argument("--no-accelerate", action="store_true")
    ap.add_argument("--data", default=None, help="(N, D) .npy with NaN = missing")
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    basis = rng.normal(size=(args.d, args.dim)) * np.linspace(3.0, 0.5, args.d)[:, None]
    x = rng.normal(size=(args.n, args.d)) @ basis + 10.0
    x += rng.normal(0.0, args.noise, x.shape)
    x = x.astype(np.float32)
    x[rng.random(x.shape) < args.missing] = np.nan
    if args.data:
        x = np.load(args.data)
        args.n, args.dim = x.shape
        args.missing = round(float(np.isnan(x).mean()), 4)
        basis = None
    dtype = np.float64 if args.dtype == "float64" else np.float32

    times, peaks, iters, angles = [], [], [], []
    model = None
    for _ in range(args.repeats):
        tracemalloc.start()
        tracemalloc.reset_peak()
        t0 = time.perf_counter()
        model = fit_pca_missing(
            x,
            args.d,
            seed=args.seed,
            dtype=dtype,
            max_iter=args.max_iter,
            accelerate=not args.no_accelerate,
        )
        times.append(time.perf_counter() - t0)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        iters.append(model.n_iter)
        if basis is not None:
            angles.append(float(np.degrees(subspace_angles(model.components.T, basis.T)).max()))
    assert model is not None

    proj = []
    for i in range(min(200, args.n)):
        t0 = time.perf_counter()
        model.project(x[i])
        proj.append(time.perf_counter() - t0)
    per_frame = _per_frame_ms(model, rng, args.dim)

    print(
        json.dumps(
            {
                "benchmark": "em_pca_fit",
                "machine": {
                    "platform": platform.platform(),
                    "processor": platform.processor() or platform.machine(),
                    "cpu_count": os.cpu_count(),
                    "python": platform.python_version(),
                    "numpy": np.__version__,
                    "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
                },
                "problem": {
                    "n_samples": args.n,
                    "n_pixels": args.dim,
                    "n_components": args.d,
                    "missing_fraction": args.missing,
                    "noise": None if args.data else args.noise,
                    "data": args.data,
                    "dtype": args.dtype,
                    "input_mb": round(x.nbytes / 2**20, 1),
                },
                "repeats": args.repeats,
                "fit_s": {
                    "median": round(statistics.median(times), 3),
                    "min": round(min(times), 3),
                    "max": round(max(times), 3),
                },
                "em_iterations": iters,
                "converged": bool(model.converged),
                "accelerate": not args.no_accelerate,
                "max_iter": args.max_iter,
                "final_log_likelihood_per_value": round(model.log_likelihood[-1], 7),
                "fit_s_per_em_iteration_incl_init": round(
                    statistics.median(times) / statistics.median(iters), 3
                ),
                "peak_memory_mb": round(max(peaks) / 2**20, 1),
                "max_angle_to_true_subspace_deg": round(max(angles), 4) if angles else None,
                "project_one_map_ms_median": round(1e3 * statistics.median(proj), 3),
                "per_frame_ms_median": per_frame,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark: PCA methods and the appearance-map build (the lab survey's map build).

Prints one JSON object. Every figure is the median of repeated runs; each measurement runs
in a fresh child process so that its peak resident memory (``ru_maxrss``) is its own.

1. Synthetic data shaped like the lab survey (N = 4000 images x D = 4800 pixels = 80 x 60,
   low rank with a power-law spectrum + noise, float32): time and peak memory of
   ``fit_pca`` with ``randomized``, ``gram`` and ``svd`` (numpy's full SVD), and the largest
   principal angle of each against the exact subspace.
2. With a dataset folder argument (e.g. the lab survey at 320 x 240): image loading +
   preprocessing (per preprocessing method and number of threads), PCA per method, and the
   whole ``build_map`` + ``save`` (what ``lino-loc map build`` does; rendering excluded).

Memory: ``tracemalloc_peak_mb`` is the peak of memory allocated through Python's allocators
during the call (numpy arrays included; LAPACK work space allocated by the library itself
is not); ``rss_extra_mb`` is the child's peak resident set minus its resident set just
before the call (everything, but includes allocator slack).

Usage::

    python benchmarks/bench_map_build.py                         # synthetic only
    python benchmarks/bench_map_build.py /path/to/lab_survey     # + the real survey
    python benchmarks/bench_map_build.py --make-lab-survey DIR   # render one first (slow)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import sys
import tempfile
import time
import tracemalloc
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def synthetic(n: int, dim: int, rank: int, noise: float, seed: int) -> np.ndarray:
    """Low-rank (power-law spectrum, like natural images) + white noise, float32, mean 0.5."""
    rng = np.random.default_rng(seed)
    scales = (1.0 + np.arange(rank)) ** -1.0
    U = rng.standard_normal((n, rank)).astype(np.float32) * scales.astype(np.float32)
    V = np.linalg.qr(rng.standard_normal((dim, rank)))[0].T.astype(np.float32)
    X = U @ V
    X *= np.float32(0.2 * np.sqrt(dim))
    X += np.float32(noise) * rng.standard_normal((n, dim), dtype=np.float32)
    X += np.float32(0.5)
    return X


def _cpu_s() -> float:
    """CPU seconds used by this process, all threads (less sensitive to a loaded machine)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


_LAST_CPU: list[float] = []


def _timed(fn, repeats: int) -> tuple[list[float], object]:
    times, out = [], None
    _LAST_CPU.clear()
    for _ in range(repeats):
        c = _cpu_s()
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
        _LAST_CPU.append(_cpu_s() - c)
    return times, out


def _cpu_median() -> float:
    return round(statistics.median(_LAST_CPU), 3)


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark (VmHWM) of this process (Linux >= 4.0)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _hwm_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return _maxrss_mb()


def _memory(fn) -> dict[str, float]:
    reset = _reset_peak_rss()
    before = _rss_mb()
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return {
        "tracemalloc_peak_mb": round(peak / 2**20, 1),
        "rss_extra_mb": round(max((_hwm_mb() if reset else _maxrss_mb()) - before, 0.0), 1),
    }


# ----------------------------------------------------------------------- child jobs
def job_synthetic_pca(method: str, n: int, dim: int, rank: int, d: int, repeats: int) -> dict:
    from lino_loc.pca import fit_pca

    X = synthetic(n, dim, rank, noise=0.02, seed=0)
    mem = _memory(lambda: fit_pca(X, d, method=method))  # fresh process: the first call
    times, pca = _timed(lambda: fit_pca(X, d, method=method), repeats)
    return {
        "median_s": round(statistics.median(times), 3),
        "times_s": [round(t, 3) for t in times],
        "median_cpu_s": _cpu_median(),
        **mem,
        "data_mb": round(X.nbytes / 2**20, 1),
        "components": pca.components,  # type: ignore[union-attr]
    }


def job_load(root: str, preprocess: str, size: tuple[int, int], workers: int, repeats: int) -> dict:
    from lino_loc.appearance_map import load_vectors
    from lino_loc.dataset import Dataset

    ds = Dataset.open(root)
    load_vectors(ds.subset(range(min(64, len(ds)))), preprocess, size, workers=workers)  # warm
    times, X = _timed(lambda: load_vectors(ds, preprocess, size, workers=workers), repeats)
    return {"median_s": round(statistics.median(times), 3), "times_s": [round(t, 3) for t in times],
            "median_cpu_s": _cpu_median(), "images": len(ds), "per_image_ms": round(1000 * statistics.median(times) / len(ds), 3)}


def job_dataset_pca(root: str, method: str, size: tuple[int, int], d: int, repeats: int) -> dict:
    from lino_loc.appearance_map import load_vectors
    from lino_loc.dataset import Dataset
    from lino_loc.pca import fit_pca

    X = load_vectors(Dataset.open(root), "none", size)
    mem = _memory(lambda: fit_pca(X, d, method=method))
    times, pca = _timed(lambda: fit_pca(X, d, method=method), repeats)
    return {"median_s": round(statistics.median(times), 3), "times_s": [round(t, 3) for t in times],
            "median_cpu_s": _cpu_median(), **mem, "components": pca.components}  # type: ignore[union-attr]


def job_build(root: str, preprocess: str, size: tuple[int, int], d: int, method: str, condition: str | None) -> dict:
    from lino_loc.appearance_map import build_map
    from lino_loc.dataset import Dataset

    before = _rss_mb()
    c0 = _cpu_s()
    t0 = time.perf_counter()
    ds = Dataset.open(root)
    t1 = time.perf_counter()
    amap = build_map(ds, n_features=d, preprocess=preprocess, size=size, condition=condition, method=method)
    t2 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        out = amap.save(Path(tmp) / "map.npz")
        size_b = out.stat().st_size
    t3 = time.perf_counter()
    return {
        "total_s": round(t3 - t0, 3),
        "cpu_s": round(_cpu_s() - c0, 3),
        "open_dataset_s": round(t1 - t0, 3),
        "build_s": round(t2 - t1, 3),
        "save_s": round(t3 - t2, 3),
        "images": len(amap),
        "rss_extra_mb": round(max(_maxrss_mb() - before, 0.0), 1),
        "peak_rss_mb": round(_maxrss_mb(), 1),
        "map_file_mb": round(size_b / 2**20, 2),
    }


def _child(fn, *args):
    with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn")) as pool:
        return pool.submit(fn, *args).result()


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    from lino_loc.pca import principal_angles

    return float(principal_angles(a, b).max())


# ----------------------------------------------------------------------- survey helper
def make_lab_survey(out: Path, step: float, heading_deg: float, width: int, height: int) -> int:
    """Render the lab survey (tube light, grey images only) with the simulator."""
    import math

    from drivers.sim.renderer import CameraModel, Renderer
    from drivers.sim.world import grid_poses, load_world
    from lino_loc.dataset import CameraInfo, DatasetMeta, DatasetWriter

    world = load_world("lab")
    cam = CameraModel(width=width, height=height)
    fx, fy, cx, cy = cam.intrinsics()
    r = Renderer(world, cam, lighting="tube")
    poses = grid_poses(world, step, math.radians(heading_deg))
    meta = DatasetMeta(
        name="lab", source=f"bench_map_build: lab, step {step} m, heading {heading_deg} deg, tube",
        camera=CameraInfo(width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy, baseline_m=cam.baseline_m),
    )
    with DatasetWriter(out, meta, overwrite=True) as w:
        for i, (x, y, th) in enumerate(poses):
            res = r.render(x, y, th, stereo=False)
            w.add(res.grey, res.camera_pose, condition="tube")
            if (i + 1) % 500 == 0:
                print(f"rendered {i + 1}/{len(poses)}", file=sys.stderr)
    return len(poses)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", nargs="?", help="dataset folder (e.g. the lab survey at 320x240)")
    ap.add_argument("--n", type=int, default=4000)
    ap.add_argument("--size", default="80x60")
    ap.add_argument("--features", type=int, default=20)
    ap.add_argument("--rank", type=int, default=200, help="rank of the synthetic signal")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--svd-repeats", type=int, default=1, help="numpy's full SVD takes about a minute")
    ap.add_argument("--methods", default="randomized,gram,svd")
    ap.add_argument("--workers", default="1,2,4", help="thread counts for image loading")
    ap.add_argument("--skip-synthetic", action="store_true")
    ap.add_argument("--condition", default=None)
    ap.add_argument("--make-lab-survey", metavar="DIR", help="render the lab survey into DIR first")
    ap.add_argument(
        "--blas-threads", type=int, default=None,
        help="set OPENBLAS_NUM_THREADS/OMP_NUM_THREADS for the measuring processes "
        "(on a loaded machine 1 is much faster than spinning BLAS threads)",
    )
    args = ap.parse_args(argv)
    if args.blas_threads is not None:  # the spawned children read it when they import numpy
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(args.blas_threads)
    w, h = (int(v) for v in args.size.split("x"))
    methods = [m for m in args.methods.split(",") if m]
    result: dict = {
        "benchmark": "map_build",
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "blas_threads_env": os.environ.get("OPENBLAS_NUM_THREADS"),
            "load_average_at_start": [round(v, 2) for v in os.getloadavg()],
        },
        "size": [w, h],
        "features": args.features,
    }
    if args.make_lab_survey:
        t = time.perf_counter()
        n = make_lab_survey(Path(args.make_lab_survey), 0.5, 10.0, 320, 240)
        result["rendered_survey"] = {"images": n, "seconds": round(time.perf_counter() - t, 1)}
        args.dataset = args.dataset or args.make_lab_survey

    if not args.skip_synthetic:
        syn: dict = {"n": args.n, "dim": w * h, "rank": args.rank, "noise": 0.02, "methods": {}}
        comps = {}
        for m in methods:
            reps = args.svd_repeats if m == "svd" else args.repeats
            r = _child(job_synthetic_pca, m, args.n, w * h, args.rank, args.features, reps)
            comps[m] = r.pop("components")
            syn["methods"][m] = r
            print(f"synthetic {m}: {r['median_s']} s", file=sys.stderr)
        ref = "svd" if "svd" in comps else None
        if ref:
            for m in comps:
                syn["methods"][m]["max_angle_vs_svd_rad"] = _angle(comps[m], comps[ref])
        result["synthetic"] = syn

    if args.dataset:
        root = str(Path(args.dataset).resolve())
        real: dict = {"dataset": root, "load_preprocess": {}, "pca": {}, "build": {}}
        for pre in ("none", "histeq", "gradient"):
            real["load_preprocess"][pre] = {}
            for nw in (int(v) for v in args.workers.split(",")):
                r = _child(job_load, root, pre, (w, h), nw, args.repeats)
                real["load_preprocess"][pre][f"threads_{nw}"] = r
                print(f"load {pre} x{nw}: {r['median_s']} s", file=sys.stderr)
        comps = {}
        for m in methods:
            reps = args.svd_repeats if m == "svd" else args.repeats
            r = _child(job_dataset_pca, root, m, (w, h), args.features, reps)
            comps[m] = r.pop("components")
            real["pca"][m] = r
            print(f"survey pca {m}: {r['median_s']} s", file=sys.stderr)
        if "svd" in comps:
            for m in comps:
                real["pca"][m]["max_angle_vs_svd_rad"] = _angle(comps[m], comps["svd"])
        for pre in ("none", "histeq", "gradient"):
            runs = [_child(job_build, root, pre, (w, h), args.features, "randomized", args.condition)
                    for _ in range(args.repeats)]
            totals = [r["total_s"] for r in runs]
            best = runs[totals.index(statistics.median(totals))] if len(runs) % 2 else runs[0]
            real["build"][pre] = {"median_total_s": round(statistics.median(totals), 3),
                                  "totals_s": totals, "median_run": best}
            print(f"build {pre}: {statistics.median(totals)} s", file=sys.stderr)
        result["survey"] = real
    result["machine"]["load_average_at_end"] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""What the disparity channel costs: per frame in an update, and the EM-PCA build of the lab map.

    .venv/bin/python benchmarks/bench_disparity_channel.py [--frames 30] [--repeats 3]
        [--build-repeats 3] [--light bulb] [--skip-build]

Real data, not synthetic: the lab survey of the paper's section 6.2 (every 50 cm and 10 deg
under tube light, 4500 views, 320 x 240) and its sparse StereoBM disparity at 80 x 60, as
``lino-loc eval sensor-model`` builds them (cached vectors and maps are reused; a missing cache
is rendered first, which takes minutes and is not timed).

1. **Per frame** (``per_frame_ms``), on ``frames`` test views rendered along the Fig. 5 path
   under ``light``: the observation step of :class:`lino_loc.localizer.Localizer` with the
   intensity channel only (preprocess + area-average + PCA projection, J = 10 nearest search,
   mixture) against intensity + disparity (the same with J = 5, plus StereoBM on the 320 x 240
   pair, NaN-aware downsampling to 80 x 60, EM-PCA projection from the valid pixels, the second
   J = 5 search, disjunctive fusion eq. 8). ``added`` is the difference of the medians; the
   stages are timed separately too. The filter update after the observation is the same for
   both (a 10-component mixture either way), so it is not included. Median over all frames
   and ``repeats`` passes.
2. **Build** (``build``): time and peak memory of ``fit_pca_missing`` on the survey's N x 4800
   sparse disparity matrix with the map builder's settings (20 components, float32 products,
   at most 100 EM iterations) plus the projection of every map (the features), median over
   ``build_repeats``; peak memory by tracemalloc (numpy buffers, beyond the input matrix) and
   the process's peak RSS; wall and process CPU time (the fairer figure when other jobs share
   the cores: see the load averages).

Threads of the numeric libraries are limited to one before numpy is imported. Prints one JSON
object with the machine (platform, processor, os.cpu_count, load average).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from drivers.sim.renderer import CameraModel, Renderer  # noqa: E402
from drivers.sim.world import grid_poses, load_world  # noqa: E402
from lino_loc.appearance_map import DISPARITY_EM_MAX_ITER, AppearanceMap  # noqa: E402
from lino_loc.disparity import compute_disparity, downsample_sparse  # noqa: E402
from lino_loc.fusion import fuse  # noqa: E402
from lino_loc.localizer import Localizer, LocalizerConfig  # noqa: E402
from lino_loc.pca_missing import fit_pca_missing  # noqa: E402
from services.evaluation.sensor_model_error import (  # noqa: E402
    SensorModelSetup,
    default_path_box,
    disparity_map,
    path_poses,
    survey_disparity_vectors,
)
from services.evaluation.views import build_sim_maps  # noqa: E402


def _ms(values: list[float]) -> float:
    return round(1e3 * statistics.median(values), 3)


def per_frame(setup: SensorModelSetup, frames: int, repeats: int, light: str) -> dict:
    world = load_world(setup.world)
    poses = grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    imap = build_sim_maps(setup.world, setup.step, setup.heading_step_deg, setup.features, (setup.preprocess,),
                          lighting="tube", width=setup.width, height=setup.height, size=setup.size,
                          seed=setup.seed)[setup.preprocess]
    dmap = disparity_map(setup, world, poses)
    both = AppearanceMap(poses=imap.poses, channels={"intensity": imap.channels["intensity"],
                                                     "disparity": dmap.channels["disparity"]},
                         camera=imap.camera)
    cfg = LocalizerConfig()
    loc_i = Localizer(imap, cfg)
    loc_f = Localizer(both, cfg)
    path = path_poses(world, setup.spacing, default_path_box(world), setup.path_exponent, avoid=poses)
    pick = path[np.linspace(0, len(path) - 1, frames).round().astype(int)]
    renderer = Renderer(world, camera=CameraModel(width=setup.width, height=setup.height), lighting=light)
    views = [renderer.render(*p, stereo=True, rng=np.random.default_rng((7, k))) for k, p in enumerate(pick)]
    ich, dch = both.channels["intensity"], both.channels["disparity"]
    mi, md = loc_f.models["intensity"], loc_f.models["disparity"]
    fc = cfg.fusion
    t: dict[str, list[float]] = {k: [] for k in (
        "intensity_only", "intensity_plus_disparity", "intensity_only_cpu", "intensity_plus_disparity_cpu", "stereo_bm", "downsample", "em_project",
        "intensity_project", "search_j10", "search_j5_intensity", "search_j5_disparity", "fuse")}
    for _ in range(repeats):
        for v in views:
            t0, c0 = time.perf_counter(), time.process_time()
            loc_i.observe(v.grey)
            t1, c1 = time.perf_counter(), time.process_time()
            disp = compute_disparity(v.left, v.right, setup.stereo)
            loc_f.observe(v.grey, disp)
            t2, c2 = time.perf_counter(), time.process_time()
            t["intensity_only"].append(t1 - t0)
            t["intensity_plus_disparity"].append(t2 - t1)
            t["intensity_only_cpu"].append(c1 - c0)
            t["intensity_plus_disparity_cpu"].append(c2 - c1)
            # stages
            s0 = time.perf_counter()
            d = compute_disparity(v.left, v.right, setup.stereo)
            s1 = time.perf_counter()
            z = downsample_sparse(d, dch.size, setup.min_valid_fraction).reshape(-1)
            s2 = time.perf_counter()
            yd = np.asarray(dch.pca.project(z), dtype=np.float64)
            s3 = time.perf_counter()
            yi = np.asarray(ich.project(v.grey), dtype=np.float64)
            s4 = time.perf_counter()
            loc_i.models["intensity"].observe(yi, 10)
            s5 = time.perf_counter()
            m_i = mi.observe(yi, fc.j_intensity)
            s6 = time.perf_counter()
            m_d = md.observe(yd, fc.j_disparity)
            s7 = time.perf_counter()
            fuse({"intensity": m_i, "disparity": m_d}, fc)
            s8 = time.perf_counter()
            for key, a, b in (("stereo_bm", s0, s1), ("downsample", s1, s2), ("em_project", s2, s3),
                              ("intensity_project", s3, s4), ("search_j10", s4, s5),
                              ("search_j5_intensity", s5, s6), ("search_j5_disparity", s6, s7),
                              ("fuse", s7, s8)):
                t[key].append(b - a)
    out = {k: _ms(v) for k, v in t.items()}
    out["added"] = round(out["intensity_plus_disparity"] - out["intensity_only"], 3)
    out["added_cpu"] = round(out["intensity_plus_disparity_cpu"] - out["intensity_only_cpu"], 3)
    return {"frames": frames, "repeats": repeats, "light": light, "image": [setup.width, setup.height],
            "map_entries": int(len(poses)), "search_index": {"intensity": mi.index_kind, "disparity": md.index_kind},
            "ms_median": out}


def build(setup: SensorModelSetup, repeats: int) -> dict:
    world = load_world(setup.world)
    poses = grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    X = survey_disparity_vectors(setup, world, poses)
    times, cpu, peaks, iters, conv = [], [], [], [], []
    for _ in range(repeats):
        tracemalloc.start()
        tracemalloc.reset_peak()
        t0, c0 = time.perf_counter(), time.process_time()
        model = fit_pca_missing(X, setup.features, seed=setup.seed, max_iter=DISPARITY_EM_MAX_ITER, dtype=np.float32)
        model.project(X)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        iters.append(model.n_iter)
        conv.append(bool(model.converged))
    return {
        "n_maps": int(X.shape[0]),
        "pixels": int(X.shape[1]),
        "valid_fraction": round(float(np.isfinite(X).mean()), 4),
        "components": setup.features,
        "input_mb": round(X.nbytes / 2**20, 1),
        "repeats": repeats,
        "fit_and_project_s": {"median": round(statistics.median(times), 2), "min": round(min(times), 2),
                              "max": round(max(times), 2)},
        "fit_and_project_cpu_s_median": round(statistics.median(cpu), 2),
        "em_iterations": iters,
        "converged": conv,
        "peak_traced_mb": round(max(peaks) / 2**20, 1),
        "peak_rss_mb_process": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=3, help="passes over the frames")
    ap.add_argument("--build-repeats", type=int, default=3)
    ap.add_argument("--light", default="bulb")
    ap.add_argument("--skip-build", action="store_true")
    ap.add_argument("--skip-frames", action="store_true")
    args = ap.parse_args(argv)
    setup = SensorModelSetup()
    result: dict = {
        "benchmark": "disparity_channel",
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
            "opencv_threads": cv2.getNumThreads(),
            "load_average_1min_start": round(os.getloadavg()[0], 2),
        },
    }
    if not args.skip_frames:
        result["per_frame"] = per_frame(setup, args.frames, args.repeats, args.light)
    if not args.skip_build:
        result["build"] = build(setup, args.build_repeats)
    result["machine"]["load_average_1min_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

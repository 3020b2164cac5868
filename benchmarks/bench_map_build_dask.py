"""Benchmark: map build time and peak memory, local against Dask (a LocalCluster), at survey scale.

Prints one JSON object (and progress on stderr). For each survey size and engine, in
interleaved order (local, dask, local, dask, ...), one fresh child process runs what
``lino-loc map build`` runs after its dataset check: open the dataset, (dask: start the
LocalCluster), ``build_map`` and ``save``. This process samples the child's whole process
tree every 0.1 s (the child, and with dask its nanny and worker processes): the peak of the
summed resident set (RSS, counts shared library pages once per process) and of the summed
proportional set size (PSS, shared pages split between the processes: the tree's real
footprint). Build phases come from the library's own phase log records
(``lino_loc.appearance_map`` / ``lino_loc.pca_dask``). CPU seconds are those of the whole
tree (``RUSAGE_CHILDREN`` once it is reaped).

Surveys (``--make-survey DIR --views N``): rendering 100 000 views takes about 30 min of
2 cores, so a survey is *composed*: ``--base-views`` (default 300) views of a world
(default the lab, tube light, 320 x 240 like the real surveys) are rendered, and view i is
base view ``i % B`` moved by a random sub-pixel shift (+-6 px horizontally, +-2 px
vertically, reflected border: a small camera turn and tilt), a random gain (0.8-1.2) and
offset (+-10 grey levels) and fresh sensor noise (sigma 3 grey levels), quantized to 8 bits
and written as PNG by :class:`lino_loc.dataset.DatasetWriter` (the project's dataset
format, docs/datasets.md). Its pose is the base view's, turned by the shift's angle
(atan(dx / fx)). Each view is seeded by its index: the same command makes the same survey.
It is a survey for *build cost* (same PNG size and decoding cost, a data matrix of the
same size, a spectrum of real rendered structure), not for localization accuracy.

Usage::

    python benchmarks/bench_map_build_dask.py --make-survey /work/data/survey20k --views 20000
    python benchmarks/bench_map_build_dask.py /work/data/survey20k /work/data/survey100k \\
        --engines local,dask --repeats 2 --blas-threads 1
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


# ----------------------------------------------------------------------- survey
def make_survey(out: Path, views: int, base_views: int, world_name: str, seed: int) -> dict:
    """Render ``base_views`` views of ``world_name`` and compose ``views`` perturbed views from
    them (module docstring) into the dataset folder ``out``."""
    import cv2

    from drivers.sim.renderer import CameraModel, Renderer
    from drivers.sim.world import grid_poses, load_world
    from lino_loc.dataset import CameraInfo, DatasetMeta, DatasetWriter

    t0 = time.perf_counter()
    world = load_world(world_name)
    cam = CameraModel(width=320, height=240)
    fx, fy, cx, cy = cam.intrinsics()
    renderer = Renderer(world, cam, lighting="tube")
    grid = grid_poses(world, 0.25, math.radians(10.0))
    pick = np.random.default_rng(seed).choice(len(grid), size=min(base_views, len(grid)), replace=False)
    base = []
    for k, (x, y, th) in enumerate(grid[np.sort(pick)]):
        res = renderer.render(float(x), float(y), float(th), stereo=False, rng=np.random.default_rng(seed + k))
        base.append((res.grey, np.asarray(res.camera_pose, dtype=np.float64)))
    t_render = time.perf_counter() - t0
    meta = DatasetMeta(
        name=f"{world_name}-composed-{views}",
        source=f"bench_map_build_dask: {views} views composed from {len(base)} rendered views of {world_name} "
        f"(tube), seed {seed}",
        camera=CameraInfo(width=320, height=240, fx=fx, fy=fy, cx=cx, cy=cy, baseline_m=cam.baseline_m),
    )
    with DatasetWriter(out, meta, overwrite=True) as w:
        for i in range(views):
            img, pose = base[i % len(base)]
            rng = np.random.default_rng([seed, i])
            dx, dy = rng.uniform(-6.0, 6.0), rng.uniform(-2.0, 2.0)
            A = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])
            moved = cv2.warpAffine(img, A, (320, 240), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
            f = moved.astype(np.float32) * np.float32(rng.uniform(0.8, 1.2)) + np.float32(rng.uniform(-10, 10))
            f += rng.standard_normal(f.shape, dtype=np.float32) * np.float32(3.0)
            grey = np.clip(np.rint(f), 0, 255).astype(np.uint8)
            p = pose.copy()
            p[2] = math.remainder(p[2] + math.atan2(-dx, fx), math.tau)  # image moved right = camera turned left
            w.add(grey, p, condition="tube")
            if (i + 1) % 10000 == 0:
                print(f"composed {i + 1}/{views}", file=sys.stderr)
    return {"views": views, "base_views": len(base), "world": world_name, "render_s": round(t_render, 1),
            "total_s": round(time.perf_counter() - t0, 1),
            "disk_mb": round(sum(f.stat().st_size for f in (out / "images").iterdir()) / 2**20, 1)}


# ----------------------------------------------------------------------- child
def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class _Phases(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.phases: dict[str, float] = {}

    def emit(self, record: logging.LogRecord) -> None:
        if hasattr(record, "phase"):
            self.phases[record.phase] = round(self.phases.get(record.phase, 0.0) + record.seconds, 3)  # type: ignore[attr-defined]


def child(engine: str, root: str, out: str, features: int, workers: int, memory_budget_mb: float | None,
          chunk_rows: int | None) -> dict:
    from lino_loc.appearance_map import DEFAULT_MEMORY_BUDGET_MB, build_map
    from lino_loc.dataset import Dataset

    handler = _Phases()
    for name in ("lino_loc.appearance_map", "lino_loc.pca_dask"):
        logging.getLogger(name).addHandler(handler)
        logging.getLogger(name).setLevel(logging.INFO)
    t0 = time.perf_counter()
    ds = Dataset.open(root)
    t1 = time.perf_counter()
    result: dict = {"open_s": round(t1 - t0, 3)}
    budget = DEFAULT_MEMORY_BUDGET_MB if memory_budget_mb is None else memory_budget_mb
    kwargs = dict(n_features=features, preprocess="none", engine=engine, memory_budget_mb=budget,
                  scratch_dir=Path(out).parent, chunk_rows=chunk_rows)
    if engine == "dask":
        from services.dask_cluster import dask_client

        with dask_client(None, workers=workers) as client:
            t2 = time.perf_counter()
            result["cluster_start_s"] = round(t2 - t1, 3)
            amap = build_map(ds, **kwargs)  # type: ignore[arg-type]
            t3 = time.perf_counter()
            result["workers"] = len(client.nthreads())
            result["worker_cpu_s"] = sorted(round(v, 2) for v in client.run(_cpu_s).values())
            result["nanny_cpu_s"] = sorted(round(v, 2) for v in client.run(_cpu_s, nanny=True).values())
        result["cluster_close_s"] = round(time.perf_counter() - t3, 3)
    else:
        t2 = time.perf_counter()
        amap = build_map(ds, **kwargs)  # type: ignore[arg-type]
        t3 = time.perf_counter()
    result["build_s"] = round(t3 - t2, 3)
    result["client_cpu_s"] = round(_cpu_s(), 2)  # with dask: the client and the LocalCluster's scheduler
    t4 = time.perf_counter()
    path = amap.save(out)
    result["save_s"] = round(time.perf_counter() - t4, 3)
    result["total_s"] = round(time.perf_counter() - t0, 3)
    result["phases_s"] = handler.phases
    result["entries"] = len(amap)
    result["map_mb"] = round(path.stat().st_size / 2**20, 2)
    result["child_maxrss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    return result


# ----------------------------------------------------------------------- tree memory
def _pss_kb(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as fh:
            for line in fh:
                if line.startswith("Pss:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


class TreeMemory(threading.Thread):
    """Peak summed RSS and PSS (MiB) of a process and all its descendants, sampled every ``dt`` s."""

    def __init__(self, pid: int, dt: float = 0.1):
        super().__init__(daemon=True)
        self.pid, self.dt = pid, dt
        self.peak_rss_mb = self.peak_pss_mb = 0.0
        self.max_processes = 0
        self._stop_evt = threading.Event()

    def run(self) -> None:
        import psutil

        try:
            root = psutil.Process(self.pid)
        except psutil.NoSuchProcess:
            return
        while not self._stop_evt.is_set():
            try:
                procs = [root, *root.children(recursive=True)]
            except psutil.NoSuchProcess:
                break
            rss = pss = 0
            for p in procs:
                try:
                    rss += p.memory_info().rss
                except psutil.Error:
                    continue
                pss += _pss_kb(p.pid) * 1024
            self.peak_rss_mb = max(self.peak_rss_mb, rss / 2**20)
            self.peak_pss_mb = max(self.peak_pss_mb, pss / 2**20)
            self.max_processes = max(self.max_processes, len(procs))
            self._stop_evt.wait(self.dt)

    def stop(self) -> None:
        self._stop_evt.set()
        self.join()


def run_child(args_list: list[str]) -> dict:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, __file__, "--child", *args_list], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    mon = TreeMemory(proc.pid)
    mon.start()
    out, err = proc.communicate()
    mon.stop()
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"child failed ({proc.returncode}): {err[-2000:]}")
    res = json.loads(out.strip().splitlines()[-1])
    res.update({
        "wall_s": round(wall, 3),
        "tree_cpu_s": round((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), 2),
        "tree_peak_rss_mb": round(mon.peak_rss_mb, 1),
        "tree_peak_pss_mb": round(mon.peak_pss_mb, 1),
        "processes": mon.max_processes,
        "load_after": [round(v, 2) for v in os.getloadavg()],
    })
    return res


def _compare(a: Path, b: Path) -> dict:
    from lino_loc.appearance_map import AppearanceMap
    from lino_loc.pca import principal_angles

    ma, mb = AppearanceMap.load(a), AppearanceMap.load(b)
    ca, cb = ma.channels["intensity"], mb.channels["intensity"]
    signs = np.sign(np.einsum("ij,ij->j", ca.features, cb.features))
    diff = np.abs(ca.features - cb.features * signs).max(axis=0)
    return {"max_principal_angle_rad": float(principal_angles(ca.pca.components, cb.pca.components).max()),
            "max_feature_diff_rel": float(diff.max() / np.abs(ca.features).max()),
            "poses_equal": bool(np.array_equal(ma.poses, mb.poses))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("datasets", nargs="*", help="survey dataset folders to build maps of")
    ap.add_argument("--make-survey", metavar="DIR", help="compose a survey into DIR (see --views) and exit")
    ap.add_argument("--views", type=int, default=20000)
    ap.add_argument("--base-views", type=int, default=300)
    ap.add_argument("--world", default="lab")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--engines", default="local,dask")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--features", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes (1 thread each)")
    ap.add_argument("--memory-budget", type=float, default=None, help="local engine's budget in MiB (default the library's)")
    ap.add_argument("--chunk-rows", type=int, default=None)
    ap.add_argument("--out-dir", default=None, help="where maps and scratch files go (default a temporary folder)")
    ap.add_argument("--blas-threads", type=int, default=None)
    ap.add_argument("--child", nargs=7, metavar="ARG", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        engine, root, out, features, workers, budget, chunk = args.child
        print(json.dumps(child(engine, root, out, int(features), int(workers),
                               None if budget == "-" else float(budget), None if chunk == "-" else int(chunk))))
        return 0
    if args.blas_threads is not None:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(args.blas_threads)
    if args.make_survey:
        info = make_survey(Path(args.make_survey), args.views, args.base_views, args.world, args.seed)
        print(json.dumps({"survey": str(args.make_survey), **info, "load_at_end": list(os.getloadavg())}))
        return 0
    result: dict = {
        "benchmark": "map_build_dask",
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "python": platform.python_version(),
                    "blas_threads_env": os.environ.get("OPENBLAS_NUM_THREADS"),
                    "load_at_start": [round(v, 2) for v in os.getloadavg()]},
        "features": args.features, "workers": args.workers, "runs": {},
    }
    engines = [e for e in args.engines.split(",") if e]
    with tempfile.TemporaryDirectory(dir=args.out_dir) as tmp:
        for root in args.datasets:
            name = Path(root).name
            runs: dict[str, list[dict]] = {e: [] for e in engines}
            maps: dict[str, Path] = {}
            for rep in range(args.repeats):
                for e in engines:
                    out = Path(tmp) / f"{name}-{e}.npz"
                    r = run_child([e, str(Path(root).resolve()), str(out), str(args.features), str(args.workers),
                                   "-" if args.memory_budget is None else str(args.memory_budget),
                                   "-" if args.chunk_rows is None else str(args.chunk_rows)])
                    runs[e].append(r)
                    maps[e] = out
                    print(f"{name} {e} #{rep}: {r['wall_s']} s, tree peak PSS {r['tree_peak_pss_mb']} MiB, "
                          f"load {r['load_after']}", file=sys.stderr)
            summary = {e: {"median_wall_s": round(statistics.median(r["wall_s"] for r in rs), 2),
                           "median_build_s": round(statistics.median(r["build_s"] for r in rs), 2),
                           "median_tree_peak_pss_mb": round(statistics.median(r["tree_peak_pss_mb"] for r in rs), 1),
                           "median_tree_peak_rss_mb": round(statistics.median(r["tree_peak_rss_mb"] for r in rs), 1),
                           "runs": rs} for e, rs in runs.items()}
            if "local" in maps and "dask" in maps:
                summary["local_vs_dask"] = _compare(maps["local"], maps["dask"])
            result["runs"][name] = summary
    result["machine"]["load_at_end"] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

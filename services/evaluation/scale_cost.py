"""What a map of 10k to 1M entries costs the localizer: ``benchmarks/bench_scale.py``.

On synthetic floor maps (:mod:`services.evaluation.synthetic_floor_map`: 40 x 25 m, 36
headings, 20 features on a smooth manifold over the pose plus noise), single-threaded:

- :func:`search_table`: per search structure, the build time, the memory it adds (the
  process's resident-set growth while it is built; for hnswlib also its own size), the median
  time of one J-nearest query (J = 10, through ``NearestNeighbourSensorModel.neighbours``
  for the project's options, the library's call for faiss) and the recall@J against exact
  search (the share of the exact J neighbours found, and the share of queries whose J set is
  exactly the exact one). The queries are observations at random off-grid poses of the floor
  with the map's noise. The structures: the sensor model's ``brute``, ``kdtree`` (scipy
  cKDTree) and ``hnsw`` (hnswlib, lino_loc/hnsw_index.py), plus faiss-cpu's exact
  ``IndexFlatL2`` and approximate ``IndexHNSWFlat`` (M = 32) when faiss is installed;
- :func:`update_costs`: one full ``Localizer.update`` (project a 320 x 240 image rendered from
  the manifold, J-nearest search, APF update, estimate) at 1000 particles along a drive
  through the floor, the filter started at the true pose, per search structure, the kinds
  interleaved in batches; and the mean position error of the estimates along the drive;
- :func:`startup_table` (each case in a fresh process, :func:`startup_main`): map load time
  with and without ``mmap``, the resident memory after the load (anonymous and file-backed
  pages apart), after building the ``Localizer`` and after 50 updates, and the peak.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

J = 10


def _rss() -> dict[str, float]:
    """VmRSS, RssAnon, RssFile and VmHWM of this process, MB (Linux /proc/self/status)."""
    out: dict[str, float] = {}
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "RssAnon", "RssFile", "VmHWM"):
                out[key] = int(rest.split()[0]) / 1024.0
    return out


def queries(n: int, seed: int = 1) -> tuple[Any, Any]:
    """(poses (n, 3), features (n, 20)): observations at uniform random poses of the floor,
    with the maps' noise."""
    import numpy as np

    from services.evaluation.synthetic_floor_map import DEFAULT_NOISE, FLOOR_M, floor_features

    rng = np.random.default_rng(seed)
    q = np.column_stack([rng.uniform(0, FLOOR_M[0], n), rng.uniform(0, FLOOR_M[1], n), rng.uniform(-math.pi, math.pi, n)])
    return q, floor_features(q, noise=DEFAULT_NOISE, rng=rng)


def _median_ms(fn: Any, ys: Any, repeats: int, cpu: dict[str, float] | None = None) -> float:
    """Median wall-clock ms of ``fn(y)`` over ``repeats`` calls cycling through ``ys``; with
    ``cpu`` also the median process-CPU ms in ``cpu["cpu_ms"]`` (the fairer figure on a
    loaded machine)."""
    import numpy as np

    fn(ys[0])
    ts, cs = [], []
    for r in range(repeats):
        y = ys[r % len(ys)]
        t0, c0 = time.perf_counter(), time.process_time()
        fn(y)
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    if cpu is not None:
        cpu["cpu_ms"] = float(np.median(cs) * 1e3)
    return float(np.median(ts) * 1e3)


def _recall(found: Any, exact: Any) -> tuple[float, float]:
    """(mean share of each exact J set found, share of queries with the exact J set)."""
    import numpy as np

    shares = [len(set(a.tolist()) & set(e.tolist())) / len(e) for a, e in zip(found, exact, strict=True)]
    return float(np.mean(shares)), float(np.mean([s == 1.0 for s in shares]))


def search_table(entries: int, n_queries: int = 200, repeats: int = 400, faiss_hnsw_max: int = 100_000,
                 ef_sweep: tuple[int, ...] = (20, 40, 80, 160), cache: Path | None = None,
                 amap: Any = None) -> dict[str, Any]:
    """The search measurements of one map size (see module docstring)."""
    import numpy as np

    from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig
    from services.evaluation.synthetic_floor_map import floor_map

    amap = amap if amap is not None else floor_map(entries)
    f = amap.channels["intensity"].features
    _, ys = queries(n_queries)
    rows: dict[str, Any] = {}
    exact = None
    for kind in ("brute", "kdtree", "hnsw"):
        before = _rss()["VmRSS"]
        t0 = time.perf_counter()
        model = NearestNeighbourSensorModel(amap.poses, f, SensorModelConfig(index=kind, j=J, index_cache=cache))
        build = time.perf_counter() - t0
        grown = _rss()["VmRSS"] - before
        idx, _ = model.neighbours(ys)
        if exact is None:
            exact = idx
        rec, same = _recall(idx, exact)
        row: dict[str, Any] = {"build_s": build, "rss_growth_mb": grown, "recall": rec, "same_set": same}
        row["query_ms"] = _median_ms(model.neighbours, ys, repeats, row)
        if kind == "hnsw":
            graph = model._graph
            assert graph is not None
            row["index_mb"] = graph.nbytes / 1e6
            sweep = {}
            for ef in ef_sweep:
                graph.graph.set_ef(ef)
                lab, _ = graph.graph.knn_query(ys.astype(np.float32), k=J, num_threads=1)
                r, s = _recall(np.asarray(lab), exact)
                ms = _median_ms(lambda y, g=graph.graph: g.knn_query(y.astype(np.float32)[None], k=J, num_threads=1),
                                ys, repeats)
                sweep[str(ef)] = {"recall": r, "same_set": s, "raw_query_ms": ms}
            row["ef_sweep"] = sweep
        rows[kind] = row
        del model
    rows.update(_faiss_rows(f, ys, exact, repeats, entries <= faiss_hnsw_max))
    return {"entries": entries, "features": int(f.shape[1]), "j": J, "search": rows}


def _faiss_rows(f: Any, ys: Any, exact: Any, repeats: int, with_hnsw: bool) -> dict[str, Any]:
    """faiss-cpu's exact flat index and (``with_hnsw``) its HNSW graph, one thread; {} when
    faiss is not installed."""
    try:
        import faiss
    except ImportError:
        return {}
    import numpy as np

    faiss.omp_set_num_threads(1)
    f32 = np.ascontiguousarray(f, dtype=np.float32)
    out: dict[str, Any] = {}
    kinds = [("faiss_flat", lambda: faiss.IndexFlatL2(f32.shape[1]))]
    if with_hnsw:
        def hnsw() -> Any:
            ix = faiss.IndexHNSWFlat(f32.shape[1], 32)
            ix.hnsw.efConstruction = 100
            return ix
        kinds.append(("faiss_hnsw32", hnsw))
    for name, make in kinds:
        before = _rss()["VmRSS"]
        t0 = time.perf_counter()
        ix = make()
        ix.add(f32)
        build = time.perf_counter() - t0
        grown = _rss()["VmRSS"] - before
        if name == "faiss_hnsw32":
            ix.hnsw.efSearch = 40
        _, lab = ix.search(ys.astype(np.float32), J)
        rec, same = _recall(lab, exact)
        row: dict[str, Any] = {"build_s": build, "rss_growth_mb": grown,
                               "index_mb": len(faiss.serialize_index(ix)) / 1e6, "recall": rec, "same_set": same}
        row["query_ms"] = _median_ms(lambda y, ix=ix: ix.search(y.astype(np.float32)[None], J), ys, repeats, row)
        out[name] = row
        if name == "faiss_hnsw32":
            out[name]["ef_search"] = 40
    return out


def drive(n_frames: int = 60, seed: int = 3) -> tuple[Any, Any]:
    """(truth robot poses (n, 3), odometry increments (n, 3) in the robot frame): a drive at
    0.5 m per frame along a gentle arc through the middle of the floor."""
    import numpy as np

    from lino_loc.poses import wrap_angle

    rng = np.random.default_rng(seed)
    truth = np.empty((n_frames, 3))
    truth[0] = (8.0, 12.5, 0.0)
    turn = rng.uniform(-0.05, 0.05, n_frames)
    for i in range(1, n_frames):
        x, y, th = truth[i - 1]
        truth[i] = (x + 0.4 * math.cos(th), y + 0.4 * math.sin(th), wrap_angle(th + turn[i]))
    inc = np.zeros_like(truth)
    d = truth[1:, :2] - truth[:-1, :2]
    c, s = np.cos(truth[:-1, 2]), np.sin(truth[:-1, 2])
    inc[1:, 0] = c * d[:, 0] + s * d[:, 1]
    inc[1:, 1] = -s * d[:, 0] + c * d[:, 1]
    inc[1:, 2] = wrap_angle(truth[1:, 2] - truth[:-1, 2])
    return truth, inc


def update_costs(entries: int, kinds: tuple[str, ...] = ("auto", "hnsw"), rounds: int = 3,
                 n_particles: int = 1000, amap: Any = None, cache: Path | None = None) -> dict[str, Any]:
    """Median wall and CPU time of one Localizer update per search kind (batches of one drive
    per kind, interleaved ``rounds`` times), the index "auto" chose, and the mean position
    error of the estimates after the first 10 frames."""
    import numpy as np

    from lino_loc.localizer import Localizer, LocalizerConfig
    from services.evaluation.synthetic_floor_map import (
        DEFAULT_NOISE,
        floor_features,
        floor_image,
        floor_map,
    )

    amap = amap if amap is not None else floor_map(entries)
    truth, inc = drive()
    rng = np.random.default_rng(11)
    images = [floor_image(amap, y) for y in floor_features(truth, noise=DEFAULT_NOISE, rng=rng)]
    locs = {}
    for kind in kinds:
        cfg = LocalizerConfig()
        cfg.filter.n_particles = n_particles
        cfg.sensor.index = kind  # type: ignore[assignment]
        cfg.sensor.index_cache = cache
        locs[kind] = Localizer(amap, cfg, rng=np.random.default_rng(0))
    wall: dict[str, list[float]] = {k: [] for k in kinds}
    cpu: dict[str, list[float]] = {k: [] for k in kinds}
    err: dict[str, list[float]] = {k: [] for k in kinds}
    cov = np.diag([0.1**2, 0.1**2, math.radians(5.0) ** 2])
    for r in range(rounds + 1):  # round 0 warms up and is not recorded
        for kind, loc in locs.items():
            loc.set_pose(truth[0], cov)
            for i in range(1, len(truth)):
                t0, c0 = time.perf_counter(), time.process_time()
                est = loc.update(inc[i], 0.0, images[i])
                if r == 0:
                    continue
                wall[kind].append(time.perf_counter() - t0)
                cpu[kind].append(time.process_time() - c0)
                if i >= 10:
                    err[kind].append(float(np.hypot(*(np.asarray(est.pose[:2]) - truth[i, :2]))))
    return {
        kind: {"index": locs[kind].sensor_model().index_kind, "update_ms": float(np.median(wall[kind]) * 1e3),
               "update_p99_ms": float(np.percentile(wall[kind], 99) * 1e3),
               "cpu_ms": float(np.median(cpu[kind]) * 1e3), "updates": len(wall[kind]),
               "mean_error_m": float(np.mean(err[kind]))}
        for kind in kinds
    }


def startup_main(argv: list[str]) -> int:
    """One start-up case in this process: ``MAP_FILE MMAP(0|1) INDEX [CACHE_DIR]``; prints JSON."""
    import numpy as np

    from lino_loc.appearance_map import AppearanceMap
    from lino_loc.localizer import Localizer, LocalizerConfig
    from services.evaluation.synthetic_floor_map import DEFAULT_NOISE, floor_features, floor_image

    path, mmap, index = Path(argv[0]), argv[1] == "1", argv[2]
    cache = Path(argv[3]) if len(argv) > 3 else None
    base = _rss()
    t0 = time.perf_counter()
    amap = AppearanceMap.load(path, mmap=mmap)
    load_s = time.perf_counter() - t0
    after_load = _rss()
    cfg = LocalizerConfig()
    cfg.filter.n_particles = 1000
    cfg.sensor.index = index  # type: ignore[assignment]
    cfg.sensor.index_cache = cache
    t0 = time.perf_counter()
    loc = Localizer(amap, cfg, rng=np.random.default_rng(0))
    model_s = time.perf_counter() - t0
    after_model = _rss()
    truth, inc = drive(51)
    images = [floor_image(amap, y) for y in floor_features(truth, noise=DEFAULT_NOISE, rng=np.random.default_rng(11))]
    loc.set_pose(truth[0], np.diag([0.01, 0.01, 0.0076]))
    for i in range(1, len(truth)):
        loc.update(inc[i], 0.0, images[i])
    print(json.dumps({"load_s": load_s, "localizer_s": model_s, "index": loc.sensor_model().index_kind,
                      "rss_imports_mb": base, "rss_after_load_mb": after_load, "rss_after_localizer_mb": after_model,
                      "rss_after_updates_mb": _rss()}))
    return 0


def startup_case(path: Path, mmap: bool, index: str, cache: Path | None = None) -> dict[str, Any]:
    """:func:`startup_main` in a fresh interpreter (one thread per numeric library)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    args = [str(path), "1" if mmap else "0", index] + ([str(cache)] if cache else [])
    code = "import sys; from services.evaluation.scale_cost import startup_main; sys.exit(startup_main(sys.argv[1:]))"
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, check=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])

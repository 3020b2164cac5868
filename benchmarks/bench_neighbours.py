"""What settling the J nearest entries one way for every search costs (``lino_loc.exact_neighbours``).

Per channel of a map and per search (KD-tree, brute force), the median time per single query
of the J candidates ranked as the search found them (J from the search, their distances,
sorted: the answer before settling) and of the settled answer (J + MARGIN candidates from the
search, ``settle``: what ``neighbours`` does after its input checks), interleaved, repeated; queries are map features plus 0.3 feature-std of noise
(seed 0). Also how many of the queries' J sets differ between the two searches (0 when the
answer does not depend on the search). Prints one JSON object.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_neighbours.py --map MAP.npz [--queries 200] [--repeat 7]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _per_query_us(fn: Any, queries: np.ndarray) -> float:
    t0 = time.perf_counter()
    for q in queries:
        fn(q)
    return (time.perf_counter() - t0) / len(queries) * 1e6


def main() -> None:
    from lino_loc.appearance_map import AppearanceMap
    from lino_loc.exact_neighbours import MARGIN, _distances, _ranked, settle
    from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--map", required=True, help="an appearance map (.npz)")
    p.add_argument("--queries", type=int, default=200)
    p.add_argument("--repeat", type=int, default=7)
    p.add_argument("--j", type=int, default=10)
    args = p.parse_args()
    amap = AppearanceMap.load(args.map)
    rng = np.random.default_rng(0)
    out: dict[str, Any] = {"benchmark": "neighbours", "map": args.map, "j": args.j,
                           "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                                       "python": platform.python_version()}, "channels": {}}
    for name, ch in amap.channels.items():
        feats = np.asarray(ch.features, dtype=np.float64)
        keep = ch.observed_rows()
        poses, feats = np.asarray(amap.poses)[keep], feats[keep]
        q = feats[rng.integers(0, len(feats), args.queries)]
        q = q + 0.3 * feats.std(axis=0) * rng.standard_normal(q.shape)
        models = {k: NearestNeighbourSensorModel(poses, feats, SensorModelConfig(index=k, j=args.j))
                  for k in ("kdtree", "brute")}
        row: dict[str, Any] = {"entries": int(len(feats)), "dim": int(feats.shape[1])}
        for kind, m in models.items():
            def ranked(y: np.ndarray, m: Any = m) -> Any:
                y = y[None, :]
                idx = m._nearest(y, args.j)
                return _ranked(idx, _distances(m.features, y, idx))

            def settled(y: np.ndarray, m: Any = m) -> Any:
                y = y[None, :]
                return settle(m.features, y, m._nearest(y, args.j + MARGIN), args.j)

            times: dict[str, list[float]] = {"ranked_us": [], "settled_us": []}
            for _ in range(args.repeat):
                times["ranked_us"].append(_per_query_us(ranked, q))
                times["settled_us"].append(_per_query_us(settled, q))
            row[kind] = {k: round(statistics.median(v), 1) for k, v in times.items()}
        a, b = (models[k].neighbours(q)[0] for k in ("kdtree", "brute"))
        row["differing_j_sets"] = int(np.any(a != b, axis=1).sum())
        out["channels"][name] = row
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

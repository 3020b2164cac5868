"""Benchmark: ``lino-loc map extend`` against a full rebuild of the same map.

Given a map built from a first survey (``--map``, e.g. the tube survey), that survey's
dataset (``--base``) and a new session's dataset (``--session``, e.g. under bulb light),
times, each the median of ``--repeat`` runs in this process (image decoding included, as
in the commands; the map file's save excluded from both):

- ``extend_projected``: load the map, decode the session's images, project them
  (``lino_loc.map_extend.extend_map`` with ``refit="never"``);
- ``extend_refitted``: the same with the incremental refit of the basis (``refit="always"``);
- ``rebuild``: decode both surveys' images and fit the map from scratch
  (``lino_loc.appearance_map.intensity_channel_from_vectors``: what ``lino-loc map build``
  does on a dataset holding both sessions; randomized PCA, the map build's default).

Prints one JSON object with the machine (``services.evaluation.machine.machine``). Run
single-threaded as the other benchmarks (``OPENBLAS_NUM_THREADS=1 ...``; it re-runs itself
with the thread variables set when they are not)::

    python benchmarks/bench_map_extend.py --map lab-tube.npz --base lab-tube --session lab-bulb --repeat 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from collections.abc import Callable

import numpy as np

from lino_loc.appearance_map import AppearanceMap, intensity_channel_from_vectors, load_vectors
from lino_loc.dataset import Dataset
from lino_loc.map_extend import extend_map
from services.evaluation.machine import THREAD_VARS, machine, single_threaded


def _median_time(fn: Callable[[], object], repeat: int) -> dict[str, float | list[float]]:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return {"median_s": round(statistics.median(times), 4), "runs_s": [round(t, 4) for t in times]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", required=True, help="map built from --base")
    ap.add_argument("--base", required=True, help="the dataset the map was built from")
    ap.add_argument("--session", required=True, help="the new session's dataset")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--workers", type=int, default=1, help="image decoding threads (both paths)")
    args = ap.parse_args(argv)
    if not single_threaded():
        env = dict(os.environ, **{v: "1" for v in THREAD_VARS})
        os.execve(sys.executable, [sys.executable, *sys.argv], env)
    amap0 = AppearanceMap.load(args.map)
    ch = amap0.channels["intensity"]
    base, sess = Dataset.open(args.base), Dataset.open(args.session)

    def extend(mode: str) -> Callable[[], object]:
        return lambda: extend_map(AppearanceMap.load(args.map), Dataset.open(args.session), refit=mode,  # type: ignore[arg-type]
                                  workers=args.workers)

    def rebuild() -> object:
        X = np.vstack([load_vectors(Dataset.open(args.base), ch.preprocess, ch.size, workers=args.workers),  # type: ignore[arg-type]
                       load_vectors(Dataset.open(args.session), ch.preprocess, ch.size, workers=args.workers)])  # type: ignore[arg-type]
        return intensity_channel_from_vectors(X, ch.preprocess, ch.size, ch.n_features)  # type: ignore[arg-type]

    res = {
        "map": args.map,
        "entries_before": len(amap0),
        "base_images": len(base),
        "session_images": len(sess),
        "features": ch.n_features,
        "size": list(ch.size),
        "repeat": args.repeat,
        "workers": args.workers,
        "extend_projected": _median_time(extend("never"), args.repeat),
        "extend_refitted": _median_time(extend("always"), args.repeat),
        "rebuild": _median_time(rebuild, args.repeat),
        "machine": machine(),
    }
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

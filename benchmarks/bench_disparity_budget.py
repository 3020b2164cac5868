"""The disparity channel's EM within a memory budget: time, peak memory and the subspace found.

    .venv/bin/python benchmarks/bench_disparity_budget.py DATASET [--budgets 1024,100000]
        [--repeats 3] [--features 5] [--virtual-headings 5]

Builds the disparity channel of ``DATASET`` (a survey folder with a ``disparity`` column, e.g.
the output of ``lino-loc dataset translate``) once per budget and repeat, each build in a fresh
process (so that its peak resident memory is its own), budgets interleaved within each repeat.
Prints one JSON object: per budget the median wall seconds, the median peak resident MiB, the
entries the EM was fitted on, and, against the largest budget's channel, the principal angles
between the two subspaces (degrees) and the mean overlap of the 10 nearest map entries of 300
seeded entries in feature space. Numeric libraries are limited to one thread.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def build_one(dataset: str, budget: float, features: int, virtual_headings: int, out: str) -> None:
    """One build in this process: saves components and features to ``out``, prints its figures."""
    import math
    import resource
    import time

    from lino_loc.appearance_map import build_disparity_channel, virtual_setup
    from lino_loc.dataset import Dataset
    from lino_loc.virtual_views import offsets

    ds = Dataset.open(dataset)
    virtual = None if virtual_headings <= 1 else virtual_setup(
        ds.meta.camera, (80, 60), offsets(math.radians(3.0), virtual_headings))
    t0 = time.perf_counter()
    ch = build_disparity_channel(ds, features, (80, 60), seed=0, virtual=virtual, memory_budget_mb=budget)
    seconds = time.perf_counter() - t0
    np.savez(out, components=ch.pca.components, features=ch.features)
    print(json.dumps({"seconds": seconds, "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "fit_rows": ch.params["fit_rows"], "entries": len(ch.features)}))


def compare(a: Path, b: Path, queries: int = 300, k: int = 10) -> dict[str, object]:
    """Principal angles (deg) between two channels' subspaces and their mean k-NN overlap."""
    from scipy.linalg import subspace_angles

    A, B = np.load(a), np.load(b)
    angles = np.degrees(subspace_angles(A["components"].T.astype(float), B["components"].T.astype(float)))
    Ya, Yb = A["features"].astype(float), B["features"].astype(float)
    picks = np.random.default_rng(0).choice(len(Ya), min(queries, len(Ya)), replace=False)
    overlap = []
    for i in picks:
        na = np.argsort(((Ya - Ya[i]) ** 2).sum(1))[1 : k + 1]
        nb = np.argsort(((Yb - Yb[i]) ** 2).sum(1))[1 : k + 1]
        overlap.append(len(set(na.tolist()) & set(nb.tolist())) / k)
    return {"principal_angles_deg": [round(float(v), 2) for v in sorted(angles)], "knn_overlap": float(np.mean(overlap))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--budgets", default="1024,100000", help="MiB, comma-separated")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--features", type=int, default=5)
    ap.add_argument("--virtual-headings", type=int, default=5)
    ap.add_argument("--one", nargs=2, metavar=("BUDGET", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        build_one(args.dataset, float(args.one[0]), args.features, args.virtual_headings, args.one[1])
        return 0
    budgets = [float(b) for b in args.budgets.split(",")]
    runs: dict[float, list[dict[str, float]]] = {b: [] for b in budgets}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeats):
            for b in budgets:
                out = Path(tmp) / f"{b:g}.npz"
                done = subprocess.run(  # noqa: S603 - this script, this interpreter
                    [sys.executable, __file__, args.dataset, "--features", str(args.features),
                     "--virtual-headings", str(args.virtual_headings), "--one", str(b), str(out)],
                    check=True, capture_output=True, text=True)
                runs[b].append(json.loads(done.stdout.strip().splitlines()[-1]))
        ref = Path(tmp) / f"{max(budgets):g}.npz"
        res = {f"{b:g}": {"seconds_median": round(statistics.median(r["seconds"] for r in runs[b]), 1),
                          "peak_mib_median": round(statistics.median(r["peak_mib"] for r in runs[b])),
                          "fit_rows": runs[b][0]["fit_rows"], "entries": runs[b][0]["entries"],
                          **({} if b == max(budgets) else compare(Path(tmp) / f"{b:g}.npz", ref))}
               for b in budgets}
    print(json.dumps({"dataset": args.dataset, "repeats": args.repeats, "budgets": res,
                      "machine": {"platform": platform.platform(), "cpu": platform.processor() or platform.machine(),
                                  "cpu_count": os.cpu_count(), "load_average": os.getloadavg()}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

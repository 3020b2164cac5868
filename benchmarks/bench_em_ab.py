"""Benchmark: the EM fit of PCA with missing data, old against new, interleaved (A/B).

Prints one JSON object: per variant the median / min / max wall time, CPU time, peak memory
(tracemalloc: numpy buffers allocated during the fit, the input excluded), EM iterations,
whether the fit converged, and the final objective per value, over ``--repeats`` runs; the
runs alternate between the variants (A B A B ...) so that a change of machine load hits
both alike; the machine (platform, CPU, cores, load average, BLAS threads) is named.

Variants:

- ``new``: :func:`lino_loc.pca_missing.fit_pca_missing` with its defaults (the MAP fit);
- ``old``: ``--baseline FILE``, another version of ``lino_loc/pca_missing.py`` loaded from
  a file (e.g. ``git show REV:lino_loc/pca_missing.py > /tmp/old_pca_missing.py``), with
  its defaults; without ``--baseline`` the ML fit of the current module
  (``prior_weight=0``).

Data: ``--data MAPS.npy`` an (N, D) NaN-sparse matrix (e.g. the 80 x 60 disparity maps of a
survey); ``--dataset DIR`` a dataset folder with a disparity (or depth) column, whose whole
map build (``build_map``, intensity + disparity, what ``lino-loc map build --channels
intensity,disparity`` does) is timed instead, the disparity channel's EM being the variant.

    python benchmarks/bench_em_ab.py --data maps.npy [--baseline old.py] [--repeats 3]
    python benchmarks/bench_em_ab.py --dataset SURVEY [--baseline old.py] [--repeats 3]
        [--d 5 --virtual-headings 5]     # the simulated service's map (config/sim.toml)

``new_against_old``: the largest and second principal angles between the two variants'
subspaces (last runs) and the fraction of the old model's variance outside the new span.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import resource
import statistics
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lino_loc import pca_missing  # noqa: E402

FitFn = Callable[..., Any]


def _baseline(path: str | None) -> FitFn:
    """The old variant's fit function (see the module docstring)."""
    if path is None:
        return lambda *a, **k: pca_missing.fit_pca_missing(*a, prior_weight=0.0, **k)
    spec = importlib.util.spec_from_file_location("baseline_pca_missing", path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"{path}: cannot load as a Python module")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up while it runs
    spec.loader.exec_module(mod)
    return mod.fit_pca_missing


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _fit_once(fit: FitFn, X: np.ndarray, d: int, max_iter: int) -> tuple[dict, Any]:
    tracemalloc.start()
    tracemalloc.reset_peak()
    c0, t0 = _cpu(), time.perf_counter()
    model = fit(X, d, seed=0, max_iter=max_iter, dtype=np.float32)
    wall, cpu = time.perf_counter() - t0, _cpu() - c0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return {"wall_s": wall, "cpu_s": cpu, "peak_mb": peak / 2**20, "iterations": model.n_iter,
            "converged": bool(model.converged), "objective": float(model.log_likelihood[-1])}, model


def _build_once(fit: FitFn, dataset: Path, d: int, virtual: int) -> tuple[dict, Any]:
    """The whole map build with the disparity channel's EM replaced by ``fit`` (``virtual``
    headings 3 deg apart per image when > 1, as the simulated service's map)."""
    import math

    from lino_loc.appearance_map import build_map
    from lino_loc.dataset import Dataset
    from lino_loc.virtual_views import offsets

    saved = pca_missing.fit_pca_missing
    pca_missing.fit_pca_missing = fit  # build_disparity_channel imports it at call time
    try:
        tracemalloc.start()
        tracemalloc.reset_peak()
        c0, t0 = _cpu(), time.perf_counter()
        amap = build_map(Dataset.open(dataset), n_features=d, channels=("intensity", "disparity"),
                         virtual_offsets=None if virtual <= 1 else offsets(math.radians(3.0), virtual))
        wall, cpu = time.perf_counter() - t0, _cpu() - c0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    finally:
        pca_missing.fit_pca_missing = saved
    p = amap.channels["disparity"].params
    model = amap.channels["disparity"].pca
    return {"wall_s": wall, "cpu_s": cpu, "peak_mb": peak / 2**20, "iterations": model.n_iter,
            "converged": bool(model.converged), "valid_fraction": p.get("valid_fraction"),
            "source": p.get("source")}, model


def _agreement(a: Any, b: Any) -> dict:
    """How the two variants' subspaces differ: the largest and second largest principal
    angles (degrees), and the fraction of b's model variance outside span(a)."""
    from scipy.linalg import subspace_angles

    ang = np.sort(np.degrees(subspace_angles(a.components.T, b.components.T)))[::-1]
    proj = a.components @ b.components.T  # (d, d)
    lost = 1.0 - float(np.sum(b.explained_variance * np.sum(proj**2, axis=0)) / np.sum(b.explained_variance))
    return {"max_angle_deg": round(float(ang[0]), 4), "second_angle_deg": round(float(ang[min(1, len(ang) - 1)]), 4),
            "variance_outside": lost}


def _summary(runs: list[dict]) -> dict:
    out: dict = {"runs": runs}
    for key in ("wall_s", "cpu_s", "peak_mb", "iterations"):
        vals = [r[key] for r in runs]
        out[key] = {"median": round(statistics.median(vals), 3), "min": round(min(vals), 3),
                    "max": round(max(vals), 3)}
    out["converged"] = [r["converged"] for r in runs]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", help="(N, D) .npy with NaN = missing")
    src.add_argument("--dataset", help="dataset folder: time the whole map build")
    ap.add_argument("--baseline", default=None, help="old pca_missing.py (default: the ML fit of this one)")
    ap.add_argument("--d", type=int, default=20)
    ap.add_argument("--max-iter", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--virtual-headings", type=int, default=1, help="with --dataset: map entries per image")
    args = ap.parse_args(argv)
    variants = {"old": _baseline(args.baseline), "new": pca_missing.fit_pca_missing}
    X = np.load(args.data) if args.data else None
    runs: dict[str, list[dict]] = {k: [] for k in variants}
    models: dict[str, Any] = {}
    load = [os.getloadavg()]
    for _ in range(args.repeats):
        for name, fit in variants.items():  # interleaved: A B A B ...
            if X is not None:
                run, models[name] = _fit_once(fit, X, args.d, args.max_iter)
            else:
                run, models[name] = _build_once(fit, Path(args.dataset), args.d, args.virtual_headings)
            runs[name].append(run)
            load.append(os.getloadavg())
    result = {
        "benchmark": "em_ab",
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                    "cpu_count": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__,
                    "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
                    "load_average_1min": [round(v[0], 2) for v in load]},
        "data": args.data or args.dataset,
        "shape": list(X.shape) if X is not None else None,
        "missing_fraction": round(float(np.isnan(X).mean()), 4) if X is not None else None,
        "baseline": args.baseline or "fit_pca_missing(prior_weight=0)",
        "d": args.d, "max_iter": args.max_iter, "repeats": args.repeats,
        "virtual_headings": args.virtual_headings if args.dataset else None,
        **{name: _summary(r) for name, r in runs.items()},
        "new_against_old": _agreement(models["new"], models["old"]),
    }
    wall = result["new"]["wall_s"]["median"] / max(result["old"]["wall_s"]["median"], 1e-9)
    result["new_over_old_wall"] = round(wall, 3)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

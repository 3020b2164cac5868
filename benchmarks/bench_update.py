"""One full localization update (preprocess + project a 320 x 240 image + J-nearest search +
APF update) on the lab map, for 150 / 1000 / 10000 particles, and its growth with the map size.

    python benchmarks/bench_update.py [--repeats 300] [--preprocess none|histeq|gradient]

Prints one JSON object, the same as ``lino-loc bench update --json`` (see
services/evaluation/update_cost.py for what is measured): ``update_ms`` {particles: {median, p99, min,
cpu_median}}, ``map_scaling`` {entries: {...}}, ``machine`` (platform, cpu, cpu_count,
load_average). Numeric libraries are limited to one thread before numpy is imported.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.evaluation.update_cost import run_update_bench  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=300)
    ap.add_argument("--preprocess", default=None, choices=("none", "histeq", "gradient"))
    args = ap.parse_args(argv)
    print(json.dumps(run_update_bench(repeats=args.repeats, preprocess=args.preprocess)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

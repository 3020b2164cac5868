"""Cost of one active-vision action evaluation H(u) against particles and actions.

    python benchmarks/bench_active.py [--repeats 30]

Prints one JSON object (see services/evaluation/action_cost.py, the same measurement as
``lino-loc bench active --json``): median wall-clock and process-CPU milliseconds per
evaluation for 50 / 150 / 500 particles (22 actions) and 11 / 22 / 44 actions (150
particles) on the office grid map, single-threaded, and the machine (platform, cpu count,
load average).
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

from services.evaluation.action_cost import run_active_bench  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args(argv)
    print(json.dumps(run_active_bench(repeats=args.repeats)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

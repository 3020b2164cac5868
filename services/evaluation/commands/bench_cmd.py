"""`lino-loc bench ...`: speed measurements a user runs on the robot's own computer.

``update`` is defined here (:mod:`services.evaluation.update_cost`); further benchmarks live in
the modules of :data:`BENCH_MODULES`, each exposing ``register_bench(bench_subparsers)``.

Numeric libraries run with one thread: their thread count is fixed when numpy is loaded, so
when the variables are not already 1 a benchmark re-runs itself
(``python -m services.evaluation.commands.bench_cmd``) with them set to 1.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys

from services.evaluation.machine import THREAD_VARS, single_threaded
from services.evaluation.update_cost import run_update_bench

BENCH_MODULES: tuple[str, ...] = ("services.evaluation.commands.bench_active_cmd",)


def _update(args: argparse.Namespace) -> int:
    if not single_threaded() and not args.no_reexec:
        env = dict(os.environ, **{v: "1" for v in THREAD_VARS})
        cmd = [sys.executable, "-m", "services.evaluation.commands.bench_cmd", "update", "--repeats", str(args.repeats), "--no-reexec"]
        if args.json:
            cmd.append("--json")
        if args.preprocess:
            cmd += ["--preprocess", args.preprocess]
        return subprocess.call(cmd, env=env)
    res = run_update_bench(repeats=args.repeats, preprocess=args.preprocess)
    if args.json:
        print(json.dumps(res))
        return 0
    m = res["machine"]
    print(f"one update on the lab map ({res['map']['entries']} entries, {res['map']['features']} features, "
          f"{res['image'][0]}x{res['image'][1]} image); {m['cpu']}, {m['cpu_count']} cpus, load {m['load_average']}")
    for n, r in res["update_ms"].items():
        print(f"  {n:>6} particles: median {r['median']:.2f} ms  p99 {r['p99']:.2f} ms  (cpu {r['cpu_median']:.2f} ms)")
    print("map size at 1000 particles:")
    for r in res["map_scaling"].values():
        print(f"  {r['entries']:>6} entries{' (synthetic)' if r['synthetic'] else ''}: median {r['median']:.2f} ms  "
              f"p99 {r['p99']:.2f} ms  search {r['search_median_ms']:.3f} ms ({r['index']})")
    st = res["standing_ms"]
    print(f"a standing robot, head turning, {st['particles']} particles: standing match on: median "
          f"{st['on']['median']:.2f} ms ({st['views_kept']} views kept), off: {st['off']['median']:.2f} ms")
    return 0


def _add_update(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser("update", help="time one localization update (150/1000/10000 particles, map sizes)")
    p.add_argument("--repeats", type=int, default=300, help="timed updates per setting (10000 particles: a third)")
    p.add_argument("--preprocess", default=None, choices=("none", "histeq", "gradient"),
                   help="map preprocessing (default: the tracking evaluation's)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--no-reexec", action="store_true", help=argparse.SUPPRESS)
    p.set_defaults(func=_update)


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("bench", help="speed measurements (run them on the robot's computer)")
    bench_sub = parser.add_subparsers(dest="benchmark", metavar="BENCHMARK", parser_class=type(parser))
    bench_sub.required = True
    _add_update(bench_sub)
    for name in BENCH_MODULES:
        importlib.import_module(name).register_bench(bench_sub)


def main(argv: list[str] | None = None) -> int:
    """Entry of the single-threaded re-run (``python -m services.evaluation.commands.bench_cmd update ...``)."""
    from services.cli import main as cli_main

    return cli_main(["bench", *(argv if argv is not None else sys.argv[1:])])


if __name__ == "__main__":
    sys.exit(main())

"""`lino-loc bench active`: the cost of one action evaluation H(u)
(:mod:`services.evaluation.action_cost`), single-threaded like ``bench update``."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from typing import Any

from services.evaluation.action_cost import run_active_bench
from services.evaluation.machine import THREAD_VARS, single_threaded


def _table(res: dict[str, Any]) -> str:
    m = res["machine"]
    lines = [f"one H(u) evaluation, office grid map ({res['map_entries']} entries, J = {res['j']}); "
             f"{m['cpu']}, {m['cpu_count']} cpus, load {m['load_average']}",
             f"{'':<24}{'median ms':>12}{'cpu ms':>10}"]
    for n, r in res["particles"].items():
        lines.append(f"{n + ' particles, 22 actions':<24}{r['median_ms']:>12.2f}{r['cpu_median_ms']:>10.2f}")
    for a, r in res["actions"].items():
        lines.append(f"{'150 particles, ' + a + ' actions':<24}{r['median_ms']:>12.2f}{r['cpu_median_ms']:>10.2f}")
    g = res["generic_path_150x22"]
    lines.append(f"{'generic path 150 x 22':<24}{g['median_ms']:>12.2f}{g['cpu_median_ms']:>10.2f}")
    v = res["virtual_headings_150x22"]
    lines.append(f"{'3-deg map, 150 x 22':<24}{v['median_ms']:>12.2f}{v['cpu_median_ms']:>10.2f}"
                 f"   ({v['map_entries']} entries: virtual headings)")
    t3 = res["translated_150x22"]
    lines.append(f"{'25 cm, 3-deg map, 150 x 22':<24}{t3['median_ms']:>12.2f}{t3['cpu_median_ms']:>10.2f}"
                 f"   ({t3['map_entries']} entries: virtual translations)")
    i = res["interpolated_150x22"]
    lines.append(f"{'interpolated, 150 x 22':<24}{i['median_ms']:>12.2f}{i['cpu_median_ms']:>10.2f}"
                 f"   (3-deg map; model built in {i['setup_s']:.2f} s)")
    t = res["target"]
    lines.append(f"target <= {t['ms_max']} ms at 150 particles x 22 actions: wall {'met' if t['met_wall'] else 'NOT met'}, "
                 f"cpu {'met' if t['met_cpu'] else 'NOT met'}")
    return "\n".join(lines)


def _active(args: argparse.Namespace) -> int:
    if not single_threaded() and not args.no_reexec:
        env = dict(os.environ, **{v: "1" for v in THREAD_VARS})
        cmd = [sys.executable, "-m", "services.evaluation.commands.bench_cmd", "active", "--repeats", str(args.repeats),
               "--no-reexec"] + (["--json"] if args.json else [])
        return subprocess.call(cmd, env=env)
    res = run_active_bench(repeats=args.repeats)
    print(json.dumps(res) if args.json else _table(res))
    return 0


def register_bench(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser("active", help="time one active-vision action evaluation H(u)")
    p.add_argument("--repeats", type=int, default=30, help="timed evaluations per setting")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--no-reexec", action="store_true", help=argparse.SUPPRESS)
    p.set_defaults(func=_active)

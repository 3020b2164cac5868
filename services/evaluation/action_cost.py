"""`lino-loc bench active`: the cost of one action evaluation H(u) (lino_loc.active_vision).

Measures :meth:`lino_loc.active_vision.ActionEvaluator.evaluate` against the number of
particles (50 / 150 / 500, at 22 actions) and of actions (11 / 22 / 44, at 150 particles),
single-threaded (numeric libraries limited to one thread; like ``bench update`` the command
re-runs itself with the thread variables set to 1). The map is the office survey's grid (75 cm
and 15 degrees over 800 x 250 cm: 11 x 4 positions x 24 headings = 1056 entries) with
5 synthetic features that vary smoothly with the pose (the cost does not depend on the
features' values, only on N, J and the grid structure); J = 10. The belief is the worst case:
``particles`` DISTINCT particles spread uniformly over the office and all headings (the
uniform initial belief; converged beliefs have many duplicate particles, which are merged
and cost less). Reported: median wall-clock and median process-CPU time per evaluation
(the CPU time is the fairer figure when other jobs share the machine), for the fast path
(product-grid map) and, at 150 particles and 22 actions, the generic path (any map). The
target is 20 ms for 150 particles and 22 actions.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from typing import Any

PARTICLES = (50, 150, 500)
ACTIONS = (11, 22, 44)
TARGET_MS = 20.0


def office_like_map(seed: int = 0, heading_step_deg: float = 15.0) -> tuple[Any, Any]:
    """(poses (N, 3), features (N, 5)): the office grid (11 x 4 positions, headings every
    ``heading_step_deg``: 1056 entries at 15 deg, 5280 at 3 deg as with virtual headings) with
    smooth synthetic features."""
    import numpy as np

    from lino_loc.poses import wrap_angle

    rng = np.random.default_rng(seed)
    xs = np.arange(11) * 0.75
    ys = np.arange(4) * 0.75
    hs = wrap_angle(np.radians(np.arange(int(round(360.0 / heading_step_deg))) * heading_step_deg))
    gx, gy, gh = np.meshgrid(xs, ys, hs, indexing="ij")
    poses = np.column_stack([gx.ravel(), gy.ravel(), gh.ravel()])
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    feats = np.column_stack([
        3 * c + 0.3 * poses[:, 0], 3 * s + 0.3 * poses[:, 1], np.sin(poses[:, 0]) * c,
        np.cos(poses[:, 1]) * s, 0.3 * rng.standard_normal(len(poses)),
    ])
    return poses, feats


def _time(fn: Any, repeats: int) -> dict[str, float]:
    import time

    import numpy as np

    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {"median_ms": float(np.median(wall) * 1e3), "cpu_median_ms": float(np.median(cpu) * 1e3),
            "min_ms": float(np.min(wall) * 1e3)}


def run_active_bench(repeats: int = 30, particles: tuple[int, ...] = PARTICLES,
                     actions: tuple[int, ...] = ACTIONS) -> dict[str, Any]:
    """The measurements of ``lino-loc bench active`` as a JSON-ready dict."""
    import numpy as np

    from lino_loc.active_vision import ActionEvaluator, ActiveVisionConfig
    from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig
    from services.commands.bench import machine

    poses, feats = office_like_map()
    model = NearestNeighbourSensorModel(poses, feats, SensorModelConfig(j=10))
    rng = np.random.default_rng(1)

    def belief(m: int) -> tuple[Any, Any]:
        p = np.column_stack([rng.uniform(0, 7.5, m), rng.uniform(0, 2.25, m), rng.uniform(-math.pi, math.pi, m)])
        return p, np.full(m, -math.log(m))

    out: dict[str, Any] = {"map_entries": int(len(poses)), "j": 10, "repeats": int(repeats),
                           "particles": {}, "actions": {}}
    for m in particles:
        ev = ActionEvaluator(model, ActiveVisionConfig(n_actions=22, max_particles=m))
        p, lw = belief(m)
        out["particles"][str(m)] = _time(lambda ev=ev, p=p, lw=lw: ev.evaluate(p, lw), repeats)
    for a in actions:
        if a == 22 and "150" in out["particles"]:  # the same setting: one measurement, one figure
            out["actions"][str(a)] = out["particles"]["150"]
            continue
        ev = ActionEvaluator(model, ActiveVisionConfig(n_actions=a, max_particles=150))
        p, lw = belief(150)
        out["actions"][str(a)] = _time(lambda ev=ev, p=p, lw=lw: ev.evaluate(p, lw), repeats)
    generic = ActionEvaluator(model, ActiveVisionConfig(), use_grid=False)
    p, lw = belief(150)
    out["generic_path_150x22"] = _time(lambda: generic.evaluate(p, lw), max(5, repeats // 3))
    # the map with virtual headings (lino_loc.virtual_views): 5 per image, every 3 deg
    vposes, vfeats = office_like_map(heading_step_deg=3.0)
    vmodel = NearestNeighbourSensorModel(vposes, vfeats, SensorModelConfig(j=10))
    vev = ActionEvaluator(vmodel, ActiveVisionConfig(n_actions=22, max_particles=150))
    out["virtual_headings_150x22"] = {"map_entries": int(len(vposes)),
                                      **_time(lambda: vev.evaluate(p, lw), repeats)}
    ref = out["particles"].get("150") or out["actions"].get("22")
    out["target"] = {"particles": 150, "actions": 22, "ms_max": TARGET_MS,
                     "met_wall": bool(ref and ref["median_ms"] <= TARGET_MS),
                     "met_cpu": bool(ref and ref["cpu_median_ms"] <= TARGET_MS)}
    out["machine"] = machine()
    return out


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
    t = res["target"]
    lines.append(f"target <= {t['ms_max']} ms at 150 particles x 22 actions: wall {'met' if t['met_wall'] else 'NOT met'}, "
                 f"cpu {'met' if t['met_cpu'] else 'NOT met'}")
    return "\n".join(lines)


def _active(args: argparse.Namespace) -> int:
    from services.commands.bench import THREAD_VARS, single_threaded

    if not single_threaded() and not args.no_reexec:
        env = dict(os.environ, **{v: "1" for v in THREAD_VARS})
        cmd = [sys.executable, "-m", "services.commands.bench", "active", "--repeats", str(args.repeats),
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

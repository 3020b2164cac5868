"""A standing robot's update on the product's map: the standing match's cost where the service runs it.

``lino-loc bench update`` times the standing update on the lab's bench map (a position every
50 cm, a heading every 10 deg), where few hypotheses lie near the estimate. The product's map
(``eval active``'s defaults: the survey every 75 cm / 15 deg, virtual headings every 3 deg,
virtual translations every 25 cm, 20 intensity + 5 disparity features) holds many more, and
the match's cost grows with them. This builds that map for a world
(:func:`services.evaluation.active.build_map`, the simulated service's cache), renders the
views of a standing robot at a free pose of the mapped area at the pans of
:data:`services.evaluation.update_cost.STANDING_PANS`, and times the update at 1000 particles
with the match on and off, interleaved (:func:`services.evaluation.update_cost.time_standing`:
median, p99 and min in ms, the updates whose match moved the belief, the views kept). Prints
one JSON object with the machine.

Usage::

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_standing_update.py --world office [--repeats 150]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def free_pose(world: object, seed: int) -> np.ndarray:
    """A free pose (x, y, 0.3 rad) drawn uniformly in the world's mapped area."""
    rng = np.random.default_rng(seed)
    xmin, xmax, ymin, ymax = world.mapped_area  # type: ignore[attr-defined]
    for _ in range(10000):
        x, y = rng.uniform(xmin, xmax), rng.uniform(ymin, ymax)
        if world.is_free(np.array([x]), np.array([y]))[0]:  # type: ignore[attr-defined]
            return np.array([x, y, 0.3])
    raise SystemExit("bench_standing_update: no free pose found in the mapped area")


def main() -> None:
    from drivers.sim.world import load_world
    from services.evaluation.active import build_map
    from services.evaluation.active_setup import product_defaults
    from services.evaluation.machine import machine
    from services.evaluation.update_cost import STANDING_PANS, time_standing
    from services.evaluation.views import ViewSpec, render_grey

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--world", default="office")
    p.add_argument("--repeats", type=int, default=150, help="timed updates per arm")
    p.add_argument("--seed", type=int, default=3, help="the standing pose's draw")
    a = p.parse_args()
    if a.repeats < 1:
        p.error(f"--repeats must be at least 1 (got {a.repeats})")
    s = product_defaults(world=a.world, seed=0, workers=2)
    t0 = time.perf_counter()
    amap = build_map(s)
    map_s = time.perf_counter() - t0
    pose = free_pose(load_world(a.world), a.seed)
    cams = np.array([[pose[0], pose[1], pose[2] + pan] for pan in STANDING_PANS])
    views = render_grey(ViewSpec(world=a.world, lighting=s.lighting, seed=7), cams, workers=1)
    result = time_standing(amap, 1000, views, pose, a.repeats)
    print(json.dumps({"benchmark": "bench_standing_update", "world": a.world, "map_entries": len(amap),
                      "pose": [round(float(v), 3) for v in pose], "standing_ms": result,
                      "map_seconds": round(map_s, 1), "machine": machine()}))


if __name__ == "__main__":
    main()

"""The cost of one action evaluation H(u) (lino_loc.active_vision), as ``lino-loc bench active`` reports it.

Measures :meth:`lino_loc.active_vision.ActionEvaluator.evaluate` against the number of
particles (50 / 150 / 500, at 22 actions) and of actions (11 / 22 / 44, at 150 particles),
single-threaded (the caller limits numeric libraries to one thread before numpy is loaded). The map is the office survey's grid (75 cm
and 15 degrees over 800 x 250 cm: 11 x 4 positions x 24 headings = 1056 entries) with
5 synthetic features that vary smoothly with the pose (the cost does not depend on the
features' values, only on N, J and the grid structure); J = 10. The belief is the worst case:
``particles`` DISTINCT particles spread uniformly over the office and all headings (the
uniform initial belief; converged beliefs have many duplicate particles, which are merged
and cost less). Reported: median wall-clock and median process-CPU time per evaluation
(the CPU time is the fairer figure when other jobs share the machine), for the fast path
(product-grid map) and, at 150 particles and 22 actions, the generic path (any map) and the
interpolated sensor model's evaluator on the map with virtual headings, and the map with virtual
headings and virtual translations (positions every 25 cm). The target is 20 ms
for 150 particles and 22 actions.
"""

from __future__ import annotations

import math
from typing import Any

from services.evaluation.machine import machine

PARTICLES = (50, 150, 500)
ACTIONS = (11, 22, 44)
TARGET_MS = 20.0


def office_like_map(seed: int = 0, heading_step_deg: float = 15.0, refinement: int = 1) -> tuple[Any, Any]:
    """(poses (N, 3), features (N, 5)): the office grid (11 x 4 positions every 75 cm, headings
    every ``heading_step_deg``: 1056 entries at 15 deg, 5280 at 3 deg as with virtual headings;
    ``refinement`` m: positions every 75 / m cm over the same area, as a map with virtual
    translations has them: 31 x 10 x 120 = 37200 entries for m = 3 at 3 deg) with smooth
    synthetic features."""
    import numpy as np

    from lino_loc.poses import wrap_angle

    rng = np.random.default_rng(seed)
    xs = np.arange(10 * refinement + 1) * (0.75 / refinement)
    ys = np.arange(3 * refinement + 1) * (0.75 / refinement)
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


def _interpolated(poses: Any, feats: Any, p: Any, lw: Any, repeats: int) -> dict[str, Any]:
    """H(u) of the interpolated sensor model (lino_loc.interpolated_appearance) on the map with
    virtual headings, 150 particles x 22 actions; ``setup_s``: building the model and its
    evaluator once (the map entries' normalizers)."""
    import time

    from lino_loc.active_vision import ActiveVisionConfig, InterpolatedActionEvaluator
    from lino_loc.interpolated_appearance import InterpolatedSensorModel
    from lino_loc.sensor_model import SensorModelConfig

    t0 = time.perf_counter()
    ev = InterpolatedActionEvaluator(InterpolatedSensorModel(poses, feats, SensorModelConfig(j=10)),
                                     ActiveVisionConfig(n_actions=22, max_particles=150))
    setup_s = time.perf_counter() - t0
    return {"map_entries": int(len(poses)), "setup_s": round(setup_s, 3), **_time(lambda: ev.evaluate(p, lw), repeats)}


def run_active_bench(repeats: int = 30, particles: tuple[int, ...] = PARTICLES,
                     actions: tuple[int, ...] = ACTIONS) -> dict[str, Any]:
    """The measurements of ``lino-loc bench active`` as a JSON-ready dict."""
    import numpy as np

    from lino_loc.active_vision import ActionEvaluator, ActiveVisionConfig
    from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig

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
    out["interpolated_150x22"] = _interpolated(vposes, vfeats, p, lw, repeats)
    # virtual translations (lino_loc.virtual_translations) on top: positions every 25 cm
    tposes, tfeats = office_like_map(heading_step_deg=3.0, refinement=3)
    tev = ActionEvaluator(NearestNeighbourSensorModel(tposes, tfeats, SensorModelConfig(j=10)),
                          ActiveVisionConfig(n_actions=22, max_particles=150))
    out["translated_150x22"] = {"map_entries": int(len(tposes)), **_time(lambda: tev.evaluate(p, lw), repeats)}
    ref = out["particles"].get("150") or out["actions"].get("22")
    out["target"] = {"particles": 150, "actions": 22, "ms_max": TARGET_MS,
                     "met_wall": bool(ref and ref["median_ms"] <= TARGET_MS),
                     "met_cpu": bool(ref and ref["cpu_median_ms"] <= TARGET_MS)}
    out["machine"] = machine()
    return out

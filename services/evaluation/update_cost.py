"""The cost of one full localization update (what ``lino-loc bench update`` reports).

:func:`run_update_bench` times :meth:`lino_loc.localizer.Localizer.update` (preprocess and
project a 320 x 240 image, the J-nearest search in feature space, the auxiliary-particle-filter
update with its estimate) on the lab map (the lab survey grid, 50 cm / 10 deg, ~4500 entries,
rendered once and cached under ~/.cache/lino-loc/maps) for 150, 1000 and 10000 particles, and
how the cost grows with the map size (400 / 4000 / 40000 entries at 1000 particles; 400 is a
random subset of the lab map, 40000 the lab map's features with Gaussian perturbations:
synthetic). The frames are those of a short drive through the lab, fed with their odometry
increments, the filter started at the true pose (the tracking regime).

Times are wall-clock per update (median, p99, min) plus the median process-CPU time, which is
the fairer figure on a shared machine (see :func:`services.evaluation.machine.machine`). The
caller limits numeric libraries to one thread before numpy is loaded
(:func:`services.evaluation.machine.single_threaded`); OpenCV is set to one thread here.
"""

from __future__ import annotations

from typing import Any

from services.evaluation.machine import machine

PARTICLES = (150, 1000, 10000)
MAP_SIZES = (400, 4000, 40000)
#: The head's pans (rad) of the standing robot's views (:func:`time_standing`).
STANDING_PANS = (0.0, 0.8, 1.6, 2.4, -0.8, -1.6, -2.4, 0.4)


def _percentiles(ts: list[float]) -> dict[str, float]:
    import numpy as np

    a = np.asarray(ts) * 1000.0
    return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)), "min": float(a.min())}


def _time_updates(amap: Any, n_particles: int, frames: Any, repeats: int, warmup: int = 5) -> dict[str, float]:
    """Time ``repeats`` Localizer updates along the drive ``frames`` (images, increments, truth)."""
    import time

    import numpy as np

    from lino_loc.localizer import Localizer, LocalizerConfig

    images, inc, truth = frames
    cfg = LocalizerConfig()
    cfg.filter.n_particles = n_particles
    loc = Localizer(amap, cfg, rng=np.random.default_rng(0))
    cov = np.diag([0.1**2, 0.1**2, np.radians(5.0) ** 2])
    wall: list[float] = []
    cpu: list[float] = []
    k = len(images)
    for r in range(repeats + warmup):
        i = r % k
        if i == 0:
            loc.set_pose(truth[0], cov)
            continue
        t0, c0 = time.perf_counter(), time.process_time()
        loc.update(inc[i], 0.0, images[i])
        t1, c1 = time.perf_counter(), time.process_time()
        if r >= warmup:
            wall.append(t1 - t0)
            cpu.append(c1 - c0)
    out = _percentiles(wall)
    out["cpu_median"] = float(np.median(cpu) * 1000.0)
    out["updates"] = len(wall)
    return out


def time_standing(amap: Any, n_particles: int, views: Any, pose: Any, repeats: int,
                   warmup: int = 40) -> dict[str, Any]:
    """Time updates of a STANDING robot whose head turns: ``views`` (K images) taken at
    ``pose`` at the pans of :data:`STANDING_PANS` in turn, zero odometry, with the standing
    match on and off (two Localizers from the same seed, interleaved, the first of each pair
    alternating), each started from a recalled pose (an operator's would hold the match). The
    warm-up fills the match's views, one per pan. ``matches``: the updates whose match moved
    the belief; ``relocations``: of them, those a far place took (``StandingMatchConfig.relocate``);
    ``state``: the filter's at the end (the far places are matched only while it is ``global``)."""
    import time

    import numpy as np

    from lino_loc.localizer import Localizer, LocalizerConfig
    from lino_loc.standing_match import StandingMatchConfig

    cov = np.diag([0.1**2, 0.1**2, np.radians(5.0) ** 2])
    locs = {}
    for arm in ("on", "off"):
        cfg = LocalizerConfig(standing_match=StandingMatchConfig(enabled=arm == "on"))
        cfg.filter.n_particles = n_particles
        locs[arm] = Localizer(amap, cfg, rng=np.random.default_rng(0))
        locs[arm].set_pose(pose, cov, confirmed=False)
    wall: dict[str, list[float]] = {"on": [], "off": []}
    zero = np.zeros(3)
    for r in range(repeats + warmup):
        i = r % len(views)
        for arm in (("on", "off") if r % 2 == 0 else ("off", "on")):
            t0 = time.perf_counter()
            locs[arm].update(zero, STANDING_PANS[i % len(STANDING_PANS)], views[i])
            if r >= warmup:
                wall[arm].append(time.perf_counter() - t0)
    match = locs["on"].standing
    out: dict[str, Any] = {"particles": n_particles, "updates": repeats,
                           "lattice": match is not None, "views_kept": 0 if match is None else match.n_views,
                           "matches": locs["on"].standing_matches, "relocations": locs["on"].standing_relocations,
                           "state": locs["on"].filter.estimate().state}
    out.update({arm: _percentiles(ts) for arm, ts in wall.items()})
    return out


def _time_search(model: Any, queries: Any, repeats: int) -> float:
    import time

    import numpy as np

    ts = []
    for r in range(repeats):
        q = queries[r % len(queries)]
        t0 = time.perf_counter()
        model.neighbours(q)
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts) * 1000.0)


def _resized_map(amap: Any, entries: int, rng: Any) -> tuple[Any, bool]:
    """The lab map cut down (random subset, real features) or grown (perturbed copies: synthetic)."""
    import dataclasses

    import numpy as np

    from lino_loc.appearance_map import AppearanceMap

    n = len(amap)
    ch = amap.channels["intensity"]
    f = np.asarray(ch.features)
    p = np.asarray(amap.poses)
    if entries <= n:
        idx = np.sort(rng.choice(n, size=entries, replace=False))
        feats, poses, synthetic = f[idx], p[idx], False
    else:
        reps = int(np.ceil(entries / n))
        std = f.std(axis=0)
        feats = np.concatenate([f] + [f + 0.25 * std * rng.standard_normal(f.shape) for _ in range(reps - 1)])[:entries]
        jitter = [np.zeros_like(p)] + [
            np.column_stack([rng.uniform(-0.25, 0.25, (n, 2)), rng.uniform(-0.087, 0.087, n)]) for _ in range(reps - 1)
        ]
        poses = np.concatenate([p + j for j in jitter])[:entries]
        synthetic = True
    ch2 = dataclasses.replace(ch, features=np.ascontiguousarray(feats, dtype=np.float32))
    return AppearanceMap(poses=poses, channels={"intensity": ch2}, camera=amap.camera, source=amap.source), synthetic


def run_update_bench(
    repeats: int = 300,
    particles: tuple[int, ...] = PARTICLES,
    map_sizes: tuple[int, ...] = MAP_SIZES,
    preprocess: str | None = None,
    amap: Any = None,
    frames: Any = None,
    standing_views: Any = None,
) -> dict[str, Any]:
    """The measurements of ``lino-loc bench update`` (see module docstring) as a JSON-ready dict.

    ``amap`` and ``frames`` (images, increments, truth) override the lab map and the rendered
    drive (tests use tiny ones); ``standing_views``, the standing robot's views (default: rendered
    at the drive's first pose at :data:`STANDING_PANS`, or the first frames when ``frames`` is
    given). ``standing_ms``: a standing robot's update at 1000 particles with the standing match
    on and off (:func:`time_standing`)."""
    import numpy as np

    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:  # pragma: no cover
        pass
    from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig
    from services.evaluation.tracking import DEFAULT_PREPROCESS

    pre = preprocess or DEFAULT_PREPROCESS
    if amap is None:
        from services.evaluation.views import build_sim_maps

        amap = build_sim_maps("lab", 0.5, 10.0, 20, (pre,))[pre]
    from services.evaluation.views import ViewSpec, render_grey

    frames_given = frames is not None
    if frames is None:
        from drivers.sim.drive import DriveConfig, plan_drive
        from drivers.sim.world import load_world

        plan = plan_drive(load_world("lab"), DriveConfig(duration=8.0, camera_rate=5.0), seed=3)
        images = render_grey(ViewSpec(world="lab", lighting="tube", seed=5), plan.truth, workers=1)
        frames = (images, plan.increments, plan.truth)
    images = frames[0]
    if standing_views is None:
        if frames_given:
            standing_views = images[: len(STANDING_PANS)]
        else:
            cams = np.array([[*frames[2][0][:2], frames[2][0][2] + pan] for pan in STANDING_PANS])
            standing_views = render_grey(ViewSpec(world="lab", lighting="tube", seed=7), cams, workers=1)
    result: dict[str, Any] = {
        "map": {"world": "lab", "entries": len(amap), "features": int(amap.channels["intensity"].n_features),
                "preprocess": amap.channels["intensity"].preprocess},
        "image": [int(images.shape[2]), int(images.shape[1])],
        "repeats": int(repeats),
        "update_ms": {},
        "map_scaling": {},
    }
    for n in particles:
        reps = repeats if n <= 1000 else max(20, repeats // 3)
        result["update_ms"][str(n)] = _time_updates(amap, n, frames, reps)
    rng = np.random.default_rng(0)
    queries = np.asarray([amap.channels["intensity"].project(im) for im in images[:10]], dtype=np.float64)
    for size in map_sizes:
        m, synthetic = (amap, False) if size == 4000 else _resized_map(amap, size, rng)
        if m is amap and "1000" in result["update_ms"]:  # the headline setting: one measurement
            entry = dict(result["update_ms"]["1000"])
        else:
            entry = _time_updates(m, 1000, frames, max(20, repeats // 2))
        model = NearestNeighbourSensorModel(m.poses, np.asarray(m.channels["intensity"].features, dtype=np.float64),
                                            SensorModelConfig())
        entry.update({"entries": len(m), "synthetic": synthetic, "index": model.index_kind,
                      "search_median_ms": _time_search(model, queries, 200)})
        result["map_scaling"][str(size)] = entry
    result["standing_ms"] = time_standing(amap, 1000, standing_views, frames[2][0], max(20, repeats // 2))
    result["target"] = {"particles": 1000, "median_ms_max": 2.0,
                        "met": bool(result["update_ms"].get("1000", {}).get("median", np.inf) <= 2.0)}
    result["machine"] = machine()
    return result

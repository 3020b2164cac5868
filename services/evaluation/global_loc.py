"""Global localization in the simulated office (paper, section 6.1 and Fig. 3): error and success
against the number of updates, from a uniform initial belief.

Setting (section 6.1): the office world (800 x 250 cm mapped area), a map every 75 cm and
15 deg rendered under the mapping light (``tube``), 5 PCA features, J = 10. For each of
``starts`` runs the robot starts at a random free pose (off the map grid) and drives along a
drive plan (:mod:`drivers.sim.drive`, with odometry noise) with the camera fixed
(pan 0); the :class:`lino_loc.localizer.Localizer` starts from the uniform belief over the
mapped area and all headings and gets one (odometry increment, image) pair per update at
``rate`` Hz. After every update the estimate is compared with the truth:

- position error (metres) of the estimate, averaged (``mean_error_m``) and medianed
  (``median_error_m``) over the starts;
- success ratio (``success``): the fraction of starts whose estimate passes the criterion of
  section 6.1 (:func:`lino_loc.metrics.success`: the map POSITION nearest to the estimate is the
  map position nearest to the truth); ``success_pose`` the stricter (x, y, theta) cell variant
  (:func:`lino_loc.metrics.success_pose`, grid units of the map's 75 cm / 15 deg);
- heading error (degrees, median) and the fraction of runs whose filter state is
  ``tracking``.

The camera here does not move (the active choice of pan angles is :mod:`services.evaluation.active`),
so the views change only because the robot drives.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.sim.drive import DriveConfig, plan_drive
from drivers.sim.world import grid_poses, load_world
from lino_loc.localizer import Localizer, LocalizerConfig
from lino_loc.metrics import heading_errors, position_errors, success, success_pose
from services.evaluation.views import ViewSpec, build_sim_maps, render_frames

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GlobalSetup:
    world: str = "office"
    step: float = 0.75
    heading_step_deg: float = 15.0
    features: int = 5
    preprocess: str = "none"
    lighting: str = "tube"
    starts: int = 20
    updates: int = 30
    rate: float = 2.0
    particles: int | None = None  # None: the LocalizerConfig's
    j: int | None = None  # None: the LocalizerConfig's
    sensor_model: str | None = None  # None: the LocalizerConfig's ("nearest_neighbour" / "interpolated")
    width: int = 320
    height: int = 240
    size: tuple[int, int] = (80, 60)
    seed: int = 0
    workers: int | None = None
    virtual_headings: int = 5  # as config/sim.toml's map (lino_loc.virtual_views); 1: images alone
    virtual_step_deg: float = 3.0
    channels: tuple[str, ...] = ("intensity",)  # with "disparity": both channels, fused (eq. 8)


def localizer_config(setup: Any, base: LocalizerConfig | None) -> LocalizerConfig:
    """``base`` (or the defaults) with the setup's particle count, J and sensor model where it
    sets them."""
    cfg = (base or LocalizerConfig()).model_copy(deep=True)
    if setup.particles is not None:
        cfg.filter.n_particles = int(setup.particles)
    if setup.j is not None:
        cfg.sensor.j = int(setup.j)
    if getattr(setup, "sensor_model", None) is not None:
        cfg = LocalizerConfig.model_validate({**cfg.model_dump(), "sensor_model": setup.sensor_model})
    return cfg


def run(
    setup: GlobalSetup,
    config: LocalizerConfig | None = None,
    appearance_map: Any = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, Any]:
    """Run the evaluation; ``appearance_map`` overrides the rendered survey map (tests)."""
    world = load_world(setup.world)
    cfg = localizer_config(setup, config)
    given = appearance_map is not None
    if appearance_map is None:
        appearance_map = build_sim_maps(
            setup.world, setup.step, setup.heading_step_deg, setup.features, (setup.preprocess,),
            lighting=setup.lighting, width=setup.width, height=setup.height, size=setup.size,
            seed=setup.seed, workers=setup.workers,
            progress=(lambda d, n: progress("map", d, n)) if progress else None,
            virtual_headings=setup.virtual_headings, virtual_step_deg=setup.virtual_step_deg,
            disparity="disparity" in setup.channels,
        )[setup.preprocess]
    entries = np.asarray(appearance_map.poses, dtype=np.float64)
    # the success criteria's training points: the survey grid (the map's entries may add
    # virtual headings to it)
    map_poses = entries if given else grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    drive_cfg = DriveConfig(duration=max(setup.updates - 1, 1) / setup.rate, camera_rate=setup.rate)
    plans = [plan_drive(world, drive_cfg, seed=setup.seed * 100_003 + 1 + s) for s in range(setup.starts)]
    poses = np.concatenate([p.truth[: setup.updates] for p in plans])
    spec = ViewSpec(world=setup.world, lighting=setup.lighting, width=setup.width, height=setup.height,
                    size=setup.size, seed=setup.seed + 1, disparity="disparity" in setup.channels)
    images, disps = render_frames(spec, poses, workers=setup.workers,
                                  progress=(lambda d, n: progress("drive", d, n)) if progress else None)
    n_up = min(setup.updates, min(len(p) for p in plans))
    err = np.zeros((setup.starts, n_up))
    head = np.zeros((setup.starts, n_up))
    ok = np.zeros((setup.starts, n_up), dtype=bool)
    ok_pose = np.zeros((setup.starts, n_up), dtype=bool)
    tracking = np.zeros((setup.starts, n_up), dtype=bool)
    step_rad = math.radians(setup.heading_step_deg)
    for s, plan in enumerate(plans):
        loc = Localizer(appearance_map, cfg, rng=np.random.default_rng((setup.seed, s)))
        loc.start_global()
        inc = plan.increments
        est = np.zeros((n_up, 3))
        for k in range(n_up):
            i = s * setup.updates + k
            e = loc.update(inc[k], 0.0, images[i], None if disps is None else disps[i])
            est[k] = e.pose
            tracking[s, k] = e.state == "tracking"
        truth = plan.truth[:n_up]
        err[s] = position_errors(est, truth)
        head[s] = np.degrees(heading_errors(est, truth))
        ok[s] = success(est, truth, map_poses)  # section 6.1: nearest map position
        ok_pose[s] = success_pose(est, truth, map_poses, setup.step, step_rad)  # + heading cell
        if progress:
            progress("filter", s + 1, setup.starts)
        log.debug("start %d: final error %.2f m, success %s", s, err[s, -1], ok[s, -1])
    first_ok = [int(np.argmax(row)) + 1 if row.any() else None for row in ok]
    return {
        "world": setup.world,
        "starts": int(setup.starts),
        "updates": int(n_up),
        "rate_hz": float(setup.rate),
        "map_images": int(map_poses.shape[0]),
        "map_entries": int(entries.shape[0]),
        "map_step_m": float(setup.step),
        "map_heading_step_deg": float(setup.heading_step_deg),
        "features": int(np.asarray(appearance_map.channels["intensity"].features).shape[1]),
        "preprocess": setup.preprocess,
        "channels": list(setup.channels),
        "particles": int(cfg.filter.n_particles),
        "J": int(cfg.sensor.j),
        "sensor_model": cfg.sensor_model,
        "lighting": setup.lighting,
        "mean_error_m": [float(v) for v in err.mean(axis=0)],
        "median_error_m": [float(v) for v in np.median(err, axis=0)],
        "success": [float(v) for v in ok.mean(axis=0)],
        "success_pose": [float(v) for v in ok_pose.mean(axis=0)],
        "median_heading_error_deg": [float(v) for v in np.median(head, axis=0)],
        "tracking": [float(v) for v in tracking.mean(axis=0)],
        "first_success_update": first_ok,
        "final": {
            "mean_error_m": float(err[:, -1].mean()),
            "median_error_m": float(np.median(err[:, -1])),
            "success": float(ok[:, -1].mean()),
            "success_pose": float(ok_pose[:, -1].mean()),
        },
    }

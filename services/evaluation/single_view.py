"""How often does ONE image tell where the robot is? (single-image ambiguity)

The office map of section 6.1 (every 75 cm and 15 deg, 5 PCA features, mapping light) and
test views rendered at random free poses OFF the map grid, under the mapping light. Each test
view is projected (eq. 1) and matched to its nearest map entry in feature space; the view is
"localized by one image" when that entry passes the success criterion of section 6.1
(:func:`lino_loc.metrics.success`, the estimate being the matched entry's pose). A world where
this is always true would make the particle filter and the active camera pointless; a
realistic building repeats itself, so it must be clearly below 100 %.

Also reported: how often the right place is among the J = 10 nearest entries (what the
sensor model's mixture can use), and the same figures when a random entry is chosen (chance).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivers.sim.world import grid_poses, load_world
from lino_loc.appearance_map import channel_margin
from lino_loc.errors import LinoLocError
from lino_loc.metrics import success, success_pose
from lino_loc.virtual_views import crop_columns
from services.evaluation.views import ViewSpec, build_sim_maps, render_vectors


@dataclass(frozen=True)
class SingleViewSetup:
    world: str = "office"
    step: float = 0.75
    heading_step_deg: float = 15.0
    features: int = 5
    preprocess: str = "none"
    views: int = 300
    j: int = 10
    min_grid_distance: float = 0.15
    width: int = 320
    height: int = 240
    seed: int = 0
    workers: int | None = None
    virtual_headings: int = 1
    virtual_step_deg: float = 3.0


def off_grid_poses(world_name: str, grid: np.ndarray, n: int, min_distance: float, seed: int) -> np.ndarray:
    """``n`` random free robot poses of the mapped area, at least ``min_distance`` from every
    grid position, with uniform headings."""
    world = load_world(world_name)
    rng = np.random.default_rng((seed, 11))
    xmin, xmax, ymin, ymax = world.mapped_area
    grid_xy = np.unique(np.round(grid[:, :2], 6), axis=0)
    out: list[np.ndarray] = []
    for _ in range(10000):
        c = np.column_stack([rng.uniform(xmin, xmax, 256), rng.uniform(ymin, ymax, 256),
                             rng.uniform(-np.pi, np.pi, 256)])
        d = np.min(np.hypot(c[:, None, 0] - grid_xy[None, :, 0], c[:, None, 1] - grid_xy[None, :, 1]), axis=1)
        out.extend(c[world.is_free(c[:, 0], c[:, 1]) & (d >= min_distance)])
        if len(out) >= n:
            return np.asarray(out[:n])
    raise LinoLocError(f"single view: could not place {n} test views in world '{world.name}' "
                       f"(free, {min_distance} m or more from the grid)")


def run(setup: SingleViewSetup, progress: Callable[[int, int], None] | None = None) -> dict:
    amap = build_sim_maps(setup.world, setup.step, setup.heading_step_deg, setup.features,
                          (setup.preprocess,), width=setup.width, height=setup.height,
                          seed=setup.seed, workers=setup.workers, virtual_headings=setup.virtual_headings,
                          virtual_step_deg=setup.virtual_step_deg)[setup.preprocess]
    channel = amap.channels["intensity"]
    grid = grid_poses(load_world(setup.world), setup.step, math.radians(setup.heading_step_deg))
    truths = off_grid_poses(setup.world, grid, setup.views, setup.min_grid_distance, setup.seed)
    spec = ViewSpec(world=setup.world, width=setup.width, height=setup.height, size=channel.size,
                    preprocess=(setup.preprocess,), seed=setup.seed + 1)
    X = render_vectors(spec, truths, workers=setup.workers, progress=progress)[setup.preprocess]
    y = channel.pca.project(crop_columns(X, channel.size, channel_margin(channel)))
    d2 = ((y[:, None, :] - channel.features[None, :, :]) ** 2).sum(axis=2)
    order = np.argsort(d2, axis=1)[:, : setup.j]
    step_rad = math.radians(setup.heading_step_deg)

    def ok(idx: np.ndarray) -> np.ndarray:
        return success(amap.poses[idx], truths, grid)

    def ok_pose(idx: np.ndarray) -> np.ndarray:
        return success_pose(amap.poses[idx], truths, grid, setup.step, step_rad)

    rng = np.random.default_rng((setup.seed, 13))
    random_idx = rng.integers(0, len(amap.poses), len(truths))
    figures = {}
    for suffix, criterion in (("", ok), ("_pose", ok_pose)):
        figures[f"top1_success{suffix}"] = float(criterion(order[:, 0]).mean())
        in_j = np.any(np.column_stack([criterion(order[:, k]) for k in range(setup.j)]), axis=1)
        figures[f"success_within_J{suffix}"] = float(in_j.mean())
        figures[f"chance_success{suffix}"] = float(criterion(random_idx).mean())
    return {
        "world": setup.world,
        "map_images": int(len(grid)),
        "map_entries": int(len(amap.poses)),
        "features": setup.features,
        "preprocess": setup.preprocess,
        "views": int(len(truths)),
        "J": setup.j,
        **figures,
    }

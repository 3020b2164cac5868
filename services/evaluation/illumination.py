"""Table 1 of the paper: how much light changes the features, against a small translation.

For each preprocessing (and the disparity channel), the features are fitted on the views
taken under the mapping light (``tube``) and the ratio of eq. 9 is computed over all usable
map poses a of the lab grid:

    r = mean_a |y_c(a) - y_a| / mean_(a,b) |y_b - y_a|

with y_a the features of the view at a under tube light, y_b those of a view with the same
heading and the same light 50 cm (one grid step) away from a (every such neighbour of a is
used), and y_c those of the view at a under the other light. The table's caption defines the
ratio as that of the *average* variations, so averages are taken before dividing; the median of
the per-triple ratios r(a, b, c) is reported beside it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivers.sim.world import grid_poses, load_world
from lino_loc.appearance_map import DISPARITY_EM_MAX_ITER
from lino_loc.pca import fit_pca
from lino_loc.pca_missing import fit_pca_missing
from services.evaluation.views import ViewSpec, render_vectors

log = logging.getLogger(__name__)

INTENSITY_ROWS = ("none", "histeq", "gradient")
ROW_NAMES = {"none": "plain", "histeq": "histeq", "gradient": "gradient", "disparity": "disparity"}


@dataclass(frozen=True)
class IlluminationSetup:
    world: str = "lab"
    step: float = 0.5
    heading_step_deg: float = 10.0
    features: int = 20
    width: int = 320
    height: int = 240
    size: tuple[int, int] = (80, 60)
    lights: tuple[str, ...] = ("bulb", "natural")
    disparity: bool = True
    seed: int = 0
    workers: int | None = None


def neighbour_pairs(poses: np.ndarray, step: float) -> np.ndarray:
    """Index pairs (a, b): same heading, positions exactly one grid step apart (eq. 9's b)."""
    keys = {
        (round(p[0] / step), round(p[1] / step), round(float(np.degrees(p[2])) * 1000)): i
        for i, p in enumerate(poses)
    }
    pairs = []
    for (ix, iy, ih), a in keys.items():
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            b = keys.get((ix + dx, iy + dy, ih))
            if b is not None:
                pairs.append((a, b))
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def ratios(features: dict[str, np.ndarray], pairs: np.ndarray, lights: tuple[str, ...]) -> dict[str, float]:
    """Eq. 9 averaged as in Table 1, for each light, and their average."""
    ya = features["tube"]
    translation = np.linalg.norm(ya[pairs[:, 1]] - ya[pairs[:, 0]], axis=1)
    out: dict[str, float] = {}
    for light in lights:
        change = np.linalg.norm(features[light] - ya, axis=1)
        out[light] = float(change.mean() / translation.mean())
        out[f"{light}_median_per_triple"] = float(np.median(change[pairs[:, 0]] / np.maximum(translation, 1e-12)))
    out["average"] = float(np.mean([out[light] for light in lights]))
    return out


def run(setup: IlluminationSetup, progress: Callable[[str, int, int], None] | None = None) -> dict:
    world = load_world(setup.world)
    poses = grid_poses(world, setup.step, np.radians(setup.heading_step_deg))
    pairs = neighbour_pairs(poses, setup.step)
    log.info("illumination: %d poses, %d neighbour pairs", len(poses), len(pairs))
    vectors: dict[str, dict[str, np.ndarray]] = {}
    for light in ("tube", *setup.lights):
        spec = ViewSpec(world=setup.world, lighting=light, width=setup.width, height=setup.height,
                        size=setup.size, preprocess=INTENSITY_ROWS, disparity=setup.disparity,
                        seed=setup.seed)
        vectors[light] = render_vectors(
            spec, poses, workers=setup.workers,
            progress=(lambda d, n, light=light: progress(light, d, n)) if progress else None,
        )
    rows = list(INTENSITY_ROWS) + (["disparity"] if setup.disparity else [])
    table: dict[str, dict[str, float]] = {}
    density: dict[str, float] = {}
    for row in rows:
        if row == "disparity":
            model = fit_pca_missing(vectors["tube"][row], setup.features, seed=setup.seed,
                                    max_iter=DISPARITY_EM_MAX_ITER)
            for light in ("tube", *setup.lights):
                density[light] = float(np.isfinite(vectors[light][row]).mean())
        else:
            model = fit_pca(vectors["tube"][row], setup.features, seed=setup.seed)
        feats = {light: model.project(vectors[light][row]) for light in ("tube", *setup.lights)}
        table[ROW_NAMES[row]] = ratios(feats, pairs, setup.lights)
    result = {
        "world": setup.world,
        "features": setup.features,
        "poses": int(len(poses)),
        "pairs": int(len(pairs)),
        "image": [setup.width, setup.height],
        "ratios": {name: {k: v for k, v in r.items() if "median" not in k} for name, r in table.items()},
        "median_per_triple": {name: {k: v for k, v in r.items() if "median" in k} for name, r in table.items()},
    }
    if density:
        result["disparity_density"] = density
    return result

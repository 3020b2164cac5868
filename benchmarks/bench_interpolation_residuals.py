"""How well the interpolated appearance predicts views taken off the survey grid.

    python benchmarks/bench_interpolation_residuals.py [--world office] [--positions 20]

The map and the test views of ``lino-loc eval active`` (its default setup: 75 cm / 15 deg
survey with virtual headings, 5 features, the test positions off the grid, all 22 pans).
Prints one JSON object: the interpolated sensor model's learnt scales s_k
(lino_loc/interpolated_appearance.py, leave-one-out residuals, ``residual_scale`` 1), and,
in units of s_k, the RMS per feature of the residual y - f(x) of the test views at their
true camera poses against the interpolation (``interpolated``) and against the map entry
nearest in pose (``nearest_pose``: the position and heading with the largest interpolation
weight). An RMS of r means the calibrated ``residual_scale`` is about r.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from drivers.sim.world import grid_poses, load_world  # noqa: E402
from services.evaluation.active import place_test_positions, render_map, render_tests  # noqa: E402
from services.evaluation.active_setup import ActiveSetup  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="office")
    ap.add_argument("--positions", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    setup = ActiveSetup(world=args.world, positions=args.positions, runs=1, seed=args.seed, workers=1,
                        sensor_model="interpolated")
    world = load_world(setup.world)
    grid = grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    pca, feats_map, entries, margin, _ = render_map(setup, None)
    truths = place_test_positions(world, setup, grid)
    pans = setup.active.actions()
    feats, _ = render_tests(setup, pca, margin, truths, pans, (), None)
    model = setup.sensor_model_for(entries, feats_map)
    cams = np.repeat(truths[:, None, :], pans.size, axis=1)
    cams[:, :, 2] += pans[None, :]
    cams = cams.reshape(-1, 3)
    y = feats.reshape(cams.shape[0], -1)
    f, ok = model.appearance.features_at(cams)
    idx, w = model.appearance.lattice.corners(cams[:, 0], cams[:, 1], cams[:, 2])
    nearest = idx[np.arange(idx.shape[0]), np.argmax(w, axis=1)]
    r_int = ((y - f) / model.scale)[ok]
    r_near = ((y - feats_map[nearest]) / model.scale)[nearest >= 0]
    print(json.dumps({
        "world": setup.world, "views": int(cams.shape[0]), "scale": [float(v) for v in model.scale],
        "interpolated_rms": [float(v) for v in np.sqrt(np.mean(r_int**2, axis=0))],
        "nearest_pose_rms": [float(v) for v in np.sqrt(np.mean(r_near**2, axis=0))],
        "interpolated_median_distance": float(np.median(np.linalg.norm(r_int, axis=1))),
        "nearest_pose_median_distance": float(np.median(np.linalg.norm(r_near, axis=1))),
    }))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""How close a virtual translation (lino_loc/virtual_translations.py) comes to the real view.

For ``--samples`` random survey poses of a world (the 75 cm / 15 deg grid, tube light) and a
floor offset of ``--offsets`` metres in a random direction (same heading, free target): the
survey view is rendered in stereo, its sparse disparity computed by the product's matcher and
area-downsampled to the working size as the map's disparity channel keeps it, and the view is
warped to the target; holes are filled from the nearest warped pixel. Distances in the
product's intensity PCA (20 features, the map of `eval active`), per sample:

* ``nearest``: real target view - survey view (what a map without the translation offers);
* ``virtual``: real target view - virtual translation;
* ``noise``: real target view - the same view with other sensor noise (the floor);
* ``half_lattice``: real target view - the real view 12.5 cm further in a random direction
  (what a 25 cm lattice of views must tell apart);
* ``virtual_turned_fill``: real target view - the virtual translation whose uncovered borders
  are filled from the survey's views at the neighbouring headings (+-15 deg, each with its own
  stereo depth), as the map builder makes it; ``virtual`` is the same warp with its holes
  filled by the nearest pixel alone (the map builder before), on the same samples.

Printed: medians of each distance over ``nearest``'s median, the share of samples where the
virtual view is nearer than the survey view and nearer than the half-lattice neighbour, and
the same share for the turned fill.

    OPENBLAS_NUM_THREADS=1 python benchmarks/virtual_translation_residuals.py --worlds office,lab,corridor \
        --samples 60 --offsets 0.125,0.25,0.375
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.world import grid_poses, load_world
from lino_loc.disparity import StereoConfig, compute_disparity, downsample_sparse
from lino_loc.preprocessing import preprocess, to_vector
from lino_loc.virtual_translations import as_uint8, dense_depth, translate_view
from lino_loc.virtual_views import crop_columns
from services.evaluation import active
from services.evaluation.active_setup import product_defaults
from services.evaluation.machine import machine


def _features(img: np.ndarray, setup: Any, pca: Any, margin: int) -> np.ndarray:
    v = to_vector(preprocess(as_uint8(img), setup.preprocess), setup.size)
    return np.asarray(pca.project(crop_columns(v[None], setup.size, margin))[0], dtype=np.float64)


def world_report(name: str, args: argparse.Namespace) -> dict[str, Any]:
    world = load_world(name)
    setup = product_defaults(world=name, channels=("intensity",), workers=args.workers)
    pca, _, _, margin, _ = active.render_map(setup, None)
    camera = CameraModel(width=setup.width, height=setup.height)
    renderer = Renderer(world, camera=camera, lighting=setup.lighting)
    intr = camera.intrinsics()
    grid = grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    rng = np.random.default_rng((args.seed, 11))
    xmin, xmax, ymin, ymax = world.mapped_area
    out: dict[str, Any] = {}
    for offset in (float(o) for o in args.offsets.split(",")):
        rows: list[list[float]] = []
        tries = 0
        while len(rows) < args.samples and tries < 100 * args.samples:
            tries += 1
            s = grid[rng.integers(grid.shape[0])]
            phi, psi = rng.uniform(-math.pi, math.pi, 2)
            t = s + np.array([offset * math.cos(phi), offset * math.sin(phi), 0.0])
            t2 = t + np.array([0.125 * math.cos(psi), 0.125 * math.sin(psi), 0.0])
            pts = np.array([t, t2])
            if not (world.is_free(pts[:, 0], pts[:, 1]).all() and xmin <= t[0] <= xmax and ymin <= t[1] <= ymax):
                continue
            k = len(rows)
            src = renderer.render(*map(float, s), stereo=True, rng=np.random.default_rng((args.seed, k, 0)))
            disp = downsample_sparse(compute_disparity(src.left, src.right, StereoConfig()), setup.size)
            if not np.isfinite(disp).any():
                continue
            depth = (src.depth if args.depth == "renderer"
                     else dense_depth(disp, src.grey.shape, intr[0], camera.baseline_m))
            others = []  # the survey's views at the neighbouring headings, with their own depth
            for turn in (1.0, -1.0):
                q = s + np.array([0.0, 0.0, turn * math.radians(setup.heading_step_deg)])
                o = renderer.render(*map(float, q), stereo=True, rng=np.random.default_rng((args.seed, k, 5, int(turn > 0))))
                o_disp = downsample_sparse(compute_disparity(o.left, o.right, StereoConfig()), setup.size)
                if args.depth == "renderer" or np.isfinite(o_disp).any():
                    others.append((o.grey, o.depth if args.depth == "renderer"
                                   else dense_depth(o_disp, o.grey.shape, intr[0], camera.baseline_m), q))
            virtual = translate_view(src.grey, depth, intr, s, t)
            filled = translate_view(src.grey, depth, intr, s, t, others)
            if virtual is None or filled is None:
                continue
            real = [renderer.render(*map(float, p), stereo=False, rng=np.random.default_rng((args.seed, k, j)))
                    for j, p in ((1, t), (2, t), (3, t2))]
            f_t, f_t_again, f_t2 = (_features(r.grey, setup, pca, margin) for r in real)
            f_s, f_v = _features(src.grey, setup, pca, margin), _features(virtual, setup, pca, margin)
            f_f = _features(filled, setup, pca, margin)
            rows.append([float(np.linalg.norm(f_t - f)) for f in (f_s, f_v, f_t_again, f_t2, f_f)])
        a = np.asarray(rows)
        ref = float(np.median(a[:, 0]))
        out[f"{offset:g}"] = {
            "samples": int(a.shape[0]),
            "median_over_nearest": {k: round(float(np.median(a[:, i])) / ref, 3)
                                    for i, k in enumerate(("nearest", "virtual", "noise", "half_lattice",
                                                           "virtual_turned_fill"))},
            "virtual_nearer_than_survey_view": round(float(np.mean(a[:, 1] < a[:, 0])), 3),
            "virtual_nearer_than_half_lattice_view": round(float(np.mean(a[:, 1] < a[:, 3])), 3),
            "turned_fill_nearer_than_half_lattice_view": round(float(np.mean(a[:, 4] < a[:, 3])), 3),
            "turned_fill_nearer_than_virtual": round(float(np.mean(a[:, 4] < a[:, 1])), 3),
            "mean_over_nearest": {k: round(float(np.mean(a[:, i])) / float(np.mean(a[:, 0])), 3)
                                  for i, k in ((1, "virtual"), (4, "virtual_turned_fill"))},
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", default="office")
    ap.add_argument("--samples", type=int, default=60)
    ap.add_argument("--offsets", default="0.125,0.25,0.375", help="floor offsets from the survey pose, metres")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--depth", choices=("stereo", "renderer"), default="stereo",
                    help="the depth the view is warped with: the survey's sparse stereo disparity (the product's), "
                    "or the renderer's exact depth (a diagnostic only: a robot has no such depth)")
    ap.add_argument("--workers", type=int, default=2, help="for the map's renders")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    result: dict[str, Any] = {"machine": machine(), "args": {k: str(v) for k, v in vars(args).items()}, "worlds": {}}
    for name in args.worlds.split(","):
        rep = world_report(name, args)
        result["worlds"][name] = rep
        for off, r in rep.items():
            print(f"{name} offset {off} m ({r['samples']} samples): median distance / survey view's "
                  f"{r['median_over_nearest']}; virtual nearer than the survey view "
                  f"{r['virtual_nearer_than_survey_view']:.0%}, than the view 12.5 cm on "
                  f"{r['virtual_nearer_than_half_lattice_view']:.0%} (turned fill "
                  f"{r['turned_fill_nearer_than_half_lattice_view']:.0%}); mean distance / survey view's "
                  f"{r['mean_over_nearest']}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

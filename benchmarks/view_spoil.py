"""What a scene change does to the views active vision chooses from, and what a view's novelty
says about it (lino_loc/pan_reliability.py).

For the test positions of ``lino-loc eval active`` (the product's map, seed 0) every candidate
pan's view is rendered as mapped and with all the world's scene changes. A view's SPOIL is the
feature distance between the two, over the sensor model's reference distance; its NOVELTY (with
the changes) is the distance to the nearest map entry over the same reference
(``PoseMixture.novelty``). Printed per world: how strongly novelty ranks spoil (Spearman), how
far spoil carries to neighbouring pans, and P(spoil > 1) by novelty band, at the same pan and
1-3 pans (14-43 deg) away.

    OPENBLAS_NUM_THREADS=1 python benchmarks/view_spoil.py --worlds office,lab,corridor --positions 30
"""

from __future__ import annotations

import argparse
import math

import numpy as np
from scipy.stats import spearmanr

from drivers.sim.world import grid_poses, load_world
from services.evaluation import active
from services.evaluation.active_setup import product_defaults

BANDS = (0.0, 0.6, 0.8, 1.0, 1.2, 1.5, 2.0, math.inf)


def world_report(name: str, positions: int, workers: int) -> None:
    world = load_world(name)
    changes = tuple(world.scene_change_names)
    setup = product_defaults(world=name, positions=positions, runs=1, movements=3, scene_changes=changes,
                             workers=workers)
    grid = grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    pans = setup.active.actions()
    pca, map_features, entries, margin, _ = active.render_map(setup, None)
    truths = active.place_test_positions(world, setup, grid)
    mapped, _ = active.render_tests(setup, pca, margin, truths, pans, (), None, None)
    changed, _ = active.render_tests(setup, pca, margin, truths, pans, changes, None, None)
    model = setup.sensor_model_for(entries, map_features)
    ref = model.reference_distance
    spoil = np.linalg.norm(changed - mapped, axis=-1) / ref  # (P, A)
    _, d2 = model.neighbours(changed.reshape(-1, changed.shape[-1]), 1)
    novelty = np.sqrt(d2[:, 0]).reshape(spoil.shape) / ref
    print(f"== {name} (changes {', '.join(changes)}; {positions} positions x {pans.size} pans)")
    print(f"   share of views with spoil > 1: {(spoil > 1).mean():.2f}; "
          f"Spearman(novelty, spoil) {spearmanr(novelty.ravel(), spoil.ravel())[0]:.2f}")
    for k in range(1, 5):
        r_s = spearmanr(spoil[:, :-k].ravel(), spoil[:, k:].ravel())[0]
        r_n = spearmanr(novelty[:, :-k].ravel(), spoil[:, k:].ravel())[0]
        print(f"   {k} pan(s) apart ({math.degrees(pans[k] - pans[0]):.0f} deg): Spearman(spoil, spoil) {r_s:.2f}, "
              f"(novelty, spoil) {r_n:.2f}")
    print("   novelty band: views, P(spoil > 1) at the pan / 1 / 2 / 3 pans away")
    for lo, hi in zip(BANDS[:-1], BANDS[1:], strict=True):
        m = (novelty >= lo) & (novelty < hi)
        if not m.any():
            continue
        away = [(spoil[:, k:][m[:, : spoil.shape[1] - k]] > 1).mean() for k in (1, 2, 3)]
        print(f"   {lo:.1f}-{hi:.1f}: {int(m.sum())}, {(spoil[m] > 1).mean():.2f} / "
              + " / ".join(f"{v:.2f}" for v in away))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", default="office,lab,corridor")
    ap.add_argument("--positions", type=int, default=30)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    for name in args.worlds.split(","):
        world_report(name.strip(), args.positions, args.workers)


if __name__ == "__main__":
    main()

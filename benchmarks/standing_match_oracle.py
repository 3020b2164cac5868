"""The standing match alone, at the truth: how well four views place a standing robot.

For each of ``eval active``'s test positions (the same map, positions and test views as
``lino-loc eval active`` with the product's defaults) and every first pan ``a0``, the views
of a set of pans are matched jointly with the map's around the TRUE pose
(:meth:`lino_loc.standing_match.StandingMatch.match`, hypotheses within 50 cm of it), as the
filter's estimate would be if it had found the neighbourhood exactly. Reported per set of
pans, over positions x first pans: the section 6.1 success of the matched pose and its median
position error (m). The sets:

- ``sweep``: a0 and the sweep's next three (stride 7 of 22, as ``eval active``'s sweep);
- ``spread``: a0 and three more, each the pan farthest from those taken
  (:mod:`lino_loc.view_spread`, the service's choice while the match acts);
- ``random``: a0 and three other pans drawn at random (seeded).

With ``--rivals`` the match is an unconfirmed belief's (``match(..., rivals=True)``): the
views are matched as well with every map position beyond 1 m of the truth, and a far place
that fits better by ``relocate_margin`` wins. ``relocated`` is the share of sets a far place
took: a right belief the relocation would move away (0 without ``--rivals``).

``on_border`` is the share of sets whose matched position is equally far from two survey
positions (within 1 nm): on the border between two of the criterion's cells, which
``success`` counts as right for both.

It isolates the match's precision and the views' choice from the filter. It also times the
match itself on the product's map (``match_ms``: median and 90th percentile of one
:meth:`StandingMatch.match` of four views, wall clock, with the machine). Prints one JSON object.

Usage::

    OPENBLAS_NUM_THREADS=1 python benchmarks/standing_match_oracle.py --world office [--seed 0] [--subcell off] \
        [--candidates K] [--scene-changes all] [--rivals]

With ``--scene-changes``, the test views are rendered with the world's scene changes (the
map as surveyed), as ``eval active``'s second condition.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    from drivers.sim.world import load_world
    from lino_loc.errors import LinoLocError
    from lino_loc.lost_detection import CONFIRM_RADIUS_XY
    from lino_loc.metrics import success
    from lino_loc.standing_match import StandingMatch
    from lino_loc.view_spread import spread_values
    from services.evaluation import active
    from services.evaluation.active_setup import product_defaults
    from services.evaluation.machine import machine

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--world", default="office")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--subcell", choices=("on", "off"), default="on")
    p.add_argument("--candidates", type=int, default=None,
                   help="lattice positions the subcell search refines (default: the product's)")
    p.add_argument("--scene-changes", default="",
                   help="comma-separated scene changes for the test views ('all': every one the world has); "
                        "the map stays as surveyed")
    p.add_argument("--rivals", action="store_true",
                   help="match as an unconfirmed belief does: far places that fit better take the match")
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args()
    t0 = time.perf_counter()
    setup = product_defaults(world=a.world, seed=a.seed, workers=a.workers, movements=3)
    update: dict[str, object] = {"subcell": a.subcell == "on"}
    if a.candidates is not None:
        if a.candidates < 1:
            p.error(f"--candidates must be at least 1 (got {a.candidates})")
        update["candidates"] = a.candidates
    setup = replace(setup, standing_match=setup.standing_match.model_copy(update=update))
    world = load_world(a.world)
    names = [n for n in a.scene_changes.split(",") if n]
    try:
        changes = world.check_changes(list(world.spec.scene_changes) if names == ["all"] else names)
    except LinoLocError as e:
        p.error(str(e))
    grid = active.grid_poses(world, setup.judged_step, math.radians(setup.heading_step_deg))
    pca, map_features, entries, margin, _ = active.render_map(setup, None)
    truths = active.place_test_positions(world, setup, grid)
    pans = setup.active.actions()
    feats, _ = active.render_tests(setup, pca, margin, truths, pans, changes, None)
    match = StandingMatch.for_map(entries, map_features, setup.standing_match)
    assert isinstance(match, StandingMatch)
    cells = np.unique(np.round(grid[:, :2], 9), axis=0)  # the criterion's survey positions
    n_a = pans.size
    rng = np.random.default_rng(a.seed)
    out: dict[str, list[tuple[float, bool, bool, bool]]] = {"sweep": [], "spread": [], "random": []}
    match_s: list[float] = []
    for i, truth in enumerate(truths):
        for a0 in range(n_a):
            spread = [a0]
            for _ in range(3):
                values = spread_values(pans[spread], pans)
                spread.append(values.best(float(pans[spread[-1]]), setup.active.move_cost, exclude=spread))
            sets = {"sweep": [(a0 + k * setup.sweep_stride) % n_a for k in range(4)], "spread": spread,
                    "random": [a0, *rng.choice(np.delete(np.arange(n_a), a0), 3, replace=False)]}
            for name, idx in sets.items():
                match.reset()
                for k in idx:
                    match.observe(np.zeros(3), float(pans[k]), feats[i, k])
                t = time.perf_counter()
                m = match.match(truth, rivals=a.rivals)
                match_s.append(time.perf_counter() - t)
                assert m is not None
                two = np.sort(np.hypot(cells[:, 0] - m[0], cells[:, 1] - m[1]))[:2]
                err = float(np.hypot(*(m[:2] - truth[:2])))
                out[name].append((err, bool(success(m[None], truth[None], grid)[0]), bool(two[1] - two[0] <= 1e-9),
                                  err > CONFIRM_RADIUS_XY))
    report = {name: {"success": round(float(np.mean([s for _, s, _, _ in v])), 4),
                     "median_error_m": round(float(np.median([e for e, _, _, _ in v])), 4), "sets": len(v),
                     "on_border": round(float(np.mean([b for _, _, b, _ in v])), 4),
                     "relocated": round(float(np.mean([r for _, _, _, r in v])), 4)}
              for name, v in out.items()}
    print(json.dumps({"benchmark": "standing_match_oracle", "world": a.world, "seed": a.seed, "subcell": a.subcell,
                      "rivals": a.rivals, "relocate_margin": setup.standing_match.relocate_margin,
                      "scene_changes": list(changes),
                      "candidates": setup.standing_match.candidates,
                      "positions": int(truths.shape[0]), "first_pans": n_a, "sets": report,
                      "match_ms": {"median": round(1e3 * float(np.median(match_s)), 3),
                                   "p90": round(1e3 * float(np.percentile(match_s, 90)), 3)},
                      "machine": machine(),
                      "seconds": round(time.perf_counter() - t0, 1)}))


if __name__ == "__main__":
    main()

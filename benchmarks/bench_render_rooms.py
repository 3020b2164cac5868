"""Render and bake cost against the number of rooms, with and without visibility culling.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_render_rooms.py [--sizes 1,2,4,8] [--poses 16]
        [--repeats 3] [--unculled-bake-max 2] [--floor] [--lab] [--json OUT]

Worlds: :func:`drivers.sim.floor_world.corridor_floor` with k offices a side (2 k offices and a
corridor: the same rooms whatever k), and with ``--floor`` the floor world, ``--lab`` the lab
(one room, no culling) for scale. Per world:

- the light bake (tube) with culling, and without it for k <= ``--unculled-bake-max`` (it grows
  with the square of the rooms);
- render cost per frame (stereo, noise, 320 x 240, as a survey renders) of the same poses, in
  the first office and the first 7 m of the corridor, culled and unculled interleaved pose by
  pose, median over poses and repeats; the number of walls and boxes each traces (mean over
  the views); and that both give the same images.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from typing import Any

import numpy as np

from drivers.sim import lighting
from drivers.sim.floor_world import corridor_floor
from drivers.sim.renderer import Renderer
from drivers.sim.world import World, WorldSpec, load_world


def _poses(world: World, n: int, region: tuple[float, float, float, float], seed: int = 0) -> list[tuple]:
    rng = np.random.default_rng(seed)
    out: list[tuple] = []
    while len(out) < n:
        x, y = rng.uniform(region[0], region[1]), rng.uniform(region[2], region[3])
        if world.is_free(x, y):
            out.append((float(x), float(y), float(rng.uniform(-math.pi, math.pi))))
    return out


def _bake_seconds(world: World, cull: bool) -> float:
    lighting._BAKE_CACHE.clear()
    lighting._PVS_CACHE.clear()
    t = time.perf_counter()
    lighting.bake(world, "tube", cull=cull)
    return time.perf_counter() - t


def measure(world: World, poses: list[tuple], repeats: int, unculled_bake: bool) -> dict[str, Any]:
    row: dict[str, Any] = {"world": world.name, "rooms": len(world.spec.rooms) or 1,
                           "cells": len(world.layout.cells) if world.layout is not None else 1}
    if unculled_bake and world.layout is not None:
        row["bake_unculled_s"] = round(_bake_seconds(world, cull=False), 2)
    row["bake_s"] = round(_bake_seconds(world, cull=True), 2)
    culled, full = Renderer(world), Renderer(world, cull=False)
    times: dict[str, list[float]] = {"culled": [], "unculled": []}
    same = True
    for _ in range(repeats):
        for p in poses:
            for name, r in (("culled", culled), ("unculled", full)):
                t = time.perf_counter()
                v = r.render(*p, rng=np.random.default_rng(7))
                times[name].append(time.perf_counter() - t)
                if name == "culled":
                    first = v
                else:
                    same &= bool(np.array_equal(first.left, v.left) and np.array_equal(first.right, v.right))
    row["render_ms_culled"] = round(1e3 * float(np.median(times["culled"])), 2)
    row["render_ms_unculled"] = round(1e3 * float(np.median(times["unculled"])), 2)
    row["same_images"] = same
    if world.layout is not None:
        rays = culled._rays_for(0.0)
        n = np.array([[len(s) for s in culled._selection(x, y, th, rays)[1:]] for x, y, th in poses])
        row["walls_traced"] = f"{n[:, 0].mean():.1f} / {len(culled._w0)}"
        row["boxes_traced"] = f"{n[:, 1].mean():.1f} / {len(culled._box)}"
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1,2,4,8", help="offices a side of the corridor floors")
    ap.add_argument("--poses", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--unculled-bake-max", type=int, default=2)
    ap.add_argument("--floor", action="store_true", help="also the floor world")
    ap.add_argument("--lab", action="store_true", help="also the lab (one room)")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args()
    rows = []
    for k in (int(s) for s in args.sizes.split(",")):
        w = World(WorldSpec.model_validate(corridor_floor(k)))
        rows.append(measure(w, _poses(w, args.poses, (0.0, 7.2, 0.0, 16.0)), args.repeats,
                            k <= args.unculled_bake_max))
        print(json.dumps(rows[-1]), flush=True)
    if args.floor:
        w = load_world("floor")
        rows.append(measure(w, _poses(w, args.poses, w.room), args.repeats, False))
        print(json.dumps(rows[-1]), flush=True)
    if args.lab:
        w = load_world("lab")
        rows.append(measure(w, _poses(w, args.poses, w.mapped_area), args.repeats, False))
        print(json.dumps(rows[-1]), flush=True)
    load = os.getloadavg()
    print(f"\nload average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {os.cpu_count()} cores")
    keys = list(dict.fromkeys(k for r in rows for k in r))
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(str(r.get(k, "")) for k in keys) + " |")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump({"rows": rows, "load": load}, f, indent=1)


if __name__ == "__main__":
    main()

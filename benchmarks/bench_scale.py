"""The localizer at scale: J-nearest search, update cost, map file size, memory
and start-up for synthetic floor maps of 10k, 100k and 1M entries, 1000 particles.

    python benchmarks/bench_scale.py [--entries 10000 100000 1000000] [--out scale.json]

What is measured: services/evaluation/scale_cost.py; the maps:
services/evaluation/synthetic_floor_map.py. Prints (and with --out writes) one JSON object:
``machine`` (cpu model, load average before and after), and per map size ``search`` (per
search structure: build time, memory, query median, recall@10 against exact), ``update`` (per
sensor-model ``index``: median Localizer update at 1000 particles), ``map_file_mb`` and
``startup`` (map load with and without mmap: time and resident memory, each in a fresh
process). Numeric libraries are limited to one thread before numpy is imported. The HNSW
graphs are built into a fresh cache folder by the search measurement (its build time) and
read from it by the update and start-up ones.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.evaluation import scale_cost  # noqa: E402
from services.evaluation.machine import machine  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--entries", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--rounds", type=int, default=3, help="interleaved drives per search kind (update cost)")
    ap.add_argument("--startup-repeats", type=int, default=3)
    ap.add_argument("--skip", nargs="*", default=[], choices=("search", "update", "startup"))
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--cache", type=Path, default=None,
                    help="keep the HNSW graphs in this folder (default: a temporary one, so every graph is built)")
    ap.add_argument("--keep-maps", type=Path, default=None, help="save the synthetic maps in this folder")
    args = ap.parse_args(argv)
    from services.evaluation.synthetic_floor_map import floor_map

    result: dict = {"machine_start": machine(), "sizes": {}}
    with tempfile.TemporaryDirectory(prefix="lino-scale-") as tmp:
        cache = args.cache or Path(tmp) / "index"
        cache.mkdir(parents=True, exist_ok=True)
        for n in args.entries:
            amap = floor_map(n)
            path = amap.save((args.keep_maps or Path(tmp)) / f"floor-{n}.map.npz")
            row: dict = {"map_file_mb": path.stat().st_size / 1e6}
            if "search" not in args.skip:
                row.update(scale_cost.search_table(n, cache=cache, amap=amap))
            if "update" not in args.skip:
                row["update"] = scale_cost.update_costs(n, kinds=("brute", "kdtree", "hnsw"), rounds=args.rounds,
                                                        amap=amap, cache=cache)
            del amap
            if "startup" not in args.skip:
                cases = [("eager", False, "auto"), ("mmap", True, "auto"), ("eager", False, "hnsw"),
                         ("mmap", True, "hnsw")]
                runs: dict = {f"{m}-{i}": [] for m, _, i in cases}
                scale_cost.startup_case(path, True, "brute")  # page cache warm for every case
                for _ in range(args.startup_repeats):  # cases interleaved
                    for name, mm, index in cases:
                        runs[f"{name}-{index}"].append(scale_cost.startup_case(path, mm, index, cache))
                row["startup"] = runs
            result["sizes"][str(n)] = row
            print(json.dumps({str(n): row}), file=sys.stderr, flush=True)
    result["machine_end"] = machine()
    text = json.dumps(result, indent=1)
    if args.out:
        args.out.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

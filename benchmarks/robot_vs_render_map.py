"""The map of a robot survey against the map of the renderer's survey of the same plan.

For one world: ``lino-loc survey`` renders the survey grid (``--step`` m, ``--heading-step``
deg, the simulated camera's ``--width`` x ``--height``, stereo); its positions, ordered as a
boustrophedon, are the plan of ``lino-loc survey --robot`` on the simulated robot (the same
camera, the robot driving itself, the daemon's drivers over the emulators, the stop poses
the plan's marked positions). Both datasets are built into maps the same way (``lino-loc map
build``: one map for global localization, ``--features 5 --virtual-headings 5``, intensity;
one for tracking, ``--features 20 --disparity-features 5 --virtual-headings 5``, intensity
and disparity, as config/sim.toml's), and evaluated on the same test views: ``lino-loc eval
global --map`` and ``lino-loc eval tracking --map`` with the same seeds.

    python benchmarks/robot_vs_render_map.py --world office --work /tmp/rvr [--json]

Every step's command is printed on stderr; finished steps (their output files) are reused
when run again with the same ``--work``. One process at a time (the surveys and the
evaluations each take the machine's cores).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _run(argv: list[str], done: Path | None = None, save: Path | None = None) -> str:
    """Run ``lino-loc ARGV`` and return its stdout, written to ``save`` if given. Skipped when
    ``done`` (a file the step makes) exists; then ``save``'s text is returned."""
    cmd = [sys.executable, "-m", "services.cli", *argv]
    print("$ lino-loc " + " ".join(argv), file=sys.stderr, flush=True)
    marker = save if save is not None else done
    if marker is not None and marker.exists():
        return save.read_text() if save is not None else ""
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1", DEPTHAI_LEVEL="error")
    t0 = time.monotonic()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if p.returncode != 0:
        raise SystemExit(f"failed ({p.returncode}): lino-loc {' '.join(argv)}\n{p.stderr[-3000:]}")
    print(f"  ({time.monotonic() - t0:.0f} s)", file=sys.stderr, flush=True)
    if save is not None:
        save.write_text(p.stdout)
    return p.stdout


def boustrophedon(xy: list[tuple[float, float]]) -> list[tuple[float, float]]:
    rows: dict[float, list[float]] = {}
    for x, y in xy:
        rows.setdefault(round(y, 6), []).append(x)
    out = []
    for j, y in enumerate(sorted(rows)):
        xs = sorted(rows[y], reverse=bool(j % 2))
        out += [(x, y) for x in xs]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="office")
    ap.add_argument("--work", required=True, help="folder for the datasets, maps and results")
    ap.add_argument("--step", type=float, default=0.75)
    ap.add_argument("--heading-step", type=float, default=15.0)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--drive-speed", type=float, default=0.5)
    ap.add_argument("--tracking-duration", type=float, default=120.0)
    ap.add_argument("--tracking-lights", default="tube,bulb")
    ap.add_argument("--starts", type=int, default=20)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    work = Path(args.work) / args.world
    work.mkdir(parents=True, exist_ok=True)
    w = args.world

    render_ds = work / "render"
    _run(["survey", "--world", w, "--step", str(args.step), "--heading-step", str(args.heading_step),
          "--width", str(args.width), "--height", str(args.height), "--out", str(render_ds)],
         render_ds / "dataset.json")
    from lino_loc.dataset import Dataset

    ds = Dataset.open(render_ds)
    xy = sorted({(round(float(x), 6), round(float(y), 6)) for x, y in ds.poses[:, :2]})
    plan = work / "plan.csv"
    plan.write_text("x,y\n" + "".join(f"{x},{y}\n" for x, y in boustrophedon(xy)))
    cfg = work / "sim.toml"
    cfg.write_text(f"""
[devices.camera]
kind = "sim"
[devices.camera.sim]
endpoint = "auto"
world = "{w}"
width = {args.width}
height = {args.height}
fps = {args.fps}
[devices.head]
kind = "dynamixel"
port = "auto"
[devices.odometry]
kind = "serial"
port = "auto"
[map]
path = "{work / 'unused.npz'}"
[logging]
level = "WARNING"
""")
    robot_ds = work / "robot"
    survey_json = work / "robot-survey.json"
    survey = json.loads(_run(["survey", "--robot", "--config", str(cfg), "--plan", str(plan), "--out", str(robot_ds),
                              "--heading-step", str(args.heading_step), "--drive-speed", str(args.drive_speed),
                              "--json"], save=survey_json).strip().splitlines()[-1])
    results: dict[str, Any] = {"world": w, "plan_stops": len(xy), "render_images": len(ds), "robot_survey": survey}
    builds = {
        "global": ["--features", "5", "--virtual-headings", "5"],
        "tracking": ["--features", "20", "--disparity-features", "5", "--virtual-headings", "5",
                     "--channels", "intensity,disparity"],
    }
    for name, src in (("render", render_ds), ("robot", robot_ds)):
        for kind, opts in builds.items():
            m = work / f"{name}-{kind}.npz"
            _run(["map", "build", str(src), "--out", str(m), *opts], m)
        g = work / f"{name}-eval-global.json"
        res_g = json.loads(_run(["eval", "global", "--world", w, "--map", str(work / f"{name}-global.npz"),
                                 "--starts", str(args.starts), "--json"], save=g))
        t = work / f"{name}-eval-tracking.json"
        res_t = json.loads(_run(["eval", "tracking", "--world", w, "--map", str(work / f"{name}-tracking.npz"),
                                 "--duration", str(args.tracking_duration), "--lights", args.tracking_lights,
                                 "--switch-lights", "none", "--no-kidnap", "--no-recovery-comparison", "--json"],
                                save=t))
        results[name] = {
            "global_final": res_g["final"],
            "global_first_success_update_median": _median([v for v in res_g["first_success_update"] if v]),
            "tracking": {light: {k: r[k] for k in ("ate_rmse_m", "mean_error_m", "max_error_m", "heading_rmse_deg",
                                                   "converged_after_s") if k in r}
                         for light, r in res_t["conditions"].items()},
            "map_entries": res_g["map_entries"],
        }
    print(json.dumps(results) if args.json else json.dumps(results, indent=1))
    return 0


def _median(v: list[float]) -> float | None:
    if not v:
        return None
    s = sorted(v)
    n = len(s)
    return float(s[n // 2]) if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])


if __name__ == "__main__":
    sys.exit(main())

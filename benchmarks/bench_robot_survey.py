"""Throughput of `lino-loc survey --robot` on the simulated robot: images per minute, and where
the time goes (driving between stops, the head's motion and settling, waiting for a frame).

It writes a simulator configuration (world, image size, frame rate), a plan of ``--stops``
stops along a row of the world's mapped area ``--spacing`` metres apart from its centre
(where the simulated robot starts: no drive to the first stop), runs the survey as
the product does (its own `lino-loc sim`, the daemon's drivers over the emulators, the
robot driving itself by the simulator's ``goto``) and prints the survey's JSON summary with
the shares of its time.

    python benchmarks/bench_robot_survey.py [--world office] [--stops 3] [--spacing 0.75]
        [--width 320 --height 240 --fps 15] [--heading-step 15] [--drive-speed 0.3] [--json]

The simulator and the survey share the machine's cores (the renderer, the block matcher of the
simulated camera's disparity, the survey): on a robot the camera computes disparity itself.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def plan_row(world: str, stops: int, spacing: float) -> list[tuple[float, float]]:
    """``stops`` free positions ``spacing`` apart along the middle of the mapped area, from its
    centre (where the simulated robot starts) toward +x."""
    from drivers.sim.world import load_world

    w = load_world(world)
    x0, x1, y0, y1 = w.mapped_area
    y = 0.5 * (y0 + y1)
    out: list[tuple[float, float]] = []
    x = 0.5 * (x0 + x1)
    while len(out) < stops and x <= x1:
        if bool(w.is_free(x, y, 0.3)):
            out.append((round(x, 3), round(y, 3)))
        x += spacing
    if len(out) < stops:
        raise SystemExit(f"{world}: only {len(out)} free stops along y = {y:.2f}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="office")
    ap.add_argument("--stops", type=int, default=3)
    ap.add_argument("--spacing", type=float, default=0.75)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--heading-step", type=float, default=15.0)
    ap.add_argument("--drive-speed", type=float, default=0.3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-robot-survey-") as tmp:
        t = Path(tmp)
        (t / "sim.toml").write_text(f"""
[devices.camera]
kind = "sim"
[devices.camera.sim]
endpoint = "auto"
world = "{args.world}"
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
path = "{t / 'unused.npz'}"
[logging]
level = "WARNING"
""")
        stops = plan_row(args.world, args.stops, args.spacing)
        (t / "plan.csv").write_text("x,y\n" + "".join(f"{x},{y}\n" for x, y in stops))
        env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")
        proc = subprocess.run(
            [sys.executable, "-m", "services.cli", "survey", "--robot", "--config", str(t / "sim.toml"),
             "--plan", str(t / "plan.csv"), "--out", str(t / "ds"), "--heading-step", str(args.heading_step),
             "--drive-speed", str(args.drive_speed), "--json"],
            capture_output=True, text=True, env=env, cwd=ROOT, timeout=3600)
        if proc.returncode != 0:
            print(proc.stderr[-3000:], file=sys.stderr)
            return 1
        s = json.loads(proc.stdout.strip().splitlines()[-1])
    total = s["seconds"]
    s["share"] = {k: round(s[k] / total, 3) for k in ("drive_s", "head_s", "frame_wait_s", "write_s")} if total else {}
    s["setting"] = {k: getattr(args, k) for k in ("world", "stops", "spacing", "width", "height", "fps",
                                                  "heading_step", "drive_speed")}
    if args.json:
        print(json.dumps(s))
    else:
        print(f"{args.world} {args.width}x{args.height} @ {args.fps:g} fps, {args.stops} stops "
              f"{args.spacing:g} m apart, every {args.heading_step:g} deg: {s['images']} images in "
              f"{total:.1f} s = {s['images_per_minute']:.1f} images/min; time: "
              + ", ".join(f"{k[:-2]} {100 * v:.0f} %" for k, v in s["share"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

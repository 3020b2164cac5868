"""What recording costs, how big it is, and how fast a recording replays.

Runs the simulated service as real processes (:mod:`benchmarks.sim_service_rig`: ``lino-loc
sim`` plus ``lino-loc run``, 320 x 240 at 15 fps, the product's map with its disparity
channel by default) and measures, interleaved A/B (off, on, off, on, ... so that the load of
the shared machine hits both alike):

- ``cpu_ms_per_frame``: the daemon process's CPU time (utime + stime of all its threads:
  the loop, the device threads, the recorder's writer thread) per pose published, over a
  window of ``--seconds`` after ``--warmup``; median of ``--repeat`` runs per mode, the
  difference of the medians on - off (what recording costs per frame), and the differences
  of each off/on pair run back to back (``paired``);
- ``pose_rate_hz`` per mode (recording must not slow the loop) and the recorder's
  ``dropped`` events;
- ``mb_per_min``: megabytes the recording grew per minute of service (status
  ``recording.megabytes``, flushed bytes, over the window), at the configured frame rate;
- ``replay``: the last recording replayed (``services.replay.replay``): its speed as a
  multiple of real time (recording span / replay wall time, the map loaded before), and
  whether its poses are the service's (bit for bit), also recomposed from the raw streams;
- ``handover_us``: in-process, the loop's side of one frame (``Recorder.frame`` + ``pose`` +
  ``particles``: a put on the queue), median of 2000.

Prints one JSON object (with the load average before and after).

Usage::

    python benchmarks/bench_recording.py                         # 3 x (off, on), 20 s each
    python benchmarks/bench_recording.py --seconds 10 --repeat 1 --no-product-map   # quick
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.sim_service_rig import (  # noqa: E402
    Rig,
    Settings,
    Stream,
    cpu_seconds,
    env,
    exit_on_sigterm,
    stop,
)


def _start_daemon(rig: Rig, record: Path | None) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", "services.cli", "run", "--config", str(rig.cfg)]
    if record is not None:
        cmd += ["--record", str(record)]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=open(rig.daemon_log, "ab"),
                            env=env(), cwd=ROOT)


def one_run(rig: Rig, record: Path | None, args: argparse.Namespace) -> dict[str, Any]:
    """One daemon session: CPU per pose and pose rate over the window (and MB/min)."""
    stream = Stream(rig.pub, rig.truth)
    proc = _start_daemon(rig, record)
    try:
        if not stream.wait_for(lambda: len(stream.poses) >= 3, 120):
            raise SystemExit(f"no poses: {rig.daemon_log.read_text()[-2000:]}")
        time.sleep(args.warmup)
        t0, c0 = time.time(), cpu_seconds(proc.pid)
        time.sleep(args.seconds)
        t1, c1 = time.time(), cpu_seconds(proc.pid)
        poses = stream.poses_between(t0, t1)
        statuses = stream.statuses_between(t0 - 1.0, t1 + 0.5)
    finally:
        stop(proc)
        stream.close()
    out: dict[str, Any] = {"poses": len(poses), "pose_rate_hz": len(poses) / (t1 - t0),
                           "cpu_ms_per_frame": 1000.0 * (c1 - c0) / max(1, len(poses)),
                           "cpu_share": (c1 - c0) / (t1 - t0)}
    recs = [s["recording"] for s in statuses if s.get("recording")]
    if record is not None and len(recs) >= 2:
        span = statuses[-1]["stamp"] - next(s for s in statuses if s.get("recording"))["stamp"]
        out["mb_per_min"] = (recs[-1]["megabytes"] - recs[0]["megabytes"]) / max(span, 1e-9) * 60.0
        out["dropped"] = recs[-1]["dropped"]
        out["error"] = recs[-1]["error"]
    return out


def handover_us(n: int = 2000) -> float:
    """Median µs of the loop's side of one frame (queue puts only; the writer not started)."""
    import numpy as np

    from services.messages import Pose2D, PoseMessage
    from services.recording import recorder as r

    left = np.zeros((240, 320), np.uint8)
    disp = np.full((240, 320), np.nan, np.float32)
    msg = PoseMessage(stamp=1.0, seq=1, pose=Pose2D(x=1.0, y=2.0, theta=0.5), covariance=[0.0] * 9,
                      state="tracking", pan=0.0, n_particles=1000, latency_ms=1.0)
    particles = np.zeros((1000, 3))
    times = []
    rec = r.Recorder(r.RecordingConfig(path=Path("/nonexistent/x.mcap")))
    for i in range(n):
        if i % 20 == 0:  # a fresh queue (its writer is not started): no put is refused
            rec = r.Recorder(r.RecordingConfig(path=Path("/nonexistent/x.mcap")))
        t = time.perf_counter()
        rec.frame(float(i), left, disp, delta=[0.0, 0.0, 0.0], pan=0.0, moving=False, image=True, disparity=True)
        rec.pose(msg)
        rec.particles(float(i), lambda: (particles, None))
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e6


def replay_figures(path: Path) -> dict[str, Any]:
    from services.replay import replay

    out: dict[str, Any] = {}
    for name, recompose in (("recorded_inputs", False), ("recomposed", True)):
        r = replay([path], out=path.with_name(f"{path.stem}-{name}.mcap"), recompose=recompose)
        out[name] = {"speed_x_realtime": round(r.speed, 2), "span_s": round(r.span_s, 2),
                     "wall_s": round(r.wall_s, 2), "poses": len(r.poses), "vs_service": r.service}
    return out


def _median(runs: list[dict[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in runs if r.get(key) is not None]
    return statistics.median(vals) if vals else None


def run(args: argparse.Namespace) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="bench-recording-"))
    settings = Settings(width=args.width, height=args.height, fps=args.fps, product_map=args.product_map)
    load0 = os.getloadavg()
    rig = Rig(tmp, settings)
    runs: dict[str, list[dict[str, Any]]] = {"off": [], "on": []}
    last: Path | None = None
    try:
        rig.start_sim()
        for i in range(args.repeat):
            for mode in (("off", "on") if i % 2 == 0 else ("on", "off")):
                last = tmp / f"rec-{i}.mcap" if mode == "on" else last
                runs[mode].append(one_run(rig, last if mode == "on" else None, args))
    finally:
        rig.close()
    off, on = (_median(runs[m], "cpu_ms_per_frame") for m in ("off", "on"))
    result = {
        "settings": {"width": args.width, "height": args.height, "fps": args.fps,
                     "product_map": args.product_map, "seconds": args.seconds, "repeat": args.repeat},
        "cpu_ms_per_frame": {"off": off, "on": on, "recording": None if off is None or on is None else on - off,
                             "paired": [b["cpu_ms_per_frame"] - a["cpu_ms_per_frame"]
                                        for a, b in zip(runs["off"], runs["on"], strict=True)]},
        "pose_rate_hz": {m: _median(runs[m], "pose_rate_hz") for m in runs},
        "mb_per_min": _median(runs["on"], "mb_per_min"),
        "dropped": [r.get("dropped") for r in runs["on"]],
        "handover_us": round(handover_us(), 1),
        "replay": replay_figures(last) if last is not None else None,
        "runs": runs,
        "loadavg": {"before": load0, "after": os.getloadavg()},
    }
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=20.0, help="measured window per run")
    p.add_argument("--warmup", type=float, default=5.0, help="seconds after the first pose")
    p.add_argument("--repeat", type=int, default=3, help="runs per mode (off/on interleaved)")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--fps", type=float, default=15.0)
    p.add_argument("--no-product-map", dest="product_map", action="store_false",
                   help="the tests' intensity-only map (no disparity recorded)")
    args = p.parse_args(argv)
    exit_on_sigterm()
    print(json.dumps(run(args), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

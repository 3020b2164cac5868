"""The running service on the simulated robot: pose rate, latency, drops, memory and CPU.

Starts ``lino-loc run`` with "auto" devices (so the daemon starts its own ``lino-loc sim``:
real head and odometry drivers over the emulators, the rendered camera over ZeroMQ), waits
for the first pose plus a warm-up, then for ``--seconds`` subscribes to the pose and status
streams and samples ``/proc`` of the daemon process (not the simulator), and prints one JSON
object:

- ``pose_rate_hz``: poses received per second; ``frame_rate_hz``: frames the daemon got;
- ``latency_ms`` p50/p99: frame capture stamp to publication (the ``latency_ms`` field the
  daemon puts in each pose: publish time minus the frame's stamp); ``rx_latency_ms``: the
  same measured at the subscriber (reception time minus stamp);
- ``dropped_frames``: frames dropped in the window (status ``dropped_frames`` difference:
  frames replaced in the one-frame mailbox while the loop was busy, plus frames the camera
  adapter skipped to deliver the newest); ``standing_matches``: updates in the window whose
  standing match moved the belief (status difference; ``--standing-match off`` switches it off);
- ``daemon``: resident memory now and peak (VmRSS / VmHWM, MB) and CPU share
  ((utime + stime) / wall time over the window; 1.0 = one full core); ``sim`` the same CPU
  share for the simulator (it renders the camera, so it is not part of the daemon's cost);
- ``state_changes_per_min``: poses whose state differs from the previous pose's, per minute
  from the window's first to its last pose (``services.evaluation.honesty``, as ``eval
  tracking`` counts them), and ``tracking_share``: the share of the window's poses in state ``tracking``
  (each run's ``state_shares``: the share of every state);
- ``truth``: the poses against the simulator's true pose (its ``truth`` topic): the median
  position error, the share of poses ``lost`` within 0.5 m of the truth
  (``false_lost_fraction``) and ``tracking`` more than 1 m off (``confident_wrong_fraction``);

With ``--repeat R`` the run is repeated and the figures are medians (all runs are listed).

Usage::

    python benchmarks/bench_service.py --seconds 30                      # the product's sim.toml
    python benchmarks/bench_service.py --seconds 30 --no-disparity       # intensity alone
    python benchmarks/bench_service.py --seconds 20 --width 160 --height 120 --fps 10 --particles 500
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zmq

ROOT = Path(__file__).resolve().parents[1]
CLK_TCK = os.sysconf("SC_CLK_TCK")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime


def _mem_mb(pid: int) -> tuple[float, float]:
    rss = hwm = 0.0
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            rss = int(line.split()[1]) / 1024.0
        elif line.startswith("VmHWM:"):
            hwm = int(line.split()[1]) / 1024.0
    return rss, hwm


def _config(args: argparse.Namespace, tmp: Path, pub: str, rep: str) -> str:
    dfeat = getattr(args, "disparity_features", None)
    disparity = getattr(args, "disparity", False)
    translations = getattr(args, "translations", 1) if disparity else 1  # they need the disparity
    map_path = Path(args.map_cache).expanduser() / (
        f"office-tube-75cm-15deg-{args.features}f-v{args.virtual_headings}-{args.width}x{args.height}"
        + ("-disparity" + (f"-d{dfeat}f" if dfeat else "") if disparity else "")
        + (f"-t{translations}" if translations > 1 else "") + ".npz"
    )
    map_section = f"""[map]
path = "{map_path}"
[map.build]
world = "office"
step = 0.75
heading_step_deg = 15.0
width = {args.width}
height = {args.height}
features = {args.features}
{f"disparity_features = {dfeat}" if dfeat else ""}
virtual_headings = {args.virtual_headings}
disparity = {"true" if disparity else "false"}
translations = {translations}"""
    if getattr(args, "map", None):  # a given map file (e.g. a synthetic one of benchmarks/bench_scale.py)
        map_section = f"""[map]
path = "{Path(args.map).expanduser()}"
mmap = {"true" if args.mmap else "false"}"""
    sensor = f'index = "{args.index}"' + (f'\nindex_cache = "{args.index_cache}"' if args.index_cache else "")
    return f"""
[devices.camera]
kind = "sim"
[devices.camera.sim]
endpoint = "auto"
world = "office"
width = {args.width}
height = {args.height}
fps = {args.fps}
[devices.head]
kind = "dynamixel"
port = "auto"
[devices.odometry]
kind = "serial"
port = "auto"
{map_section}
[localizer.sensor]
{sensor}
[localizer.filter]
n_particles = {args.particles}
state_hold = {args.state_hold}
[localizer.filter.view_fit]
{"" if args.misfit_alpha is None else f"misfit_alpha = {args.misfit_alpha}"}
{"" if args.invariant_prior is None else f"invariant_prior = {args.invariant_prior}"}
[localizer.filter.challenge]
after_misfit = {"true" if args.after_misfit == "on" else "false"}
[localizer.standing_match]
enabled = {"false" if getattr(args, "standing_match", "on") == "off" else "true"}
[active_vision]
enabled = {"true" if args.active_vision else "false"}
[endpoints]
pub = "{pub}"
rep = "{rep}"
[endpoints.relay]
enabled = {"false" if getattr(args, "no_relay", False) else "true"}
[persistence]
state_file = "{tmp / 'state.json'}"
"""


class _Collector(threading.Thread):
    def __init__(self, endpoint: str) -> None:
        super().__init__(daemon=True)
        self.endpoint = endpoint
        self.poses: list[tuple[float, float, float, str]] = []  # (rx, stamp, latency_ms, state)
        self.xy: list[tuple[float, float]] = []  # each pose's position, m
        self.truth: list[tuple[float, float, float]] = []  # (stamp, x, y) of the simulator's truth
        self.seqs: list[int] = []  # the update number of each pose received
        self.statuses: list[tuple[float, dict[str, Any]]] = []
        self.stop_event = threading.Event()

    def run(self) -> None:
        ctx = zmq.Context()
        s = ctx.socket(zmq.SUB)
        s.setsockopt(zmq.SUBSCRIBE, b"pose")
        s.setsockopt(zmq.SUBSCRIBE, b"status")
        s.setsockopt(zmq.SUBSCRIBE, b"truth")
        s.connect(self.endpoint)
        while not self.stop_event.is_set():
            if not s.poll(100):
                continue
            topic, payload = s.recv_multipart()
            rx = time.time()
            m = json.loads(payload)
            if topic == b"pose":
                self.poses.append((rx, m["stamp"], m.get("latency_ms") or float("nan"), str(m.get("state"))))
                self.seqs.append(int(m["seq"]))
                self.xy.append((float(m["pose"]["x"]), float(m["pose"]["y"])))
            elif topic == b"truth":
                self.truth.append((float(m["stamp"]), float(m["pose"]["x"]), float(m["pose"]["y"])))
            elif topic == b"status":
                self.statuses.append((rx, m))
        s.close(0)
        ctx.term()


def one_run(args: argparse.Namespace) -> dict[str, Any]:
    sys.path.insert(0, str(ROOT))
    from services.evaluation.honesty import state_changes_per_min

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    with tempfile.TemporaryDirectory(prefix="bench-service-") as td:
        tmp = Path(td)
        pub, rep = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
        cfg = tmp / "bench.toml"
        cfg.write_text(_config(args, tmp, pub, rep))
        Path(args.map_cache).expanduser().mkdir(parents=True, exist_ok=True)
        log = tmp / "daemon.log"
        col = _Collector(pub)
        col.start()
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "run", "--config", str(cfg)],
            stdout=subprocess.DEVNULL, stderr=open(log, "wb"), env=env, cwd=ROOT,
        )
        try:
            deadline = time.time() + args.start_timeout
            while not col.poses:
                if proc.poll() is not None or time.time() > deadline:
                    raise SystemExit(f"daemon did not publish (status {proc.poll()}): {log.read_text()[-2000:]}")
                time.sleep(0.2)
            time.sleep(args.warmup)
            text = log.read_text()
            sim_pid = int(text.split("simulator  pid ")[1].split(":")[0]) if "simulator  pid " in text else None
            t0 = time.time()
            cpu0 = _cpu_seconds(proc.pid)
            sim0 = _cpu_seconds(sim_pid) if sim_pid else 0.0
            status0 = col.statuses[-1][1] if col.statuses else None
            time.sleep(args.seconds)
            t1 = time.time()
            cpu1 = _cpu_seconds(proc.pid)
            sim1 = _cpu_seconds(sim_pid) if sim_pid else 0.0
            rss, hwm = _mem_mb(proc.pid)
            status1 = col.statuses[-1][1] if col.statuses else None
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                code = proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                code = proc.wait()
            col.stop_event.set()
            col.join(5)
    idx = [i for i, p in enumerate(col.poses) if t0 <= p[0] <= t1]
    window = [col.poses[i] for i in idx]
    lat = np.array([w[2] for w in window], dtype=float)
    rx_lat = np.array([(w[0] - w[1]) * 1000.0 for w in window], dtype=float)
    states = [w[3] for w in window]

    def pct(a: np.ndarray) -> dict[str, float | None]:
        a = a[np.isfinite(a)]
        if not a.size:
            return {"p50": None, "p99": None}
        return {"p50": round(float(np.percentile(a, 50)), 2), "p99": round(float(np.percentile(a, 99)), 2)}

    dropped = frames = standing = None
    if status0 is not None and status1 is not None:
        dropped = status1["dropped_frames"] - status0["dropped_frames"]
        frames = status1["frames"] - status0["frames"]
        standing = status1.get("standing_matches", 0) - status0.get("standing_matches", 0)
    return {
        "pose_rate_hz": round(len(window) / (t1 - t0), 3),
        "frame_rate_hz": round(frames / (t1 - t0), 3) if frames is not None else None,
        "latency_ms": pct(lat),
        "rx_latency_ms": pct(rx_lat),
        "frames": frames,
        "dropped_frames": dropped,
        "standing_matches": standing,
        "final_state": status1["state"] if status1 else None,
        "state_changes_per_min": round(state_changes_per_min([w[0] for w in window], states), 2),
        "tracking_share": round(states.count("tracking") / len(states), 3) if states else None,
        "state_shares": {st: round(states.count(st) / len(states), 3) for st in sorted(set(states))},
        "truth": _against_truth(col, idx, states),
        "daemon": {
            "rss_mb": round(rss, 1),
            "peak_rss_mb": round(hwm, 1),
            "cpu_share": round((cpu1 - cpu0) / (t1 - t0), 3),
        },
        "sim": {"cpu_share": round((sim1 - sim0) / (t1 - t0), 3) if sim_pid else None},
        "exit_status": code,
    }


def _against_truth(col: _Collector, idx: list[int], states: list[str]) -> dict[str, Any] | None:
    """The window's poses against the simulator's truth (``truth`` topic), interpolated to
    each pose's stamp: the median position error, and the shares of poses ``lost`` within
    0.5 m (``false_lost_fraction``) and ``tracking`` more than 1 m off
    (``confident_wrong_fraction``, :mod:`services.evaluation.honesty`); None without truth."""
    from services.evaluation.honesty import confident_wrong_fraction, false_lost_fraction

    tr = np.array(sorted(col.truth), dtype=float).reshape(-1, 3)
    stamps = np.array([col.poses[i][1] for i in idx], dtype=float)
    inside = (stamps >= tr[0, 0]) & (stamps <= tr[-1, 0]) if len(tr) >= 2 else np.zeros(len(idx), bool)
    if not inside.any():
        return None
    xy = np.array([col.xy[i] for i in idx], dtype=float)[inside]
    tx, ty = (np.interp(stamps[inside], tr[:, 0], tr[:, k]) for k in (1, 2))
    err = np.hypot(xy[:, 0] - tx, xy[:, 1] - ty)
    st = [s for s, ok in zip(states, inside, strict=True) if ok]
    return {"poses": int(inside.sum()), "median_error_m": round(float(np.median(err)), 3),
            "false_lost_fraction": round(false_lost_fraction(err, st), 3),
            "confident_wrong_fraction": round(confident_wrong_fraction(err, st), 3)}


def _sim_toml_build() -> dict[str, Any]:
    """config/sim.toml's ``[map.build]`` (the simulated service's map), read from the file."""
    import tomllib

    with (Path(__file__).resolve().parents[1] / "config" / "sim.toml").open("rb") as f:
        return dict(tomllib.load(f)["map"]["build"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=30.0, help="measurement window")
    p.add_argument("--warmup", type=float, default=5.0, help="seconds after the first pose")
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--fps", type=float, default=15.0)
    p.add_argument("--particles", type=int, default=1000)
    p.add_argument("--no-active-vision", dest="active_vision", action="store_false")
    p.add_argument("--no-disparity", dest="disparity", action="store_false",
                   help="the map without its disparity channel (config/sim.toml's has it)")
    p.add_argument("--map-cache", default="~/.cache/lino-loc/maps", help="folder of the cached maps")
    sim_build = _sim_toml_build()
    p.add_argument("--features", type=int, default=sim_build["features"],
                   help="the map's intensity features (default config/sim.toml's, %(default)s)")
    p.add_argument("--disparity-features", type=int, default=sim_build.get("disparity_features"),
                   help="the disparity channel's features (default config/sim.toml's, %(default)s)")
    p.add_argument("--translations", type=int, default=sim_build.get("translations", 1),
                   help="the map's views between the survey positions, every 0.75 m / m (default config/sim.toml's, "
                   "%(default)s; 1: the survey positions alone; ignored with --no-disparity)")
    p.add_argument("--virtual-headings", type=int, default=5,
                   help="map entries per survey image, as config/sim.toml (default %(default)s; 1: images alone)")
    p.add_argument("--map", default=None,
                   help="use this map file as it is (no build; e.g. a synthetic floor map), with --mmap to map it")
    p.add_argument("--mmap", action="store_true", help="with --map: [map] mmap = true")
    p.add_argument("--index", default="auto", choices=("auto", "brute", "kdtree", "hnsw"),
                   help="[localizer.sensor] index (default %(default)s)")
    p.add_argument("--index-cache", default=None, help="[localizer.sensor] index_cache (the hnsw graph's folder)")
    p.add_argument("--state-hold", type=int, default=1,
                   help="[localizer.filter] state_hold (default %(default)s: the filter's default)")
    p.add_argument("--misfit-alpha", type=float, default=None,
                   help="[localizer.filter.view_fit] misfit_alpha (default: the filter's; 1: the share rule alone)")
    p.add_argument("--invariant-prior", type=float, default=None,
                   help="[localizer.filter.view_fit] invariant_prior (default: the filter's; 0: none)")
    p.add_argument("--after-misfit", choices=("on", "off"), default="on",
                   help="[localizer.filter.challenge] after_misfit (default %(default)s: the filter's default)")
    p.add_argument("--standing-match", choices=("on", "off"), default="on",
                   help="[localizer.standing_match] enabled (default %(default)s: the service's default)")
    p.add_argument("--start-timeout", type=float, default=900.0, help="s (includes building the map once)")
    args = p.parse_args(argv)
    runs = [one_run(args) for _ in range(args.repeat)]

    def med(path: list[str]) -> Any:
        vals = []
        for r in runs:
            v: Any = r
            for k in path:
                v = v.get(k) if isinstance(v, dict) else None
            if v is not None:
                vals.append(v)
        return statistics.median(vals) if vals else None

    out = {
        "benchmark": "service",
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_avg_1m": round(os.getloadavg()[0], 2)},
        "config": {"world": "office", "map": args.map, "mmap": args.mmap, "index": args.index, "width": args.width, "height": args.height, "fps": args.fps,
                   "particles": args.particles, "active_vision": args.active_vision, "state_hold": args.state_hold,
                   "misfit_alpha": args.misfit_alpha, "invariant_prior": args.invariant_prior, "after_misfit": args.after_misfit, "standing_match": args.standing_match, "seconds": args.seconds, "repeat": args.repeat,
                   "disparity": args.disparity, "translations": args.translations if args.disparity else 1},
        "pose_rate_hz": med(["pose_rate_hz"]),
        "frame_rate_hz": med(["frame_rate_hz"]),
        "latency_ms": {"p50": med(["latency_ms", "p50"]), "p99": med(["latency_ms", "p99"])},
        "rx_latency_ms": {"p50": med(["rx_latency_ms", "p50"]), "p99": med(["rx_latency_ms", "p99"])},
        "dropped_frames": med(["dropped_frames"]),
        "standing_matches": med(["standing_matches"]),
        "state_changes_per_min": med(["state_changes_per_min"]),
        "tracking_share": med(["tracking_share"]),
        "truth": {k: med(["truth", k]) for k in ("median_error_m", "false_lost_fraction", "confident_wrong_fraction")},
        "frames": med(["frames"]),
        "daemon": {"rss_mb": med(["daemon", "rss_mb"]), "peak_rss_mb": med(["daemon", "peak_rss_mb"]),
                   "cpu_share": med(["daemon", "cpu_share"])},
        "sim": {"cpu_share": med(["sim", "cpu_share"])},
        "runs": runs,
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())

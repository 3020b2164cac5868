"""A soak of the simulated service: memory slope, CPU share, pose rate and error drift.

Starts ``lino-loc sim`` and ``lino-loc run`` as two processes (:mod:`sim_service_rig`: the
office, 80 x 60 images at 15 fps, 1000 particles), waits for the first pose and ``--warmup``
seconds, then for ``--minutes`` samples every ``--sample-s`` seconds the daemon's resident
memory (VmRSS, ``/proc/PID/status``) and CPU time (``/proc/PID/stat``), while a subscriber
collects the poses and the simulator's true pose. It prints a table and, with ``--json``, one
JSON object:

- ``rss_slope_mb_per_min``: least-squares slope of VmRSS against time over the samples;
  ``rss_mb`` first / last / max; ``relay_rss_slope_mb_per_min`` and ``relay_rss_mb`` the same
  for the pose relay (``services/pose_relay.py``, the daemon's child that owns the pose port;
  null without one), and ``relay_pids`` the relay processes seen (more than one: it restarted);
- ``cpu_share``: daemon CPU seconds / wall seconds over the window (1.0 = one core);
- ``pose_rate_hz``: poses per second over the window, and min / max over one-minute bins;
- ``error_m``: position error (estimate vs truth at the pose's stamp) median / p95, and
  ``error_drift_m_per_min``: the least-squares slope of the per-minute median error;
- ``states``: poses per state.

``--churn`` adds clients that connect and disconnect in a loop on loopback: up to
``CHURN_SUBSCRIBERS`` SUB sockets on the pose port at once (each subscribes, reads for up to
``CHURN_LIFETIME_S``, closes) and REQ clients on the control port (``ping``, ``status`` or
``get_pose``, 1 s timeout, then closed); the counts of connections and replies are reported.

Usage::

    python benchmarks/soak.py --minutes 10
    python benchmarks/soak.py --minutes 10 --churn --json
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zmq

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sim_service_rig import Rig, Settings, Stream, cpu_seconds, exit_on_sigterm, relay_pid, rss_mb  # noqa: E402

#: At most this many churning subscribers on the pose port at once.
CHURN_SUBSCRIBERS = 20
#: A churning subscriber lives at most this long, s.
CHURN_LIFETIME_S = 2.0


def slope_per_min(t: np.ndarray, y: np.ndarray) -> float | None:
    """Least-squares slope of y against t (s), per minute; None with fewer than 2 points."""
    ok = np.isfinite(y)
    if ok.sum() < 2:
        return None
    return float(np.polyfit(t[ok], y[ok], 1)[0] * 60.0)


class Churn(threading.Thread):
    """Clients connecting and disconnecting in a loop (see the module docstring)."""

    def __init__(self, pub: str, rep: str, seed: int = 0) -> None:
        super().__init__(daemon=True, name="churn")
        self.pub, self.rep = pub, rep
        self.rng = random.Random(seed)
        self.stop_event = threading.Event()
        self.counts = {"subscribers": 0, "messages": 0, "requests": 0, "replies": 0, "timeouts": 0}

    def run(self) -> None:
        ctx = zmq.Context()
        subs: list[tuple[zmq.Socket, float]] = []
        try:
            while not self.stop_event.is_set():
                now = time.monotonic()
                for s, end in [x for x in subs if x[1] <= now]:
                    s.close(0)
                    subs.remove((s, end))
                if len(subs) < CHURN_SUBSCRIBERS:
                    s = ctx.socket(zmq.SUB)
                    s.setsockopt(zmq.LINGER, 0)
                    s.setsockopt(zmq.SUBSCRIBE, self.rng.choice([b"pose", b"status", b"", b"po"]))
                    s.connect(self.pub)
                    subs.append((s, now + self.rng.uniform(0.05, CHURN_LIFETIME_S)))
                    self.counts["subscribers"] += 1
                for s, _ in subs:
                    while s.poll(0):
                        s.recv_multipart()
                        self.counts["messages"] += 1
                self._one_request(ctx)
                self.stop_event.wait(0.02)
        finally:
            for s, _ in subs:
                s.close(0)
            ctx.term()

    def _one_request(self, ctx: zmq.Context) -> None:
        r = ctx.socket(zmq.REQ)
        r.setsockopt(zmq.LINGER, 0)
        r.connect(self.rep)
        try:
            r.send(json.dumps({"cmd": self.rng.choice(["ping", "status", "get_pose"])}).encode())
            self.counts["requests"] += 1
            if r.poll(1000):
                r.recv()
                self.counts["replies"] += 1
            else:
                self.counts["timeouts"] += 1
        finally:
            r.close(0)


def sample(rig: Rig, stream: Stream, args: argparse.Namespace) -> dict[str, Any]:
    assert rig.daemon is not None
    pid = rig.daemon.pid
    t_start = time.time()
    samples: list[tuple[float, float, float, float]] = []  # (t, rss, cpu, relay rss)
    relays: set[int] = set()
    end = t_start + args.minutes * 60.0
    while True:
        if rig.daemon.poll() is not None:
            raise SystemExit(f"the daemon exited ({rig.daemon.returncode}): {rig.daemon_log.read_text()[-2000:]}")
        samples.append((time.time(), rss_mb(pid), cpu_seconds(pid), _relay_rss(pid, relays)))
        if time.time() >= end:
            break
        time.sleep(min(args.sample_s, max(0.0, end - time.time())))
    out = summarize(stream, np.array(samples), t_start, time.time())
    out["relay_pids"] = len(relays)
    return out


def _relay_rss(daemon: int, seen: set[int]) -> float:
    """The relay's VmRSS in MB (nan: no relay running), its pid added to ``seen``."""
    relay = relay_pid(daemon)
    if relay is None:
        return float("nan")
    seen.add(relay)
    try:
        return rss_mb(relay)
    except OSError:
        return float("nan")


def summarize(stream: Stream, s: np.ndarray, t0: float, t1: float) -> dict[str, Any]:
    poses = stream.poses_between(t0, t1)
    errs = np.array([stream.error(p) if stream.error(p) is not None else np.nan for p in poses], float)
    rx = np.array([p["_rx"] for p in poses], float)
    bins = np.arange(t0, t1 + 1e-9, 60.0)
    rates, med_err, mids = [], [], []
    for a, b in zip(bins, bins[1:], strict=False):
        m = (rx >= a) & (rx < b)
        rates.append(m.sum() / (b - a))
        e = errs[m]
        med_err.append(float(np.nanmedian(e)) if np.isfinite(e).any() else np.nan)
        mids.append(0.5 * (a + b))
    states: dict[str, int] = {}
    for p in poses:
        states[p["state"]] = states.get(p["state"], 0) + 1
    fin = errs[np.isfinite(errs)]
    return {
        "window_s": round(t1 - t0, 1),
        "samples": len(s),
        "rss_mb": {"first": round(float(s[0, 1]), 1), "last": round(float(s[-1, 1]), 1),
                   "max": round(float(s[:, 1].max()), 1)},
        "rss_slope_mb_per_min": _r(slope_per_min(s[:, 0] - t0, s[:, 1]), 4),
        "relay_rss_mb": None if not np.isfinite(s[:, 3]).any() else {
            "first": _r(float(s[np.isfinite(s[:, 3])][0, 3]), 1),
            "last": _r(float(s[np.isfinite(s[:, 3])][-1, 3]), 1), "max": _r(float(np.nanmax(s[:, 3])), 1)},
        "relay_rss_slope_mb_per_min": _r(slope_per_min(s[:, 0] - t0, s[:, 3]), 4),
        "cpu_share": round(float((s[-1, 2] - s[0, 2]) / (s[-1, 0] - s[0, 0])), 3),
        "pose_rate_hz": {"mean": round(len(poses) / (t1 - t0), 2),
                         "min_1min": _r(min(rates), 2) if rates else None,
                         "max_1min": _r(max(rates), 2) if rates else None},
        "error_m": {"median": _r(float(np.median(fin)), 3) if fin.size else None,
                    "p95": _r(float(np.percentile(fin, 95)), 3) if fin.size else None},
        "error_drift_m_per_min": _r(slope_per_min(np.array(mids) - t0, np.array(med_err)), 4),
        "error_median_per_min": [_r(e, 3) for e in med_err],
        "states": states,
    }


def _r(v: float | None, n: int) -> float | None:
    return None if v is None or not np.isfinite(v) else round(float(v), n)


def run(args: argparse.Namespace) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="lino-soak-") as td:
        rig = Rig(Path(td), Settings(width=args.width, height=args.height, fps=args.fps))
        rig.start_sim("--seed", str(args.seed))
        stream = Stream(rig.pub, rig.truth)
        churn = None
        try:
            rig.start_daemon()
            if not stream.wait_for(lambda: stream.poses_between(0, 1e12), args.start_timeout):
                raise SystemExit(f"no pose: {rig.daemon_log.read_text()[-2000:]}")
            time.sleep(args.warmup)
            if args.churn:
                churn = Churn(rig.pub, rig.rep, args.seed)
                churn.start()
            out = sample(rig, stream, args)
        finally:
            if churn is not None:
                churn.stop_event.set()
                churn.join(10)
            rig.close()
            stream.close()
        out["daemon_exit_status"] = rig.daemon.returncode if rig.daemon else None
        text = rig.daemon_log.read_text()
        out["tracebacks_in_log"] = text.count("Traceback")
    out["churn"] = churn.counts if churn is not None else None
    out["config"] = {"minutes": args.minutes, "warmup_s": args.warmup, "sample_s": args.sample_s,
                     "width": args.width, "height": args.height, "fps": args.fps, "seed": args.seed}
    return out


def table(o: dict[str, Any]) -> str:
    rows = [
        ("window", f"{o['window_s']} s, {o['samples']} samples"),
        ("resident memory slope", f"{o['rss_slope_mb_per_min']} MB/min"),
        ("resident memory first / last / max", f"{o['rss_mb']['first']} / {o['rss_mb']['last']} / {o['rss_mb']['max']} MB"),
        ("relay memory slope, first / last / max (relay processes)",
         "-" if o["relay_rss_mb"] is None else f"{o['relay_rss_slope_mb_per_min']} MB/min, {o['relay_rss_mb']['first']} / "
         f"{o['relay_rss_mb']['last']} / {o['relay_rss_mb']['max']} MB ({o['relay_pids']})"),
        ("CPU share", f"{o['cpu_share']} core"),
        ("pose rate mean (1-min min / max)",
         f"{o['pose_rate_hz']['mean']} Hz ({o['pose_rate_hz']['min_1min']} / {o['pose_rate_hz']['max_1min']})"),
        ("position error median / p95", f"{o['error_m']['median']} / {o['error_m']['p95']} m"),
        ("error drift", f"{o['error_drift_m_per_min']} m/min"),
        ("states", json.dumps(o["states"])),
        ("churn", json.dumps(o["churn"]) if o["churn"] else "-"),
        ("daemon exit / tracebacks", f"{o['daemon_exit_status']} / {o['tracebacks_in_log']}"),
    ]
    return "\n".join(f"| {a} | {b} |" for a, b in [("", ""), ("---", "---"), *rows])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--churn", action="store_true", help="clients connecting and disconnecting in a loop")
    p.add_argument("--warmup", type=float, default=30.0, help="s after the first pose, not measured")
    p.add_argument("--sample-s", type=float, default=5.0, help="memory / CPU sampling period")
    p.add_argument("--width", type=int, default=80)
    p.add_argument("--height", type=int, default=60)
    p.add_argument("--fps", type=float, default=15.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--start-timeout", type=float, default=300.0)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    exit_on_sigterm()
    out = run(args)
    print(json.dumps(out) if args.json else table(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())

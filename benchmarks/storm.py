"""A storm of hostile requests and subscriptions against the running simulated service.

Starts ``lino-loc run`` on the simulated robot as ``benchmarks/bench_service.py`` does (the
daemon starts its own ``lino-loc sim``: 320 x 240 at 15 fps, 1000 particles, active vision on),
waits for the first pose and a warm-up, then sends ``--requests`` operations, drawn with a
seeded generator from these kinds:

- ``malformed``: random bytes, invalid UTF-8, JSON of the wrong type, NaN / inf, unknown
  commands, 1 MB payloads (and, ``--huge`` of them, 10 MB), 30,000-deep nesting, multipart;
- ``extreme``: well-formed ``set_pose`` requests far outside the map (up to 1e6 m) or with
  covariances up to 1e300, and ``global_localization``;
- ``status``: ordinary ``status`` / ``get_pose`` / ``ping`` requests;
- ``subscribe``: a subscriber that subscribes to 200 distinct topics of up to 211 bytes
  (some duplicated), unsubscribes half, and goes without reading.

Each request waits for its reply (REQ, 5 s timeout), except a frame over the control socket's
limit (``services.control.CONTROL_MAX_FRAME_BYTES``): the daemon drops its connection unread,
so it gets no reply by design and is counted as ``dropped_oversize`` (0.2 s wait). It prints one
JSON object: the daemon's exit status (None: still running, i.e. no crash), the pose rate per
one-second window (the minimum over the storm) by the poses' stamps (what the daemon
published, counted by the poses' update numbers so that poses lost on the way count; a pose
is stamped with its frame's time) and by their arrival at this process's
subscriber (what a client received: this process also runs the storm, so it competes for
the CPU), the daemon's resident memory (VmRSS) at the
start and its maximum, the pose relay's (services/pose_relay.py: the process that owns the
pose port, which the daemon starts again when it passes its limit; ``--no-relay`` has the
daemon bind the port itself) and its restarts, the reply latency (median, p99, maximum, per kind), the replies that
were errors and the requests that got no reply.
Loopback only; the number of operations and the time are bounded.

Usage::

    python benchmarks/storm.py --requests 10000
    python benchmarks/storm.py --requests 10000 --repeat 3       # and a summary line
    python benchmarks/storm.py --requests 560 --only subscribe   # a burst of subscribers
    python benchmarks/storm.py --requests 560 --only subscribe --no-relay
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zmq

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_service import ROOT, _Collector, _config, _free_port, _mem_mb  # noqa: E402
from sim_service_rig import relay_pid  # noqa: E402

sys.path.insert(0, str(ROOT))
from services.control import CONTROL_MAX_FRAME_BYTES  # noqa: E402

KINDS = ("malformed", "extreme", "status", "subscribe")
#: How long a frame over the control socket's limit waits for the reply it never gets, ms.
OVERSIZE_WAIT_MS = 200
#: Share of each kind in the storm (sums to 1).
MIX = (0.45, 0.3, 0.2, 0.05)


def malformed(rng: np.random.Generator, huge: bool) -> list[bytes]:
    """One malformed request (the frames of one message)."""
    k = int(rng.integers(10))
    if k == 0:
        return [rng.bytes(int(rng.integers(1, 4096)))]
    if k == 1:
        return [b"\xff\xfe\x80" + rng.bytes(16)]
    if k == 2:
        return [json.dumps(rng.choice(["[]", "1", "null", '"x"'])).encode()]
    if k == 3:
        return [b'{"cmd": "set_pose", "pose": {"x": NaN, "y": Infinity, "theta": 0}}']
    if k == 4:
        return [json.dumps({"cmd": "teleport", "where": "mars"}).encode()]
    if k == 5:
        size = 10_000_000 if huge else 1_000_000
        return [b'{"cmd": "status", "pad": "' + b"x" * size + b'"}']
    if k == 6:
        return [b"[" * 30_000 + b"]" * 30_000]
    if k == 7:
        return [b'{"cmd": "ping"}', b'{"cmd": "ping"}']
    if k == 8:
        return [json.dumps({"cmd": "set_pose", "pose": [1, 2, 3], "covariance": "big"}).encode()]
    return [json.dumps({"cmd": "set_pose", "pose": {"x": 1, "y": 1, "theta": 0},
                        "covariance": [1, 2, 3]}).encode()]


def extreme(rng: np.random.Generator) -> list[bytes]:
    """One well-formed request with extreme values."""
    if rng.random() < 0.2:
        return [b'{"cmd": "global_localization"}']
    x, y = (float(v) for v in rng.choice([1.0, -1.0], 2) * 10.0 ** rng.uniform(0, 6, 2))
    var = float(10.0 ** rng.uniform(-12, 300))
    cov = [var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, min(var, 1e3)]
    return [json.dumps({"cmd": "set_pose", "pose": {"x": x, "y": y, "theta": 0.5},
                        "covariance": cov}).encode()]


def ordinary(rng: np.random.Generator) -> list[bytes]:
    return [json.dumps({"cmd": str(rng.choice(["status", "get_pose", "ping"]))}).encode()]


class Requester:
    """One REQ socket, re-made after a timeout (a REQ socket is stuck after a lost reply)."""

    def __init__(self, ctx: zmq.Context[Any], endpoint: str, timeout_ms: int = 5000) -> None:
        self.ctx, self.endpoint, self.timeout_ms = ctx, endpoint, timeout_ms
        self.sock = self._make(timeout_ms)

    def _make(self, timeout_ms: int) -> zmq.Socket[Any]:
        s = self.ctx.socket(zmq.REQ)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.RCVTIMEO, timeout_ms)
        s.connect(self.endpoint)
        return s

    def send(self, frames: list[bytes], timeout_ms: int | None = None) -> tuple[float, dict[str, Any] | None]:
        """(seconds to the reply, the parsed reply or None on a timeout / unparsable reply);
        with ``timeout_ms`` on a socket of its own with that timeout."""
        sock = self.sock if timeout_ms is None else self._make(timeout_ms)
        t0 = time.perf_counter()
        try:
            sock.send_multipart(frames)
            raw = sock.recv()
        except zmq.Again:
            sock.close(0)
            if sock is self.sock:
                self.sock = self._make(self.timeout_ms)
            return math.inf, None
        dt = time.perf_counter() - t0
        if sock is not self.sock:
            sock.close(0)
        try:
            return dt, json.loads(raw)
        except ValueError:
            return dt, None


def subscribe_storm(ctx: zmq.Context[Any], endpoint: str, rng: np.random.Generator,
                    subs: list[zmq.Socket[Any]]) -> None:
    """A subscriber with 200 distinct long topics (some twice), half of them unsubscribed;
    kept open without reading until the end of the storm."""
    s = ctx.socket(zmq.SUB)
    s.setsockopt(zmq.LINGER, 0)
    s.setsockopt(zmq.RCVHWM, 10)
    s.connect(endpoint)
    topics = [rng.bytes(int(rng.integers(1, 212))) for _ in range(200)]
    for t in topics + topics[:20]:
        s.setsockopt(zmq.SUBSCRIBE, t)
    for t in topics[::2]:
        s.setsockopt(zmq.UNSUBSCRIBE, t)
    s.setsockopt(zmq.SUBSCRIBE, b"pose")
    subs.append(s)


class MemorySampler(threading.Thread):
    """The daemon's resident memory, and its relay's (when it has one), every ``period``."""

    def __init__(self, pid: int, period: float = 0.5) -> None:
        super().__init__(daemon=True)
        self.pid, self.period = pid, period
        self.samples: list[tuple[float, float]] = []
        self.relay_samples: list[tuple[float, float]] = []
        self.stop_event = threading.Event()

    def run(self) -> None:
        while not self.stop_event.wait(self.period):
            try:
                self.samples.append((time.time(), _mem_mb(self.pid)[0]))
            except OSError:
                return
            relay = relay_pid(self.pid)
            if relay is not None:
                try:
                    self.relay_samples.append((time.time(), _mem_mb(relay)[0]))
                except OSError:
                    pass


def storm(args: argparse.Namespace, rep: str, pub: str) -> dict[str, Any]:
    rng = np.random.default_rng(args.seed)
    mix = np.array([m if not args.only or k in args.only else 0.0
                    for k, m in zip(KINDS, MIX, strict=True)])
    mix = mix / mix.sum()
    timeline: list[tuple[float, str]] = []
    ctx = zmq.Context()
    req = Requester(ctx, rep)
    subs: list[zmq.Socket[Any]] = []
    lat: dict[str, list[float]] = {k: [] for k in KINDS}
    errors = {k: 0 for k in KINDS}
    no_reply = {k: 0 for k in KINDS}
    dropped_oversize = 0
    huge_left = args.huge
    deadline = time.time() + args.max_seconds
    sent = 0
    try:
        for _ in range(args.requests):
            if time.time() > deadline:
                break
            kind = KINDS[int(rng.choice(len(KINDS), p=mix))]
            timeline.append((time.time(), kind))
            if kind == "subscribe":
                t0 = time.perf_counter()
                subscribe_storm(ctx, pub, rng, subs)
                lat[kind].append(time.perf_counter() - t0)
            else:
                if kind == "malformed":
                    frames = malformed(rng, huge_left > 0)
                    huge_left -= int(len(frames[0]) > 5_000_000)
                else:
                    frames = extreme(rng) if kind == "extreme" else ordinary(rng)
                if max(len(f) for f in frames) > CONTROL_MAX_FRAME_BYTES:
                    _, reply = req.send(frames, timeout_ms=OVERSIZE_WAIT_MS)
                    dropped_oversize += int(reply is None)
                    sent += 1
                    continue
                dt, reply = req.send(frames)
                if reply is None:
                    no_reply[kind] += 1
                else:
                    lat[kind].append(dt)
                    errors[kind] += int(not reply.get("ok", False))
            sent += 1
    finally:
        for s in subs:
            s.close(0)
        req.sock.close(0)
        ctx.term()

    def stats(v: list[float]) -> dict[str, float | None]:
        a = np.asarray(v, dtype=float) * 1000.0
        if not a.size:
            return {"n": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
        return {"n": int(a.size), "p50_ms": round(float(np.median(a)), 2),
                "p99_ms": round(float(np.percentile(a, 99)), 2), "max_ms": round(float(a.max()), 2)}

    replied = [x for k in KINDS if k != "subscribe" for x in lat[k]]
    return {"sent": sent, "latency": {k: stats(v) for k, v in lat.items()},
            "reply_latency_all": stats(replied), "error_replies": errors, "no_reply": no_reply,
            "dropped_oversize": dropped_oversize, "timeline": timeline,
            "subscribers_left_open": len(subs)}


def worst_window(stamps: list[float], timeline: list[tuple[float, str]], t0: float,
                 t1: float) -> dict[str, Any] | None:
    """The one-second window of the storm with the fewest poses published: its start (s
    after the storm's), its poses and the operations sent in it and in the second before."""
    bins = np.arange(t0, t1 + 1e-9, 1.0)
    if bins.size < 2:
        return None
    counts = np.histogram(np.asarray(stamps), bins=bins)[0]
    i = int(np.argmin(counts))
    lo, hi = bins[i], bins[i + 1]
    ops: dict[str, int] = {}
    for t, kind in timeline:
        if lo - 1.0 <= t < hi:
            ops[kind] = ops.get(kind, 0) + 1
    return {"start_s": round(float(lo - t0), 1), "poses": int(counts[i]), "ops_then_and_before": ops}


def produced_stamps(seqs: list[int], stamps: list[float]) -> list[float]:
    """The stamps of every update the daemon numbered, received or not: a pose's ``seq``
    counts the updates, so the ones between two received poses were made (and lost on the
    way: the relay's queue, a relay restart) at stamps interpolated between theirs."""
    if not seqs:
        return []
    s, t = np.asarray(seqs, float), np.asarray(stamps, float)
    order = np.argsort(s, kind="stable")
    s, t = s[order], t[order]
    every = np.arange(s[0], s[-1] + 1.0)
    return [float(v) for v in np.interp(every, s, t)]


def final_status(rep: str) -> dict[str, Any]:
    """The daemon's ``status`` reply's status ({} when it does not answer within 5 s)."""
    ctx = zmq.Context()
    try:
        _, reply = Requester(ctx, rep).send([b'{"cmd": "status"}'])
    finally:
        ctx.destroy(linger=0)
    return (reply or {}).get("status") or {}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--requests", type=int, default=10_000)
    p.add_argument("--huge", type=int, default=5, help="10 MB requests among the malformed ones")
    p.add_argument("--max-seconds", type=float, default=900.0, help="the storm stops by then")
    p.add_argument("--warmup", type=float, default=10.0, help="seconds after the first pose")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--settle", type=float, default=2.0, help="seconds observed after the storm")
    p.add_argument("--only", type=lambda v: v.split(","), default=None,
                   help=f"comma-separated kinds to send, of {', '.join(KINDS)} (default: all, mixed)")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--fps", type=float, default=15.0)
    p.add_argument("--particles", type=int, default=1000)
    p.add_argument("--no-active-vision", dest="active_vision", action="store_false")
    p.add_argument("--map-cache", default="~/.cache/lino-loc/maps")
    p.add_argument("--virtual-headings", type=int, default=5)
    p.add_argument("--start-timeout", type=float, default=900.0)
    p.add_argument("--no-relay", action="store_true",
                   help="the daemon binds the pose port itself ([endpoints.relay] enabled = false)")
    p.add_argument("--repeat", type=int, default=1,
                   help="run the storm this many times (a fresh daemon each); then a summary line")
    args = p.parse_args(argv)
    runs = []
    for _ in range(max(args.repeat, 1)):
        runs.append(one_storm(args))
        print(json.dumps(runs[-1]), flush=True)
    if len(runs) > 1:
        print(json.dumps(summary(runs)))
    return 0


def summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians and worst cases over repeated storms."""

    def spread(values: list[float]) -> dict[str, float]:
        return {"median": round(float(np.median(values)), 2), "min": round(min(values), 2),
                "max": round(max(values), 2)}

    return {
        "benchmark": "storm-summary",
        "runs": len(runs),
        "crashes": sum(r["daemon_exit_status_during_storm"] is not None for r in runs),
        "no_reply": sum(sum(r["no_reply"].values()) for r in runs),
        "pose_rate_mean_hz": spread([r["pose_rate_hz"]["mean"] for r in runs]),
        "pose_rate_min_1s": spread([r["pose_rate_hz"]["min_1s"] for r in runs]),
        "rss_growth_mb": spread([r["rss_mb"]["growth"] for r in runs]),
        "relay_rss_max_mb": spread([(r["relay_rss_mb"] or {}).get("max", 0.0) for r in runs]),
        "relay_restarts": [((r["status_pose_port_after"] or {}).get("relay_restarts")) for r in runs],
        "reply_p99_ms": spread([r["reply_latency_all"]["p99_ms"] or 0.0 for r in runs]),
        "reply_max_ms": spread([r["reply_latency_all"]["max_ms"] or 0.0 for r in runs]),
        "load_avg_1m": [r["machine"]["load_avg_1m"] for r in runs],
    }


def one_storm(args: argparse.Namespace) -> dict[str, Any]:
    """One storm against a fresh daemon: the JSON object described in the module docstring."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    with tempfile.TemporaryDirectory(prefix="storm-") as td:
        tmp = Path(td)
        pub, rep = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
        (tmp / "storm.toml").write_text(_config(args, tmp, pub, rep))
        Path(args.map_cache).expanduser().mkdir(parents=True, exist_ok=True)
        log = tmp / "daemon.log"
        col = _Collector(pub)
        col.start()
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--config",
                                 str(tmp / "storm.toml")],
                                stdout=subprocess.DEVNULL, stderr=open(log, "wb"), env=env, cwd=ROOT)
        mem = MemorySampler(proc.pid)
        try:
            deadline = time.time() + args.start_timeout
            while not col.poses:
                if proc.poll() is not None or time.time() > deadline:
                    raise SystemExit(f"daemon did not publish: {log.read_text()[-2000:]}")
                time.sleep(0.2)
            time.sleep(args.warmup)
            rss0 = _mem_mb(proc.pid)[0]
            relay0 = relay_pid(proc.pid)
            relay_rss0 = _mem_mb(relay0)[0] if relay0 is not None else None
            mem.start()
            t0 = time.time()
            result = storm(args, rep, pub)
            time.sleep(args.settle)
            t1 = time.time()
            exit_status = proc.poll()
            pose_port = final_status(rep).get("pose_port")
        finally:
            mem.stop_event.set()
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
            col.stop_event.set()
            col.join(5)
        tail = log.read_text()[-1500:]
    def per_second(times: list[float]) -> tuple[float, int]:
        """(mean rate, fewest in a one-second window) of the times within the storm."""
        a = np.array([t for t in times if t0 <= t <= t1])
        bins = np.arange(t0, t1 + 1e-9, 1.0)
        windows = np.histogram(a, bins=bins)[0] if a.size and bins.size > 1 else np.zeros(1)
        return round(float(a.size / (t1 - t0)), 2), int(windows.min())

    published = per_second(produced_stamps(col.seqs, [stamp for _, stamp, _ in col.poses]))
    received = per_second([r for r, _, _ in col.poses])
    worst = worst_window(produced_stamps(col.seqs, [stamp for _, stamp, _ in col.poses]),
                         result.pop("timeline"), t0, t1)
    peak = max((m for _, m in mem.samples), default=rss0)
    out = {
        "benchmark": "storm",
        "machine": {"cpus": os.cpu_count(), "load_avg_1m": round(os.getloadavg()[0], 2)},
        "daemon_exit_status_during_storm": exit_status,
        "storm_seconds": round(t1 - t0, 1),
        "pose_rate_hz": {"mean": published[0], "min_1s": published[1]},
        "received_rate_hz": {"mean": received[0], "min_1s": received[1]},
        "worst_second": worst,
        "rss_mb": {"start": round(rss0, 1), "max": round(peak, 1), "growth": round(peak - rss0, 1)},
        "relay_rss_mb": None if relay_rss0 is None else {
            "start": round(relay_rss0, 1),
            "max": round(max((m for _, m in mem.relay_samples), default=relay_rss0), 1),
        },
        **result,
        "status_pose_port_after": pose_port,
        "log_tail": tail if exit_status is not None else None,
    }
    return out


if __name__ == "__main__":
    sys.exit(main())

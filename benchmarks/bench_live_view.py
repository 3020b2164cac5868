"""What the live view costs the daemon: off, on with no client, on with one Foxglove client.

Runs the simulated service as real processes (:mod:`benchmarks.sim_service_rig`: ``lino-loc
sim`` plus ``lino-loc run``, 320 x 240 at 15 fps, the product's map with its disparity
channel by default) in three modes, interleaved (the order rotates every repeat, so that the
load of the shared machine hits all alike):

- ``off``: ``[live_view] enabled = false`` (the rig's configuration);
- ``idle``: enabled (``LINO_LOC__LIVE_VIEW__ENABLED=true``, a free port), no client;
- ``client``: enabled, one WebSocket client in this process speaking the Foxglove protocol,
  subscribed to every advertised channel (it counts the messages and bytes, decodes nothing).

Per run: ``cpu_ms_per_frame``, the daemon process's CPU time (utime + stime of all its threads:
the loop, the device threads, the live view's sender and foxglove-sdk's server) per pose
published over a window of ``--seconds`` after ``--warmup``; ``pose_rate_hz`` (the live view
must not slow the loop); the status's ``live_view`` counters (``messages``, ``dropped``); the
client's messages and kB per second. Per mode the median of ``--repeat`` runs, and the
differences to ``off`` (medians, and per repeat: ``paired``). ``handover_us``: in-process, the
loop's side of one frame (``LiveView.frame`` + ``pose`` + ``particles``), with no subscriber
(a set lookup) and with every topic subscribed (puts on the queue), median of 2000.

Prints one JSON object (with the load average before and after).

Usage::

    python benchmarks/bench_live_view.py                          # 3 x (off, idle, client), 20 s each
    python benchmarks/bench_live_view.py --seconds 8 --repeat 1 --no-product-map   # quick
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
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
    free_port,
    stop,
)

MODES = ("off", "idle", "client")


class Client(threading.Thread):
    """A Foxglove WebSocket client (``websockets``): subscribes to every channel it is told of
    and counts the binary message frames and their bytes."""

    def __init__(self, port: int) -> None:
        super().__init__(name="foxglove-client", daemon=True)
        self.port = port
        self.messages = 0
        self.bytes = 0
        self.subscribed = threading.Event()
        self._quit = threading.Event()
        self.error: str | None = None

    def run(self) -> None:
        try:
            asyncio.run(self._client())
        except Exception as exc:  # noqa: BLE001 - reported in the result
            self.error = f"{type(exc).__name__}: {exc}"

    async def _client(self) -> None:
        import websockets

        async with websockets.connect(f"ws://127.0.0.1:{self.port}", subprotocols=["foxglove.sdk.v1"],
                                      max_size=None) as ws:
            next_id = 1
            while not self._quit.is_set():
                try:
                    msg = await asyncio.wait_for(ws.recv(), 0.2)
                except TimeoutError:
                    continue
                if isinstance(msg, bytes):
                    self.messages += 1
                    self.bytes += len(msg)
                    continue
                op = json.loads(msg)
                if op.get("op") == "advertise":
                    subs = [{"id": next_id + i, "channelId": c["id"]} for i, c in enumerate(op["channels"])]
                    next_id += len(subs)
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                    self.subscribed.set()

    def stop(self) -> None:
        self._quit.set()
        self.join(5.0)


def one_run(rig: Rig, mode: str, args: argparse.Namespace) -> dict[str, Any]:
    """One daemon session in ``mode``: CPU per pose and pose rate over the window."""
    port = free_port()
    extra = {} if mode == "off" else {"LINO_LOC__LIVE_VIEW__ENABLED": "true",
                                      "LINO_LOC__LIVE_VIEW__PORT": str(port)}
    stream = Stream(rig.pub, rig.truth)
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--config", str(rig.cfg)],
                            stdout=subprocess.DEVNULL, stderr=open(rig.daemon_log, "ab"),
                            env={**env(), **extra}, cwd=ROOT)
    client: Client | None = None
    try:
        if not stream.wait_for(lambda: len(stream.poses) >= 3, 120):
            raise SystemExit(f"no poses: {rig.daemon_log.read_text()[-2000:]}")
        if mode == "client":
            client = Client(port)
            client.start()
            if not client.subscribed.wait(10.0):
                raise SystemExit(f"the client could not subscribe: {client.error}")
        time.sleep(args.warmup)
        m0 = client.messages if client else 0
        b0 = client.bytes if client else 0
        t0, c0 = time.time(), cpu_seconds(proc.pid)
        time.sleep(args.seconds)
        t1, c1 = time.time(), cpu_seconds(proc.pid)
        m1 = client.messages if client else 0
        b1 = client.bytes if client else 0
        poses = stream.poses_between(t0, t1)
        statuses = stream.statuses_between(t0 - 1.0, t1 + 0.5)
    finally:
        if client is not None:
            client.stop()
        stop(proc)
        stream.close()
    out: dict[str, Any] = {"poses": len(poses), "pose_rate_hz": len(poses) / (t1 - t0),
                           "cpu_ms_per_frame": 1000.0 * (c1 - c0) / max(1, len(poses)),
                           "cpu_share": (c1 - c0) / (t1 - t0)}
    lv = [s["live_view"] for s in statuses if s.get("live_view")]
    if lv:
        out["live_view"] = {k: lv[-1][k] for k in ("serving", "clients", "messages", "dropped", "error")}
    if client is not None:
        out["client_msgs_per_s"] = (m1 - m0) / (t1 - t0)
        out["client_kb_per_s"] = (b1 - b0) / (t1 - t0) / 1e3
    return out


def handover_us(subscribed: bool, n: int = 2000) -> float:
    """Median µs of the loop's side of one frame (the sender not started)."""
    import numpy as np

    from services.messages import Pose2D, PoseMessage
    from services.recording import live_view as lv

    left = np.zeros((240, 320), np.uint8)
    msg = PoseMessage(stamp=1.0, seq=1, pose=Pose2D(x=1.0, y=2.0, theta=0.5), covariance=[0.0] * 9,
                      state="tracking", pan=0.0, n_particles=1000, latency_ms=1.0)
    particles = np.zeros((1000, 3))
    cfg = lv.LiveViewConfig(enabled=True)

    def fresh() -> lv.LiveView:
        live = lv.LiveView(cfg)
        live._listener.topics = frozenset(lv.LIVE_TOPICS) if subscribed else frozenset()
        return live

    live, times = fresh(), []
    for i in range(n):
        if i % 20 == 0:  # a fresh queue (its sender is not started): no put is refused
            live = fresh()
        stamp = i / 15.0
        t = time.perf_counter()
        live.frame(stamp, left)
        live.pose(msg)
        live.particles(stamp, lambda: (particles, None))
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e6


def _median(runs: list[dict[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in runs if r.get(key) is not None]
    return statistics.median(vals) if vals else None


def run(args: argparse.Namespace) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="bench-live-view-"))
    settings = Settings(width=args.width, height=args.height, fps=args.fps, product_map=args.product_map)
    load0 = os.getloadavg()
    rig = Rig(tmp, settings)
    runs: dict[str, list[dict[str, Any]]] = {m: [] for m in MODES}
    try:
        rig.start_sim()
        for i in range(args.repeat):
            for mode in MODES[i % 3:] + MODES[: i % 3]:
                runs[mode].append(one_run(rig, mode, args))
    finally:
        rig.close()
    cpu = {m: _median(runs[m], "cpu_ms_per_frame") for m in MODES}
    return {
        "settings": {"width": args.width, "height": args.height, "fps": args.fps,
                     "product_map": args.product_map, "seconds": args.seconds, "repeat": args.repeat},
        "cpu_ms_per_frame": {
            **cpu,
            **{f"{m}_minus_off": None if cpu[m] is None or cpu["off"] is None else cpu[m] - cpu["off"]
               for m in ("idle", "client")},
            "paired": {m: [b["cpu_ms_per_frame"] - a["cpu_ms_per_frame"]
                           for a, b in zip(runs["off"], runs[m], strict=True)] for m in ("idle", "client")},
        },
        "pose_rate_hz": {m: _median(runs[m], "pose_rate_hz") for m in MODES},
        "client_msgs_per_s": _median(runs["client"], "client_msgs_per_s"),
        "client_kb_per_s": _median(runs["client"], "client_kb_per_s"),
        "dropped": [r.get("live_view", {}).get("dropped") for r in runs["client"]],
        "handover_us": {"no_subscriber": round(handover_us(False), 2),
                        "all_subscribed": round(handover_us(True), 2)},
        "runs": runs,
        "loadavg": {"before": load0, "after": os.getloadavg()},
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=20.0, help="measured window per run")
    p.add_argument("--warmup", type=float, default=5.0, help="seconds after the first pose")
    p.add_argument("--repeat", type=int, default=3, help="runs per mode (interleaved)")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--fps", type=float, default=15.0)
    p.add_argument("--no-product-map", dest="product_map", action="store_false",
                   help="the tests' intensity-only map")
    args = p.parse_args(argv)
    exit_on_sigterm()
    print(json.dumps(run(args), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

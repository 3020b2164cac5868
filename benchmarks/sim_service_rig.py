"""The simulated service as real processes, for the long benchmarks (fault campaign, soak).

``lino-loc sim`` and ``lino-loc run`` are started as two processes (as
``tests/test_daemon_integration.py`` does): the simulator with fixed stable links for the
head and the odometry board and fixed camera, truth and fault-control endpoints, so that a
simulator started again offers the same devices at the same places; the daemon with those
devices in its configuration. :class:`Stream` subscribes to the daemon's ``pose`` and
``status`` and to the simulator's ``truth`` (directly, so the truth keeps coming while the
daemon is down) and keeps them with their reception times.

The map is the integration tests' (the office surveyed every 50 cm and 15 deg, 80 x 60
images, 5 features), built once by :func:`services.sim_launcher.ensure_sim_map` and cached
in the temporary folder; for other image sizes (``Settings.width`` x ``height``) the same
survey at that size (:func:`map_cache`). ``Settings.product_map`` uses the product's simulated
map instead (``config/sim.toml``'s ``[map.build]``, read from the file: every 75 cm and 15
deg with virtual headings, the disparity channel fused with intensity), cached beside it.
"""

from __future__ import annotations

import bisect
import json
import math
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zmq

ROOT = Path(__file__).resolve().parents[1]
MAP_CACHE = Path(tempfile.gettempdir()) / "lino-loc-test-maps" / "office-80x60-50cm-15deg-5f.npz"


def map_cache(width: int = 80, height: int = 60) -> Path:
    """The cached map for images of ``width`` x ``height`` (80 x 60: :data:`MAP_CACHE`)."""
    return MAP_CACHE.with_name(f"office-{width}x{height}-50cm-15deg-5f.npz")


def product_map_cache(width: int = 320, height: int = 240) -> Path:
    """The cached map of ``config/sim.toml``'s ``[map.build]`` for ``width`` x ``height`` images."""
    return MAP_CACHE.with_name(f"office-{width}x{height}-sim-toml-map.npz")


def _product_map_build() -> str:
    """``config/sim.toml``'s ``[map.build]`` (the simulated service's map) as TOML lines, read
    from the file so that the benchmarks follow it; ``world``, ``width`` and ``height`` are the
    rig's own."""
    with (ROOT / "config" / "sim.toml").open("rb") as f:
        build = tomllib.load(f)["map"]["build"]
    return "\n".join(f"{k} = {json.dumps(v)}" for k, v in build.items() if k not in ("world", "width", "height"))
CLK_TCK = os.sysconf("SC_CLK_TCK")
_PORTS = random.Random(os.getpid())


def free_port() -> int:
    """A free TCP port on 127.0.0.1 below the ephemeral range (not handed out to port-0 binds)."""
    for _ in range(200):
        port = _PORTS.randrange(20000, 32000)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        return port
    raise RuntimeError("no free TCP port in 20000-32000")


def env() -> dict[str, str]:
    """This environment with the tree first on PYTHONPATH, single-threaded BLAS, no systemd."""
    e = dict(os.environ)
    e["PYTHONPATH"] = os.pathsep.join([str(ROOT), *[p for p in e.get("PYTHONPATH", "").split(os.pathsep) if p]])
    for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        e[v] = "1"
    for k in [k for k in e if k.upper().startswith("LINO_LOC__") or k in ("NOTIFY_SOCKET", "WATCHDOG_USEC")]:
        del e[k]
    return e


@dataclass(frozen=True)
class Settings:
    width: int = 80
    height: int = 60
    fps: float = 15.0
    particles: int = 1000
    save_period_s: float = 1.0
    product_map: bool = False  # config/sim.toml's map (both channels) instead of the tests' 50 cm one


def _map_section(s: Settings) -> str:
    path = product_map_cache(s.width, s.height) if s.product_map else map_cache(s.width, s.height)
    build = _product_map_build() if s.product_map else "step = 0.5\nheading_step_deg = 15.0\nfeatures = 5"
    return f"""[map]
path = "{path}"
[map.build]
world = "office"
width = {s.width}
height = {s.height}
{build}"""


def config_text(s: Settings, tmp: Path, *, head: str, odometry: str, camera: str, pub: str, rep: str) -> str:
    return f"""
[devices.camera]
kind = "sim"
[devices.camera.sim]
endpoint = "{camera}"
world = "office"
width = {s.width}
height = {s.height}
fps = {s.fps}
[devices.head]
kind = "dynamixel"
port = "{head}"
[devices.odometry]
kind = "serial"
port = "{odometry}"
{_map_section(s)}
[localizer.filter]
n_particles = {s.particles}
[endpoints]
pub = "{pub}"
rep = "{rep}"
[persistence]
state_file = "{tmp / 'state.json'}"
save_period_s = {s.save_period_s}
[logging]
level = "INFO"
"""


class Rig:
    """A simulator and a daemon in ``tmp``; :meth:`start_sim`, :meth:`start_daemon`, :meth:`close`."""

    def __init__(self, tmp: Path, settings: Settings = Settings()) -> None:
        from services.config import load_config
        from services.sim_launcher import ensure_sim_map

        self.tmp = tmp
        self.settings = settings
        port = {k: free_port() for k in ("camera", "truth", "faults", "pub", "rep")}
        self.camera = f"tcp://127.0.0.1:{port['camera']}"
        self.truth = f"tcp://127.0.0.1:{port['truth']}"
        self.faults = f"tcp://127.0.0.1:{port['faults']}"
        self.pub = f"tcp://127.0.0.1:{port['pub']}"
        self.rep = f"tcp://127.0.0.1:{port['rep']}"
        self.head_link, self.odometry_link = str(tmp / "head"), str(tmp / "odometry")
        sim_cfg = tmp / "sim.toml"
        sim_cfg.write_text(config_text(settings, tmp, head=self.head_link, odometry=self.odometry_link,
                                       camera=self.camera, pub=self.pub, rep=self.rep))
        self.sim_cfg = sim_cfg
        self.cfg = sim_cfg  # the same file: the daemon opens the links and endpoint the simulator makes
        self.state = tmp / "state.json"
        MAP_CACHE.parent.mkdir(parents=True, exist_ok=True)
        ensure_sim_map(load_config(sim_cfg))
        self.sim: subprocess.Popen[bytes] | None = None
        self.sim_info: dict[str, Any] = {}
        self.daemon: subprocess.Popen[bytes] | None = None
        self.sim_log, self.daemon_log = tmp / "sim.log", tmp / "daemon.log"

    def start_sim(self, *extra: str) -> dict[str, Any]:
        self.sim = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "sim", "--config", str(self.sim_cfg), "--stats-period", "0",
             "--truth-endpoint", self.truth, *extra],
            stdout=subprocess.PIPE, stderr=open(self.sim_log, "ab"), env=env(), cwd=ROOT,
        )
        assert self.sim.stdout is not None
        line = self.sim.stdout.readline()
        if not line:
            raise SystemExit(f"lino-loc sim printed nothing: {self.sim_log.read_text()[-2000:]}")
        self.sim_info = json.loads(line)
        return self.sim_info

    def start_daemon(self) -> subprocess.Popen[bytes]:
        self.daemon = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "run", "--config", str(self.cfg)],
            stdout=subprocess.DEVNULL, stderr=open(self.daemon_log, "ab"), env=env(), cwd=ROOT,
        )
        return self.daemon

    def close(self) -> None:
        for p in (self.daemon, self.sim):
            if p is not None:
                stop(p)


def exit_on_sigterm() -> None:
    """SIGTERM raises SystemExit, so that the benchmark's ``finally`` stops its processes."""
    def handler(*_: object) -> None:
        raise SystemExit(143)

    signal.signal(signal.SIGTERM, handler)


def stop(proc: subprocess.Popen[bytes], sig: int = signal.SIGTERM, timeout: float = 20.0) -> int:
    """Signal ``proc`` and wait; SIGKILL after ``timeout`` s. Returns its exit status."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    return int(proc.returncode)


def request(endpoint: str, payload: dict[str, Any], timeout: float = 5.0) -> dict[str, Any]:
    """One REQ/REP exchange (a fresh socket); {"ok": False, "error": "timeout"} on no reply."""
    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.REQ)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(endpoint)
    try:
        s.send(json.dumps(payload).encode())
        if not s.poll(int(timeout * 1000)):
            return {"ok": False, "error": "timeout"}
        return dict(json.loads(s.recv()))
    finally:
        s.close(0)


def rss_mb(pid: int) -> float:
    """VmRSS of ``pid`` in MB (/proc/PID/status)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def relay_pid(daemon: int) -> int | None:
    """The pose relay among the daemon's children (None: none running)."""
    for task in Path(f"/proc/{daemon}/task").glob("*/children"):
        try:
            children = task.read_text().split()
        except OSError:
            continue
        for c in children:
            try:
                if b"services.pose_relay" in Path(f"/proc/{c}/cmdline").read_bytes():
                    return int(c)
            except OSError:
                continue
    return None


def cpu_seconds(pid: int) -> float:
    """utime + stime of ``pid`` in s (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


@dataclass
class Stream:
    """Collects pose / status (daemon's PUB) and truth (simulator's PUB) in a thread."""

    pub: str
    truth: str
    poses: list[dict[str, Any]] = field(default_factory=list)
    statuses: list[dict[str, Any]] = field(default_factory=list)
    truths: list[tuple[float, float, float, float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._stamps: list[float] = []
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        ctx = zmq.Context()
        sub = ctx.socket(zmq.SUB)
        for t in (b"pose", b"status"):
            sub.setsockopt(zmq.SUBSCRIBE, t)
        sub.connect(self.pub)
        ts = ctx.socket(zmq.SUB)
        ts.setsockopt(zmq.SUBSCRIBE, b"truth")
        ts.connect(self.truth)
        poller = zmq.Poller()
        poller.register(sub, zmq.POLLIN)
        poller.register(ts, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                for s, _ in poller.poll(100):
                    topic, payload = s.recv_multipart()[:2]
                    m = json.loads(payload)
                    m["_rx"] = time.time()
                    with self._lock:
                        if topic == b"pose":
                            self.poses.append(m)
                        elif topic == b"status":
                            self.statuses.append(m)
                        elif topic == b"truth" and s is ts:
                            p = m["pose"]
                            self.truths.append((m["stamp"], p["x"], p["y"], p["theta"]))
                            self._stamps.append(m["stamp"])
                            if len(self.truths) > 200_000:
                                del self.truths[:100_000], self._stamps[:100_000]
        finally:
            sub.close(0)
            ts.close(0)
            ctx.term()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def truth_at(self, stamp: float) -> tuple[float, float, float] | None:
        with self._lock:
            ts = self._stamps
            i = bisect.bisect_left(ts, stamp)
            if not ts or i >= len(ts) or abs(ts[i] - stamp) > 0.05:
                return None
            return self.truths[i][1:]

    def error(self, pose: dict[str, Any]) -> float | None:
        t = self.truth_at(pose["stamp"])
        if t is None:
            return None
        return math.hypot(pose["pose"]["x"] - t[0], pose["pose"]["y"] - t[1])

    def poses_between(self, t0: float, t1: float) -> list[dict[str, Any]]:
        with self._lock:
            return [p for p in self.poses if t0 <= p["_rx"] < t1]

    def statuses_between(self, t0: float, t1: float) -> list[dict[str, Any]]:
        with self._lock:
            return [s for s in self.statuses if t0 <= s["_rx"] < t1]

    def wait_for(self, pred: Any, timeout: float) -> Any:
        deadline = time.time() + timeout
        while time.time() < deadline:
            got = pred()
            if got:
                return got
            time.sleep(0.1)
        return None

"""Fake-hardware integration tests of `lino-loc run`, real processes and sockets.

`lino-loc sim` (the simulated robot: Dynamixel and odometry-board emulators on pseudo-terminals,
the rendered camera over ZeroMQ, the true pose on a `truth` stream) and `lino-loc run` run as
subprocesses with a temporary configuration: 80 x 60 images at 5 fps, 1000 particles, the map
of the office surveyed every 50 cm and 15 deg (built once and cached in the temp folder; with
the paper's 75 cm grid the estimate is pulled towards grid poses and sits near 0.5 m too often
for a 0.5 m test to be stable). A
plain pyzmq subscriber checks what the daemon publishes against the truth stream.

The daemon under test is shared by the tests of this module, in order: convergence and
tracking, control (set_pose, global_localization, malformed requests), a subscriber that
never reads, an odometry failure, ``kill -9`` and restart from the saved pose, and finally a
camera failure (the simulator stopped) followed by a clean SIGTERM. The last test runs the
product path: ``lino-loc run`` with "auto" devices starts its own simulator.
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
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zmq

from services.evaluation.honesty import WRONG_M

ROOT = Path(__file__).resolve().parents[1]
#: Map cache shared by runs of this test module (rebuilt when its build record differs).
MAP_CACHE = Path(tempfile.gettempdir()) / "lino-loc-test-maps" / "office-80x60-50cm-15deg-5f.npz"


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]])
    for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env[v] = "1"
    env.pop("NOTIFY_SOCKET", None)
    env.pop("WATCHDOG_USEC", None)
    for k in [k for k in env if k.upper().startswith("LINO_LOC__")]:
        del env[k]
    return env


_PORTS = random.Random(os.getpid())
_PORTS_GIVEN: set[int] = set()
_PORTS_LOCK = threading.Lock()


def _free_port() -> int:
    """A free TCP port BELOW the kernel's ephemeral range (32768-60999 here): a port the OS
    handed out for port 0 and we released may be handed out again to the next process that
    binds port 0 (the simulator's camera stream, ZeroMQ's own sockets) before the daemon
    binds it - a race seen when several rigs start at once."""
    with _PORTS_LOCK:  # rigs start from several threads: never hand out a port twice
        for _ in range(200):
            port = _PORTS.randrange(20000, 32000)
            if port in _PORTS_GIVEN:
                continue
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", port))
                except OSError:
                    continue
            _PORTS_GIVEN.add(port)
            return port
    raise RuntimeError("no free TCP port in 20000-32000")


def config_text(
    tmp: Path, *, head: str = "auto", odometry: str = "auto", camera: str = "auto",
    pub: str, rep: str, state: Path,
) -> str:
    return f"""
[devices.camera]
kind = "sim"
[devices.camera.sim]
endpoint = "{camera}"
world = "office"
width = 80
height = 60
fps = 5.0
[devices.head]
kind = "dynamixel"
port = "{head}"
[devices.odometry]
kind = "serial"
port = "{odometry}"
[map]
path = "{MAP_CACHE}"
[map.build]
world = "office"
step = 0.5
heading_step_deg = 15.0
width = 80
height = 60
features = 5
[localizer.filter]
n_particles = 1000
[endpoints]
pub = "{pub}"
rep = "{rep}"
sndhwm = 20
[publish]
particles_max_rate_hz = 2.0
[persistence]
state_file = "{state}"
save_period_s = 1.0
[logging]
level = "INFO"
"""


# --------------------------------------------------------------------------------------------
# a plain subscriber
# --------------------------------------------------------------------------------------------


@dataclass
class Stream:
    """Collects pose/status (daemon) and truth (simulator) messages in a thread."""

    pub: str
    truth: str | None
    poses: list[dict[str, Any]] = field(default_factory=list)
    statuses: list[dict[str, Any]] = field(default_factory=list)
    truths: list[tuple[float, float, float, float]] = field(default_factory=list)
    relayed_truths: int = 0

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        ctx = zmq.Context()
        sub = ctx.socket(zmq.SUB)
        for t in (b"pose", b"status", b"truth"):
            sub.setsockopt(zmq.SUBSCRIBE, t)
        sub.connect(self.pub)
        socks = [sub]
        if self.truth:
            ts = ctx.socket(zmq.SUB)
            ts.setsockopt(zmq.SUBSCRIBE, b"truth")
            ts.connect(self.truth)
            socks.append(ts)
        poller = zmq.Poller()
        for s in socks:
            poller.register(s, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                for s, _ in poller.poll(100):
                    topic, payload = s.recv_multipart()
                    m = json.loads(payload)
                    m["_rx"] = time.time()
                    with self._lock:
                        if topic == b"pose":
                            self.poses.append(m)
                        elif topic == b"status":
                            self.statuses.append(m)
                        elif topic == b"truth":
                            if s is sub:
                                self.relayed_truths += 1
                                if self.truth:
                                    continue
                            p = m["pose"]
                            self.truths.append((m["stamp"], p["x"], p["y"], p["theta"]))
        finally:
            for s in socks:
                s.close(0)
            ctx.term()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def truth_at(self, stamp: float) -> tuple[float, float, float] | None:
        with self._lock:
            ts = [t[0] for t in self.truths]
            i = bisect.bisect_left(ts, stamp)
            if not ts or i >= len(ts) or (i == 0 and ts[0] - stamp > 0.05):
                return None
            return self.truths[i][1:]

    def truth_when(self, stamp: float, timeout: float = 5.0) -> tuple[float, float, float]:
        """The truth at ``stamp``, waiting for the simulator's message of that frame: it may
        arrive after the daemon's pose of the same frame."""
        return self.wait_for(lambda: self.truth_at(stamp), timeout, f"the truth at {stamp:.3f}")

    def error(self, pose: dict[str, Any]) -> float | None:
        t = self.truth_at(pose["stamp"])
        if t is None:
            return None
        return math.hypot(pose["pose"]["x"] - t[0], pose["pose"]["y"] - t[1])

    def poses_since(self, t: float) -> list[dict[str, Any]]:
        with self._lock:
            return [p for p in self.poses if p["_rx"] >= t]

    def statuses_since(self, t: float) -> list[dict[str, Any]]:
        with self._lock:
            return [s for s in self.statuses if s["_rx"] >= t]

    def wait_for(self, pred: Any, timeout: float, what: str) -> Any:
        deadline = time.time() + timeout
        while time.time() < deadline:
            got = pred()
            if got:
                return got
            time.sleep(0.1)
        raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


def request(endpoint: str, payload: bytes | dict[str, Any], timeout: float = 10.0) -> dict[str, Any]:
    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.REQ)
    s.setsockopt(zmq.LINGER, 0)
    s.setsockopt(zmq.RCVTIMEO, int(timeout * 1000))
    s.connect(endpoint)
    try:
        s.send(payload if isinstance(payload, bytes) else json.dumps(payload).encode())
        return json.loads(s.recv())
    finally:
        s.close(0)


# --------------------------------------------------------------------------------------------
# processes
# --------------------------------------------------------------------------------------------


def start_sim(cfg: Path, log: Path, *extra: str) -> tuple[subprocess.Popen[bytes], dict[str, Any]]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "sim", "--config", str(cfg), "--stats-period", "0", *extra],
        stdout=subprocess.PIPE, stderr=open(log, "ab"), env=_env(), cwd=ROOT,
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line, f"lino-loc sim printed nothing (see {log}): {log.read_text()[-2000:]}"
    return proc, json.loads(line)


def start_daemon(cfg: Path, log: Path, **env: str) -> subprocess.Popen[bytes]:
    full = {**_env(), **env}
    for k in [k for k, v in full.items() if v == ""]:
        del full[k]  # "" = unset
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", "run", "--config", str(cfg)],
        stdout=subprocess.DEVNULL, stderr=open(log, "ab"), env=full, cwd=ROOT,
    )


def stop(proc: subprocess.Popen[bytes], sig: int = signal.SIGTERM, timeout: float = 20.0) -> int:
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    return int(proc.returncode)


@dataclass
class Rig:
    tmp: Path
    sim: subprocess.Popen[bytes]
    sim_info: dict[str, Any]
    cfg: Path
    pub: str
    rep: str
    state: Path
    log: Path
    daemon: subprocess.Popen[bytes] | None = None
    stream: Stream | None = None


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    from services.config import load_config
    from services.sim_launcher import ensure_sim_map

    tmp = tmp_path_factory.mktemp("daemon")
    state = tmp / "state.json"
    pub, rep = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    sim_cfg = tmp / "sim.toml"
    sim_cfg.write_text(config_text(tmp, pub=pub, rep=rep, state=state))
    MAP_CACHE.parent.mkdir(parents=True, exist_ok=True)
    ensure_sim_map(load_config(sim_cfg))  # built once, cached across runs
    sim, info = start_sim(sim_cfg, tmp / "sim.log")
    cfg = tmp / "daemon.toml"
    cfg.write_text(
        config_text(tmp, head=info["head"], odometry=info["odometry"], camera=info["camera"],
                    pub=pub, rep=rep, state=state)
    )
    r = Rig(tmp=tmp, sim=sim, sim_info=info, cfg=cfg, pub=pub, rep=rep, state=state, log=tmp / "daemon.log")
    r.stream = Stream(pub, info["truth"])
    r.daemon = start_daemon(cfg, r.log)
    try:
        yield r
    finally:
        if r.daemon is not None:
            stop(r.daemon)
        stop(sim)
        r.stream.close()


def _log_tail(r: Rig) -> str:
    return r.log.read_text()[-3000:] if r.log.exists() else "(no log)"


def _wait_tracking(r: Rig, timeout: float) -> dict[str, Any]:
    assert r.stream is not None
    t0 = time.time()

    def converged() -> dict[str, Any] | None:
        ps = r.stream.poses_since(t0)[-3:]
        errs = [r.stream.error(p) for p in ps]
        if len(ps) == 3 and all(e is not None and e < 0.5 for e in errs) and ps[-1]["state"] == "tracking":
            return ps[-1]
        return None

    try:
        return r.stream.wait_for(converged, timeout, "poses within 0.5 m of the truth")
    except AssertionError as exc:
        last = [(p["seq"], p["state"], r.stream.error(p)) for p in r.stream.poses_since(t0)[-10:]]
        raise AssertionError(f"{exc}; last poses (seq, state, error): {last}; log:\n{_log_tail(r)}") from None


# --------------------------------------------------------------------------------------------
# the tests (in order, sharing one daemon)
# --------------------------------------------------------------------------------------------


def test_pose_converges_to_truth_and_keeps_tracking(rig: Rig) -> None:
    s = rig.stream
    assert s is not None
    first = s.wait_for(lambda: s.poses_since(0)[:1], 90, f"a first pose; daemon log:\n{_log_tail(rig)}")[0]
    assert first["frame_id"] == "map" and len(first["covariance"]) == 9
    assert 0 <= first["latency_ms"] < 1000
    _wait_tracking(rig, 60)
    # keep tracking while the robot drives for a while
    t0 = time.time()
    time.sleep(8)
    ps = [p for p in s.poses_since(t0) if s.error(p) is not None]
    assert len(ps) >= 20, "pose rate collapsed"
    in_order = [round(s.error(p), 2) for p in ps]
    errs = sorted(in_order)
    a, b = s.truth_at(ps[0]["stamp"]), s.truth_at(ps[-1]["stamp"])
    assert a is not None and b is not None
    travelled = sum(
        math.hypot(q[1] - p[1], q[2] - p[2]) for p, q in zip(s.truths, s.truths[1:], strict=False)
        if t0 <= p[0] <= ps[-1]["stamp"]
    )
    assert travelled > 0.5, "the simulated robot did not drive"
    # the filter may briefly jump to another mode of an ambiguous view; most poses stay close
    assert errs[len(errs) // 2] < 0.5 and sum(e < 0.5 for e in errs) >= 0.7 * len(errs), f"errors: {in_order}"
    # poses are stamped with the frames' times: strictly increasing, close to reception
    stamps = [p["stamp"] for p in ps]
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    st = s.statuses_since(t0)[-1]
    assert st["state"] == "tracking" and set(st["devices"]) == {"camera", "head", "odometry"}
    assert st["pose_rate_hz"] > 2.0 and st["latency_ms"]["p50"] is not None


def test_set_pose_and_global_localization_over_control(rig: Rig) -> None:
    s = rig.stream
    assert s is not None
    # set_pose far from the truth: the belief follows the request
    target = {"x": 1.0, "y": 1.0, "theta": 0.5}
    cov = [0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.005]
    reply = request(rig.rep, {"cmd": "set_pose", "pose": target, "covariance": cov})
    assert reply["ok"] is True and reply["cmd"] == "set_pose", reply
    t0 = time.time()
    p = s.wait_for(lambda: s.poses_since(t0)[:1], 10, "a pose after set_pose")[0]
    assert math.hypot(p["pose"]["x"] - 1.0, p["pose"]["y"] - 1.0) < 0.5
    # global localization spreads the belief
    reply = request(rig.rep, {"cmd": "global_localization"})
    assert reply["ok"] is True and reply["cmd"] == "global_localization", reply
    t1 = time.time()
    p = s.wait_for(lambda: s.poses_since(t1)[:1], 10, "a pose after global_localization")[0]
    assert p["state"] == "global"
    assert p["covariance"][0] + p["covariance"][4] > 0.5  # spread
    # set_pose at the truth: tracking again at once
    # the latest truth (the robot drives on: an older one, e.g. at the last pose's stamp, is
    # further behind the robot when the request is applied, the more so on a loaded machine)
    t = s.wait_for(lambda: s.truths[-1] if s.truths else None, 20, "the simulator's truth")[1:]
    reply = request(rig.rep, {"cmd": "set_pose", "pose": {"x": t[0], "y": t[1], "theta": t[2]}})
    assert reply["ok"] is True
    t2 = time.time()
    ps = s.wait_for(lambda: s.poses_since(t2)[:3] if len(s.poses_since(t2)) >= 3 else None, 10, "poses")
    assert all(q["state"] == "tracking" for q in ps)
    s.truth_when(ps[-1]["stamp"])  # the simulator's truth of the last frame may come after its pose
    errors = [s.error(q) for q in ps]
    assert all(e is not None and e < 0.6 for e in errors), errors
    got = request(rig.rep, {"cmd": "get_pose"})
    assert got["ok"] and got["pose"]["seq"] >= ps[-1]["seq"]


def test_malformed_control_messages_get_errors_and_the_loop_keeps_publishing(rig: Rig) -> None:
    s = rig.stream
    assert s is not None
    t0 = time.time()
    bad: list[bytes] = [
        b"{not json", b"[]", b'{"cmd": "self_destruct"}', b'{"cmd": "set_pose"}',
        b'{"cmd": "set_pose", "pose": {"x": 1, "y": 2, "theta": 0}, "covariance": [1, 2]}',
        b'{"cmd": "set_pose", "pose": {"x": NaN, "y": 0, "theta": 0}}',
        b'{"cmd": "pause", "target": "wheels"}', b"\xff" * 10, b"",
    ]
    for raw in bad:
        reply = request(rig.rep, raw)
        assert reply["ok"] is False and reply["error"], (raw, reply)
    assert request(rig.rep, {"cmd": "ping"})["ok"] is True
    st = request(rig.rep, {"cmd": "status"})
    assert st["ok"] and st["status"]["state"] in ("global", "tracking", "lost")
    assert isinstance(st["status"]["appearance_changes"], int) and st["status"]["appearance_changes"] >= 0
    for cmd in ({"cmd": "pause"}, {"cmd": "resume"}, {"cmd": "set_active_vision", "enabled": False},
                {"cmd": "set_active_vision", "enabled": True}):
        reply = request(rig.rep, cmd)
        assert reply["ok"] is True and "active_vision" in reply, reply
    saved = request(rig.rep, {"cmd": "save_state"})
    assert saved["ok"] is True and Path(saved["path"]) == rig.state
    time.sleep(2.0)
    ps = s.poses_since(t0)
    assert len(ps) >= 5 and ps[-1]["seq"] > ps[0]["seq"]


def test_the_set_pose_that_once_crashed_the_daemon_is_refused_in_one_line(rig: Rig) -> None:
    """Regression: ``set_pose`` at (3000, 3000) with variances of 1e9, then a camera gap, took
    the daemon down (MemoryError from the mode clustering). The request is refused in one
    line naming the value, the belief is untouched, the loop keeps publishing."""
    s = rig.stream
    assert s is not None
    before = request(rig.rep, {"cmd": "get_pose"})["pose"]
    crash = {"cmd": "set_pose", "pose": {"x": 3000.0, "y": 3000.0, "theta": 0.0},
             "covariance": [1e9, 0, 0, 0, 1e9, 0, 0, 0, 1e9]}
    reply = request(rig.rep, crash)
    assert reply["ok"] is False and reply["cmd"] == "set_pose", reply
    assert "position standard deviation 3.162e+04 m exceeds 1000 m" in reply["error"], reply
    assert "\n" not in reply["error"]
    far = request(rig.rep, {"cmd": "set_pose", "pose": {"x": 3000.0, "y": 3000.0, "theta": 0.0}})
    assert far["ok"] is False and "pose (3000, 3000) lies outside the map" in far["error"], far
    wide = request(rig.rep, {"cmd": "set_pose", "pose": {"x": 1.0, "y": 1.0, "theta": 0.0},
                             "covariance": [1e4, 0, 0, 0, 1e4, 0, 0, 0, 0.1]})
    assert wide["ok"] is False and "position standard deviation 100 m exceeds" in wide["error"], wide
    t0 = time.time()
    time.sleep(2.0)
    ps = s.poses_since(t0)
    assert len(ps) >= 5 and ps[0]["seq"] > before["seq"], "the loop stopped publishing"
    assert all(math.isfinite(p["pose"]["x"]) and abs(p["pose"]["x"]) < 100 for p in ps)
    st = request(rig.rep, {"cmd": "status"})["status"]
    assert st["update_errors"] == 0 and rig.daemon is not None and rig.daemon.poll() is None


def _pose_rate(s: Stream, seconds: float) -> float:
    t0 = time.time()
    time.sleep(seconds)
    ps = s.poses_since(t0)
    if len(ps) < 2:
        return 0.0
    return (len(ps) - 1) / (ps[-1]["_rx"] - ps[0]["_rx"])


def test_a_subscriber_that_never_reads_does_not_slow_the_loop(rig: Rig) -> None:
    s = rig.stream
    assert s is not None
    before = _pose_rate(s, 4.0)
    ctx = zmq.Context()
    stalled = ctx.socket(zmq.SUB)
    stalled.setsockopt(zmq.RCVHWM, 1)
    stalled.setsockopt(zmq.RCVBUF, 4096)
    stalled.setsockopt(zmq.SUBSCRIBE, b"")  # everything, particles included; never read
    stalled.connect(rig.pub)
    try:
        time.sleep(0.5)
        during = _pose_rate(s, 4.0)
    finally:
        stalled.close(0)
        ctx.term()
    assert before > 2.0
    assert during > 0.7 * before, (before, during)  # a blocking send would stop the loop


def test_kill_9_and_restart_resume_from_the_saved_pose(rig: Rig) -> None:
    s = rig.stream
    assert s is not None and rig.daemon is not None
    # start from a known belief (an operator's set_pose at the true pose): tracking
    # (the first truth may not have arrived yet when this test runs alone)
    t = s.wait_for(lambda: s.truths[-1] if s.truths else None, 20, "the simulator's truth")
    reply = request(rig.rep, {"cmd": "set_pose", "pose": {"x": t[1], "y": t[2], "theta": t[3]}})
    assert reply["ok"] is True, reply
    t0 = time.time()
    s.wait_for(lambda: [p["state"] for p in s.poses_since(t0)[-3:]] == ["tracking"] * 3, 20, "tracking")
    reply = request(rig.rep, {"cmd": "save_state"})
    assert reply["ok"] is True, reply
    time.sleep(1.5)  # and at least one periodic save
    rig.daemon.send_signal(signal.SIGKILL)
    rig.daemon.wait(10)
    saved = json.loads(rig.state.read_text())
    assert saved["state"] == "tracking"
    # the robot drives on: the board's counters would refuse the pose; a file written before
    # they were saved has none, and then the check is skipped (next test: with them)
    assert saved["odometry"]["board_ms"] > 0
    del saved["odometry"]
    rig.state.write_text(json.dumps(saved))
    t_restart = time.time()
    rig.daemon = start_daemon(rig.cfg, rig.log)
    first = s.wait_for(lambda: s.poses_since(t_restart)[:3] if len(s.poses_since(t_restart)) >= 3 else None,
                       60, f"poses after the restart; log:\n{_log_tail(rig)}")
    # the robot kept driving while the daemon was down: compare with its true displacement
    a = s.truth_at(saved["stamp"])
    b = s.truth_when(first[0]["stamp"])
    assert a is not None
    moved = math.hypot(b[0] - a[0], b[1] - a[1])
    d = math.hypot(first[0]["pose"]["x"] - saved["pose"]["x"], first[0]["pose"]["y"] - saved["pose"]["y"])
    # resumed around the saved pose, not from a global belief: within 1 m of it, plus the robot's
    # own travel while the daemon was down, which the daemon cannot see (a clean-clone CI run under
    # load: the restart took long enough for 0.96 m of travel, the first pose 1.04 m from the save)
    assert d < 1.0 + moved, (d, moved)
    assert first[0]["covariance"][0] < 2.0 and first[0]["covariance"][4] < 2.0  # not spread over the map
    # ... but not trusted: 'global' until the views confirm it (a quick row of
    # benchmarks/restart_table.py: the robot moved since the save)
    assert first[0]["state"] == "global", first[0]["state"]
    assert first[0]["seq"] < 20  # a new process (its update counter restarted)
    log = rig.log.read_text()
    assert "to be confirmed by the views" in log
    assert "the odometry check is skipped: the saved state has no odometry counters" in log
    _wait_tracking(rig, 60)  # converged: three poses in a row tracking within 0.5 m
    # and no pose before that was confidently wrong (`tracking` over WRONG_M = 1 m off): this
    # map's own tracking error reaches 0.45-0.6 m (docs/results.md, "Honest restarts")
    wrong = [(p["seq"], round(e, 2)) for p in s.poses_since(t_restart)
             if p["state"] == "tracking" and (e := s.error(p)) is not None and e > WRONG_M]
    assert not wrong, f"tracking poses more than {WRONG_M} m wrong after the restart: {wrong}"


def test_a_robot_that_moved_since_the_save_is_refused_by_the_boards_counters(rig: Rig) -> None:
    """kill -9 while the robot drives: the board counted on while the daemon was down, and
    its counters at the restart say the robot moved (refused, global localization), or, if
    the robot happened to stand, how little."""
    s = rig.stream
    assert s is not None and rig.daemon is not None
    _wait_tracking(rig, 60)
    time.sleep(1.5)  # a periodic save (every second)
    rig.daemon.send_signal(signal.SIGKILL)
    rig.daemon.wait(10)
    saved = json.loads(rig.state.read_text())
    time.sleep(2.0)  # the robot drives on
    t_restart = time.time()
    offset = rig.log.stat().st_size
    rig.daemon = start_daemon(rig.cfg, rig.log)
    s.wait_for(lambda: s.poses_since(t_restart)[:1], 60, f"a pose after the restart; log:\n{_log_tail(rig)}")
    line = next(ln for ln in rig.log.read_text()[offset:].splitlines() if "initial belief" in ln)
    assert "the odometry board says the robot moved" in line, line
    a, b = s.truth_at(saved["stamp"]), s.truth_when(s.poses_since(t_restart)[0]["stamp"])
    assert a is not None
    if math.hypot(b[0] - a[0], b[1] - a[1]) > 1.0:
        assert "refused" in line, line
        status = request(rig.rep, {"cmd": "status"})["status"]["persistence"]["initial_belief"]
        assert "refused: the odometry board says the robot moved" in status, status
    _wait_tracking(rig, 90)


def test_a_state_of_another_map_is_refused_at_restart(rig: Rig) -> None:
    s = rig.stream
    assert s is not None and rig.daemon is not None
    _wait_tracking(rig, 60)
    assert request(rig.rep, {"cmd": "save_state"})["ok"] is True
    rig.daemon.send_signal(signal.SIGKILL)
    rig.daemon.wait(10)
    saved = json.loads(rig.state.read_text())
    saved["map_checksum"] = "0" * 64
    rig.state.write_text(json.dumps(saved))
    leftover = rig.state.with_name(".state.json.tmp-999999-0badf00d")  # an interrupted save's
    leftover.write_text("{")
    t_restart = time.time()
    rig.daemon = start_daemon(rig.cfg, rig.log)
    s.wait_for(lambda: s.poses_since(t_restart)[:1], 60, f"a pose after the restart; log:\n{_log_tail(rig)}")
    log = rig.log.read_text()
    assert "refused: saved for another map" in log
    assert not leftover.exists()
    first = s.poses_since(t_restart)[0]
    assert first["state"] == "global"
    persistence = request(rig.rep, {"cmd": "status"})["status"]["persistence"]
    assert "refused: saved for another map" in persistence["initial_belief"]
    _wait_tracking(rig, 90)


def test_odometry_failure_is_reported_and_the_daemon_keeps_running(rig: Rig) -> None:
    s = rig.stream
    assert s is not None
    t0 = time.time()
    rig.sim.send_signal(signal.SIGUSR1)  # the simulator unplugs its odometry board for 2 s

    def odometry_bad() -> dict[str, Any] | None:
        for st in s.statuses_since(t0):
            if st["devices"]["odometry"]["state"] != "ok":
                return st
        return None

    st = s.wait_for(odometry_bad, 10, "status reporting the odometry failure")
    assert st["devices"]["odometry"]["error"]
    assert st["devices"]["camera"]["state"] == "ok"
    s.wait_for(lambda: len(s.poses_since(t0)) >= 5, 10, "poses while the odometry is unplugged")
    t1 = time.time()
    s.wait_for(
        lambda: any(x["devices"]["odometry"]["state"] == "ok" for x in s.statuses_since(t1)),
        15, "the odometry to recover",
    )
    assert rig.daemon is not None and rig.daemon.poll() is None


def test_camera_failure_dead_reckoning_then_clean_sigterm(rig: Rig) -> None:
    s = rig.stream
    assert s is not None and rig.daemon is not None
    assert stop(rig.sim) == 0  # the simulator (camera, head, odometry) goes away
    t0 = time.time()
    p = s.wait_for(
        lambda: next((q for q in s.poses_since(t0) if q["dead_reckoning"]), None), 15,
        "dead-reckoning poses without the camera",
    )
    assert p["dead_reckoning"] is True
    st = s.wait_for(
        lambda: next((x for x in s.statuses_since(t0) if x["devices"]["camera"]["state"] != "ok"), None),
        15, "status reporting the camera failure",
    )
    assert st["devices"]["camera"]["error"]
    assert rig.daemon.poll() is None
    rig.state.unlink(missing_ok=True)
    last_state = s.poses_since(0)[-1]["state"]
    assert stop(rig.daemon, signal.SIGTERM) == 0
    log = rig.log.read_text()
    assert "Traceback" not in log
    assert log.rstrip().endswith("stopped")
    if last_state == "tracking":  # a converged pose is saved at shutdown
        assert json.loads(rig.state.read_text())["format"] == "lino-loc-state"
    rig.daemon = None


def test_run_with_auto_devices_starts_its_simulator_and_stops_it(tmp_path: Path) -> None:
    """The product path: "auto" devices, so `lino-loc run` starts `lino-loc sim` itself, reuses
    the cached map, relays the truth, tells systemd READY/WATCHDOG/STATUS/STOPPING, and on
    SIGINT stops cleanly (exit 0) together with its simulator."""
    pub, rep = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    cfg = tmp_path / "auto.toml"
    cfg.write_text(config_text(tmp_path, pub=pub, rep=rep, state=tmp_path / "state.json"))
    log = tmp_path / "run.log"
    notify_path = str(tmp_path / "notify.sock")
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(notify_path)
    notify.settimeout(0.2)
    stream = Stream(pub, None)
    proc = start_daemon(cfg, log, NOTIFY_SOCKET=notify_path, WATCHDOG_USEC="1000000")
    sim_pid = None
    try:
        stream.wait_for(lambda: len(stream.poses_since(0)) >= 3, 90, f"poses; log:\n{log.read_text()[-3000:]}")
        stream.wait_for(lambda: stream.relayed_truths > 10, 10, "truth relayed by the daemon")
        time.sleep(1.5)
        text = log.read_text()
        assert "using the cached simulated map" in text
        assert "lino-loc echo --topic pose" in text and pub in text
        sim_pid = int(text.split("simulator  pid ")[1].split(":")[0])
        os.kill(sim_pid, 0)  # alive
    finally:
        code = stop(proc, signal.SIGINT)
        stream.close()
    assert code == 0
    notes: list[str] = []
    while True:
        try:
            notes.append(notify.recv(4096).decode())
        except TimeoutError:
            break
    notify.close()
    assert notes and notes[0].startswith("READY=1")
    assert sum(n == "WATCHDOG=1" for n in notes) >= 2  # every 0.5 s from the loop
    assert any(n.startswith("STATUS=") and "Hz" in n for n in notes)
    assert notes[-1].startswith("STOPPING=1")
    assert sim_pid is not None
    deadline = time.time() + 10
    while time.time() < deadline:
        try:
            os.kill(sim_pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        raise AssertionError("the simulator outlived the daemon")


def test_run_stops_with_status_1_when_its_simulator_dies(tmp_path: Path) -> None:
    """`lino-loc run` with "auto" devices: the simulated robot is killed (-9); the daemon says
    so in one line, shuts down cleanly and exits 1 (so that a supervisor restarts both)."""
    pub, rep = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    cfg = tmp_path / "auto.toml"
    cfg.write_text(config_text(tmp_path, pub=pub, rep=rep, state=tmp_path / "state.json"))
    log = tmp_path / "run.log"
    stream = Stream(pub, None)
    proc = start_daemon(cfg, log)
    try:
        stream.wait_for(lambda: len(stream.poses_since(0)) >= 3, 90, f"poses; log:\n{log.read_text()[-3000:]}")
        sim_pid = int(log.read_text().split("simulator  pid ")[1].split(":")[0])
        os.kill(sim_pid, signal.SIGKILL)
        code = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            stop(proc)
        stream.close()
    text = log.read_text()
    assert code == 1, text[-3000:]
    assert "the simulated robot (lino-loc sim) exited with status -9: stopping" in text
    assert "Traceback" not in text


# --------------------------------------------------------------------------------------------
# the launcher's pieces (no processes)
# --------------------------------------------------------------------------------------------


def test_sim_info_parse_and_resolve_auto(tmp_path: Path) -> None:
    from lino_loc.errors import LinoLocError
    from services.config import load_config
    from services.sim_launcher import SimInfo, needs_sim, resolve_auto

    line = json.dumps({"head": "/dev/pts/7", "odometry": "/tmp/x/odometry", "camera": "tcp://127.0.0.1:9",
                       "truth": "tcp://127.0.0.1:10", "world": "office", "pid": 42})
    info = SimInfo.parse(line)
    assert (info.head, info.truth, info.pid) == ("/dev/pts/7", "tcp://127.0.0.1:10", 42)
    for bad in ("nope", "[1]", json.dumps({"head": "/dev/pts/1"})):
        with pytest.raises(LinoLocError, match="lino-loc sim"):
            SimInfo.parse(bad)
    cfg_path = tmp_path / "c.toml"
    cfg_path.write_text(config_text(tmp_path, pub="tcp://127.0.0.1:1", rep="tcp://127.0.0.1:2", state=tmp_path / "s"))
    cfg = load_config(cfg_path)
    assert needs_sim(cfg)
    done = resolve_auto(cfg, info)
    assert not needs_sim(done)
    assert done.devices.head.port == "/dev/pts/7" and done.devices.odometry.port == "/tmp/x/odometry"
    assert done.devices.camera.sim.endpoint == "tcp://127.0.0.1:9"
    assert done.devices.head.driver_config().port == "/dev/pts/7"


def test_sim_map_is_built_once_then_reused_and_rebuilt_when_settings_change(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from services.config import load_config
    from services.sim_launcher import ensure_sim_map, sidecar_path

    def cfg(features: int) -> Any:
        p = tmp_path / f"c{features}.toml"
        text = config_text(tmp_path, pub="tcp://127.0.0.1:1", rep="tcp://127.0.0.1:2", state=tmp_path / "s")
        text = text.replace(str(MAP_CACHE), str(tmp_path / "m.npz"))
        text = text.replace("step = 0.5", "step = 2.0").replace("heading_step_deg = 15.0", "heading_step_deg = 90.0")
        text = text.replace("width = 80\nheight = 60\nfeatures = 5", f"width = 24\nheight = 16\nfeatures = {features}")
        p.write_text(text)
        return load_config(p)

    amap, built = ensure_sim_map(cfg(3))
    assert built and amap.channels["intensity"].n_features == 3
    assert sidecar_path(tmp_path / "m.npz").is_file()
    assert not (tmp_path / ".m.survey").exists()  # the survey is removed after the build
    mtime = (tmp_path / "m.npz").stat().st_mtime_ns
    again, built = ensure_sim_map(cfg(3))
    assert not built and (tmp_path / "m.npz").stat().st_mtime_ns == mtime
    _, built = ensure_sim_map(cfg(4), in_subprocess=True)  # other settings: rebuilt (as the daemon does)
    assert built
    assert ensure_sim_map(cfg(4), in_subprocess=True)[1] is False  # and then reused
    (tmp_path / "m.npz").write_bytes(b"PK\x03\x04 truncated")  # corrupt: rebuilt
    amap, built = ensure_sim_map(cfg(4))
    assert built and amap.channels["intensity"].n_features == 4
    # other map-building code (a changed renderer, PCA, ...): the cached map is stale, rebuilt
    with monkeypatch.context() as m:
        m.setattr("services.sim_launcher._code_fingerprint", lambda: "0000dead")
        assert ensure_sim_map(cfg(4))[1] is True
        assert ensure_sim_map(cfg(4))[1] is False
    assert ensure_sim_map(cfg(4))[1] is True

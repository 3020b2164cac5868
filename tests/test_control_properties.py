"""Property-based tests of a running daemon's sockets (hypothesis, stateful).

A real ``lino-loc sim`` and ``lino-loc run`` (the rig of ``tests/test_daemon_integration.py``:
80 x 60 images at 5 fps, the office map) are driven by a hypothesis state machine whose rules
send what any client may send to the control socket (valid requests with extreme values,
malformed bytes, arbitrary JSON) and to the pose port (subscriptions to arbitrary topics, some
repeated, unsubscriptions). After every step the invariants must hold:

- the daemon is alive and answers ``status`` with one reply;
- every reply arrives within ``REPLY_S`` and is one JSON object with ``ok``;
- the poses keep coming (one in the last ``POSE_GAP_S``) and are finite;
- the belief stays inside the map: the published position within ``MAP_MARGIN_M`` of the
  office's 8 x 2.5 m (a request that would put it elsewhere is refused);
- the daemon's resident memory stays within ``MEMORY_GROWTH_MB`` of its start.

The examples are few (the storm in ``benchmarks/storm.py`` sends thousands), the database off
and the seed fixed, so a run is reproducible and takes under a minute.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zmq

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, Phase, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.stateful import (  # noqa: E402
    RuleBasedStateMachine,
    invariant,
    rule,
    run_state_machine_as_test,
)
from test_daemon_integration import (  # noqa: E402
    MAP_CACHE,
    Stream,
    _free_port,
    config_text,
    start_daemon,
    start_sim,
    stop,
)

REPLY_S = 2.0  # a reply slower than this fails (the storm benchmark measures the real figure)
POSE_GAP_S = 2.0  # at 5 fps: ten frames without a pose fails
MAP_MARGIN_M = 4.0  # the office is 8 x 2.5 m; set_pose is accepted to 2 m beyond the map bounds
MEMORY_GROWTH_MB = 100.0
OFFICE = (0.0, 8.0, 0.0, 2.5)


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError(f"no VmRSS for pid {pid}")


class _Rig:
    def __init__(self, tmp: Path) -> None:
        from services.config import load_config
        from services.sim_launcher import ensure_sim_map

        self.pub = f"tcp://127.0.0.1:{_free_port()}"
        self.rep = f"tcp://127.0.0.1:{_free_port()}"
        state = tmp / "state.json"
        sim_cfg = tmp / "sim.toml"
        sim_cfg.write_text(config_text(tmp, pub=self.pub, rep=self.rep, state=state))
        MAP_CACHE.parent.mkdir(parents=True, exist_ok=True)
        ensure_sim_map(load_config(sim_cfg))
        self.sim, info = start_sim(sim_cfg, tmp / "sim.log")
        cfg = tmp / "daemon.toml"
        cfg.write_text(config_text(tmp, head=info["head"], odometry=info["odometry"],
                                   camera=info["camera"], pub=self.pub, rep=self.rep, state=state))
        self.log = tmp / "daemon.log"
        self.stream = Stream(self.pub, info["truth"])
        self.daemon = start_daemon(cfg, self.log)
        self.stream.wait_for(lambda: self.stream.poses_since(0.0), 120.0, "the first pose")
        self.ctx = zmq.Context()
        self.rss0 = _rss_mb(self.daemon.pid)
        self.subs: list[zmq.Socket[Any]] = []
        self.first_failure: str | None = None

    def expect(self, ok: bool, what: str) -> None:
        """Fail with ``what`` (and keep the first failure: the daemon's state outlives an
        example, so hypothesis's replay of a failing example may fail differently)."""
        if not ok:
            self.first_failure = self.first_failure or what
            raise AssertionError(what)

    def request(self, frames: list[bytes]) -> dict[str, Any]:
        s = self.ctx.socket(zmq.REQ)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.RCVTIMEO, int(REPLY_S * 1000))
        s.connect(self.rep)
        raw = None
        try:
            s.send_multipart(frames)
            raw = s.recv()
        except zmq.Again:
            pass
        finally:
            s.close(0)
        self.expect(raw is not None, f"no reply within {REPLY_S} s to {frames[0][:80]!r}")
        reply = json.loads(raw)
        self.expect(isinstance(reply, dict) and isinstance(reply.get("ok"), bool), f"reply {reply!r}")
        return reply

    def close(self) -> None:
        for s in self.subs:
            s.close(0)
        self.ctx.term()
        stop(self.daemon)
        stop(self.sim)
        self.stream.close()


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[_Rig]:
    r = _Rig(tmp_path_factory.mktemp("properties"))
    try:
        yield r
    finally:
        r.close()


finite = st.floats(allow_nan=False, allow_infinity=False)
coordinate = st.one_of(st.floats(-10.0, 10.0), st.floats(-1e6, 1e6), st.sampled_from([3000.0, -1e300, 1e300]))
variance = st.one_of(st.sampled_from([1e-12, 1e-3, 0.01, 1.0, 1e9, 1e300]), st.floats(1e-12, 1e6))
json_values = st.recursive(
    st.none() | st.booleans() | finite | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=20,
)


class DaemonSockets(RuleBasedStateMachine):
    """Rules: what a client can send; invariants: what the daemon must keep."""

    rig: _Rig

    @rule(x=coordinate, y=coordinate, theta=st.floats(-10.0, 10.0), var=variance)
    def set_pose(self, x: float, y: float, theta: float, var: float) -> None:
        cov = [var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, min(var, 10.0)]
        body = {"cmd": "set_pose", "pose": {"x": x, "y": y, "theta": theta}, "covariance": cov}
        self.rig.request([json.dumps(body).encode()])

    @rule()
    def global_localization(self) -> None:
        assert self.rig.request([b'{"cmd": "global_localization"}'])["ok"]

    @rule(raw=st.binary(max_size=2048))
    def malformed(self, raw: bytes) -> None:
        self.rig.request([raw])

    @rule(cmd=st.sampled_from(["set_pose", "status", "pause", "save_state", "nope"]), body=json_values)
    def arbitrary_json(self, cmd: str, body: Any) -> None:
        self.rig.request([json.dumps({"cmd": cmd, "args": body, "pose": body}).encode()])

    @rule(topics=st.lists(st.binary(max_size=211), min_size=1, max_size=50), repeat=st.booleans())
    def subscribe(self, topics: list[bytes], repeat: bool) -> None:
        s = self.rig.ctx.socket(zmq.SUB)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.RCVHWM, 5)
        s.connect(self.rig.pub)
        for t in topics + (topics if repeat else []):
            s.setsockopt(zmq.SUBSCRIBE, t)
        for t in topics[::2]:
            s.setsockopt(zmq.UNSUBSCRIBE, t)
        self.rig.subs.append(s)  # never read

    @invariant()
    def daemon_alive_and_answering(self) -> None:
        self.rig.expect(self.rig.daemon.poll() is None,
                        "the daemon died: " + self.rig.log.read_text()[-3000:])
        self.rig.expect(self.rig.request([b'{"cmd": "status"}'])["ok"], "status refused")

    @invariant()
    def poses_keep_coming_finite_and_inside_the_map(self) -> None:
        recent = self.rig.stream.poses_since(time.time() - POSE_GAP_S)
        self.rig.expect(bool(recent), f"no pose for {POSE_GAP_S} s")
        p = recent[-1]["pose"]
        self.rig.expect(all(math.isfinite(p[k]) for k in ("x", "y", "theta")), f"pose {p}")
        x0, x1, y0, y1 = OFFICE
        m = MAP_MARGIN_M
        inside = x0 - m <= p["x"] <= x1 + m and y0 - m <= p["y"] <= y1 + m
        self.rig.expect(inside, f"pose {p} outside the map (and its {m} m margin)")

    @invariant()
    def memory_bounded(self) -> None:
        rss = _rss_mb(self.rig.daemon.pid)
        self.rig.expect(rss < self.rig.rss0 + MEMORY_GROWTH_MB,
                        f"resident memory {rss:.0f} MB, from {self.rig.rss0:.0f} MB")


def test_no_client_stalls_crashes_or_bloats_the_daemon(rig: _Rig) -> None:
    DaemonSockets.rig = rig
    try:
        run_state_machine_as_test(
            DaemonSockets,
            settings=settings(max_examples=6, stateful_step_count=20, deadline=None,
                              database=None, derandomize=True, phases=[Phase.generate],
                              suppress_health_check=list(HealthCheck)),
        )
    except Exception as exc:
        if rig.first_failure is not None:
            raise AssertionError(rig.first_failure) from exc
        raise

"""The pose relay process (services/pose_relay.py, services/relay_publisher.py): real
processes and sockets.

It republishes what the daemon sends, forwards upstream only subscriptions that can match a
topic, reports its counters, binds errors in one line, is started again when it exits (its
memory limit, a kill), dies with the daemon, and keeps what subscribers cost out of the
daemon's process."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest
import zmq

from services.messages import Pose2D, PoseMessage, decode
from services.relay_publisher import RelayConfig, RelayedPublisher

ROOT = Path(__file__).resolve().parent.parent
COV = [0.1, 0, 0, 0, 0.1, 0, 0, 0, 0.01]


def _pose(seq: int) -> PoseMessage:
    return PoseMessage(stamp=1.0 + seq, seq=seq, pose=Pose2D(x=seq, y=0, theta=0), covariance=COV, state="tracking")


def _until(cond: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is gone for our purpose
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def _rss(pid: int) -> int:
    return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _receives(pub: RelayedPublisher, sub: zmq.Socket[Any], timeout: float) -> bool:
    """Publish poses until ``sub`` gets one (True) or ``timeout`` passes."""
    deadline = time.monotonic() + timeout
    seq = 0
    while time.monotonic() < deadline:
        seq += 1
        pub.publish("pose", _pose(seq))
        if sub.poll(20):
            topic, msg = decode(sub.recv_multipart())
            return topic == "pose"
    return False


@pytest.fixture
def ctx() -> Any:
    c: zmq.Context[Any] = zmq.Context()
    yield c
    c.destroy(0)


def test_messages_go_through_and_only_topic_prefixes_go_upstream(ctx: zmq.Context[Any]) -> None:
    pub = RelayedPublisher(ctx, "tcp://127.0.0.1:*", 10)
    sub, junk = ctx.socket(zmq.SUB), ctx.socket(zmq.SUB)
    try:
        assert pub.last_endpoint.startswith("tcp://127.0.0.1:") and not pub.last_endpoint.endswith(":*")
        sub.setsockopt(zmq.SUBSCRIBE, b"pose")
        junk.setsockopt(zmq.SUBSCRIBE, b"x" * 300)  # matches no topic
        junk.setsockopt(zmq.SUBSCRIBE, b"posex")
        for s in (sub, junk):
            s.connect(pub.last_endpoint)
        _until(lambda: pub.wanted("pose"), 5.0, "the subscription never reached the daemon")
        assert _receives(pub, sub, 5.0)
        assert not pub.wanted("particles") and not pub.wanted("status")
        # the daemon's side holds only the topic prefix; the relay saw and ignored the others
        assert pub.subscriptions == {b"pose"}
        # the counters are the relay's report every REPORT_PERIOD_S: one taken after the junk's
        # subscriptions were read but before the "pose" one (the junk's handshake may finish first)
        # says 2 and 305 bytes, and the "pose" forwarded just after it can reach the daemon before
        # the next report does; so wait for a report that has seen all three
        _until(lambda: (i := pub.info()).ignored_subscriptions >= 2 and i.subscriptions >= 3, 5.0,
               "the relay's counters never counted the three subscriptions")
        info = pub.info()
        assert info.subscribers == 2 and info.subscriptions == 3 and info.subscription_bytes == 4 + 300 + 5
        assert info.relay_running and info.relay_restarts == 0 and info.relay_resident_bytes > 10e6
        sub.setsockopt(zmq.UNSUBSCRIBE, b"pose")
        _until(lambda: not pub.wanted("pose"), 5.0, "the unsubscription never reached the daemon")
        # an empty prefix wants everything
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        _until(lambda: pub.wanted("particles") and pub.wanted("status"), 5.0, "'' never arrived")
    finally:
        sub.close(0)
        junk.close(0)
        pub.close()


def test_a_port_taken_is_one_line_and_leaves_nothing_behind(ctx: zmq.Context[Any], monkeypatch: Any) -> None:
    holder = ctx.socket(zmq.PUB)
    port = holder.bind_to_random_port("tcp://127.0.0.1")
    tmp = Path(tempfile.mkdtemp(prefix="lr-", dir="/tmp"))  # short: ipc:// paths end at 107 bytes
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    try:
        with pytest.raises(OSError) as err:
            RelayedPublisher(ctx, f"tcp://127.0.0.1:{port}", 10)
        text = str(err.value)
        assert text.startswith(f"cannot bind the PUB socket to tcp://127.0.0.1:{port}") and "\n" not in text
        assert list(tmp.iterdir()) == []  # the private socket's folder is removed
    finally:
        holder.close(0)
        tmp.rmdir()


def test_a_killed_relay_is_started_again_on_the_same_port(ctx: zmq.Context[Any], caplog: Any) -> None:
    pub = RelayedPublisher(ctx, "tcp://127.0.0.1:*", 10)
    sub = ctx.socket(zmq.SUB)
    try:
        sub.setsockopt(zmq.SUBSCRIBE, b"pose")
        sub.connect(pub.last_endpoint)
        assert _receives(pub, sub, 5.0)
        first = pub.relay_pid
        assert first is not None
        with caplog.at_level(logging.WARNING, logger="lino_loc.service.publisher"):
            os.kill(first, signal.SIGKILL)
            # the subscriber reconnects and subscribes again by itself (ZeroMQ)
            assert _receives(pub, sub, 10.0)
        assert pub.relay_pid not in (None, first) and pub.info().relay_restarts == 1
        assert any("pose relay exited" in r.getMessage() and "-9" in r.getMessage() for r in caplog.records)
    finally:
        sub.close(0)
        pub.close()
    assert not _alive(first)


def test_a_relay_over_its_memory_limit_exits_and_is_started_again(ctx: zmq.Context[Any], caplog: Any) -> None:
    """A limit below what any Python process takes: the relay binds, reports ready, exits at
    its first memory check (code EXIT_MEMORY), and is started again with a growing delay."""
    tiny = RelayConfig.model_construct(enabled=True, max_resident_mb=1.0)
    with caplog.at_level(logging.WARNING, logger="lino_loc.service.publisher"):
        pub = RelayedPublisher(ctx, "tcp://127.0.0.1:*", 10, relay=tiny)
        try:
            _until(lambda: (pub.wanted("pose"), pub.info().relay_restarts >= 2)[1], 15.0, "never restarted twice")
        finally:
            pub.close()
    exits = [r.getMessage() for r in caplog.records if "pose relay exited" in r.getMessage()]
    assert exits and all("over its memory limit" in m for m in exits), exits


def test_the_relay_dies_with_the_daemon(tmp_path: Path) -> None:
    """kill -9 of the process that owns the relay: the relay goes too (PR_SET_PDEATHSIG)."""
    script = tmp_path / "owner.py"
    script.write_text(textwrap.dedent("""
        import sys, time, zmq
        from services.relay_publisher import RelayedPublisher
        pub = RelayedPublisher(zmq.Context(), "tcp://127.0.0.1:*", 10)
        print(pub.relay_pid, flush=True)
        time.sleep(60)
    """))
    owner = subprocess.Popen([sys.executable, str(script)], cwd=ROOT, stdout=subprocess.PIPE,
                             env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert owner.stdout is not None
        relay = int(owner.stdout.readline())
        assert _alive(relay)
        owner.kill()
        owner.wait(5)
        _until(lambda: not _alive(relay), 5.0, "the relay outlived its daemon")
    finally:
        owner.kill()


FLOOD = """
import sys, time, zmq
ctx = zmq.Context()
subs = []
for i in range({n}):
    s = ctx.socket(zmq.SUB)
    s.setsockopt(zmq.RCVHWM, 1)
    for k in range({topics}):
        s.setsockopt(zmq.SUBSCRIBE, b"%06d-%06d-" % (i, k) + b"x" * 180)
    s.connect(sys.argv[1])
    subs.append(s)
print("connected", flush=True)
time.sleep(60)
"""


@pytest.mark.timeout(120)
def test_a_subscription_flood_costs_the_relay_not_the_daemon(ctx: zmq.Context[Any], tmp_path: Path) -> None:
    """60 subscribers of 100 distinct 194-byte topics each (1.2 MB of subscriptions, about
    50 MB of libzmq's table) arrive at once while this process publishes at 50 Hz: its sends
    never wait, its memory does not grow, and the relay's does (or it is restarted)."""
    pub = RelayedPublisher(ctx, "tcp://127.0.0.1:*", 10)
    script = tmp_path / "flood.py"
    script.write_text(FLOOD.format(n=60, topics=100))
    me = os.getpid()
    try:
        for i in range(50):  # warm up: the first sends allocate
            pub.publish("pose", _pose(i))
            time.sleep(0.02)
        rss0 = _rss(me)
        flood = subprocess.Popen([sys.executable, str(script), pub.last_endpoint], stdout=subprocess.PIPE)
        worst = 0.0
        peak_relay = 0
        restarts = 0
        deadline = time.monotonic() + 8.0
        seq = 0
        while time.monotonic() < deadline:
            seq += 1
            t = time.perf_counter()
            pub.publish("pose", _pose(seq))
            worst = max(worst, time.perf_counter() - t)
            info = pub.info()
            peak_relay = max(peak_relay, info.relay_resident_bytes or 0)
            restarts = info.relay_restarts
            time.sleep(0.02)
        grown = _rss(me) - rss0
        flood.kill()
        flood.wait(5)
    finally:
        pub.close()
    print(f"worst send {worst * 1e3:.1f} ms, grown {grown / 1e6:.1f} MB, relay peak {peak_relay / 1e6:.0f} MB, "
          f"restarts {restarts}")
    assert worst < 0.05, f"a send took {worst * 1e3:.1f} ms"
    assert grown < 10e6, f"this process grew by {grown / 1e6:.1f} MB"
    assert peak_relay > 60e6 or restarts >= 1, (peak_relay, restarts)

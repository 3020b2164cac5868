"""The pose stream publisher: never blocks on a subscriber that does not read, counts what
it could not send, sees subscriptions (XPUB); and the rate limiter."""

from __future__ import annotations

import time

import pytest
import zmq

from services.messages import Pose2D, PoseMessage, decode
from services.publisher import Publisher, RateLimiter

COV = [0.1, 0, 0, 0, 0.1, 0, 0, 0, 0.01]


def _pose(seq: int) -> PoseMessage:
    return PoseMessage(stamp=1.0 + seq, seq=seq, pose=Pose2D(x=seq, y=0, theta=0), covariance=COV, state="tracking")


def _wait_subscribed(pub: Publisher, topic: str, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not pub.wanted(topic):
        assert time.monotonic() < deadline, "subscription never arrived"
        time.sleep(0.01)


def test_rate_limiter() -> None:
    r = RateLimiter(2.0)
    fired = [t / 100 for t in range(0, 300) if r.ready(t / 100)]
    assert fired == [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]
    assert not any(RateLimiter(0.0).ready(t) for t in range(10))
    late = RateLimiter.every(1.0)
    assert late.ready(0.0) and late.ready(5.0) and not late.ready(5.5) and late.ready(6.0)


def test_subscriber_receives_two_frames_and_xpub_sees_it() -> None:
    ctx = zmq.Context()
    pub = Publisher(ctx, "inproc://pub-test-1", sndhwm=10)
    sub = ctx.socket(zmq.SUB)
    try:
        sub.setsockopt(zmq.SUBSCRIBE, b"pose")
        sub.connect("inproc://pub-test-1")
        assert not pub.wanted("particles")
        _wait_subscribed(pub, "pose")
        assert pub.n_subscriptions == 1 and not pub.wanted("particles")
        assert pub.publish("pose", _pose(7))
        assert sub.poll(2000)
        topic, msg = decode(sub.recv_multipart())
        assert topic == "pose" and msg.seq == 7
        assert pub.sent["pose"] == 1 and pub.dropped == 0
    finally:
        sub.close(0)
        pub.close()
        ctx.term()


def test_a_subscriber_that_never_reads_does_not_block_or_starve_others() -> None:
    """2000 messages of 20 kB (40 MB) to a subscriber that never reads and to one that
    does: the stalled one's queue stops at the high-water mark (400 messages plus socket
    buffers, well below 2000), the sends never block, and the reading subscriber gets
    (almost) everything."""
    ctx = zmq.Context()
    pub = Publisher(ctx, "tcp://127.0.0.1:*", sndhwm=400)
    endpoint = pub.last_endpoint
    stalled = ctx.socket(zmq.SUB)
    reader = ctx.socket(zmq.SUB)
    try:
        stalled.setsockopt(zmq.RCVHWM, 5)
        stalled.setsockopt(zmq.RCVBUF, 4096)
        for s, prefix in ((stalled, b""), (reader, b"particles")):  # two distinct prefixes
            s.setsockopt(zmq.SUBSCRIBE, prefix)
            s.connect(endpoint)
        deadline = time.monotonic() + 5
        while pub.n_subscriptions < 2:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        payload = b"x" * 20_000
        n = 2000
        got = 0
        last = None
        t0 = time.monotonic()
        worst = 0.0
        for i in range(n):
            ts = time.monotonic()
            pub.send_frames([b"particles", payload + str(i).encode()])
            worst = max(worst, time.monotonic() - ts)
            while reader.poll(0):  # the live client keeps up
                last = reader.recv_multipart()
                got += 1
            if i % 10 == 0:
                time.sleep(0.001)  # a paced stream, as the loop's
        elapsed = time.monotonic() - t0
        assert worst < 0.5 and elapsed < 30.0  # no send waited for the stalled subscriber
        assert sum(pub.sent.values()) + pub.dropped == n
        end = time.monotonic() + 3
        while time.monotonic() < end and reader.poll(300):
            last = reader.recv_multipart()
            got += 1
        assert got > 0.8 * n  # the stalled subscriber does not starve the reader
        assert last is not None and last[1].endswith(str(n - 1).encode())
    finally:
        stalled.close(0)
        reader.close(0)
        pub.close()
        ctx.term()


def _pose_subscriber(ctx: zmq.Context, endpoint: str) -> zmq.Socket:
    """A SUB socket on ``endpoint`` subscribed to ``pose`` (no linger)."""
    s = ctx.socket(zmq.SUB)
    s.setsockopt(zmq.LINGER, 0)
    s.setsockopt(zmq.SUBSCRIBE, b"pose")
    s.connect(endpoint)
    return s


def _until(pred, what: str, timeout: float = 5.0) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def _settled(pub: Publisher, sub: zmq.Socket, marker: bytes) -> None:
    """Subscribe ``sub`` to ``marker`` and wait until the publisher sees it: everything
    ``sub`` sent before has been read too (one connection keeps its order)."""
    sub.setsockopt(zmq.SUBSCRIBE, marker)
    _until(lambda: pub.wanted(marker.decode()) and marker in pub.subscriptions, f"marker {marker!r}")


def test_duplicate_subscriptions_are_counted_right() -> None:
    """subscribe x2, unsubscribe x1: still wanted; the second unsubscribe, or a disconnect
    after duplicates, leaves nobody; two clients on one topic: wanted until both left."""
    ctx = zmq.Context()
    pub = Publisher(ctx, "tcp://127.0.0.1:*", sndhwm=10)
    endpoint = pub.last_endpoint
    a, b = ctx.socket(zmq.SUB), ctx.socket(zmq.SUB)
    try:
        a.connect(endpoint)
        a.setsockopt(zmq.SUBSCRIBE, b"particles")
        a.setsockopt(zmq.SUBSCRIBE, b"particles")
        _until(lambda: pub.wanted("particles"), "particles wanted")
        a.setsockopt(zmq.UNSUBSCRIBE, b"particles")
        _settled(pub, a, b"status")
        assert pub.wanted("particles") and pub.subscriptions == {b"particles", b"status"}
        a.setsockopt(zmq.UNSUBSCRIBE, b"particles")
        _until(lambda: not pub.wanted("particles"), "particles no longer wanted")
        # duplicates, then a disconnect: nobody left (a verbose XPUB leaked one here)
        a.setsockopt(zmq.SUBSCRIBE, b"particles")
        a.setsockopt(zmq.SUBSCRIBE, b"particles")
        _until(lambda: pub.wanted("particles"), "particles wanted again")
        a.close(0)
        _until(lambda: pub.n_subscriptions == 0, "every subscription gone with its client")
        # two clients on one topic
        c = ctx.socket(zmq.SUB)
        for s in (b, c):
            s.connect(endpoint)
            s.setsockopt(zmq.SUBSCRIBE, b"particles")
        _settled(pub, b, b"pose")
        _settled(pub, c, b"truth")
        c.close(0)
        _until(lambda: not pub.wanted("truth"), "c's subscriptions gone")
        assert pub.wanted("particles")
        b.setsockopt(zmq.UNSUBSCRIBE, b"particles")
        _until(lambda: not pub.wanted("particles"), "particles no longer wanted")
        assert pub.subscriptions == {b"pose"} and pub.ignored_subscriptions == 0
    finally:
        a.close(0)
        b.close(0)
        pub.close()
        ctx.term()


def test_subscriptions_that_match_no_topic_are_ignored_counted_and_logged_once(caplog) -> None:  # noqa: ANN001
    """5000 distinct 211-byte subscriptions (and non-subscription messages from an XSUB):
    the publisher's view keeps only the prefixes of its topics; each read is bounded."""
    import logging
    import os

    from services.publisher import MAX_SUBSCRIPTION_MESSAGES, TOPIC_PREFIXES

    assert len(TOPIC_PREFIXES) == 24 and b"" in TOPIC_PREFIXES and b"partic" in TOPIC_PREFIXES
    caplog.set_level(logging.WARNING, logger="lino_loc.service.publisher")
    ctx = zmq.Context()
    pub = Publisher(ctx, "tcp://127.0.0.1:*", sndhwm=10)
    pub.guard.max_distinct = pub.guard.max_bytes = 10**9  # the view alone (the cap: below)
    endpoint = pub.last_endpoint
    hostile, raw = ctx.socket(zmq.SUB), ctx.socket(zmq.XSUB)
    try:
        hostile.setsockopt(zmq.SNDHWM, 0)
        hostile.connect(endpoint)
        raw.connect(endpoint)
        n = 5000
        for i in range(n):
            hostile.setsockopt(zmq.SUBSCRIBE, os.urandom(210) + b"\x01")
            if i == n // 2:
                hostile.setsockopt(zmq.SUBSCRIBE, b"pose")
        raw.send(b"not a subscription")
        raw.send(b"\x01" + b"particles and more")
        hostile.setsockopt(zmq.SUBSCRIBE, b"sta")
        t0 = time.monotonic()
        reads = 0
        while b"sta" not in pub.subscriptions or pub.ignored_subscriptions < n + 2:
            assert time.monotonic() - t0 < 20, (pub.ignored_subscriptions, pub.subscriptions)
            ts = time.monotonic()
            pub.wanted("pose")
            reads += 1
            assert time.monotonic() - ts < 0.5  # each read bounded (MAX_SUBSCRIPTION_MESSAGES)
            time.sleep(0.005)
        assert reads >= n // MAX_SUBSCRIPTION_MESSAGES
        assert pub.subscriptions == {b"pose", b"sta"} and pub.wanted("status") and not pub.wanted("particles")
        assert pub.ignored_subscriptions == n + 2
        warnings = [r for r in caplog.records if "matches no topic" in r.getMessage()]
        assert len(warnings) == 1
    finally:
        hostile.close(0)
        raw.close(0)
        pub.close()
        ctx.term()


HOSTILE_SUBSCRIBER = """
import os, sys, time, zmq
ctx = zmq.Context()
s = ctx.socket(zmq.SUB)
s.setsockopt(zmq.SNDHWM, 0)
s.connect(sys.argv[1])
for i in range(int(sys.argv[2])):
    s.setsockopt(zmq.SUBSCRIBE, os.urandom(210))
    if i % 50 == 0:
        time.sleep(0.05)
time.sleep(60)
"""


def test_a_subscriber_past_the_cap_is_evicted_and_the_memory_stays_bounded() -> None:
    """A subscriber process sending 600 distinct 210-byte subscriptions (twice the table's
    cap), 1000 a second: its connection is ended each time the table passes the cap (it
    reconnects and sends them all again, and is ended again), the table stays within four
    caps, the process's memory within a few MB, an honest subscriber keeps its poses, and
    the status counters say what happened."""
    import subprocess
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_control import _rss_mb

    from services.subscription_guard import EVICTION_MAX_FACTOR

    ctx = zmq.Context()
    pub = Publisher(ctx, "tcp://127.0.0.1:*", sndhwm=10)
    endpoint = pub.last_endpoint
    honest = _pose_subscriber(ctx, endpoint)
    _until(lambda: pub.wanted("pose"), "the honest subscriber")
    before = _rss_mb()
    hostile = subprocess.Popen([sys.executable, "-c", HOSTILE_SUBSCRIBER, endpoint, "600"])
    got, peak, seq = 0, 0, 0
    try:
        t_end = time.monotonic() + 8.0
        while time.monotonic() < t_end:
            seq += 1
            pub.send_frames([b"pose", str(seq).encode()])
            while honest.poll(0):
                honest.recv_multipart()
                got += 1
            peak = max(peak, pub.guard.distinct_bytes)
            time.sleep(1 / 30)
        info = pub.info()
        grown = _rss_mb() - before
    finally:
        hostile.kill()
        hostile.wait()
        honest.close(0)
        pub.close()
        ctx.term()
    assert info.evicted_subscribers >= 1, info
    assert peak <= EVICTION_MAX_FACTOR * pub.guard.max_bytes, peak
    assert grown < 10.0, f"the publisher grew by {grown:.1f} MB"
    assert got > 0.9 * seq, (got, seq)


def test_the_guard_evicts_over_a_cap_but_not_past_four_caps_nor_while_reports_wait() -> None:
    """The guard's regimes on a real connection, its counts set by hand: under the caps
    nothing happens; past four times a cap, or with reports waiting (backlog), nothing is
    ended (logged once); just over a cap, the connection is ended (and reconnects)."""
    from services.subscription_guard import EVICTION_MAX_FACTOR

    ctx = zmq.Context()
    pub = Publisher(ctx, "tcp://127.0.0.1:*", sndhwm=10)
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"pose")
    sub.connect(pub.last_endpoint)
    g = pub.guard
    try:
        _until(lambda: pub.info().subscribers == 1, "the subscriber accepted")
        with pub._lock:
            g.reported(True, g.max_bytes)  # at the cap, not over
            g.enforce()
            assert g.evicted == 0 and not g.over
            g.reported(True, (EVICTION_MAX_FACTOR - 1) * g.max_bytes + 1)  # past four caps
            g.enforce()
            assert g.over and g.beyond_eviction and g.evicted == 0
            g.reported(False, (EVICTION_MAX_FACTOR - 1) * g.max_bytes + 1)
            g.reported(True, 1)  # just over one cap, but reports are waiting
            g.enforce(backlog=True)
            assert g.evicted == 0
            g.enforce()
            assert g.evicted == 1 and g.evicting
            g.reported(False, g.max_bytes)  # the hand-made part of the table goes
        _until(lambda: pub.info() is not None and not g.evicting, "libzmq dropped the connection")
        _until(lambda: pub.info().subscribers == 1, "the subscriber back")
    finally:
        sub.close(0)
        pub.close()
        ctx.term()


def test_bind_error_is_an_oserror_naming_the_endpoint() -> None:
    ctx = zmq.Context()
    a = Publisher(ctx, "inproc://pub-twice")
    try:
        with pytest.raises(OSError, match="inproc://pub-twice"):
            Publisher(ctx, "inproc://pub-twice")
    finally:
        a.close()
        ctx.term()


# ------------------------------------------------------------------ PosePublisher
def test_pose_publisher_numbers_keeps_and_throttles() -> None:
    import sys
    from pathlib import Path

    import numpy as np

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from service_fakes import FakeLocalizer, FakePublisher, estimate

    from services.config import PublishConfig
    from services.messages import ParticlesMessage
    from services.publisher import PosePublisher

    pub, loc = FakePublisher(), FakeLocalizer(n=50)
    poses = PosePublisher(pub, PublishConfig(particles_max_count=20, particles_max_rate_hz=1000.0), loc.particles)  # type: ignore[arg-type]
    msg = poses.publish(estimate(), stamp=10.0, pan=0.1)
    assert msg is not None and msg.seq == 1 and msg.pan == 0.1 and poses.latest()[0] is msg
    assert pub.messages[-1] == ("pose", msg)
    # an invalid estimate is not published but still counted by seq
    bad = estimate(pose=(float("nan"), 0.0, 0.0))
    assert poses.publish(bad, stamp=11.0, pan=None) is None and poses.seq == 2
    assert poses.latest()[0] is msg
    assert poses.publish_particles(11.0)
    topic, part = pub.messages[-1]
    assert topic == "particles" and isinstance(part, ParticlesMessage)
    assert len(part.poses) == 20 and part.n_total == 50 and part.seq == 2
    assert abs(sum(part.weights) - 1.0) < 1e-9
    # distinct particles of the filter's set (subset without replacement)
    assert len({tuple(p) for p in part.poses}) == 20
    assert all(any(np.allclose(p, q) for q in loc.p) for p in part.poses)
    # nobody subscribed: nothing sent
    pub.subscribed = False
    time.sleep(0.002)
    assert not poses.publish_particles(12.0)


def test_particles_of_zero_weight_are_uniform() -> None:
    import sys
    from pathlib import Path

    import numpy as np

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from service_fakes import FakeLocalizer, FakePublisher

    from services.config import PublishConfig
    from services.publisher import PosePublisher

    loc = FakeLocalizer(n=4)
    loc.w = np.zeros(4)
    poses = PosePublisher(FakePublisher(), PublishConfig(), loc.particles)  # type: ignore[arg-type]
    assert poses.particles_message(1.0).weights == [0.25] * 4


def test_a_200_mb_frame_from_a_subscriber_is_dropped_and_the_others_keep_their_stream() -> None:
    """A raw client on the pose port announcing a 200 MB frame (as a subscription) is
    disconnected at the header (PUB_MAX_FRAME_BYTES); real subscribers keep receiving."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_control import _announce_huge_frame, _rss_mb

    from services.publisher import PUB_MAX_FRAME_BYTES

    assert PUB_MAX_FRAME_BYTES <= 64 * 1024
    ctx = zmq.Context()
    pub = Publisher(ctx, "tcp://127.0.0.1:*", sndhwm=10)
    endpoint = pub.last_endpoint
    sub = _pose_subscriber(ctx, endpoint)
    try:
        before = _rss_mb()
        for _ in range(3):
            sent, closed = _announce_huge_frame(endpoint, 200 * 1024 * 1024, 40, kind=b"SUB")
            assert closed and sent < 40 * (1 << 20)
        assert _rss_mb() - before < 10.0
        deadline = time.monotonic() + 5.0
        while not sub.poll(50) and time.monotonic() < deadline:
            pub.send_frames([b"pose", b"{}"])
        assert sub.recv_multipart() == [b"pose", b"{}"]
    finally:
        sub.close(0)
        pub.close()
        ctx.term()

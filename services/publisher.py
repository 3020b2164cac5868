"""The daemon's ZeroMQ pose stream: a publisher that never blocks, and rate limits.

:class:`Publisher` binds an XPUB socket (every message is two frames
``[topic, json]``). It behaves as a PUB socket for the subscribers; XPUB is used because it
also delivers the subscriptions, so the daemon knows which topics someone listens to
(:attr:`Publisher.subscriptions`) and can skip serializing topics nobody wants (the particle
set is the largest message).

Counting subscriptions: the XPUB is not verbose, so libzmq reports a subscription prefix once
when its first subscriber (over all connections) takes it and once more when its last one
drops it, by an unsubscription or by disconnecting; a SUB socket itself counts its own
duplicates and sends the unsubscription only when its last one goes. The daemon's view is
therefore the set of prefixes someone holds, and it is right however many times each client
subscribed. (A verbose XPUB reports every duplicate subscription but only one unsubscription,
so counts made from it leak.)

What subscriptions can cost: only prefixes of a published topic (:data:`TOPIC_PREFIXES`, at
most :data:`MAX_SUBSCRIPTION_BYTES` long, 24 distinct values for the four topics) can ever
match a message; any other subscription is ignored (counted in
:attr:`Publisher.ignored_subscriptions`, logged once), so the daemon's own view holds at most
that many entries. At most :data:`MAX_SUBSCRIPTION_MESSAGES` subscription messages are read
per publish, so a flood of them costs each publish a bounded time. libzmq keeps its own table
of every distinct prefix subscribed, ignored ones included: ``ZMQ_MAXMSGSIZE``
(:data:`PUB_MAX_FRAME_BYTES`) bounds a prefix's length, and
:class:`services.subscription_guard.SubscriptionGuard` their number and summed length, by
ending the connection of the subscriber that sent the most once a cap is passed.

Never blocking: each subscriber has a send queue of ``sndhwm`` messages
(``ZMQ_SNDHWM``); when a subscriber does not read, ZeroMQ drops further messages *for that
subscriber only* once its queue is full, and the other subscribers and the loop are not
affected. Every send uses ``zmq.NOBLOCK``; a send that fails anyway (``EAGAIN`` or another
error) is counted in :attr:`Publisher.dropped` and never raises into the loop.

The socket is used from several threads (the loop publishes poses, the truth relay
republishes the simulator's truth): sends are serialized by a lock. A send with NOBLOCK
takes microseconds, so the lock is never held for long.

:class:`RateLimiter` throttles the ``particles`` topic (``publish.particles_max_rate_hz``)
and paces ``status`` (:data:`services.status.STATUS_PERIOD_S`).

:class:`PosePublisher` is what the daemon's loop calls after each filter update: it numbers
the update (``seq``), publishes its :class:`services.messages.PoseMessage` on ``pose``, keeps
it (and the estimate) as the latest for the control thread, and publishes the particle set
on ``particles`` when a subscriber wants it and the rate limit allows: a uniform random
subset of ``particles_max_count`` particles without replacement when there are more (drawn
from the publisher's own seeded generator, never the filter's), with the weights of the
subset normalised to sum to 1 (uniform when they sum to 0).

Usage::

    pub = Publisher(zmq.Context.instance(), "tcp://127.0.0.1:5556", sndhwm=100)
    pub.publish("pose", PoseMessage(...))
    limiter = RateLimiter(2.0)
    if limiter.ready(time.monotonic()): pub.publish("particles", msg)
    poses = PosePublisher(pub, cfg.publish, localizer.particles)
    msg = poses.publish(estimate, stamp=frame.stamp, pan=pan)   # None if invalid
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np
import zmq
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.pose_estimate import Estimate
from services.curve_auth import CurveConfig, CurveKeyError, attach_server
from services.messages import TOPICS, ParticlesMessage, PoseMessage, PosePortInfo, encode
from services.subscription_guard import SubscriptionGuard

log = logging.getLogger("lino_loc.service.publisher")

#: Every subscription prefix that can match a published topic (a topic's name starts with
#: it), the empty one included; subscriptions outside it are ignored.
TOPIC_PREFIXES: frozenset[bytes] = frozenset(
    t.encode("ascii")[:k] for t in TOPICS for k in range(len(t) + 1)
)
#: The longest subscription that can match a topic: the longest topic name, bytes.
MAX_SUBSCRIPTION_BYTES = max(len(t) for t in TOPICS)
#: Subscription messages read from the socket per call (publish, wanted): a flood is read
#: over several calls, each bounded in time.
MAX_SUBSCRIPTION_MESSAGES = 1000


class PublishConfig(BaseModel):
    """The service's ``[publish]`` section: what is published besides the poses."""

    model_config = ConfigDict(extra="forbid")

    particles_max_rate_hz: float = Field(2.0, ge=0.0, description="0 = never publish particles")
    particles_max_count: int = Field(500, ge=1, description="subsample the particle set to this many")
    truth: bool = Field(True, description="republish the simulator's true pose (simulation only)")


class RateLimiter:
    """``ready(now)`` is True at most ``rate_hz`` times per second (0 = never)."""

    def __init__(self, rate_hz: float) -> None:
        self.period = (1.0 / rate_hz) if rate_hz > 0 else None
        self._next: float | None = None

    @classmethod
    def every(cls, period_s: float) -> RateLimiter:
        return cls(1.0 / period_s)

    def ready(self, now: float) -> bool:
        if self.period is None:
            return False
        if self._next is None or now >= self._next:
            # schedule from the previous slot when on time (no drift), from now when late
            nxt = (self._next or now) + self.period
            self._next = nxt if nxt > now else now + self.period
            return True
        return False


#: Largest frame a subscriber may send (``ZMQ_MAXMSGSIZE`` on the XPUB socket). Subscribers
#: send only subscriptions, topic prefixes (the longest topic, ``particles``, is 9 bytes), and
#: their handshake, whose largest frame is CURVE's INITIATE command (about 300 bytes with
#: a SUB's metadata); a frame announced larger closes that subscriber's connection before
#: anything is allocated.
PUB_MAX_FRAME_BYTES = 512


class Publisher:
    """Non-blocking XPUB publisher of ``[topic, json]`` messages (thread-safe)."""

    def __init__(
        self, ctx: zmq.Context[Any], endpoint: str, sndhwm: int = 100, curve: CurveConfig | None = None
    ) -> None:
        """Bind ``endpoint``; with ``curve`` keys, as a CURVE server (services/curve_auth.py).
        Raises OSError when the endpoint cannot be bound or the keys cannot be read."""
        self.endpoint = endpoint
        self._lock = threading.Lock()
        self._sock = ctx.socket(zmq.XPUB)
        self._sock.setsockopt(zmq.SNDHWM, int(sndhwm))
        self._sock.setsockopt(zmq.LINGER, 0)
        # Not verbose: one report per prefix when its first subscriber comes and when its
        # last one goes (module docstring), so duplicates are counted by libzmq.
        self._sock.setsockopt(zmq.XPUB_VERBOSE, 0)
        self._sock.setsockopt(zmq.MAXMSGSIZE, PUB_MAX_FRAME_BYTES)
        self._release_curve: Callable[[], None] = lambda: None
        try:
            self._release_curve = attach_server(ctx, self._sock, curve)
            self._sock.bind(endpoint)
        except (zmq.ZMQError, CurveKeyError) as exc:
            self._sock.close(linger=0)
            self._release_curve()
            raise OSError(f"cannot bind the PUB socket to {endpoint}: {exc}") from exc
        self.last_endpoint = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self.guard = SubscriptionGuard(self._sock)
        self.sent: Counter[str] = Counter()
        self.dropped = 0
        self.subscriptions: set[bytes] = set()
        self.ignored_subscriptions = 0
        self._closed = False

    # ---------------------------------------------------------------------------------
    def _drain_subscriptions(self) -> None:
        """Read up to :data:`MAX_SUBSCRIPTION_MESSAGES` (un)subscription reports (called with
        the lock held): a prefix of a topic is added or removed, anything else is ignored."""
        backlog = True
        for _ in range(MAX_SUBSCRIPTION_MESSAGES):
            try:
                msg = self._sock.recv(zmq.NOBLOCK)
            except zmq.ZMQError:  # zmq.Again included: nothing more to read
                backlog = False
                break
            topic = bytes(msg[1:])
            if msg[:1] in (b"\x00", b"\x01"):
                self.guard.reported(msg[0] == 1, len(topic))
            if msg[:1] not in (b"\x00", b"\x01") or topic not in TOPIC_PREFIXES:
                self._ignore(msg)
            elif msg[0] == 1:
                self.subscriptions.add(topic)
            else:
                self.subscriptions.discard(topic)
        self.guard.enforce(backlog)

    def _ignore(self, msg: bytes) -> None:
        """Count a message that is not the (un)subscription of a topic prefix; log the first."""
        self.ignored_subscriptions += 1
        if self.ignored_subscriptions == 1:
            log.warning(
                "pose port: ignoring a subscription that matches no topic (%d bytes, %r...; "
                "topics: %s; further ones are counted, not logged)",
                len(msg), bytes(msg[:24]), ", ".join(TOPICS),
            )

    def wanted(self, topic: str) -> bool:
        """True if some subscriber's prefix matches ``topic`` (XPUB's view)."""
        t = topic.encode("ascii")
        with self._lock:
            if self._closed:
                return False
            self._drain_subscriptions()
            return any(t.startswith(p) for p in self.subscriptions)

    @property
    def n_subscriptions(self) -> int:
        """Distinct topic prefixes someone subscribes to (not the number of clients)."""
        with self._lock:
            if not self._closed:
                self._drain_subscriptions()
            return len(self.subscriptions)

    def info(self) -> PosePortInfo:
        """The subscribers' counters for the status."""
        with self._lock:
            if not self._closed:
                self.guard.read_events()  # the connections open now
            return PosePortInfo(
                subscribers=self.guard.subscribers,
                subscriptions=self.guard.distinct,
                subscription_bytes=self.guard.distinct_bytes,
                ignored_subscriptions=self.ignored_subscriptions,
                evicted_subscribers=self.guard.evicted,
                dropped_sends=self.dropped,
                refused_handshakes=self.guard.refused_handshakes,
            )

    def send_frames(self, frames: list[bytes], topic: str | None = None) -> bool:
        """Send raw frames without blocking; False (and counted) if ZeroMQ refused."""
        name = topic or bytes(frames[0]).decode("ascii", errors="replace")
        with self._lock:
            if self._closed:
                return False
            try:
                self._drain_subscriptions()
                self._sock.send_multipart(frames, flags=zmq.NOBLOCK, copy=True)
            except zmq.Again:
                self.dropped += 1
                return False
            except zmq.ZMQError as exc:
                self.dropped += 1
                log.debug("publish %s failed: %s", name, exc)
                return False
        self.sent[name] += 1
        return True

    def publish(self, topic: str, message: BaseModel) -> bool:
        """Publish a pydantic message on ``topic`` (validated against the topic's model)."""
        return self.send_frames(encode(topic, message), topic)

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self.guard.close()
                self._sock.close(linger=0)
                self._release_curve()


#: Seed of the generator that picks the published subset of particles.
PARTICLE_SUBSET_SEED = 0

ParticleSource = Callable[[], tuple[np.ndarray, np.ndarray]]


class PosePublisher:
    """Poses and particles of each update on a :class:`Publisher` (module docstring).

    ``particles`` returns copies of the filter's particles (M x 3) and linear weights (M,)
    (``Localizer.particles``). :meth:`latest` may be called from any thread."""

    def __init__(self, publisher: Publisher, cfg: PublishConfig, particles: ParticleSource) -> None:
        self.publisher = publisher
        self.cfg = cfg
        self.particles = particles
        self.seq = 0
        self.published = 0
        self._limiter = RateLimiter(cfg.particles_max_rate_hz)
        self._rng = np.random.default_rng(PARTICLE_SUBSET_SEED)
        self._lock = threading.Lock()
        self._last_pose: PoseMessage | None = None
        self._last_estimate: Estimate | None = None

    def latest(self) -> tuple[PoseMessage | None, Estimate | None]:
        """The last published pose message and the estimate it came from."""
        with self._lock:
            return self._last_pose, self._last_estimate

    def publish(
        self, est: Estimate, *, stamp: float, pan: float | None, dead_reckoning: bool = False
    ) -> PoseMessage | None:
        """Publish the pose of ``est`` (and maybe the particles); None when the estimate holds
        a non-finite value (logged, nothing published, ``seq`` still counts the update)."""
        self.seq += 1
        try:
            msg = PoseMessage.from_estimate(
                est, stamp=stamp, seq=self.seq, pan=pan, dead_reckoning=dead_reckoning
            )
        except ValueError as exc:
            log.warning("pose not published (invalid estimate): %s", exc)
            return None
        self.publisher.publish("pose", msg)
        with self._lock:
            self._last_pose, self._last_estimate = msg, est
        self.published += 1
        return msg

    def publish_particles(self, stamp: float) -> bool:
        """Publish the particle set of update ``seq`` if wanted and due; True if sent."""
        if not self._limiter.ready(time.monotonic()) or not self.publisher.wanted("particles"):
            return False
        return self.publisher.publish("particles", self.particles_message(stamp))

    def particles_message(self, stamp: float) -> ParticlesMessage:
        """The (maybe subsampled) particle set with normalised weights."""
        p, w = self.particles()
        n = p.shape[0]
        cap = self.cfg.particles_max_count
        if n > cap:
            idx = self._rng.choice(n, size=cap, replace=False)
            p, w = p[idx], w[idx]
        total = float(w.sum())
        w = w / total if total > 0 else np.full(len(w), 1.0 / max(len(w), 1))
        return ParticlesMessage(
            stamp=stamp,
            seq=self.seq,
            poses=[tuple(float(v) for v in row) for row in p],
            weights=[float(v) for v in w],
            n_total=n,
        )

"""One XPUB socket that subscribers connect to: sends that never block, subscriptions
counted, their table capped.

:class:`PosePort` binds an XPUB socket (every message is two frames ``[topic, json]``). It
behaves as a PUB socket for the subscribers; XPUB is used because it also delivers the
subscriptions, so its owner knows which topics someone listens to
(:attr:`PosePort.subscriptions`) and can skip serializing topics nobody wants (the particle
set is the largest message). It is the public side of the pose relay
(:mod:`services.pose_relay`) and, with ``[endpoints.relay] enabled = false``, of the daemon
itself (:class:`services.publisher.Publisher`).

Counting subscriptions: the XPUB is not verbose, so libzmq reports a subscription prefix once
when its first subscriber (over all connections) takes it and once more when its last one
drops it, by an unsubscription or by disconnecting; a SUB socket itself counts its own
duplicates and sends the unsubscription only when its last one goes. The view is therefore
the set of prefixes someone holds, and it is right however many times each client
subscribed. (A verbose XPUB reports every duplicate subscription but only one
unsubscription, so counts made from it leak.)

What subscriptions can cost: only prefixes of a published topic
(:data:`services.topics.TOPIC_PREFIXES`, 24 distinct values for the four topics) can ever
match a message; any other subscription is ignored (counted in
:attr:`PosePort.ignored_subscriptions`, logged once), so the owner's view holds at most that
many entries. At most :data:`MAX_SUBSCRIPTION_MESSAGES` subscription messages are read per
call, so a flood of them costs each send a bounded time. libzmq keeps its own table of every
distinct prefix subscribed, ignored ones included: ``ZMQ_MAXMSGSIZE``
(:data:`PUB_MAX_FRAME_BYTES`) bounds a prefix's length, and
:class:`services.subscription_guard.SubscriptionGuard` their number and summed length, by
ending the connection of the subscriber that sent the most once a cap is passed.

Never blocking: each subscriber has a send queue of ``sndhwm`` messages (``ZMQ_SNDHWM``);
when a subscriber does not read, ZeroMQ drops further messages *for that subscriber only*
once its queue is full, and the other subscribers are not affected. Every send uses
``zmq.NOBLOCK``; a send that fails anyway (``EAGAIN`` or another error) is counted in
:attr:`PosePort.dropped` and never raises.

Thread-safe: sends and reads are serialized by a lock (a send with NOBLOCK takes
microseconds).
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable
from typing import Any

import zmq

from services.curve_auth import CurveConfig, CurveKeyError, attach_server
from services.subscription_guard import SubscriptionGuard
from services.topics import TOPIC_NAMES, TOPIC_PREFIXES

log = logging.getLogger("lino_loc.service.publisher")

#: Subscription messages read from the socket per call (send, wanted): a flood is read
#: over several calls, each bounded in time.
MAX_SUBSCRIPTION_MESSAGES = 1000
#: Largest frame a subscriber may send (``ZMQ_MAXMSGSIZE`` on the XPUB socket). Subscribers
#: send only subscriptions, topic prefixes (the longest topic, ``particles``, is 9 bytes), and
#: their handshake, whose largest frame is CURVE's INITIATE command (about 300 bytes with
#: a SUB's metadata); a frame announced larger closes that subscriber's connection before
#: anything is allocated.
PUB_MAX_FRAME_BYTES = 512


class NonBlockingSender:
    """Sends on ``self._sock`` that never block, serialized by a lock and counted: ``sent``
    per topic, ``dropped`` when ZeroMQ refused (``EAGAIN``: a full queue, or another error,
    logged at DEBUG). Subclasses set ``_sock`` and may do work before each send
    (:meth:`_before_send`, lock held)."""

    _sock: zmq.Socket[Any]

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._closed = False
        self.sent: Counter[str] = Counter()
        self.dropped = 0

    def _before_send(self) -> None:
        """Called with the lock held before every send."""

    def send_frames(self, frames: list[bytes], topic: str | None = None) -> bool:
        """Send raw frames without blocking; False (and counted) if ZeroMQ refused."""
        name = topic or bytes(frames[0]).decode("ascii", errors="replace")
        with self._lock:
            if self._closed:
                return False
            try:
                self._before_send()
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


class PosePort(NonBlockingSender):
    """Non-blocking XPUB of ``[topic, json]`` messages with its subscriptions counted and
    capped (module docstring)."""

    def __init__(
        self, ctx: zmq.Context[Any], endpoint: str, sndhwm: int = 100, curve: CurveConfig | None = None
    ) -> None:
        """Bind ``endpoint``; with ``curve`` keys, as a CURVE server (services/curve_auth.py).
        Raises OSError when the endpoint cannot be bound or the keys cannot be read."""
        super().__init__()
        self.endpoint = endpoint
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
        self.subscriptions: set[bytes] = set()
        self.ignored_subscriptions = 0

    @property
    def socket(self) -> zmq.Socket[Any]:
        """The XPUB socket, for a poller (readable when subscriptions arrive); read it only
        through :meth:`refresh`."""
        return self._sock

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
                len(msg), bytes(msg[:24]), ", ".join(TOPIC_NAMES),
            )

    def refresh(self) -> frozenset[bytes]:
        """Read the waiting subscription reports (a bounded number) and enforce the cap; the
        topic prefixes someone holds now."""
        with self._lock:
            if not self._closed:
                self._drain_subscriptions()
            return frozenset(self.subscriptions)

    def wanted(self, topic: str) -> bool:
        """True if some subscriber's prefix matches ``topic`` (XPUB's view)."""
        t = topic.encode("ascii")
        return any(t.startswith(p) for p in self.refresh())

    @property
    def n_subscriptions(self) -> int:
        """Distinct topic prefixes someone subscribes to (not the number of clients)."""
        return len(self.refresh())

    def counters(self) -> dict[str, int]:
        """The subscribers' counters (the fields of :class:`services.messages.PosePortInfo`)."""
        with self._lock:
            if not self._closed:
                self.guard.read_events()  # the connections open now
            return {
                "subscribers": self.guard.subscribers,
                "subscriptions": self.guard.distinct,
                "subscription_bytes": self.guard.distinct_bytes,
                "ignored_subscriptions": self.ignored_subscriptions,
                "evicted_subscribers": self.guard.evicted,
                "dropped_sends": self.dropped,
                "refused_handshakes": self.guard.refused_handshakes,
            }

    def _before_send(self) -> None:
        self._drain_subscriptions()

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self.guard.close()
                self._sock.close(linger=0)
                self._release_curve()

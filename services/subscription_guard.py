"""What subscribers can make libzmq hold on the pose port: a cap, enforced by eviction.

libzmq keeps, inside the XPUB socket, a trie of every distinct subscription prefix its
connections hold, one node per byte (with a pointer table at each branching). The daemon
cannot limit it through libzmq: there is no option for it, and ``ZMQ_XPUB_MANUAL`` keeps the
same trie for the unsubscriptions at disconnect. What the daemon can see is the non-verbose
XPUB's reports (services/publisher.py): one when a prefix gets its first holder, one when it
loses its last, each with the prefix. Their balance is the number of distinct prefixes in
libzmq's table, :attr:`SubscriptionGuard.distinct`, and their summed length,
:attr:`SubscriptionGuard.distinct_bytes`: the table's size is bounded by a constant times the
bytes plus a pointer table (at most 256 pointers) per prefix.

The cap: when ``distinct`` exceeds :data:`MAX_DISTINCT_SUBSCRIPTIONS` or ``distinct_bytes``
exceeds :data:`MAX_SUBSCRIPTION_TABLE_BYTES`, the guard ends a subscriber's connection; libzmq
then drops that connection's subscriptions and reports the prefixes nobody else holds, which
brings the counts down. The connection ended is the one that has sent the most bytes
(``tcpi_bytes_received`` of Linux's ``TCP_INFO``): a subscriber sends nothing but
subscriptions after its handshake, so the connection that filled the table is the one that
sent the most (where the kernel cannot say, IPC or another OS, the one accepted last).

One connection at a time, the next once libzmq has dropped the previous one (its
``DISCONNECTED`` event), and at most :data:`MAX_EVICTIONS_PER_S` a second: an ended subscriber
comes back (ZeroMQ reconnects by itself) and sends its table again, so ending subscribers
as fast as they fill the table keeps it at its cap, and ending them faster only adds churn.
This bounds the table against subscribers that arrive over time. A burst of hundreds at
once fills it faster than that; and libzmq drops an ended connection's subscriptions by
walking its whole table, inside the loop's calls on the socket, so evicting from a large
table stalls the loop for as long as the table is large. Past
:data:`EVICTION_MAX_FACTOR` times a cap, or while subscription reports are waiting unread,
the guard therefore leaves the table to libzmq (logged once), as without the guard: what a
burst costs is then libzmq's memory, not the loop's time.

The number of connections is not capped here: a connection ended for its number comes back
every reconnect interval (ZeroMQ retries by itself), and hundreds of them handshaking ten
times a second cost the daemon more than their buffers do. Their number is reported
(:attr:`SubscriptionGuard.subscribers`) and bounded by the process's file descriptors
(``LimitNOFILE`` in the systemd unit).

Connections are known from the socket's monitor (``ZMQ_EVENT_ACCEPTED`` gives the file
descriptor libzmq owns); the same monitor counts the handshakes refused
(:data:`HANDSHAKE_FAILED`: a client without the CURVE keys or with a key not authorized). The guard ends one with ``shutdown(2)`` on a duplicate of that
descriptor, after checking it is still a connected socket on the pose port's own port: libzmq
sees the end of the stream and cleans up as for any peer that left; the guard never closes
libzmq's descriptor.

Not thread-safe: called by :class:`services.publisher.Publisher` with its lock held.
"""

from __future__ import annotations

import ctypes
import logging
import os
import socket
import struct
import time
from typing import Any

import zmq
from zmq.utils.monitor import parse_monitor_message

log = logging.getLogger("lino_loc.service.publisher")

#: Distinct subscription prefixes the pose port holds before it evicts a subscriber. Only
#: the 24 prefixes of the published topics can match a message; 1024 leaves room for
#: clients that subscribe to more than they use.
MAX_DISTINCT_SUBSCRIPTIONS = 1024
#: Summed length of the distinct prefixes held before a subscriber is evicted, bytes.
MAX_SUBSCRIPTION_TABLE_BYTES = 64 * 1024
#: Most evictions per second. An ended subscriber comes back (ZeroMQ reconnects every
#: 100 ms by default) and sends its subscriptions again, which libzmq adds to the table
#: again inside the loop's calls on the socket: ending faster than subscribers arrive
#: turns a burst of them into a churn that costs more than their table.
MAX_EVICTIONS_PER_S = 20
#: Past this many times a cap, or while reports wait unread, the guard does not evict:
#: libzmq removes an ended connection's subscriptions by walking its whole table, in the
#: loop's calls on the socket, so ending subscribers of a table that large stalls the loop.
EVICTION_MAX_FACTOR = 4
#: Shortest time between two ``malloc_trim`` calls after evictions, s.
TRIM_PERIOD_S = 1.0
#: Longest wait for libzmq to close an evicted connection before the next eviction, s.
EVICTION_WAIT_S = 1.0
#: Offset of ``tcpi_bytes_received`` (u64) in Linux's ``struct tcp_info`` (since 4.1):
#: 8 one-byte fields, 24 u32, then pacing_rate, max_pacing_rate, bytes_acked (u64).
_TCPI_BYTES_RECEIVED = 8 + 24 * 4 + 3 * 8
_TCP_INFO_LEN = _TCPI_BYTES_RECEIVED + 8
#: Monitor events of a handshake refused: the wrong security mechanism (a client without
#: CURVE keys), a key the authenticator does not know, or a malformed greeting.
HANDSHAKE_FAILED = (
    zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
    | zmq.EVENT_HANDSHAKE_FAILED_AUTH
)
_EVENTS = zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_CLOSED | HANDSHAKE_FAILED


def _libc(name: str, argtypes: list[Any], restype: Any) -> Any:
    """The C library's function ``name`` (ctypes), None where it has none (``malloc_trim``
    is glibc's: not on musl or macOS)."""
    try:
        fn = getattr(ctypes.CDLL(None, use_errno=True), name)
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = argtypes, restype
    return fn


_GETSOCKOPT = _libc(
    "getsockopt",
    [ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.POINTER(ctypes.c_uint32)],
    ctypes.c_int,
)
_MALLOC_TRIM = _libc("malloc_trim", [ctypes.c_size_t], ctypes.c_int)
_TCP_INFO = getattr(socket, "TCP_INFO", None)


def bytes_received(fd: int) -> int | None:
    """Bytes the kernel received on the TCP connection of descriptor ``fd`` (``TCP_INFO``,
    read with one ``getsockopt(2)`` on the descriptor itself); None where unknown (not TCP,
    not Linux)."""
    if _GETSOCKOPT is None or _TCP_INFO is None:
        return None
    buf = ctypes.create_string_buffer(_TCP_INFO_LEN)
    size = ctypes.c_uint32(_TCP_INFO_LEN)
    if _GETSOCKOPT(fd, socket.IPPROTO_TCP, _TCP_INFO, buf, ctypes.byref(size)) != 0:
        return None
    if size.value < _TCP_INFO_LEN:
        return None
    return int(struct.unpack_from("=Q", buf.raw, _TCPI_BYTES_RECEIVED)[0])


class SubscriptionGuard:
    """Counts the pose port's connections and distinct prefixes, and ends the connection that
    sent the most when the prefixes pass a cap (module docstring)."""

    def __init__(
        self,
        sock: zmq.Socket[Any],
        max_distinct: int = MAX_DISTINCT_SUBSCRIPTIONS,
        max_bytes: int = MAX_SUBSCRIPTION_TABLE_BYTES,
    ) -> None:
        """Attach to a bound XPUB socket ``sock`` (not verbose)."""
        self.max_distinct, self.max_bytes = int(max_distinct), int(max_bytes)
        self.distinct = 0
        self.distinct_bytes = 0
        self.evicted = 0  # connections ended for the table
        self.refused_handshakes = 0  # connections whose handshake failed (CURVE keys, ZMTP)
        self._sock = sock
        self._monitor = sock.get_monitor_socket(_EVENTS)
        self._accepted: dict[int, float] = {}  # fd -> monotonic time accepted
        self._closing: dict[int, float] = {}  # fd shut by the guard -> when
        self._evicting: set[int] = set()  # fds ended for the table, not yet dropped by libzmq
        self._warned = -1  # evictions at the last warning (-1: none yet)
        self._tokens = float(MAX_EVICTIONS_PER_S)  # token bucket of evictions
        self._beyond_logged = False
        self._trimmed = 0.0
        self._refilled = time.monotonic()
        self._port = _tcp_port(sock.getsockopt_string(zmq.LAST_ENDPOINT))

    @property
    def subscribers(self) -> int:
        """Connections open on the pose port (those being ended aside)."""
        return len(self._accepted) - len(self._closing)

    def reported(self, subscribe: bool, size: int) -> None:
        """Count one report of the XPUB: a prefix of ``size`` bytes got its first holder
        (``subscribe``), or lost its last."""
        sign = 1 if subscribe else -1
        self.distinct = max(self.distinct + sign, 0)
        self.distinct_bytes = max(self.distinct_bytes + sign * int(size), 0)

    @property
    def evicting(self) -> bool:
        """Whether a connection ended for the table has not been dropped by libzmq yet."""
        return bool(self._evicting)

    @property
    def beyond_eviction(self) -> bool:
        """Whether the table is past :data:`EVICTION_MAX_FACTOR` times one of its caps."""
        return (
            self.distinct > EVICTION_MAX_FACTOR * self.max_distinct
            or self.distinct_bytes > EVICTION_MAX_FACTOR * self.max_bytes
        )

    @property
    def over(self) -> bool:
        """Whether the table is past one of its caps."""
        return self.distinct > self.max_distinct or self.distinct_bytes > self.max_bytes

    def read_events(self) -> None:
        """Read the monitor's events: connections accepted and dropped, handshakes refused
        (what :attr:`subscribers` and :attr:`refused_handshakes` count)."""
        while True:
            try:
                event = parse_monitor_message(self._monitor.recv_multipart(zmq.NOBLOCK))
            except zmq.ZMQError:
                return
            if event["event"] & HANDSHAKE_FAILED:
                self.refused_handshakes += 1  # its value is an error number, not a descriptor
                continue
            fd = int(event["value"])
            if event["event"] != zmq.EVENT_ACCEPTED:
                self._forget(fd)
                continue
            self._accepted[fd] = time.monotonic()

    def enforce(self, backlog: bool = False) -> None:
        """Read the monitor's events; over a cap, end the connection that sent the most, one
        at a time (the next once libzmq has dropped it) and at most
        :data:`MAX_EVICTIONS_PER_S` a second; never while the reports are behind
        (``backlog``: more are waiting to be read) or the table is past
        :data:`EVICTION_MAX_FACTOR` times a cap, when an eviction would cost more than the
        table (module docstring)."""
        self.read_events()
        now = time.monotonic()
        for fd in [fd for fd, t in self._closing.items() if now - t > EVICTION_WAIT_S]:
            self._forget(fd)  # its event was lost: do not wait for ever
        if not self.over or self._evicting:
            return
        if backlog or self.beyond_eviction:
            if not self._beyond_logged:
                self._beyond_logged = True
                log.warning(
                    "pose port: a burst of subscriptions (%d distinct, %d bytes so far, more "
                    "waiting: %s): too many to end subscribers cheaply; left to libzmq",
                    self.distinct, self.distinct_bytes, backlog,
                )
            return
        self._tokens = min(self._tokens + (now - self._refilled) * MAX_EVICTIONS_PER_S,
                           float(MAX_EVICTIONS_PER_S))
        self._refilled = now
        if self._tokens < 1.0:
            return
        for fd in self._victims():
            if self._shut(fd):
                self._evicting.add(fd)
                self._tokens -= 1.0
                self.evicted += 1
                break
            self._forget(fd)
        if self._evicting and (self._warned < 0 or self.evicted - self._warned >= 100):
            self._warned = self.evicted
            log.warning(
                "pose port: %d distinct subscriptions, %d bytes (caps %d, %d): ended the "
                "subscriber that sent the most (%d evictions so far)",
                self.distinct, self.distinct_bytes, self.max_distinct, self.max_bytes, self.evicted,
            )

    def close(self) -> None:
        """Stop the monitor (before the XPUB socket is closed)."""
        try:
            self._sock.disable_monitor()
        except zmq.ZMQError:
            pass
        self._monitor.close(linger=0)

    # ---------------------------------------------------------------------------------
    def _forget(self, fd: int) -> None:
        self._accepted.pop(fd, None)
        self._closing.pop(fd, None)
        if fd in self._evicting:
            self._evicting.discard(fd)
            self._trim()

    def _trim(self) -> None:
        """Give the pages libzmq freed with an evicted table back to the system
        (``malloc_trim(3)``), at most once per :data:`TRIM_PERIOD_S`: the table's nodes are
        small allocations that otherwise stay in the heap, free but resident."""
        now = time.monotonic()
        if _MALLOC_TRIM is None or now - self._trimmed < TRIM_PERIOD_S:
            return
        self._trimmed = now
        _MALLOC_TRIM(0)

    def _victims(self) -> list[int]:
        """The open connections, the one that sent the most first (where the kernel cannot
        say, the newest first)."""
        ranked: list[tuple[int, float, int]] = []
        for fd, accepted in self._accepted.items():
            if fd not in self._closing:
                sent = bytes_received(fd)
                ranked.append((-1 if sent is None else sent, accepted, fd))
        return [fd for _, _, fd in sorted(ranked, reverse=True)]

    def _shut(self, fd: int) -> bool:
        """``shutdown(2)`` the connection ``fd`` if it is one of the pose port's; True if done."""

        def shut(s: socket.socket) -> bool:
            s.getpeername()  # a connected socket (not the listener)
            if self._port is not None and s.getsockname()[1] != self._port:
                return False
            s.shutdown(socket.SHUT_RDWR)
            return True

        done = bool(_with_dup(fd, shut))
        if done:
            self._closing[fd] = time.monotonic()
        return done


def _with_dup(fd: int, fn: Any) -> Any:
    """``fn(socket)`` on a duplicate of descriptor ``fd`` (closed after); None on OSError."""
    try:
        dup = os.dup(fd)
    except OSError:
        return None
    try:
        s = socket.socket(fileno=dup)
    except OSError:  # not a socket (the descriptor was closed and reused)
        os.close(dup)
        return None
    with s:
        try:
            return fn(s)
        except OSError:
            return None


def _tcp_port(endpoint: str) -> int | None:
    """The port of a ``tcp://host:port`` endpoint; None for other transports."""
    if not endpoint.startswith("tcp://"):
        return None
    try:
        return int(endpoint.rsplit(":", 1)[1])
    except ValueError:
        return None

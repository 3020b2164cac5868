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
exceeds :data:`MAX_SUBSCRIPTION_TABLE_BYTES`, the guard ends one subscriber's connection. libzmq then drops that connection's subscriptions (and reports the
prefixes nobody else holds, which brings ``distinct`` down). The connection ended is the one
that has sent the most bytes (``tcpi_bytes_received`` of Linux's ``TCP_INFO``): a subscriber
sends nothing but subscriptions after its handshake, so the connection that filled the table
is the one that sent the most. Where the kernel cannot say (IPC, another OS) it is the one
accepted last. One eviction at a time: the next waits until libzmq has closed the previous
one (its ``DISCONNECTED`` event), since the reports of its prefixes come only then. A
subscriber that connects again (ZeroMQ reconnects by itself) and sends the same table is
evicted again; the others keep receiving.

The number of connections is not capped here: a connection ended for its number comes back
every reconnect interval (ZeroMQ retries by itself), and hundreds of them handshaking ten
times a second cost the daemon more than their buffers do. Their number is reported
(:attr:`SubscriptionGuard.subscribers`) and bounded by the process's file descriptors
(``LimitNOFILE`` in the systemd unit).

Connections are known from the socket's monitor (``ZMQ_EVENT_ACCEPTED`` gives the file
descriptor libzmq owns). The guard ends one with ``shutdown(2)`` on a duplicate of that
descriptor, after checking it is still a connected socket on the pose port's own port: libzmq
sees the end of the stream and cleans up as for any peer that left; the guard never closes
libzmq's descriptor.

Not thread-safe: called by :class:`services.publisher.Publisher` with its lock held.
"""

from __future__ import annotations

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
#: Longest wait for libzmq to close an evicted connection before the next eviction, s.
EVICTION_WAIT_S = 1.0
#: Offset of ``tcpi_bytes_received`` (u64) in Linux's ``struct tcp_info`` (since 4.1):
#: 8 one-byte fields, 24 u32, then pacing_rate, max_pacing_rate, bytes_acked (u64).
_TCPI_BYTES_RECEIVED = 8 + 24 * 4 + 3 * 8
_TCP_INFO_LEN = _TCPI_BYTES_RECEIVED + 8
_EVENTS = zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_CLOSED


def bytes_received(sock: socket.socket) -> int | None:
    """Bytes the kernel received on a TCP connection (``TCP_INFO``), None where unknown."""
    tcp_info = getattr(socket, "TCP_INFO", None)
    if tcp_info is None or sock.family not in (socket.AF_INET, socket.AF_INET6):
        return None
    try:
        raw = sock.getsockopt(socket.IPPROTO_TCP, tcp_info, _TCP_INFO_LEN)
    except OSError:
        return None
    if len(raw) < _TCP_INFO_LEN:
        return None
    return int(struct.unpack_from("=Q", raw, _TCPI_BYTES_RECEIVED)[0])


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
        self._sock = sock
        self._monitor = sock.get_monitor_socket(_EVENTS)
        self._accepted: dict[int, float] = {}  # fd -> monotonic time accepted
        self._closing: dict[int, float] = {}  # fd shut by the guard -> when
        self._evicting: int | None = None
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
        return self._evicting is not None

    @property
    def over(self) -> bool:
        """Whether the table is past one of its caps."""
        return self.distinct > self.max_distinct or self.distinct_bytes > self.max_bytes

    def enforce(self) -> None:
        """Read the monitor's events, then end the connection that sent the most if the table
        is over a cap."""
        self._read_events()
        now = time.monotonic()
        for fd in [fd for fd, t in self._closing.items() if now - t > EVICTION_WAIT_S]:
            self._forget(fd)  # its event was lost: do not wait for ever
        if not self.over or self._evicting is not None:
            return
        for fd in self._victims():
            if self._shut(fd):
                self._evicting = fd
                self.evicted += 1
                if self.evicted == 1 or self.evicted % 100 == 0:
                    log.warning(
                        "pose port: %d distinct subscriptions, %d bytes (caps %d, %d): ended the "
                        "subscriber that sent the most (%d evictions so far)",
                        self.distinct, self.distinct_bytes, self.max_distinct, self.max_bytes,
                        self.evicted,
                    )
                return
            self._forget(fd)

    def close(self) -> None:
        """Stop the monitor (before the XPUB socket is closed)."""
        try:
            self._sock.disable_monitor()
        except zmq.ZMQError:
            pass
        self._monitor.close(linger=0)

    # ---------------------------------------------------------------------------------
    def _read_events(self) -> None:
        while True:
            try:
                event = parse_monitor_message(self._monitor.recv_multipart(zmq.NOBLOCK))
            except zmq.ZMQError:
                return
            fd = int(event["value"])
            if event["event"] != zmq.EVENT_ACCEPTED:
                self._forget(fd)
                continue
            self._accepted[fd] = time.monotonic()

    def _forget(self, fd: int) -> None:
        self._accepted.pop(fd, None)
        self._closing.pop(fd, None)
        if fd == self._evicting:
            self._evicting = None

    def _victims(self) -> list[int]:
        """Open connections, the one that sent the most first (else the newest first)."""
        ranked: list[tuple[int, float, int]] = []
        for fd, accepted in self._accepted.items():
            if fd not in self._closing:
                sent = _with_dup(fd, bytes_received)
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

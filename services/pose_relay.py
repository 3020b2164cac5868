"""The pose relay: a process of its own that owns the public pose port.

Why a process: libzmq keeps every distinct subscription prefix of an XPUB socket in a
table that no option limits, and it works on that table (adds subscriptions, walks it whole
for every connection that leaves) inside the calls made on the socket, from the thread that
makes them (services/subscription_guard.py). On the daemon's own socket, hundreds of
subscribers arriving or leaving at once stall the filter's loop and take its memory. The
relay takes that work out of the daemon: the daemon publishes to a private XPUB on an
``ipc://`` socket in a folder only its user can open
(:class:`services.relay_publisher.RelayedPublisher`), the relay is its only subscriber and
republishes every message on the public endpoint, with the same options, guard and CURVE
keys as a direct :class:`services.pose_port.PosePort`. What subscribers cost then lands in
the relay: the daemon's loop and memory do not see them.

The relay's own bounds:

- it forwards upstream only the subscriptions that can match a topic
  (:data:`services.topics.TOPIC_PREFIXES`, 24 at most, as one holder: the union of its
  subscribers'), so the daemon's table is bounded and the daemon still serializes the
  particle set only when someone wants it;
- it measures its resident memory every :data:`REPORT_PERIOD_S` and, above the configured
  limit, exits at once (``os._exit``, code :data:`EXIT_MEMORY`: the kernel frees the table
  in one go, where closing the socket would walk it per connection). The daemon starts a new
  relay on the same address; ZeroMQ subscribers reconnect and subscribe again by themselves;
- it dies with the daemon (``PR_SET_PDEATHSIG``, and a check of its parent's id);
- the kernel's OOM killer takes it before the daemon (``oom_score_adj`` raised to
  :data:`OOM_SCORE_ADJ`), should the unit's ``MemoryMax`` be reached between two checks.

Its counters (the fields of :class:`services.messages.PosePortInfo` and its resident
memory) go upstream every :data:`REPORT_PERIOD_S` as one message ``b"\\x02" + JSON`` (an
XSUB may send any message to its XPUB; those that do not start with 0 or 1 are not
subscriptions), for the daemon's status.

Protocol with the daemon: started as ``python -m services.pose_relay SETTINGS_JSON``
(:class:`RelaySettings`); it prints one line on stdout, ``ready ENDPOINT`` once bound or
``error MESSAGE`` (exit :data:`EXIT_BIND`), and logs on stderr. SIGTERM ends it at once.
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import resource
import signal
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import zmq

from services.curve_auth import CurveConfig
from services.pose_port import PosePort

log = logging.getLogger("lino_loc.service.relay")

#: Seconds between two reports of the counters upstream (and two memory checks).
REPORT_PERIOD_S = 0.5
#: Longest wait in the poll, ms: the guard's evictions and the memory check run at least
#: this often.
POLL_MS = 100
#: Messages forwarded per poll before the subscriptions are read again.
MAX_FORWARD = 1000
#: First byte of the counters message sent upstream.
COUNTERS_MARK = b"\x02"
#: Exit codes: the public endpoint could not be bound / the resident memory passed the limit.
EXIT_BIND = 2
EXIT_MEMORY = 3
#: The relay's ``/proc/self/oom_score_adj`` (-1000..1000; a process may raise its own).
OOM_SCORE_ADJ = 500
_PR_SET_PDEATHSIG = 1


@dataclass(frozen=True)
class RelaySettings:
    """What the daemon passes to the relay (one JSON argument)."""

    upstream: str  # the daemon's private XPUB (ipc://)
    bind: str  # the public endpoint
    sndhwm: int
    max_resident_bytes: int
    parent_pid: int
    server_secret_key: str | None = None
    authorized_clients: str | None = None
    log_level: str = "INFO"

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> RelaySettings:
        return cls(**json.loads(text))


def resident_bytes() -> int:
    """This process's resident memory now (``/proc/self/statm``; the peak where there is no
    /proc)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return int(peak if sys.platform == "darwin" else peak * 1024)


def _die_with_parent() -> None:
    """Ask Linux to kill this process when its parent dies (no-op elsewhere)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def _oom_first() -> None:
    """Make this process the OOM killer's first choice in its cgroup (best effort)."""
    try:
        Path("/proc/self/oom_score_adj").write_text(str(OOM_SCORE_ADJ))
    except OSError:
        pass


def _say(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


class Relay:
    """The relay's sockets and its loop (module docstring)."""

    def __init__(self, ctx: zmq.Context[Any], s: RelaySettings) -> None:
        curve = CurveConfig(server_secret_key=s.server_secret_key, authorized_clients=s.authorized_clients)
        self.settings = s
        self.port = PosePort(ctx, s.bind, s.sndhwm, curve)  # OSError: one line
        self.up = ctx.socket(zmq.XSUB)
        self.up.setsockopt(zmq.LINGER, 0)
        self.up.setsockopt(zmq.RCVHWM, s.sndhwm)
        self.up.connect(s.upstream)
        self.forwarded: set[bytes] = set()
        self._poller = zmq.Poller()
        self._poller.register(self.up, zmq.POLLIN)
        self._poller.register(self.port.socket, zmq.POLLIN)
        self._next_report = 0.0

    def step(self) -> int | None:
        """One poll: forward messages, sync the subscriptions upstream, maybe report; an exit
        code when the relay must end."""
        ready = dict(self._poller.poll(POLL_MS))
        if self.up in ready:
            for _ in range(MAX_FORWARD):
                try:
                    frames = self.up.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    break
                self.port.send_frames(frames)
        self._sync(self.port.refresh())
        now = time.monotonic()
        if now >= self._next_report:
            self._next_report = now + REPORT_PERIOD_S
            return self._report()
        return None

    def _sync(self, held: frozenset[bytes]) -> None:
        """Subscribe upstream to the topic prefixes the subscribers hold, and no more."""
        for topic, mark in [(t, b"\x01") for t in held - self.forwarded] + [
            (t, b"\x00") for t in self.forwarded - held
        ]:
            try:
                self.up.send(mark + topic, zmq.NOBLOCK)
            except zmq.ZMQError:
                return  # tried again at the next step
            if mark == b"\x01":
                self.forwarded.add(topic)
            else:
                self.forwarded.discard(topic)

    def _report(self) -> int | None:
        if os.getppid() != self.settings.parent_pid:
            log.warning("the daemon (pid %d) is gone: exiting", self.settings.parent_pid)
            return 0
        rss = resident_bytes()
        counters = {**self.port.counters(), "resident_bytes": rss}
        if rss > self.settings.max_resident_bytes:
            log.warning(
                "resident memory %.0f MB is over the limit of %.0f MB (%d subscribers, %d distinct "
                "subscriptions, %d bytes): exiting for the daemon to start a fresh relay",
                rss / 1e6, self.settings.max_resident_bytes / 1e6, counters["subscribers"],
                counters["subscriptions"], counters["subscription_bytes"],
            )
            return EXIT_MEMORY
        try:
            self.up.send(COUNTERS_MARK + json.dumps(counters).encode(), zmq.NOBLOCK)
        except zmq.ZMQError:
            pass
        return None


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    try:
        settings = RelaySettings.from_json(args[0])
    except (IndexError, TypeError, ValueError) as exc:
        _say(f"error pose relay: bad settings argument: {exc}")
        return EXIT_BIND
    _die_with_parent()
    _oom_first()
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    logging.basicConfig(
        stream=sys.stderr, level=settings.log_level,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if os.getppid() != settings.parent_pid:  # the daemon died before the death signal was set
        return 0
    ctx: zmq.Context[Any] = zmq.Context()
    try:
        relay = Relay(ctx, settings)
    except OSError as exc:
        _say(f"error {exc}")
        return EXIT_BIND
    _say(f"ready {relay.port.last_endpoint}")
    while True:
        code = relay.step()
        if code is not None:
            os._exit(code)  # not a close: the kernel frees libzmq's table at once


if __name__ == "__main__":
    sys.exit(main())

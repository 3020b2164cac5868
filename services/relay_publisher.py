"""The daemon's side of the pose relay: a private XPUB, and the relay process kept running.

:class:`RelayedPublisher` is what the daemon publishes through when ``[endpoints.relay]`` is
enabled (the default). It has the interface of :class:`services.publisher.Publisher`
(``send_frames``, ``publish``, ``wanted``, ``n_subscriptions``, ``info``, ``close``,
``last_endpoint``, ``sent``, ``dropped``), so the loop does not know which one it has.

- It binds an XPUB (not verbose, ``ZMQ_SNDHWM`` = ``endpoints.sndhwm``) on ``ipc://`` in a
  fresh folder that only the daemon's user can open, and starts the relay
  (``python -m services.pose_relay``, services/pose_relay.py) on the public endpoint. It
  returns once the relay said ``ready``; a relay that cannot bind makes it raise OSError with
  the relay's one line (the same message as a direct bind).
- The relay is the private socket's only subscriber: what the daemon holds is the set of
  topic prefixes the public subscribers want (24 at most), and the relay's counters.
- Supervision, from the calls the loop makes anyway (at most every
  :data:`SUPERVISE_PERIOD_S`): a relay that exited (its memory limit, a crash, a kill) is
  logged and started again on the address it had bound (a ``*`` port keeps its number),
  immediately when it had lived :data:`STABLE_S`, else after a delay that doubles from
  :data:`RESTART_DELAY_S` up to :data:`MAX_RESTART_DELAY_S`. The loop never waits for it:
  poses sent while no relay runs are dropped by the private XPUB (no subscriber) and counted
  nowhere else. ``status.pose_port.relay_restarts`` counts the restarts.
"""

from __future__ import annotations

import json
import logging
import os
import selectors
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import zmq
from pydantic import BaseModel, ConfigDict, Field

import services
from services.curve_auth import CurveConfig
from services.messages import PosePortInfo, encode
from services.pose_port import NonBlockingSender
from services.pose_relay import COUNTERS_MARK, EXIT_MEMORY, RelaySettings
from services.topics import TOPIC_PREFIXES

log = logging.getLogger("lino_loc.service.publisher")

#: Longest wait for a new relay's ``ready`` line at start, s.
RELAY_START_TIMEOUT_S = 20.0
#: Shortest time between two checks of the relay from the loop's calls, s.
SUPERVISE_PERIOD_S = 0.2
#: A relay that lived this long is started again at once when it exits, s.
STABLE_S = 10.0
#: First and longest delay before starting again a relay that exited sooner, s.
RESTART_DELAY_S = 0.5
MAX_RESTART_DELAY_S = 10.0
#: Largest message the relay may send upstream (its counters are a few hundred bytes).
RELAY_MAX_FRAME_BYTES = 16 * 1024
#: Messages read from the private socket per call.
MAX_UPSTREAM_MESSAGES = 1000


class RelayConfig(BaseModel):
    """``[endpoints.relay]``: the pose relay process (services/pose_relay.py)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        True, description="publish through the relay process (false: the daemon binds the pose port itself)"
    )
    max_resident_mb: float = Field(
        128.0, ge=64.0, description="the relay's resident memory above which it is restarted, MB"
    )


class _Child:
    """One relay process and what it said on stdout."""

    def __init__(self, settings: RelaySettings) -> None:
        env = dict(os.environ)
        root = str(Path(services.__file__).resolve().parent.parent)  # services/ importable
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.pose_relay", settings.to_json()],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, env=env, close_fds=True,
        )
        self.started = time.monotonic()
        self.endpoint: str | None = None  # once ready
        self.error: str | None = None
        self._sel = selectors.DefaultSelector()
        assert self.proc.stdout is not None
        self._sel.register(self.proc.stdout, selectors.EVENT_READ)

    def poll_line(self, timeout: float) -> bool:
        """Read the ready/error line if there is one within ``timeout``; True once read."""
        if self.endpoint is not None or self.error is not None:
            return True
        if not self._sel.select(timeout):
            return False
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline().decode("utf-8", "replace").strip()
        if line.startswith("ready "):
            self.endpoint = line[len("ready "):]
        else:
            self.error = line.removeprefix("error ") or f"the pose relay exited (code {self.proc.wait(5)})"
        self._sel.close()
        self.proc.stdout.close()
        return True

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(2.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(2.0)
        if self.proc.stdout is not None and not self.proc.stdout.closed:
            self._sel.close()
            self.proc.stdout.close()


class RelayedPublisher(NonBlockingSender):
    """Publishes through the pose relay (module docstring); thread-safe."""

    def __init__(
        self,
        ctx: zmq.Context[Any],
        endpoint: str,
        sndhwm: int = 100,
        curve: CurveConfig | None = None,
        relay: RelayConfig | None = None,
    ) -> None:
        """Bind the private socket and start the relay on ``endpoint``. Raises OSError with
        one line when the relay cannot bind it or does not start."""
        super().__init__()
        self.endpoint = endpoint
        self.relay_cfg = relay or RelayConfig()
        self._curve = curve or CurveConfig()
        self._sndhwm = int(sndhwm)
        self._dir = Path(tempfile.mkdtemp(prefix="lino-loc-relay-"))  # mode 0700
        self._upstream = f"ipc://{self._dir / 'pose'}"
        self._sock = ctx.socket(zmq.XPUB)
        self._sock.setsockopt(zmq.SNDHWM, self._sndhwm)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.XPUB_VERBOSE, 0)
        self._sock.setsockopt(zmq.MAXMSGSIZE, RELAY_MAX_FRAME_BYTES)
        self.subscriptions: set[bytes] = set()
        self.restarts = 0
        self._relay_counters: dict[str, int] = {}
        self._delay = RESTART_DELAY_S
        self._restart_at: float | None = None
        self._checked = 0.0
        try:
            self._sock.bind(self._upstream)
            self._child: _Child | None = _Child(self._settings(endpoint))
            if not self._child.poll_line(RELAY_START_TIMEOUT_S):
                raise OSError(f"cannot bind the PUB socket to {endpoint}: the pose relay did not start "
                              f"within {RELAY_START_TIMEOUT_S:.0f} s")
            if self._child.error is not None:
                raise OSError(self._child.error)
        except BaseException:
            self._teardown()
            raise
        assert self._child.endpoint is not None
        self.last_endpoint = self._child.endpoint

    def _settings(self, bind: str) -> RelaySettings:
        c = self._curve
        return RelaySettings(
            upstream=self._upstream, bind=bind, sndhwm=self._sndhwm,
            max_resident_bytes=int(self.relay_cfg.max_resident_mb * 1e6), parent_pid=os.getpid(),
            server_secret_key=None if c.server_secret_key is None else str(c.server_secret_key),
            authorized_clients=None if c.authorized_clients is None else str(c.authorized_clients),
            log_level=logging.getLevelName(logging.getLogger().getEffectiveLevel()),
        )

    @property
    def relay_pid(self) -> int | None:
        """The running relay's process id (None between two relays)."""
        with self._lock:
            return None if self._child is None else self._child.proc.pid

    # ---------------------------------------------------------------------------------
    def _supervise(self, now: float) -> None:
        """Start the relay again if it exited (module docstring); called with the lock held."""
        if now - self._checked < SUPERVISE_PERIOD_S:
            return
        self._checked = now
        child = self._child
        if child is not None:
            if child.endpoint is None and child.poll_line(0.0) and child.error is not None:
                log.error("pose relay: %s (starting it again in %.1f s)", child.error, self._delay)
                child.proc.wait(5.0)
            code = child.proc.poll()
            if code is None:
                return
            lived = now - child.started
            child.stop()
            self._child = None
            if lived >= STABLE_S:
                self._delay = RESTART_DELAY_S
                self._restart_at = now
            else:
                self._restart_at = now + self._delay
                self._delay = min(2.0 * self._delay, MAX_RESTART_DELAY_S)
            why = "over its memory limit" if code == EXIT_MEMORY else f"exit code {code}"
            log.warning("pose relay exited after %.1f s (%s): starting it again on %s",
                        lived, why, self.last_endpoint)
            self._relay_counters = {}
        if self._restart_at is not None and now >= self._restart_at:
            self._restart_at = None
            self.restarts += 1
            self._child = _Child(self._settings(self.last_endpoint))

    def _drain(self) -> None:
        """Read the relay's subscriptions and counters (lock held)."""
        for _ in range(MAX_UPSTREAM_MESSAGES):
            try:
                msg = self._sock.recv(zmq.NOBLOCK)
            except zmq.ZMQError:
                break
            kind, body = msg[:1], bytes(msg[1:])
            if kind == COUNTERS_MARK:
                try:
                    counters = json.loads(body)
                except ValueError:
                    continue
                if isinstance(counters, dict):
                    self._relay_counters = counters
            elif kind in (b"\x00", b"\x01") and body in TOPIC_PREFIXES:
                if kind == b"\x01":
                    self.subscriptions.add(body)
                else:
                    self.subscriptions.discard(body)

    def _refresh(self) -> None:
        self._drain()
        self._supervise(time.monotonic())

    def wanted(self, topic: str) -> bool:
        """True if some public subscriber's prefix matches ``topic``."""
        t = topic.encode("ascii")
        with self._lock:
            if self._closed:
                return False
            self._refresh()
            return any(t.startswith(p) for p in self.subscriptions)

    @property
    def n_subscriptions(self) -> int:
        """Distinct topic prefixes the public subscribers hold."""
        with self._lock:
            if not self._closed:
                self._refresh()
            return len(self.subscriptions)

    def info(self) -> PosePortInfo:
        """The public port's counters (from the relay's last report) for the status."""
        with self._lock:
            if not self._closed:
                self._refresh()
            c = dict(self._relay_counters)
            c["dropped_sends"] = int(c.get("dropped_sends", 0)) + self.dropped
            return PosePortInfo(
                **c, relay_restarts=self.restarts,
                relay_resident_bytes=c.get("resident_bytes"), relay_running=self._child is not None,
            )

    def _before_send(self) -> None:
        self._refresh()

    def publish(self, topic: str, message: BaseModel) -> bool:
        """Publish a pydantic message on ``topic`` (validated against the topic's model)."""
        return self.send_frames(encode(topic, message), topic)

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self._teardown()

    def _teardown(self) -> None:
        child = getattr(self, "_child", None)
        if child is not None:
            child.stop()
            self._child = None
        self._sock.close(linger=0)
        shutil.rmtree(self._dir, ignore_errors=True)

"""Wheel odometry from the base board over a serial port, through ``pyserial``.

Implements :class:`drivers.interfaces.Odometry`. A reader thread reads the ``$ODO`` line
stream (``drivers.odometry_protocol``, docs/protocols.md), turns consecutive encoder
counts into pose increments of the base (exact arc of a differential drive, wheel radius,
ticks per revolution and track width from the configuration) and queues them for ``read``.
``counters`` gives the board's absolute counters at the latest valid line
(:class:`drivers.interfaces.BoardCounters`, stamped like the increments): they outlive the
daemon, so the daemon can tell how far the robot went while it was down.

Robustness (nothing here raises into the caller):
- counters wrap modulo 2^32 (signed 32-bit difference);
- a sequence gap (dropped lines) is counted; the counter difference is integrated anyway,
  since the counters are absolute, so no motion is lost;
- a bad checksum, garbage or an over-long run without newline is counted and skipped, and
  leaves the health DEGRADED (naming it) until ``NOISE_HOLD_S`` of clean lines;
- a partial line is buffered until its newline arrives;
- a line whose counters jump implausibly (board reset, ``seq`` restarting at 0) re-baselines
  the counters instead of integrating the jump;
- a port that disappears is reopened at once; a port that cannot be opened is retried after
  waits that double from ``reconnect_backoff_min`` up to ``reconnect_backoff_max`` and fall
  back to the minimum after a successful open (:class:`drivers.backoff.Backoff`); health is
  DEGRADED meanwhile (and when no valid line arrived for ``stale_after`` s). Use a stable path
  (``/dev/serial/by-id/...``, or the emulator's symlink) since the device may come back under
  another ``/dev/tty*`` name.

Timestamps: each increment is stamped with the board's sample time mapped to the host clock
(seconds since the epoch) by the smallest observed (host receive - board time) offset over the
last few seconds, so serial latency jitter does not enter the stamps.

Waiting: the thread blocks in ``select`` (pyserial read with a ``read_timeout`` slice), it
never spins.

Usage::

    odo = SerialOdometry(OdometryConfig(port="/dev/serial/by-id/usb-lino-base"))
    odo.open(); increments = odo.read(timeout=0.1); odo.close()
"""

from __future__ import annotations

import collections
import logging
import math
import termios
import threading
import time

import serial
from pydantic import BaseModel, ConfigDict, Field

from drivers.backoff import Backoff
from drivers.interfaces import (
    BoardCounters,
    DeviceHealth,
    HealthState,
    HealthTracker,
    OdometryIncrement,
)
from drivers.odometry_protocol import (
    MAX_LINE,
    LineError,
    OdometrySample,
    arc_step,
    parse_line,
    wrap_delta,
)
from lino_loc.poses import compose

#: Garbage or a corrupt line keeps the health DEGRADED for this long after it, s (then the
#: next valid line makes it OK again).
NOISE_HOLD_S = 1.0

log = logging.getLogger("lino_loc.drivers.odometry")


class OdometryConfig(BaseModel):
    """Configuration of the odometry board and the base geometry."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    port: str = Field("/dev/ttyACM0", description="serial device (a stable by-id path)")
    baudrate: int = Field(115200, gt=0)
    wheel_radius: float = Field(0.05, gt=0.0, description="m")
    ticks_per_rev: float = Field(4096.0, gt=0.0, description="encoder ticks per wheel revolution")
    track_width: float = Field(0.30, gt=0.0, description="m between the wheels' contact points")
    left_sign: int = Field(1, description="+1 or -1: encoder direction of the left wheel")
    right_sign: int = Field(1, description="+1 or -1: encoder direction of the right wheel")
    rate_hz: float = Field(50.0, gt=0.0, description="nominal line rate of the board")
    max_wheel_speed: float = Field(
        3.0, gt=0.0, description="m/s; faster apparent motion means a board reset"
    )
    read_timeout: float = Field(0.05, gt=0.0, le=1.0, description="s; serial read slice")
    stale_after: float = Field(0.5, gt=0.0, description="s without a valid line -> degraded")
    reconnect_backoff_min: float = Field(0.05, gt=0.0)
    reconnect_backoff_max: float = Field(2.0, gt=0.0)
    queue_max: int = Field(1000, ge=2, description="queued increments before merging oldest")


class SerialOdometry:
    """:class:`~drivers.interfaces.Odometry` from a serial ``$ODO`` stream."""

    def __init__(self, config: OdometryConfig | None = None) -> None:
        self.config = config or OdometryConfig()
        c = self.config
        if c.left_sign not in (1, -1) or c.right_sign not in (1, -1):
            raise ValueError("left_sign and right_sign must be +1 or -1")
        self._metres_per_tick = 2.0 * math.pi * c.wheel_radius / c.ticks_per_rev
        self._health = HealthTracker(
            ("lines", "increments", "corrupt_lines", "garbage_bytes", "gap_events",
             "lines_missed", "resets", "reconnects", "merged")
        )  # fmt: skip
        self._cond = threading.Condition()
        self._queue: collections.deque[OdometryIncrement] = collections.deque()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ser: serial.Serial | None = None
        self._prev: OdometrySample | None = None
        self._counters: BoardCounters | None = None  # at the latest valid line
        self._t_unwrapped_ms = 0
        self._offsets: collections.deque[tuple[float, float]] = collections.deque()
        self._last_valid = time.monotonic()
        self._last_noise = -math.inf  # monotonic time of the last garbage or corrupt line
        self._connected_once = False

    # ---------------------------------------------------------------------------------------
    def open(self) -> None:
        """Start the reader thread (it opens the port and keeps reopening it)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="odometry-reader", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close_port()

    def __enter__(self) -> SerialOdometry:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def health(self) -> DeviceHealth:
        if (
            self._health.state is HealthState.OK
            and time.monotonic() - self._last_valid > self.config.stale_after
        ):
            self._health.error(f"odometry: no valid line for more than {self.config.stale_after} s")
        return self._health.snapshot()

    def read(self, timeout: float | None = None) -> list[OdometryIncrement]:
        """All increments since the previous call; waits up to ``timeout`` s for at least one
        (``None``: do not wait)."""
        with self._cond:
            if not self._queue and timeout:
                self._cond.wait_for(lambda: bool(self._queue), timeout)
            out = list(self._queue)
            self._queue.clear()
        return out

    def counters(self) -> BoardCounters | None:
        """The board's absolute counters at the latest valid line (None before the first)."""
        return self._counters

    # ---------------------------------------------------------------------------------------
    # reader thread
    # ---------------------------------------------------------------------------------------
    def _run(self) -> None:
        """Open the port (with backoff while it cannot be opened) and pump it until ``close``.

        A lost port is reopened at once; only failed opens wait, ``reconnect_backoff_min``
        doubling per failure up to ``reconnect_backoff_max``."""
        c = self.config
        backoff = Backoff(c.reconnect_backoff_min, c.reconnect_backoff_max)
        while not self._stop.is_set():
            if self._ser is None:
                if not self._open_port():
                    backoff.wait(self._stop)
                    continue
                backoff.reset()
            try:
                self._pump()
            except (serial.SerialException, OSError, termios.error, TypeError) as exc:
                # TypeError: pyserial on a port closed under it by close()
                if self._stop.is_set():
                    break
                self._health.count("reconnects")
                self._health.error(f"odometry port {c.port} lost: {exc}")
                log.warning("odometry: port %s lost (%s); reopening", c.port, exc)
                self._close_port()

    def _open_port(self) -> bool:
        c = self.config
        try:
            self._ser = serial.Serial(c.port, c.baudrate, timeout=c.read_timeout)
        except (serial.SerialException, OSError, termios.error, ValueError) as exc:
            self._ser = None
            self._health.error(f"odometry: cannot open {c.port}: {exc}")
            return False
        log.info("odometry: opened %s", c.port)
        self._buf = bytearray()
        self._discard_partial = self._connected_once  # first bytes after reopen may be a tail
        self._connected_once = True
        return True

    def _close_port(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError, termios.error):
                pass

    def _pump(self) -> None:
        ser = self._ser
        assert ser is not None
        while not self._stop.is_set():
            chunk = ser.read(max(1, ser.in_waiting))  # blocks in select up to read_timeout
            if not chunk:
                continue
            self._buf += chunk
            while True:
                nl = self._buf.find(b"\n")
                if nl < 0:
                    if len(self._buf) > MAX_LINE:
                        self._health.count("garbage_bytes", len(self._buf))
                        self._noise(f"{len(self._buf)} bytes without a newline skipped")
                        self._buf.clear()
                    break
                line = bytes(self._buf[: nl + 1])
                del self._buf[: nl + 1]
                if self._discard_partial and not line.startswith(b"$"):
                    self._discard_partial = False
                    continue
                self._discard_partial = False
                self._handle_line(line, time.time())

    def _handle_line(self, line: bytes, host_time: float) -> None:
        start = line.rfind(b"$")  # line noise may precede a sentence on the same line
        if start < 0:
            self._health.count("garbage_bytes", len(line))
            self._noise(f"a line of {len(line)} bytes without a sentence skipped")
            return
        if start:
            self._health.count("garbage_bytes", start)
            self._noise(f"{start} bytes of line noise before a sentence skipped", corrupt=False)
            line = line[start:]
        try:
            sample = parse_line(line)
        except LineError as exc:
            self._noise(f"corrupt line skipped ({exc})")
            log.debug("odometry: skipped line (%s)", exc)
            return
        self._health.count("lines")
        self._last_valid = time.monotonic()
        self._integrate(sample, host_time)

    def _board_time(self, sample: OdometrySample, host_time: float) -> float:
        """Board sample time mapped to host seconds: board time + the smallest
        (host receive - board) offset of the last 5 s (sliding-window minimum, O(1))."""
        board_s = self._t_unwrapped_ms / 1000.0
        offset = host_time - board_s
        window = self._offsets  # (board_s, offset), offsets increasing from the left
        while window and window[-1][1] >= offset:
            window.pop()
        window.append((board_s, offset))
        while board_s - window[0][0] > 5.0:
            window.popleft()
        return board_s + window[0][1]

    def _integrate(self, s: OdometrySample, host_time: float) -> None:
        c = self.config
        prev = self._prev
        self._prev = s
        if prev is None:
            self._t_unwrapped_ms = s.t_ms
            self._offsets.clear()
            self._keep_counters(s, self._board_time(s, host_time))
            self._mark_ok()
            return
        dt_ms = wrap_delta(s.t_ms, prev.t_ms)
        d_seq = wrap_delta(s.seq, prev.seq)
        dl = wrap_delta(s.left, prev.left) * c.left_sign * self._metres_per_tick
        dr = wrap_delta(s.right, prev.right) * c.right_sign * self._metres_per_tick
        limit = c.max_wheel_speed * max(dt_ms, 1) / 1000.0 + 4 * self._metres_per_tick
        reason = (
            "sequence did not increase" if d_seq <= 0
            else "board time went back" if dt_ms < 0
            else f"wheel travel {max(abs(dl), abs(dr)):.3f} m in {dt_ms} ms"
            if abs(dl) > limit or abs(dr) > limit
            else None
        )  # fmt: skip
        if reason is not None:
            self._health.count("resets")
            msg = (
                f"odometry: implausible jump ({reason}; seq {prev.seq}->{s.seq}, t_ms "
                f"{prev.t_ms}->{s.t_ms}): board reset? counters re-baselined"
            )
            self._health.error(msg)
            log.warning("%s", msg)
            self._t_unwrapped_ms = s.t_ms
            self._offsets.clear()
            self._keep_counters(s, self._board_time(s, host_time))
            return
        if d_seq > 1:
            self._health.count("gap_events")
            self._health.count("lines_missed", d_seq - 1)
        self._t_unwrapped_ms += dt_ms
        stamp = self._board_time(s, host_time)
        self._keep_counters(s, stamp)
        dx, dy, dth = arc_step(dl, dr, c.track_width)
        inc = OdometryIncrement(
            stamp=stamp, dx=float(dx), dy=float(dy), dtheta=float(dth),
            dt=dt_ms / 1000.0, sequence=s.seq,
        )  # fmt: skip
        self._health.count("increments")
        with self._cond:
            q = self._queue
            q.append(inc)
            if len(q) > c.queue_max:  # nobody reads: merge the two oldest, lose no motion
                a, b = q.popleft(), q.popleft()
                m = compose((a.dx, a.dy, a.dtheta), (b.dx, b.dy, b.dtheta))
                q.appendleft(OdometryIncrement(b.stamp, float(m[0]), float(m[1]),
                                               a.dtheta + b.dtheta, a.dt + b.dt, b.sequence))  # fmt: skip
                self._health.count("merged")
            self._cond.notify_all()
        self._mark_ok()

    def _keep_counters(self, s: OdometrySample, stamp: float) -> None:
        c = self.config
        self._counters = BoardCounters(
            stamp=stamp, board_ms=s.t_ms, left=s.left, right=s.right,
            left_m_per_tick=c.left_sign * self._metres_per_tick,
            right_m_per_tick=c.right_sign * self._metres_per_tick, track_width=c.track_width,
        )  # fmt: skip

    def _noise(self, what: str, corrupt: bool = True) -> None:
        """Line noise (``corrupt``: a whole line lost, counted): the health DEGRADED, naming
        it, for ``NOISE_HOLD_S``."""
        if corrupt:
            self._health.count("corrupt_lines")
        self._last_noise = time.monotonic()
        if self._health.state is HealthState.OK:
            self._health.error(f"odometry: {what}")

    def _mark_ok(self) -> None:
        if (
            self._health.state is not HealthState.OK
            and time.monotonic() - self._last_noise > NOISE_HOLD_S
        ):
            self._health.set_state(HealthState.OK)

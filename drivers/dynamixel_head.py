"""Pan-tilt head on two Dynamixel X-series servos, through the real ``dynamixel_sdk``.

Implements :class:`drivers.interfaces.PanTiltHead`. One sync write sends both goals
(Goal Position, 116); one sync read of addresses 64..135 returns, per servo, Torque Enable
(64), Hardware Error Status (70), Goal Position (116), Moving (122) and Present Position (132),
so every read also shows a servo that lost torque, missed a goal or raised a hardware error.

Angles: 4096 ticks per revolution, tick 2048 = 0 rad (``dynamixel_protocol.rad_to_tick``).
Commands are clamped to the configured limits (also written to the servos' EEPROM Min/Max
Position Limit at start) and the clamping is reported in the returned :class:`HeadCommand`
and counted in the health.

Faults never raise into the caller:
- a timeout or a corrupt status packet is retried (``retries`` times; a retry that succeeds
  loses nothing and is only counted); if it persists, each servo is read alone to name the
  silent one, the state comes back ``stale`` and the health is DEGRADED, naming the servo,
  until ``READ_FAILURE_HOLD_S`` of clean reads (so that a bus that fails now and then shows in
  the status, not only in the counters);
- a servo reporting a hardware error is rebooted (logged and counted as ``reboots``), then its
  profile velocity, goal and torque are restored; the health stays DEGRADED, naming the error
  and the reboot, for ``INCIDENT_HOLD_S`` after it (so that a servo that recovered at once still
  shows in the status, not only in the counters); more than ``max_reboots`` reboots within a
  minute leave it off and the health FAILED, until ``GIVEN_UP_RETRY_S`` later a new round of
  reboots is tried (an overheated or overloaded servo has cooled down by then, and only a
  reboot clears its error status);
- a servo found without torque (a brown-out) is set up again and a goal it missed is written
  again (counted as ``torque_restores`` / ``goal_rewrites``), with the health DEGRADED, naming
  it, for ``INCIDENT_HOLD_S`` as well;
- a port that cannot be opened or vanishes leaves the health FAILED and is reopened on later
  calls, after a pause that doubles per failed attempt from ``RECONNECT_BACKOFF_MIN`` up to
  ``reconnect_backoff_max`` and falls back to the minimum after a successful set-up
  (:class:`drivers.backoff.Backoff`; a lost port pauses the current delay before the first
  reopen).

Waiting: the SDK reads the port with ``timeout=0`` and spins until its packet timeout
(2 x ``LATENCY_TIMER`` + 2 ms, from the module-level ``LATENCY_TIMER``). The adapter gives
the pyserial object a short blocking timeout (``poll_interval``), so waiting sleeps in
``select`` instead of spinning, and sets ``LATENCY_TIMER`` from the configuration
(process-wide, the SDK has no per-port value). The adapter has no background thread, and
``read`` is rate limited (``min_read_interval``). All bus access happens under one lock.

Usage::

    head = DynamixelHead(HeadConfig(port="/dev/serial/by-id/usb-FTDI-...")); head.open()
    head.command(0.5, 0.0); head.wait_until_still(2.0); state = head.read(); head.close()
"""

from __future__ import annotations

import logging
import math
import termios
import threading
import time
from collections import deque
from typing import Any

import dynamixel_sdk
import dynamixel_sdk.port_handler as _sdk_port_handler
import serial
from pydantic import BaseModel, ConfigDict, Field, model_validator

from drivers.backoff import Backoff
from drivers.dynamixel_protocol import (
    ALERT_BIT,
    XAddr,
    describe_hardware_error,
    le,
    rad_s_to_profile_velocity,
    rad_to_tick,
    tick_to_rad,
    to_signed32,
)
from drivers.interfaces import (
    DeviceHealth,
    HeadCommand,
    HeadLimits,
    HeadState,
    HealthState,
    HealthTracker,
)

log = logging.getLogger("lino_loc.drivers.head")

# What a vanished or broken port raises through pyserial (termios.error is no OSError).
_PORT_ERRORS = (serial.SerialException, OSError, termios.error)

SDK_BAUDRATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
                 1000000, 1152000, 2000000, 2500000, 3000000, 3500000, 4000000)  # fmt: skip

#: First delay between reopen attempts, s (doubling per failure up to ``reconnect_backoff_max``).
RECONNECT_BACKOFF_MIN = 0.1
#: A servo given up (``max_reboots`` reboots within a minute) gets a new round of reboots this
#: long after, s; its torque stays off in between.
GIVEN_UP_RETRY_S = 60.0
#: A state read that failed after its retries keeps the health DEGRADED, naming it, for this
#: long after it, s (twice the daemon's status period: at least one status shows it).
READ_FAILURE_HOLD_S = 2.0
#: A hardware error (the servo rebooted), a servo found without torque or a goal written again
#: keeps the health DEGRADED, naming it, for this long after it, s (then OK, if every read since
#: was clean); longer than the daemon's status period, so that at least one status shows it.
INCIDENT_HOLD_S = 5.0

_BLOCK_START = XAddr.TORQUE_ENABLE  # 64
_BLOCK_LEN = XAddr.PRESENT_POSITION + 4 - _BLOCK_START  # 72 bytes: 64..135


class HeadConfig(BaseModel):
    """Configuration of the pan-tilt head: bus, servo ids, limits, motion and fault handling."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    port: str = Field("/dev/ttyUSB0", description="serial device (a stable /dev/serial/by-id path)")
    baudrate: int = Field(1_000_000, description="bus rate, one of the SDK's rates")
    pan_id: int = Field(1, ge=0, le=252)
    tilt_id: int = Field(2, ge=0, le=252)
    pan_min: float = Field(-2.6, ge=-3.14, le=3.14, description="rad")
    pan_max: float = Field(2.6, ge=-3.14, le=3.14, description="rad")
    tilt_min: float = Field(-0.6, ge=-3.14, le=3.14, description="rad")
    tilt_max: float = Field(0.6, ge=-3.14, le=3.14, description="rad")
    profile_velocity: float = Field(1.5, gt=0.0, description="rad/s while moving to a goal")
    retries: int = Field(3, ge=0, le=20, description="retries of a failed transaction")
    latency_timer_ms: float = Field(
        16.0, gt=0.0, description="SDK LATENCY_TIMER: packet timeout = 2 x this + 2 ms"
    )
    poll_interval: float = Field(
        0.001, gt=0.0, le=0.05, description="s; blocking serial read slice (no busy-wait)"
    )
    min_read_interval: float = Field(
        0.005, ge=0.0, description="s; reads closer together return the cached state"
    )
    auto_reboot: bool = True
    max_reboots: int = Field(3, ge=0, description="per servo per minute before giving up")
    boot_wait: float = Field(1.0, gt=0.0, description="s to wait for a rebooted servo")
    reconnect_backoff_max: float = Field(5.0, gt=0.0, description="s between reopen attempts")

    @model_validator(mode="after")
    def _check(self) -> HeadConfig:
        if self.baudrate not in SDK_BAUDRATES:
            raise ValueError(f"baudrate {self.baudrate} is not one of {SDK_BAUDRATES}")
        if self.pan_id == self.tilt_id:
            raise ValueError("pan_id and tilt_id must differ")
        if not self.pan_min < self.pan_max:
            raise ValueError("pan_min must be < pan_max")
        if not self.tilt_min < self.tilt_max:
            raise ValueError("tilt_min must be < tilt_max")
        return self


class _Fault(Exception):
    """A bus transaction failed after retries (internal; never leaves the adapter)."""

    def __init__(self, message: str, timeout: bool = True) -> None:
        super().__init__(message)
        self.timeout = timeout


class DynamixelHead:
    """:class:`~drivers.interfaces.PanTiltHead` on Dynamixel X-series servos (Protocol 2.0)."""

    def __init__(self, config: HeadConfig | None = None) -> None:
        self.config = config or HeadConfig()
        c = self.config
        self._limits = HeadLimits(c.pan_min, c.pan_max, c.tilt_min, c.tilt_max)
        self._ids = (c.pan_id, c.tilt_id)
        self._names = {c.pan_id: "pan", c.tilt_id: "tilt"}
        self._lock = threading.RLock()
        self._health = HealthTracker(
            ("timeouts", "crc_errors", "retries", "clamped", "hardware_errors", "reboots",
             "torque_restores", "goal_rewrites", "reconnects", "reads", "commands")
        )  # fmt: skip
        self._port: Any = None
        self._ph: Any = None
        self._sync_write: Any = None
        self._sync_read: Any = None
        self._connected = False
        self._next_connect = 0.0
        self._backoff = Backoff(RECONNECT_BACKOFF_MIN, c.reconnect_backoff_max)
        self._goal: dict[int, int] = {}
        self._state = HeadState(stamp=0.0, pan=0.0, tilt=0.0, moving=False, stale=True)
        self._last_read_mono = -1e9
        self._reboot_times: dict[int, deque[float]] = {i: deque() for i in self._ids}
        self._given_up: dict[int, float] = {}  # servo id -> when it was given up (monotonic)
        self._last_incident = -math.inf  # monotonic time of the last incident (INCIDENT_HOLD_S)
        self._last_read_failure = -math.inf  # ... of the last failed read (READ_FAILURE_HOLD_S)
        self._closed = False

    # ---------------------------------------------------------------------------------------
    # lifecycle
    # ---------------------------------------------------------------------------------------
    @property
    def limits(self) -> HeadLimits:
        return self._limits

    def open(self) -> bool:
        """Open the port and set up the servos. Returns False (health FAILED) on failure."""
        with self._lock:
            self._closed = False
            return self._connect()

    def close(self) -> None:
        """Disable torque (best effort) and close the port."""
        with self._lock:
            self._closed = True
            if self._connected:
                for dxl_id in self._ids:
                    try:
                        self._write(dxl_id, XAddr.TORQUE_ENABLE, 1, 0, retries=0)
                    except (*_PORT_ERRORS, _Fault):
                        break
            self._disconnect()

    def __enter__(self) -> DynamixelHead:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def health(self) -> DeviceHealth:
        return self._health.snapshot()

    # ---------------------------------------------------------------------------------------
    # public operations
    # ---------------------------------------------------------------------------------------
    def command(self, pan: float, tilt: float) -> HeadCommand:
        """Send goal angles (radians), clamped to the limits, in one sync write."""
        p, t, clamped = self._limits.clamp(float(pan), float(tilt))
        if clamped:
            self._health.count("clamped")
            log.info("head command (%.3f, %.3f) clamped to (%.3f, %.3f)", pan, tilt, p, t)
        with self._lock:
            self._health.count("commands")
            self._last_read_mono = -1e9  # the next read must show the new motion
            self._goal = {self.config.pan_id: rad_to_tick(p), self.config.tilt_id: rad_to_tick(t)}
            if self._ensure_connected():
                try:
                    self._send_goals()
                except _PORT_ERRORS as exc:
                    self._port_lost(exc)
        return HeadCommand(p, t, clamped)

    def read(self) -> HeadState:
        """Present state by one sync read (rate limited by ``min_read_interval``).

        On a persistent failure the last known state is returned with ``stale=True``.
        """
        with self._lock:
            now = time.monotonic()
            if now - self._last_read_mono < self.config.min_read_interval and not self._state.stale:
                return self._state
            self._last_read_mono = now
            if not self._ensure_connected():
                return self._stale()
            try:
                return self._read_state()
            except _PORT_ERRORS as exc:
                self._port_lost(exc)
                return self._stale()

    def wait_until_still(self, timeout: float, poll: float = 0.02) -> HeadState:
        """Poll (sleeping ``poll`` s between reads) until no servo moves or ``timeout`` s pass."""
        deadline = time.monotonic() + timeout
        while True:
            state = self.read()
            if (not state.moving and not state.stale) or time.monotonic() >= deadline:
                return state
            time.sleep(poll)

    # ---------------------------------------------------------------------------------------
    # connection
    # ---------------------------------------------------------------------------------------
    def _ensure_connected(self) -> bool:
        if self._connected:
            return True
        if self._closed or time.monotonic() < self._next_connect:
            return False
        return self._connect()

    def _connect(self) -> bool:
        c = self.config
        t_start = time.monotonic()
        self._disconnect()
        # The SDK derives every packet timeout from this module-level value (milliseconds).
        _sdk_port_handler.LATENCY_TIMER = c.latency_timer_ms
        try:
            port = dynamixel_sdk.PortHandler(c.port)
            if not port.openPort() or not port.setBaudRate(c.baudrate):
                raise OSError(f"cannot open {c.port} at {c.baudrate} baud")
            # Block in select() for at most poll_interval per read instead of spinning.
            port.ser.timeout = c.poll_interval
            self._port = port
            self._ph = dynamixel_sdk.PacketHandler(2.0)
            self._connected = True
            for dxl_id in self._ids:
                self._setup_servo(dxl_id, initial=True)
            self._sync_write = dynamixel_sdk.GroupSyncWrite(port, self._ph, XAddr.GOAL_POSITION, 4)
            self._sync_read = dynamixel_sdk.GroupSyncRead(port, self._ph, _BLOCK_START, _BLOCK_LEN)
            for dxl_id in self._ids:
                self._sync_read.addParam(dxl_id)
        except (*_PORT_ERRORS, _Fault) as exc:
            self._disconnect()
            delay = self._backoff.failed()
            self._next_connect = time.monotonic() + delay
            self._health.error(f"head on {c.port}: {exc}", HealthState.FAILED)
            log.warning("head: cannot set up %s: %s (retry in %.1f s)", c.port, exc, delay)
            return False
        self._backoff.reset()
        if not self._given_up and self._last_incident < t_start:
            self._health.set_state(HealthState.OK)  # else: as the set-up's incident left it
        log.info("head: connected on %s (ids %s)", c.port, self._ids)
        return True

    def _disconnect(self) -> None:
        if self._port is not None:
            try:
                if self._port.ser is not None:
                    self._port.closePort()
            except _PORT_ERRORS:
                pass
        self._port = None
        self._connected = False
        self._sync_read = self._sync_write = None

    def _port_lost(self, exc: BaseException) -> None:
        self._health.count("reconnects")
        self._health.error(f"head port {self.config.port} lost: {exc}", HealthState.FAILED)
        log.warning("head: port lost (%s); will reopen", exc)
        self._disconnect()
        self._next_connect = time.monotonic() + self._backoff.delay  # hold off d_k, not a failure

    # ---------------------------------------------------------------------------------------
    # servo set-up and recovery
    # ---------------------------------------------------------------------------------------
    def _setup_servo(self, dxl_id: int, initial: bool) -> None:
        """Torque off, limits (EEPROM), profile velocity, goal = present or last goal, torque on."""
        c = self.config
        if dxl_id == c.pan_id:
            lo, hi = rad_to_tick(c.pan_min), rad_to_tick(c.pan_max)
        else:
            lo, hi = rad_to_tick(c.tilt_min), rad_to_tick(c.tilt_max)
        err = self._read(dxl_id, XAddr.HARDWARE_ERROR_STATUS, 1)
        if err and initial:
            self._hardware_error(dxl_id, err)
            return
        self._write(dxl_id, XAddr.TORQUE_ENABLE, 1, 0)
        if self._read(dxl_id, XAddr.MAX_POSITION_LIMIT, 4) != hi:
            self._write(dxl_id, XAddr.MAX_POSITION_LIMIT, 4, hi)
        if self._read(dxl_id, XAddr.MIN_POSITION_LIMIT, 4) != lo:
            self._write(dxl_id, XAddr.MIN_POSITION_LIMIT, 4, lo)
        self._write(
            dxl_id, XAddr.PROFILE_VELOCITY, 4, rad_s_to_profile_velocity(c.profile_velocity)
        )
        present = to_signed32(self._read(dxl_id, XAddr.PRESENT_POSITION, 4))
        goal = self._goal.get(dxl_id, min(max(present, lo), hi))
        self._write(dxl_id, XAddr.GOAL_POSITION, 4, goal)
        self._write(dxl_id, XAddr.TORQUE_ENABLE, 1, 1)
        self._goal.setdefault(dxl_id, goal)

    def _hardware_error(self, dxl_id: int, bits: int) -> None:
        """Reboot a servo that reports a hardware error, then restore it (or give up)."""
        c = self.config
        name = self._names[dxl_id]
        what = f"servo {dxl_id} ({name}) reported hardware error {describe_hardware_error(bits)}"
        now = time.monotonic()
        times = self._reboot_times[dxl_id]
        if dxl_id in self._given_up:
            if not c.auto_reboot or now - self._given_up[dxl_id] < GIVEN_UP_RETRY_S:
                return
            del self._given_up[dxl_id]  # cooled down: a new round of reboots
            times.clear()
        self._health.count("hardware_errors")
        while times and now - times[0] > 60.0:
            times.popleft()
        if not c.auto_reboot or len(times) >= c.max_reboots:
            self._given_up[dxl_id] = now
            msg = f"{what}; not rebooting (auto_reboot={c.auto_reboot}, {len(times)} reboots in 60 s), torque off"
            log.error("head: %s", msg)
            self._health.error(msg, HealthState.FAILED)
            return
        log.warning("head: %s; rebooting it", what)
        self._last_incident = now
        times.append(now)
        self._health.count("reboots")
        result, _ = self._ph.reboot(self._port, dxl_id)
        self._port.is_using = False
        deadline = time.monotonic() + c.boot_wait
        while True:
            time.sleep(0.01)
            _, res, _ = self._ph.ping(self._port, dxl_id)
            self._port.is_using = False
            if res == dynamixel_sdk.COMM_SUCCESS:
                break
            if time.monotonic() > deadline:
                msg = f"{what}; rebooted it but it did not come back within {c.boot_wait} s"
                self._health.error(msg, HealthState.DEGRADED)
                log.error("head: %s", msg)
                return
        try:
            self._setup_servo(dxl_id, initial=False)
        except _Fault as exc:
            self._health.error(f"{what}; rebooted it, restore failed: {exc}")
            return
        self._incident(f"{what}; rebooted it and restored torque")

    def _incident(self, msg: str) -> None:
        """A fault the adapter repaired: logged, the health DEGRADED naming it for
        ``INCIDENT_HOLD_S``."""
        log.warning("head: %s", msg)
        self._last_incident = time.monotonic()
        self._health.error(msg, HealthState.DEGRADED)

    # ---------------------------------------------------------------------------------------
    # transactions (caller holds the lock)
    # ---------------------------------------------------------------------------------------
    def _check(self, result: int, error: int, what: str) -> bool:
        """True on success; counts failures. Status errors other than the alert bit fail."""
        if result == dynamixel_sdk.COMM_SUCCESS and not (error & ~ALERT_BIT):
            return True
        self._port.is_using = False
        if result == dynamixel_sdk.COMM_RX_TIMEOUT:
            self._health.count("timeouts")
        elif result == dynamixel_sdk.COMM_RX_CORRUPT:
            self._health.count("crc_errors")
        log.debug("head: %s failed: %s %s", what, self._ph.getTxRxResult(result),
                  self._ph.getRxPacketError(error) if error else "")  # fmt: skip
        return False

    def _retry_pause(self) -> None:
        self._health.count("retries")
        time.sleep(self.config.poll_interval)  # let stragglers arrive; txPacket clears them
        self._port.clearPort()

    def _read(self, dxl_id: int, addr: int, size: int, retries: int | None = None) -> int:
        n = self.config.retries if retries is None else retries
        for attempt in range(n + 1):
            if attempt:
                self._retry_pause()
            data, result, error = self._ph.readTxRx(self._port, dxl_id, addr, size)
            if self._check(result, error, f"read {addr} of id {dxl_id}"):
                return int.from_bytes(bytes(data[:size]), "little")
        raise _Fault(f"no valid reply from servo {dxl_id} ({self._names.get(dxl_id)}) "
                     f"to a read of address {addr} after {n + 1} tries")  # fmt: skip

    def _write(self, dxl_id: int, addr: int, size: int, value: int,
               retries: int | None = None) -> None:  # fmt: skip
        n = self.config.retries if retries is None else retries
        for attempt in range(n + 1):
            if attempt:
                self._retry_pause()
            result, error = self._ph.writeTxRx(
                self._port, dxl_id, addr, size, list(le(value, size))
            )
            if self._check(result, error, f"write {addr} of id {dxl_id}"):
                return
        raise _Fault(f"servo {dxl_id} ({self._names.get(dxl_id)}) did not accept a write "
                     f"of {value} to address {addr} after {n + 1} tries")  # fmt: skip

    def _send_goals(self) -> None:
        sw = self._sync_write
        for dxl_id, tick in self._goal.items():
            data = list(le(tick, 4))
            if not sw.changeParam(dxl_id, data):
                sw.addParam(dxl_id, data)
        result = sw.txPacket()
        self._port.is_using = False
        if result != dynamixel_sdk.COMM_SUCCESS:
            self._health.error(f"head: sync write failed: {self._ph.getTxRxResult(result)}")

    def _sync_read_block(self) -> dict[int, bytes] | None:
        sr = self._sync_read
        for attempt in range(self.config.retries + 1):
            if attempt:
                self._retry_pause()
            result = sr.txRxPacket()
            if self._check(result, 0, "sync read"):
                return {i: bytes(sr.data_dict[i]) for i in self._ids}
        return None

    def _read_block_each(self) -> tuple[dict[int, bytes], list[str]]:
        """Fallback after a failed sync read: read each servo alone, naming the silent ones."""
        blocks: dict[int, bytes] = {}
        problems: list[str] = []
        for dxl_id in self._ids:
            data, result, error = self._ph.readTxRx(self._port, dxl_id, _BLOCK_START, _BLOCK_LEN)
            if self._check(result, error, f"read of id {dxl_id}"):
                blocks[dxl_id] = bytes(data[:_BLOCK_LEN])
            else:
                kind = "no reply" if result == dynamixel_sdk.COMM_RX_TIMEOUT else "corrupt replies"
                problems.append(f"{kind} from servo {dxl_id} ({self._names[dxl_id]})")
        return blocks, problems

    def _read_state(self) -> HeadState:
        c = self.config
        self._health.count("reads")
        blocks = self._sync_read_block()
        problems: list[str] = []
        if blocks is None:
            blocks, problems = self._read_block_each()
            if problems:
                problems[-1] += f" (sync read failed {c.retries + 1} times)"
        stamp = time.time()

        def field(dxl_id: int, addr: int, size: int) -> int:
            off = addr - _BLOCK_START
            return int.from_bytes(blocks[dxl_id][off : off + size], "little")

        for dxl_id, _ in list(blocks.items()):
            hw = field(dxl_id, XAddr.HARDWARE_ERROR_STATUS, 1)
            if hw:
                try:
                    self._hardware_error(dxl_id, hw)  # rebooted, or still given up
                except _Fault as exc:
                    problems.append(str(exc))
                continue
            self._given_up.pop(dxl_id, None)
            try:
                name = f"servo {dxl_id} ({self._names[dxl_id]})"
                if not field(dxl_id, XAddr.TORQUE_ENABLE, 1):
                    self._health.count("torque_restores")
                    self._setup_servo(dxl_id, initial=False)
                    self._incident(f"{name} had lost torque; set it up again")
                elif (
                    dxl_id in self._goal
                    and to_signed32(field(dxl_id, XAddr.GOAL_POSITION, 4)) != self._goal[dxl_id]
                ):
                    self._health.count("goal_rewrites")
                    self._write(dxl_id, XAddr.GOAL_POSITION, 4, self._goal[dxl_id])
                    self._incident(f"{name} held another goal than the one sent; wrote it again")
            except _Fault as exc:
                problems.append(str(exc))

        prev = self._state
        pan_id, tilt_id = c.pan_id, c.tilt_id
        pan = (tick_to_rad(to_signed32(field(pan_id, XAddr.PRESENT_POSITION, 4)))
               if pan_id in blocks else prev.pan)  # fmt: skip
        tilt = (tick_to_rad(to_signed32(field(tilt_id, XAddr.PRESENT_POSITION, 4)))
                if tilt_id in blocks else prev.tilt)  # fmt: skip
        moving = any(field(i, XAddr.MOVING, 1) for i in blocks) or (len(blocks) < 2 and prev.moving)
        errs = {i: field(i, XAddr.HARDWARE_ERROR_STATUS, 1) for i in blocks}
        state = HeadState(
            stamp=stamp if len(blocks) == 2 else prev.stamp,
            pan=pan,
            tilt=tilt,
            moving=moving,
            pan_error=errs.get(pan_id, prev.pan_error),
            tilt_error=errs.get(tilt_id, prev.tilt_error),
            stale=len(blocks) < 2,
        )
        self._state = state
        now = time.monotonic()
        if problems:
            self._last_read_failure = now
            self._health.error("head: " + "; ".join(problems), HealthState.DEGRADED)
        elif self._given_up:
            self._health.set_state(HealthState.FAILED)
        elif (
            not any(errs.values())
            and now - self._last_incident >= INCIDENT_HOLD_S
            and now - self._last_read_failure >= READ_FAILURE_HOLD_S
        ):
            self._health.set_state(HealthState.OK)
        return state

    def _stale(self) -> HeadState:
        s = self._state
        if not s.stale:
            s = HeadState(s.stamp, s.pan, s.tilt, s.moving, s.pan_error, s.tilt_error, True)
            self._state = s
        return s

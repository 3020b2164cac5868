"""A Dynamixel Protocol 2.0 bus with X-series servos, emulated on a pseudo-terminal.

The head adapter opens :attr:`DynamixelBusEmulator.port` with the real ``dynamixel_sdk`` and
cannot tell it from a USB serial adapter with servos on it. The emulator implements ping,
read, write, sync read, sync write and reboot on the control-table fields the project uses
(``drivers.dynamixel_protocol.XAddr``), with Protocol 2.0 framing, CRC and byte stuffing.

Motion: with torque on, the present position moves towards the goal at the profile velocity
(units of 0.229 rev/min; 0 = the servo's maximum, taken as ``max_velocity_units``) in real
time, computed lazily from the monotonic clock. Goals outside the position limits are
rejected (status error "data limit"), EEPROM writes with torque on are rejected ("access").

Fault injection (thread-safe, switch at any time):

- ``set_no_reply(id, True)``: the servo stays silent (the adapter times out);
- ``corrupt_replies(n)``: the next ``n`` status packets go out with a wrong CRC;
- ``set_corruption_rate(p)``: from now on each status packet goes out with a wrong CRC with
  probability ``p`` (seeded; 0 stops it);
- ``set_hardware_error(id, bits)``: Hardware Error Status bits set, torque off, alert bit in
  every status packet, until the servo is rebooted; with ``persistent=True`` the fault comes
  back after every reboot (the cause persists, e.g. an overload) until
  ``clear_hardware_error(id)``, after which the next reboot clears it for good;
- a reboot makes the servo silent for ``boot_time`` seconds and resets its RAM area;
- ``disconnect()`` / ``reconnect()``: the USB adapter vanishes (the pty is closed, the ``link``
  removed) and comes back on a new pty (the link re-pointed), as the odometry board does.

Run it as its own process with ``python -m drivers.sim.dynamixel_emulator`` (prints the port).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import select
import signal
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

from drivers.dynamixel_protocol import (
    ALERT_BIT,
    BROADCAST_ID,
    CENTER_TICK,
    CONTROL_TABLE_SIZE,
    EEPROM_END,
    PROFILE_VELOCITY_UNIT_RPM,
    TICKS_PER_REV,
    X_SERIES_MODEL,
    CorruptPacket,
    Inst,
    Packet,
    PacketParser,
    StatusError,
    XAddr,
    encode_status,
    le,
    to_signed32,
)
from drivers.sim.pty import PseudoTerminal

_SIZES = {
    XAddr.MODEL_NUMBER: 2,
    XAddr.MAX_POSITION_LIMIT: 4,
    XAddr.MIN_POSITION_LIMIT: 4,
    XAddr.PROFILE_ACCELERATION: 4,
    XAddr.PROFILE_VELOCITY: 4,
    XAddr.GOAL_POSITION: 4,
    XAddr.REALTIME_TICK: 2,
    XAddr.PRESENT_VELOCITY: 4,
    XAddr.PRESENT_POSITION: 4,
}


@dataclass
class EmulatedServo:
    """One X-series servo: a 256-byte control table plus a motion state."""

    dxl_id: int
    position: float = float(CENTER_TICK)  # ticks, continuous
    max_velocity_units: int = 265  # used when Profile Velocity is 0
    table: bytearray = field(default_factory=lambda: bytearray(CONTROL_TABLE_SIZE))
    last_update: float = field(default_factory=time.monotonic)
    silent_until: float = 0.0
    no_reply: bool = False
    persistent_error: int = 0  # Hardware Error Status bits raised again after every reboot

    def __post_init__(self) -> None:
        t = self.table
        t[XAddr.MODEL_NUMBER : XAddr.MODEL_NUMBER + 2] = le(X_SERIES_MODEL, 2)
        t[XAddr.FIRMWARE_VERSION] = 45
        t[XAddr.ID] = self.dxl_id
        t[XAddr.BAUD_RATE] = 3  # 1 Mbps
        t[XAddr.RETURN_DELAY_TIME] = 0
        t[XAddr.OPERATING_MODE] = 3  # position control
        self.set(XAddr.MAX_POSITION_LIMIT, 4095)
        self.set(XAddr.MIN_POSITION_LIMIT, 0)
        t[XAddr.STATUS_RETURN_LEVEL] = 2
        self.reset_ram()

    # table access --------------------------------------------------------------------------
    def get(self, addr: int, size: int | None = None) -> int:
        """Unsigned little-endian value of the field at ``addr`` (``size`` bytes; default: the
        field's size in the X-series table, else 1)."""
        size = size or _SIZES.get(XAddr(addr), 1)
        return int.from_bytes(self.table[addr : addr + size], "little")

    def set(self, addr: int, value: int, size: int | None = None) -> None:
        """Write ``value`` little-endian into the field at ``addr`` (size as in :meth:`get`)."""
        size = size or _SIZES.get(XAddr(addr), 1)
        self.table[addr : addr + size] = le(value, size)

    def reset_ram(self) -> None:
        """Power-on state of the RAM area (after a reboot)."""
        self.table[EEPROM_END:] = bytes(CONTROL_TABLE_SIZE - EEPROM_END)
        self.table[XAddr.STATUS_RETURN_LEVEL] = 2
        self.set(XAddr.GOAL_POSITION, int(round(self.position)))
        self.last_update = time.monotonic()
        self._refresh_present(0.0)

    # motion ----------------------------------------------------------------------------------
    def velocity_ticks_s(self) -> float:
        """Profile velocity in ticks/s: units x 0.229 rev/min (0 = max_velocity_units)."""
        units = self.get(XAddr.PROFILE_VELOCITY) or self.max_velocity_units
        return units * PROFILE_VELOCITY_UNIT_RPM / 60.0 * TICKS_PER_REV

    def advance(self, now: float) -> None:
        """Move the present position towards the goal for the time since the last call (torque
        on: at most velocity_ticks_s() dt, landing exactly on the goal), then refresh the
        present-value fields. A clock that goes backwards moves nothing.
        """
        dt = max(0.0, now - self.last_update)
        self.last_update = now
        velocity = 0.0
        if self.table[XAddr.TORQUE_ENABLE]:
            goal = to_signed32(self.get(XAddr.GOAL_POSITION))
            step = self.velocity_ticks_s() * dt
            err = goal - self.position
            if abs(err) <= step:
                self.position = float(goal)
            else:
                self.position += math.copysign(step, err)
                velocity = math.copysign(self.velocity_ticks_s(), err)
        self._refresh_present(velocity)

    def _refresh_present(self, velocity_ticks_s: float) -> None:
        pos = int(round(self.position))
        self.set(XAddr.PRESENT_POSITION, pos)
        goal = to_signed32(self.get(XAddr.GOAL_POSITION))
        moving = 1 if (self.table[XAddr.TORQUE_ENABLE] and pos != goal) else 0
        self.table[XAddr.MOVING] = moving
        self.table[XAddr.MOVING_STATUS] = 0 if moving else 1  # bit 0: in position
        vel_units = int(round(velocity_ticks_s / TICKS_PER_REV * 60.0 / PROFILE_VELOCITY_UNIT_RPM))
        self.set(XAddr.PRESENT_VELOCITY, vel_units)
        self.set(XAddr.REALTIME_TICK, int(time.monotonic() * 1000) % 32768)
        self.table[XAddr.PRESENT_TEMPERATURE] = 35

    @property
    def alert(self) -> int:
        """The alert bit of the status packet's error byte while a hardware error is set, else 0."""
        return ALERT_BIT if self.table[XAddr.HARDWARE_ERROR_STATUS] else 0


class DynamixelBusEmulator:
    """Servos on an emulated Protocol 2.0 bus behind a pseudo-terminal, served by a thread."""

    def __init__(
        self,
        ids: tuple[int, ...] = (1, 2),
        *,
        boot_time: float = 0.05,
        link: str | None = None,
        seed: int = 0,
    ) -> None:
        self.servos: dict[int, EmulatedServo] = {i: EmulatedServo(i) for i in ids}
        self.boot_time = boot_time
        self._pty = PseudoTerminal(link)
        self._lock = threading.RLock()
        self._parser = PacketParser()
        self._corrupt_budget = 0
        self._corrupt_rate = 0.0
        self._rng = random.Random(seed)
        self._thread: threading.Thread | None = None
        self._stop_r, self._stop_w = -1, -1
        self.instructions: Counter[str] = Counter()  # what the adapter sent, by name
        self.crc_errors_received = 0
        self.wire_log: list[bytes] | None = None  # set to [] to record incoming packets

    # lifecycle ---------------------------------------------------------------------------------
    @property
    def port(self) -> str:
        """Path for ``PortHandler(port)``."""
        return self._pty.path

    def start(self) -> DynamixelBusEmulator:
        """Open the pty and start the serving thread; returns self."""
        self._pty.open()
        self._stop_r, self._stop_w = os.pipe()
        self._thread = threading.Thread(target=self._serve, name="dxl-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the serving thread (waiting up to 2 s for it) and close the pty."""
        if self._thread is not None:
            os.write(self._stop_w, b"x")
            self._thread.join(timeout=2.0)
            self._thread = None
            os.close(self._stop_r)
            os.close(self._stop_w)
        self._pty.close()

    def __enter__(self) -> DynamixelBusEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # fault injection -------------------------------------------------------------------------
    def set_no_reply(self, dxl_id: int, silent: bool = True) -> None:
        """Make servo dxl_id silent (no status packets) or answer again."""
        with self._lock:
            self.servos[dxl_id].no_reply = silent

    def corrupt_replies(self, n: int) -> None:
        """Send the next ``n`` status packets with a wrong CRC."""
        with self._lock:
            self._corrupt_budget = n

    def set_corruption_rate(self, p: float) -> None:
        """Send each status packet with a wrong CRC with probability ``p`` (0 <= p <= 1) from
        now on; 0 stops it (a ``corrupt_replies`` budget is spent first either way)."""
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"corruption rate must be in [0, 1], got {p}")
        with self._lock:
            self._corrupt_rate = float(p)

    def set_hardware_error(self, dxl_id: int, bits: int, persistent: bool = False) -> None:
        """Raise Hardware Error Status bits (torque goes off) until the servo is rebooted; with
        ``persistent`` they are raised again after every reboot until :meth:`clear_hardware_error`."""
        with self._lock:
            s = self.servos[dxl_id]
            s.advance(time.monotonic())
            s.table[XAddr.HARDWARE_ERROR_STATUS] |= bits & 0xFF
            s.table[XAddr.TORQUE_ENABLE] = 0
            if persistent:
                s.persistent_error |= bits & 0xFF

    def clear_hardware_error(self, dxl_id: int) -> None:
        """End a persistent hardware error: the bits set now stay until the next reboot (as on the
        real servo, only a reboot clears Hardware Error Status)."""
        with self._lock:
            self.servos[dxl_id].persistent_error = 0

    def disconnect(self) -> None:
        """The bus adapter vanishes (USB unplugged): the pty is closed, the link removed."""
        with self._lock:
            self._pty.close()
            self._parser = PacketParser()

    def reconnect(self) -> str:
        """The adapter comes back on a new pty (the link re-pointed); returns the slave path."""
        with self._lock:
            return self._pty.open()

    @property
    def connected(self) -> bool:
        return self._pty.is_open

    @property
    def corruption_rate(self) -> float:
        """The probability of a wrong CRC set by :meth:`set_corruption_rate`."""
        return self._corrupt_rate

    # inspection --------------------------------------------------------------------------------
    def position_rad(self, dxl_id: int) -> float:
        """Present position of servo ``dxl_id`` in radians, (position - CENTER_TICK) 2 pi /
        TICKS_PER_REV (motion advanced first)."""
        with self._lock:
            s = self.servos[dxl_id]
            s.advance(time.monotonic())
            return (s.position - CENTER_TICK) * 2.0 * math.pi / TICKS_PER_REV

    def register(self, dxl_id: int, addr: XAddr) -> int:
        """Current value of the control-table field addr of servo dxl_id (motion advanced first)."""
        with self._lock:
            s = self.servos[dxl_id]
            s.advance(time.monotonic())
            return s.get(addr)

    # serving -----------------------------------------------------------------------------------
    def _serve(self) -> None:
        while True:
            fd = self._pty.master_fd  # None while disconnected; a new one after reconnect
            try:
                ready, _, _ = select.select([self._stop_r] + ([fd] if fd is not None else []), [], [],
                                            1.0 if fd is not None else 0.05)
            except (OSError, ValueError):  # closed by disconnect() during the select
                continue
            if self._stop_r in ready:
                return
            if fd is None or fd not in ready:
                continue
            with self._lock:
                data = self._pty.read(4096) if self._pty.master_fd == fd else b""
            if not data:
                continue
            if self.wire_log is not None:
                self.wire_log.append(data)
            for item in self._parser.feed(data):
                if isinstance(item, CorruptPacket):
                    self.crc_errors_received += 1
                    continue
                with self._lock:
                    replies = self._handle(item)
                for reply in replies:
                    self._pty.write(reply)

    def _status(self, servo: EmulatedServo, error: int = 0, params: bytes = b"") -> bytes | None:
        now = time.monotonic()
        if servo.no_reply or now < servo.silent_until:
            return None
        wire = encode_status(servo.dxl_id, error | servo.alert, params)
        if self._corrupt_budget > 0:
            self._corrupt_budget -= 1
            wire = wire[:-2] + bytes((wire[-2] ^ 0xFF, wire[-1]))
        elif self._corrupt_rate > 0.0 and self._rng.random() < self._corrupt_rate:
            wire = wire[:-2] + bytes((wire[-2] ^ 0xFF, wire[-1]))
        return wire

    def _handle(self, pkt: Packet) -> list[bytes]:
        if pkt.is_status:
            return []
        try:
            name = Inst(pkt.instruction).name
        except ValueError:
            name = f"0x{pkt.instruction:02x}"
        self.instructions[name] += 1
        now = time.monotonic()
        for s in self.servos.values():
            s.advance(now)
        p = pkt.params
        out: list[bytes | None] = []
        if pkt.instruction == Inst.SYNC_WRITE:
            if len(p) >= 4:
                addr, size = p[0] | p[1] << 8, p[2] | p[3] << 8
                for k in range(4, len(p) - size, size + 1):
                    s = self.servos.get(p[k])
                    if s is not None and not s.no_reply and now >= s.silent_until:
                        self._write(s, addr, p[k + 1 : k + 1 + size])
            return []
        if pkt.instruction == Inst.SYNC_READ:
            if len(p) >= 4:
                addr, size = p[0] | p[1] << 8, p[2] | p[3] << 8
                for dxl_id in p[4:]:
                    s = self.servos.get(dxl_id)
                    if s is not None:
                        out.append(self._status(s, 0, bytes(s.table[addr : addr + size])))
            return [r for r in out if r is not None]
        targets = (
            list(self.servos.values())
            if pkt.id == BROADCAST_ID
            else [self.servos[pkt.id]]
            if pkt.id in self.servos
            else []
        )
        for s in targets:
            if now < s.silent_until:
                continue
            reply = self._single(s, pkt)
            if pkt.id != BROADCAST_ID or pkt.instruction == Inst.PING:
                out.append(reply)
        return [r for r in out if r is not None]

    def _single(self, s: EmulatedServo, pkt: Packet) -> bytes | None:
        p = pkt.params
        inst = pkt.instruction
        if inst == Inst.PING:
            return self._status(s, 0, bytes(s.table[0:2]) + bytes((s.table[6],)))
        if inst == Inst.READ:
            if len(p) != 4:
                return self._status(s, StatusError.DATA_LENGTH)
            addr, size = p[0] | p[1] << 8, p[2] | p[3] << 8
            if addr + size > CONTROL_TABLE_SIZE:
                return self._status(s, StatusError.DATA_RANGE)
            return self._status(s, 0, bytes(s.table[addr : addr + size]))
        if inst == Inst.WRITE:
            if len(p) < 3:
                return self._status(s, StatusError.DATA_LENGTH)
            err = self._write(s, p[0] | p[1] << 8, p[2:])
            return self._status(s, err)
        if inst == Inst.REBOOT:
            reply = self._status(s, 0)
            if not s.no_reply:
                s.reset_ram()  # Hardware Error Status is in RAM: cleared, unless the cause persists
                s.table[XAddr.HARDWARE_ERROR_STATUS] = s.persistent_error
                s.silent_until = time.monotonic() + self.boot_time
            return reply
        return self._status(s, StatusError.INSTRUCTION)

    def _write(self, s: EmulatedServo, addr: int, data: bytes) -> int:
        """Apply a write; returns the status error number (0 = ok)."""
        if addr + len(data) > CONTROL_TABLE_SIZE:
            return StatusError.DATA_RANGE
        if addr < EEPROM_END and s.table[XAddr.TORQUE_ENABLE]:
            return StatusError.ACCESS
        if addr <= XAddr.HARDWARE_ERROR_STATUS < addr + len(data) or (
            addr < XAddr.PRESENT_POSITION + 4 and addr + len(data) > XAddr.REALTIME_TICK
        ):
            return StatusError.ACCESS  # read-only fields
        if addr <= XAddr.GOAL_POSITION and addr + len(data) >= XAddr.GOAL_POSITION + 4:
            k = XAddr.GOAL_POSITION - addr
            goal = to_signed32(int.from_bytes(data[k : k + 4], "little"))
            lo = to_signed32(s.get(XAddr.MIN_POSITION_LIMIT))
            hi = to_signed32(s.get(XAddr.MAX_POSITION_LIMIT))
            if not lo <= goal <= hi:
                return StatusError.DATA_LIMIT
        if (
            addr <= XAddr.TORQUE_ENABLE < addr + len(data)
            and data[XAddr.TORQUE_ENABLE - addr]
            and s.table[XAddr.HARDWARE_ERROR_STATUS]
        ):
            return StatusError.RESULT_FAIL  # torque stays off until reboot
        s.table[addr : addr + len(data)] = data
        s.last_update = time.monotonic()
        s.advance(s.last_update)
        return 0


def main(argv: list[str] | None = None) -> int:
    """Run the emulator as its own process until SIGINT/SIGTERM; prints {"port": ...}."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ids", default="1,2", help="servo ids, comma separated")
    ap.add_argument("--link", default=None, help="stable symlink to create for the port")
    args = ap.parse_args(argv)
    emu = DynamixelBusEmulator(tuple(int(x) for x in args.ids.split(",")), link=args.link)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    with emu:
        print(json.dumps({"port": emu.port}), flush=True)
        done.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

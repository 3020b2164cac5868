"""Dynamixel Protocol 2.0 on the byte level: CRC-16, byte stuffing, packets, X-series table.

Shared by the bus emulator (``drivers.sim.dynamixel_emulator``) and the tests; the head
adapter itself talks through the real ``dynamixel_sdk``.

Packet layout (ROBOTIS e-Manual, "Protocol 2.0")::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAM ... | CRC_L CRC_H

``LEN`` counts INST + (stuffed) parameters + CRC. Status packets use INST = 0x55 and carry
an ERROR byte before their parameters. The CRC is CRC-16 with polynomial 0x8005, initial
value 0, no reflection, no final XOR, computed over every byte from the header up to the
last (stuffed) parameter. Byte stuffing: whenever ``FF FF FD`` appears in INST+PARAM, an
extra ``FD`` is inserted after it, so the header pattern never appears inside a packet.

Usage::

    from drivers.dynamixel_protocol import encode_instruction, PacketParser, Inst
    wire = encode_instruction(1, Inst.PING)          # FF FF FD 00 01 03 00 01 19 4E
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

HEADER = b"\xff\xff\xfd"
HEADER_RESERVED = HEADER + b"\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC
MAX_PACKET_LENGTH = 1024  # LEN field larger than this is treated as garbage


class Inst(enum.IntEnum):
    """Instruction codes used here."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    BULK_READ = 0x92
    BULK_WRITE = 0x93


class StatusError(enum.IntEnum):
    """Error numbers in bits 0-6 of a status packet's ERROR byte (bit 7 = hardware alert)."""

    NONE = 0
    RESULT_FAIL = 1
    INSTRUCTION = 2
    CRC = 3
    DATA_RANGE = 4
    DATA_LENGTH = 5
    DATA_LIMIT = 6
    ACCESS = 7


ALERT_BIT = 0x80


class HardwareError(enum.IntFlag):
    """X-series Hardware Error Status (address 70) bits."""

    INPUT_VOLTAGE = 0x01
    OVERHEATING = 0x04
    MOTOR_ENCODER = 0x08
    ELECTRICAL_SHOCK = 0x10
    OVERLOAD = 0x20


def describe_hardware_error(bits: int) -> str:
    """'overheating|overload' style text for a Hardware Error Status value."""
    names = [f.name.lower() for f in HardwareError if bits & f.value and f.name]
    return "|".join(names) if names else f"0x{bits:02x}"


class XAddr(enum.IntEnum):
    """X-series (XM/XH/XL-430 style) control table addresses used by the project."""

    MODEL_NUMBER = 0  # 2 bytes, EEPROM
    FIRMWARE_VERSION = 6  # 1
    ID = 7  # 1
    BAUD_RATE = 8  # 1
    RETURN_DELAY_TIME = 9  # 1
    OPERATING_MODE = 11  # 1
    MAX_POSITION_LIMIT = 48  # 4, EEPROM
    MIN_POSITION_LIMIT = 52  # 4, EEPROM
    TORQUE_ENABLE = 64  # 1, RAM (EEPROM area is locked while 1)
    LED = 65  # 1
    STATUS_RETURN_LEVEL = 68  # 1
    HARDWARE_ERROR_STATUS = 70  # 1, read only
    PROFILE_ACCELERATION = 108  # 4
    PROFILE_VELOCITY = 112  # 4, unit 0.229 rev/min, 0 = maximum
    GOAL_POSITION = 116  # 4
    REALTIME_TICK = 120  # 2
    MOVING = 122  # 1
    MOVING_STATUS = 123  # 1
    PRESENT_VELOCITY = 128  # 4
    PRESENT_POSITION = 132  # 4
    PRESENT_TEMPERATURE = 146  # 1


EEPROM_END = 64  # addresses below are EEPROM: writable only with torque disabled
CONTROL_TABLE_SIZE = 256
TICKS_PER_REV = 4096
CENTER_TICK = 2048
PROFILE_VELOCITY_UNIT_RPM = 0.229
X_SERIES_MODEL = 1020  # XM430-W350


def rad_to_tick(angle: float) -> int:
    """Radians -> position ticks (4096 per revolution, 2048 = 0 rad), rounded."""
    return int(round(CENTER_TICK + angle * TICKS_PER_REV / (2.0 * math.pi)))


def tick_to_rad(tick: int) -> float:
    """Position ticks -> radians (2048 = 0 rad)."""
    return (tick - CENTER_TICK) * 2.0 * math.pi / TICKS_PER_REV


def rad_s_to_profile_velocity(rad_s: float) -> int:
    """Angular speed (rad/s) -> Profile Velocity units (0.229 rev/min), at least 1."""
    rpm = rad_s * 60.0 / (2.0 * math.pi)
    return max(1, int(round(rpm / PROFILE_VELOCITY_UNIT_RPM)))


def profile_velocity_to_rad_s(units: int) -> float:
    """Profile Velocity units -> rad/s (0 means 'maximum' on a real servo: returns inf)."""
    if units <= 0:
        return math.inf
    return units * PROFILE_VELOCITY_UNIT_RPM * 2.0 * math.pi / 60.0


def to_signed32(value: int) -> int:
    value &= 0xFFFFFFFF
    return value - (1 << 32) if value & 0x80000000 else value


# --------------------------------------------------------------------------------------------
# CRC-16 (poly 0x8005, init 0, MSB first)
# --------------------------------------------------------------------------------------------


def _make_crc_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x8005) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16 of Protocol 2.0 (polynomial 0x8005, initial value 0)."""
    table = _CRC_TABLE
    for b in data:
        crc = ((crc << 8) ^ table[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


# --------------------------------------------------------------------------------------------
# Byte stuffing
# --------------------------------------------------------------------------------------------


def stuff(body: bytes | bytearray) -> bytes:
    """Insert FD after every FF FF FD in ``body`` (INST + parameters)."""
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes | bytearray) -> bytes:
    """Inverse of :func:`stuff`: drop the FD that follows every FF FF FD."""
    out = bytearray()
    i = 0
    n = len(body)
    while i < n:
        b = body[i]
        out.append(b)
        i += 1
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF:
            if i < n and body[i] == 0xFD:
                i += 1
    return bytes(out)


# --------------------------------------------------------------------------------------------
# Encoding
# --------------------------------------------------------------------------------------------


def _frame(dxl_id: int, body: bytes) -> bytes:
    stuffed = stuff(body)
    length = len(stuffed) + 2
    head = HEADER_RESERVED + bytes((dxl_id & 0xFF, length & 0xFF, (length >> 8) & 0xFF))
    packet = head + stuffed
    crc = crc16(packet)
    return packet + bytes((crc & 0xFF, crc >> 8))


def encode_instruction(dxl_id: int, inst: int, params: bytes | bytearray = b"") -> bytes:
    """Wire bytes of an instruction packet (stuffed, with CRC)."""
    return _frame(dxl_id, bytes((inst,)) + bytes(params))


def encode_status(dxl_id: int, error: int = 0, params: bytes | bytearray = b"") -> bytes:
    """Wire bytes of a status packet (INST 0x55, ERROR byte, parameters)."""
    return _frame(dxl_id, bytes((Inst.STATUS, error & 0xFF)) + bytes(params))


def le(value: int, size: int) -> bytes:
    """Little-endian bytes of an unsigned (or two's-complement) value."""
    return (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def read_params(address: int, length: int) -> bytes:
    return le(address, 2) + le(length, 2)


def write_params(address: int, data: bytes) -> bytes:
    return le(address, 2) + bytes(data)


def sync_read_params(address: int, length: int, ids: list[int]) -> bytes:
    return le(address, 2) + le(length, 2) + bytes(ids)


def sync_write_params(address: int, length: int, data: dict[int, bytes]) -> bytes:
    out = bytearray(le(address, 2) + le(length, 2))
    for dxl_id, d in data.items():
        if len(d) != length:
            raise ValueError(f"sync write data for id {dxl_id} has {len(d)} bytes, not {length}")
        out.append(dxl_id)
        out += d
    return bytes(out)


# --------------------------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Packet:
    """A decoded packet. For status packets ``error`` is the ERROR byte and ``params`` excludes
    it; for instruction packets ``error`` is None."""

    id: int
    instruction: int
    params: bytes
    error: int | None = None

    @property
    def is_status(self) -> bool:
        return self.instruction == Inst.STATUS


@dataclass(frozen=True)
class CorruptPacket:
    """A framed packet whose CRC did not match (its bytes are dropped)."""

    raw: bytes


class PacketParser:
    """Incremental parser: feed bytes, get packets (and CorruptPacket events) back.

    Bytes before a header are skipped (counted in ``skipped_bytes``); a packet whose length is
    implausible is treated as garbage one byte at a time.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.skipped_bytes = 0

    def feed(self, data: bytes | bytearray) -> list[Packet | CorruptPacket]:
        self._buf += data
        out: list[Packet | CorruptPacket] = []
        buf = self._buf
        while True:
            start = buf.find(HEADER_RESERVED)
            if start < 0:
                # keep a possible partial header at the end
                keep = 0
                for k in (3, 2, 1):
                    if len(buf) >= k and HEADER_RESERVED.startswith(bytes(buf[-k:])):
                        keep = k
                        break
                self.skipped_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                break
            if start:
                self.skipped_bytes += start
                del buf[:start]
            if len(buf) < 7:
                break
            length = buf[5] | (buf[6] << 8)
            if length < 3 or length > MAX_PACKET_LENGTH:
                self.skipped_bytes += 1
                del buf[:1]
                continue
            total = 7 + length
            if len(buf) < total:
                break
            raw = bytes(buf[:total])
            crc = raw[-2] | (raw[-1] << 8)
            if crc16(raw[:-2]) != crc:
                out.append(CorruptPacket(raw))
                del buf[:total]
                continue
            del buf[:total]
            body = unstuff(raw[7:-2])
            inst = body[0]
            if inst == Inst.STATUS:
                if len(body) < 2:
                    out.append(CorruptPacket(raw))
                    continue
                out.append(Packet(raw[4], inst, bytes(body[2:]), body[1]))
            else:
                out.append(Packet(raw[4], inst, bytes(body[1:])))
        return out


def decode(data: bytes) -> Packet:
    """Decode exactly one packet (raises ValueError on anything else)."""
    parser = PacketParser()
    items = parser.feed(data)
    if len(items) != 1 or not isinstance(items[0], Packet) or parser.skipped_bytes:
        raise ValueError(f"not exactly one valid packet: {data.hex(' ')}")
    return items[0]

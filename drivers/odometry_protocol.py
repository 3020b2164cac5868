"""The odometry board's line protocol (docs/protocols.md) and differential-drive kinematics.

One ASCII line per encoder sample (50 Hz)::

    $ODO,<seq>,<t_ms>,<left_ticks>,<right_ticks>*<crc8>\\r\\n

All four numbers are unsigned 32-bit decimals that wrap modulo 2^32; ``crc8`` is two upper-case
hex digits of CRC-8/SMBUS (polynomial 0x07, initial value 0, no reflection, no final XOR) over
every byte between ``$`` and ``*`` (both excluded). Extra comma-separated fields after
``right_ticks`` are allowed and ignored (forward compatibility).

Kinematics (exact for constant wheel speeds during a sample interval, i.e. a circular arc)::

    dl, dr   = 2 pi r * d(ticks) / N            wheel travel (m)
    ds       = (dl + dr) / 2,  dtheta = (dr - dl) / b
    dx       = ds * sin(dtheta) / dtheta
    dy       = ds * (1 - cos(dtheta)) / dtheta = ds * 2 sin^2(dtheta/2) / dtheta

in the base frame at the start of the interval (x forward, y left, theta CCW, REP-103), with a
Taylor series below |dtheta| = 1e-6; this is the odometry increment u_t consumed by the
filter's motion model.

The counters are absolute: they count from the board's power-up and outlive the daemon, so
:func:`wheel_travel` tells how far each wheel went between two readings
(:class:`drivers.interfaces.BoardCounters`) taken by two runs of the daemon, unless the board
restarted in between. The protocol has no boot id; a restart shows as the board's clock
disagreeing with the host's over the same interval (it went back, or it advanced by more
than :data:`CLOCK_TOLERANCE_S` plus :data:`CLOCK_TOLERANCE_FRACTION` of the interval more
or less than the host's).

Usage::

    from drivers.odometry_protocol import format_line, parse_line, arc_increment
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from drivers.interfaces import BoardCounters

TALKER = b"ODO"
U32 = 1 << 32
MAX_LINE = 128  # longer runs without a newline are garbage


def _make_table() -> bytes:
    table = bytearray(256)
    for i in range(256):
        c = i
        for _ in range(8):
            c = ((c << 1) ^ 0x07) if c & 0x80 else (c << 1)
        table[i] = c & 0xFF
    return bytes(table)


_CRC8_TABLE = _make_table()


def crc8(data: bytes | bytearray) -> int:
    """CRC-8/SMBUS (poly 0x07, init 0, no reflection, no xorout). crc8(b"123456789") == 0xF4."""
    crc = 0
    table = _CRC8_TABLE
    for b in data:
        crc = table[crc ^ b]
    return crc


@dataclass(frozen=True)
class OdometrySample:
    """One parsed line: raw board values (unsigned 32-bit)."""

    seq: int
    t_ms: int
    left: int
    right: int


class LineError(ValueError):
    """A line that is not a valid ``$ODO`` sentence (``reason`` in a few words)."""

    def __init__(self, reason: str, line: bytes) -> None:
        super().__init__(f"{reason}: {line[:80]!r}")
        self.reason = reason


def format_line(seq: int, t_ms: int, left: int, right: int) -> bytes:
    """The wire bytes of one sample (values are reduced modulo 2^32)."""
    body = b"ODO,%d,%d,%d,%d" % (seq % U32, t_ms % U32, left % U32, right % U32)
    return b"$%s*%02X\r\n" % (body, crc8(body))


def parse_line(line: bytes | bytearray) -> OdometrySample:
    """Parse one line (with or without the trailing CR/LF). Raises :class:`LineError`."""
    raw = bytes(line).rstrip(b"\r\n")
    if not raw.startswith(b"$"):
        raise LineError("no '$' at the start", raw)
    star = raw.rfind(b"*")
    if star < 0 or len(raw) - star != 3:
        raise LineError("no '*hh' checksum", raw)
    body = raw[1:star]
    try:
        expected = int(raw[star + 1 :], 16)
    except ValueError:
        raise LineError("bad checksum digits", raw) from None
    if crc8(body) != expected:
        raise LineError("checksum mismatch", raw)
    fields = body.split(b",")
    if fields[0] != TALKER:
        raise LineError("unknown sentence", raw)
    if len(fields) < 5:
        raise LineError("too few fields", raw)
    try:
        values = [int(f) for f in fields[1:5]]
    except ValueError:
        raise LineError("non-numeric field", raw) from None
    if any(v < 0 or v >= U32 for v in values) or any(not f.isdigit() for f in fields[1:5]):
        raise LineError("field out of range", raw)
    return OdometrySample(*values)


def wrap_delta(new: int, old: int) -> int:
    """Signed difference of two unsigned 32-bit counters (valid for |delta| < 2^31)."""
    d = (new - old) % U32
    return d - U32 if d >= U32 // 2 else d


#: s: how far the board's clock may disagree with the host's over an interval (serial latency
#: of the two samples' stamps, clock steps) before :func:`wheel_travel` takes it for a board
#: restart; plus :data:`CLOCK_TOLERANCE_FRACTION` of the interval (crystal drift, 1 %).
CLOCK_TOLERANCE_S = 2.0
CLOCK_TOLERANCE_FRACTION = 0.01


def wheel_travel(then: BoardCounters, now: BoardCounters) -> tuple[float, float] | str:
    """The net travel (m) of the left and right wheels from ``then`` to ``now``, by the
    signed 32-bit differences of the counts (:func:`wrap_delta`) times ``now``'s metres per
    tick; or, when the readings cannot be of one board run, why (in a few words): the
    board's clock went back, or it advanced by more than ``CLOCK_TOLERANCE_S +
    CLOCK_TOLERANCE_FRACTION * host`` more or less than the host clock did (``host`` = the
    stamps' difference). Net travel: a motion whose wheel travels cancel (forward, then back
    the same way) counts as none."""
    host = now.stamp - then.stamp
    board = wrap_delta(now.board_ms, then.board_ms) / 1000.0
    if host < -CLOCK_TOLERANCE_S:
        return f"the readings are out of order (host clock {host:.1f} s)"
    if board < 0.0:
        return f"the board's clock went back {-board:.1f} s: the board restarted"
    if abs(board - host) > CLOCK_TOLERANCE_S + CLOCK_TOLERANCE_FRACTION * abs(host):
        return (f"the board's clock advanced {board:.1f} s while the host's advanced "
                f"{host:.1f} s: the board restarted")  # fmt: skip
    return (wrap_delta(now.left, then.left) * now.left_m_per_tick,
            wrap_delta(now.right, then.right) * now.right_m_per_tick)  # fmt: skip


def arc_increment(d_left: ArrayLike, d_right: ArrayLike, track_width: float) -> NDArray[np.float64]:
    """(dx, dy, dtheta) of a differential drive whose wheels travelled d_left, d_right metres
    at constant speeds (exact circular arc). Vectorized over leading axes -> shape (..., 3)."""
    dl = np.asarray(d_left, dtype=np.float64)
    dr = np.asarray(d_right, dtype=np.float64)
    ds = 0.5 * (dl + dr)
    dth = (dr - dl) / track_width
    small = np.abs(dth) < 1e-6
    safe = np.where(small, 1.0, dth)
    th2 = dth * dth
    sx = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)
    # (1 - cos x) / x written as 2 sin^2(x/2) / x: no cancellation at small angles
    sy = np.where(small, dth / 2.0 - dth * th2 / 24.0, 2.0 * np.sin(0.5 * safe) ** 2 / safe)
    return np.stack(np.broadcast_arrays(ds * sx, ds * sy, dth), axis=-1)


def arc_step(d_left: float, d_right: float, track_width: float) -> tuple[float, float, float]:
    """Scalar :func:`arc_increment` on plain floats (the reader thread's per-line path)."""
    ds = 0.5 * (d_left + d_right)
    dth = (d_right - d_left) / track_width
    if abs(dth) < 1e-6:
        th2 = dth * dth
        return ds * (1.0 - th2 / 6.0), ds * (dth / 2.0 - dth * th2 / 24.0), dth
    return ds * math.sin(dth) / dth, ds * 2.0 * math.sin(0.5 * dth) ** 2 / dth, dth


def ticks_to_metres(ticks: ArrayLike, wheel_radius: float, ticks_per_rev: float) -> NDArray:
    """Wheel travel for encoder ticks: 2 pi r ticks / N."""
    return np.asarray(ticks, dtype=np.float64) * (2.0 * math.pi * wheel_radius / ticks_per_rev)

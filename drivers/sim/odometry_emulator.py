"""The base's odometry board, emulated on a pseudo-terminal.

Streams ``$ODO`` lines (``drivers.odometry_protocol``) at ``rate_hz`` from encoder counters
driven by wheel speeds that the caller sets (m/s or ticks/s), in real time, from a thread. The
counters are unsigned 32-bit and wrap; ``set_counters`` starts them anywhere (e.g. just below
2^32 to exercise the wrap), ``reboot`` restarts them, the sequence and the clock from 0 as
a board restart does.

Fault injection (thread-safe):
- ``inject_garbage(n)``: n random bytes before the next line;
- ``drop_lines(n)``: the next n lines are not sent (sequence numbers still advance);
- ``corrupt_lines(n)``: the next n lines have a digit changed after the checksum was computed;
- ``split_lines(n)``: the next n lines are written in two pieces ``split_delay`` s apart;
- ``set_fault_rate(kind, p, garbage_bytes=16)``: from now on each line gets the fault ``kind``
  (``"garbage"``, ``"drop"``, ``"corrupt"``, ``"split"``) with probability ``p`` (seeded; 0
  stops it), ``garbage_bytes`` random bytes for garbage;
- ``disconnect()`` / ``reconnect()``: close the pty (the adapter's port vanishes) and open a new
  one; with ``link`` the stable symlink is removed and re-pointed at the new ``/dev/pts/N``, as
  udev does with ``/dev/serial/by-id`` (see docs/protocols.md).

Run it as its own process with ``python -m drivers.sim.odometry_emulator --link PATH``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import select
import signal
import threading
import time

import numpy as np

from drivers.odometry_protocol import U32, format_line
from drivers.sim.pty import PseudoTerminal

#: The line faults :meth:`OdometryBoardEmulator.set_fault_rate` takes.
FAULT_KINDS = ("garbage", "drop", "corrupt", "split")


class OdometryBoardEmulator:
    """Encoder-count streamer on a pty, with fault injection."""

    def __init__(
        self,
        *,
        link: str | None = None,
        rate_hz: float = 50.0,
        wheel_radius: float = 0.05,
        ticks_per_rev: float = 4096.0,
        track_width: float = 0.30,
        seed: int = 0,
        split_delay: float = 0.005,
    ) -> None:
        self._pty = PseudoTerminal(link)
        self.rate_hz = rate_hz
        self.ticks_per_metre = ticks_per_rev / (2.0 * math.pi * wheel_radius)
        self.track_width = track_width
        self.split_delay = split_delay
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._rates = (0.0, 0.0)  # ticks/s
        self._left = 0.0
        self._right = 0.0
        self._seq = 0
        self._t_ms = 0.0
        self._garbage = 0
        self._drop = 0
        self._corrupt = 0
        self._split = 0
        self._rates_p = dict.fromkeys(FAULT_KINDS, 0.0)
        self._garbage_bytes = 16
        self._connected = False
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.lines_sent = 0
        self.lines_dropped = 0  # by injection or because nobody read (pty full)

    # lifecycle ---------------------------------------------------------------------------------
    @property
    def port(self) -> str:
        """The path the adapter should open (the stable link if one was given)."""
        return self._pty.path

    def start(self, stream: bool = True) -> OdometryBoardEmulator:
        """Open the pty and (with ``stream``) start sending at ``rate_hz``."""
        self._pty.open()
        self._connected = True
        self._stop.clear()
        if stream:
            self._thread = threading.Thread(target=self._run, name="odometry-board", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop streaming (waiting up to 2 s for the thread) and close the pty."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._pty.close()

    def __enter__(self) -> OdometryBoardEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # driving -----------------------------------------------------------------------------------
    def set_wheel_speeds(self, left_mps: float, right_mps: float) -> None:
        """Wheel speeds in m/s, converted with ticks_per_metre (see :meth:`set_tick_rates`)."""
        self.set_tick_rates(left_mps * self.ticks_per_metre, right_mps * self.ticks_per_metre)

    def set_tick_rates(self, left_ticks_s: float, right_ticks_s: float) -> None:
        """Encoder rates in ticks/s from now on; the counters integrate them in real time."""
        with self._lock:
            self._rates = (float(left_ticks_s), float(right_ticks_s))

    def set_counters(self, left: int, right: int, t_ms: int | None = None) -> None:
        """Set the raw counters (and, with ``t_ms``, the lines' millisecond clock), e.g. just
        below 2^32 to exercise the wrap."""
        with self._lock:
            self._left, self._right = float(left), float(right)
            if t_ms is not None:
                self._t_ms = float(t_ms)

    def reboot(self) -> None:
        """A board restart: the sequence, the clock and the counters start again from 0 (the
        wheel speeds stay)."""
        with self._lock:
            self._left = self._right = 0.0
            self._t_ms = 0.0
            self._seq = 0

    def counters(self) -> tuple[int, int]:
        """Current (left, right) raw counters, unwrapped (may exceed 2^32)."""
        with self._lock:
            return int(math.floor(self._left)), int(math.floor(self._right))

    # faults --------------------------------------------------------------------------------
    def inject_garbage(self, n: int) -> None:
        """Send n random bytes (never a '$') before the next line; adds to any pending count."""
        with self._lock:
            self._garbage += n

    def drop_lines(self, n: int) -> None:
        """Do not send the next n lines (sequence numbers still advance); adds to any pending
        count."""
        with self._lock:
            self._drop += n

    def corrupt_lines(self, n: int) -> None:
        """Change a digit of the next n lines after their checksum; adds to any pending count."""
        with self._lock:
            self._corrupt += n

    def split_lines(self, n: int) -> None:
        """Write the next n lines in two pieces split_delay s apart; adds to any pending count."""
        with self._lock:
            self._split += n

    def set_fault_rate(self, kind: str, p: float, garbage_bytes: int = 16) -> None:
        """Give each line from now on the fault ``kind`` (one of :data:`FAULT_KINDS`) with
        probability ``p`` in [0, 1] (0 stops it); ``garbage_bytes`` random bytes per garbage
        fault. Raises ValueError on an unknown kind or a p outside [0, 1]."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown line fault {kind!r} (one of {', '.join(FAULT_KINDS)})")
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"fault rate must be in [0, 1], got {p}")
        if garbage_bytes < 1:
            raise ValueError(f"garbage_bytes must be >= 1, got {garbage_bytes}")
        with self._lock:
            self._rates_p[kind] = float(p)
            if kind == "garbage":
                self._garbage_bytes = int(garbage_bytes)

    def fault_rate(self, kind: str) -> float:
        """The probability of the line fault ``kind`` set by :meth:`set_fault_rate`."""
        return self._rates_p[kind]

    @property
    def connected(self) -> bool:
        return self._connected

    def disconnect(self) -> None:
        """The board vanishes (USB unplugged): the pty is closed, the link removed."""
        with self._lock:
            self._connected = False
            self._pty.close()

    def reconnect(self) -> str:
        """The board comes back on a new pty; returns the new slave path."""
        with self._lock:
            path = self._pty.open()
            self._connected = True
            return path

    # streaming ---------------------------------------------------------------------------------
    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        last = next_t
        while not self._stop.is_set():
            now = time.monotonic()
            if now < next_t:
                self._stop.wait(next_t - now)
                continue
            next_t += period
            if next_t < now:  # fell behind (host load): skip samples, never send bursts
                next_t = now + period
            dt = now - last
            last = now
            self._tick(dt)

    def _tick(self, dt: float) -> None:
        split_piece: bytes | None = None
        with self._lock:
            rl, rr = self._rates
            self._left += rl * dt
            self._right += rr * dt
            self._t_ms += dt * 1000.0
            self._seq += 1
            line = format_line(self._seq, int(self._t_ms), math.floor(self._left) % U32,
                               math.floor(self._right) % U32)  # fmt: skip
            if not self._connected:
                return
            self._draw_faults()
            if self._drop > 0:
                self._drop -= 1
                self.lines_dropped += 1
                return
            if self._corrupt > 0:
                self._corrupt -= 1
                line = self._corrupt_digit(line)
            if self._garbage > 0:
                junk = self._rng.integers(0, 256, self._garbage, dtype=np.uint8).tobytes()
                junk = junk.replace(b"$", b"?")  # noise never forms a sentence start
                line = junk + line
                self._garbage = 0
            if self._split > 0:
                self._split -= 1
                cut = int(self._rng.integers(1, len(line) - 1))
                line, split_piece = line[:cut], line[cut:]
        self._send(line)
        if split_piece is not None:
            time.sleep(self.split_delay)
            self._send(split_piece)

    def _draw_faults(self) -> None:
        """Turn the fault rates into this line's faults (caller holds the lock)."""
        p = self._rates_p
        if p["drop"] and self._rng.random() < p["drop"]:
            self._drop += 1
        if p["corrupt"] and self._rng.random() < p["corrupt"]:
            self._corrupt += 1
        if p["garbage"] and self._rng.random() < p["garbage"]:
            self._garbage += self._garbage_bytes
        if p["split"] and self._rng.random() < p["split"]:
            self._split += 1

    def _corrupt_digit(self, line: bytes) -> bytes:
        digits = [i for i, ch in enumerate(line) if 48 <= ch <= 57 and i < line.index(b"*")]
        i = digits[int(self._rng.integers(0, len(digits)))]
        b = bytearray(line)
        b[i] = 48 + (b[i] - 48 + 1 + int(self._rng.integers(0, 9))) % 10
        return bytes(b)

    def _send(self, data: bytes, timeout: float = 0.0) -> bool:
        """Write all of ``data``; if the pty stays full for ``timeout`` s the rest is lost."""
        deadline = time.monotonic() + timeout
        while data:
            fd = self._pty.master_fd
            if fd is None:
                return False
            n = self._pty.write(data)
            data = data[n:]
            if data:
                left = deadline - time.monotonic()
                if left <= 0:
                    self.lines_dropped += 1
                    return False
                try:
                    select.select([], [fd], [], left)
                except (OSError, ValueError):  # closed by disconnect()
                    return False
        self.lines_sent += 1
        return True

    def blast(self, n: int, ticks_per_line: tuple[int, int] = (3, 5), timeout: float = 5.0) -> int:
        """Send ``n`` lines as fast as the reader takes them (benchmark). Returns lines sent."""
        sent = 0
        for _ in range(n):
            with self._lock:
                self._left += ticks_per_line[0]
                self._right += ticks_per_line[1]
                self._t_ms += 1000.0 / self.rate_hz
                self._seq += 1
                line = format_line(self._seq, int(self._t_ms), int(self._left) % U32,
                                   int(self._right) % U32)  # fmt: skip
            if not self._send(line, timeout):
                break
            sent += 1
        return sent


def main(argv: list[str] | None = None) -> int:
    """Run the board as its own process until SIGINT/SIGTERM; prints {"port": ...}."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--link", default=None, help="stable symlink to create for the port")
    ap.add_argument("--left", type=float, default=0.0, help="left wheel speed, m/s")
    ap.add_argument("--right", type=float, default=0.0, help="right wheel speed, m/s")
    args = ap.parse_args(argv)
    emu = OdometryBoardEmulator(link=args.link)
    emu.set_wheel_speeds(args.left, args.right)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    with emu:
        print(json.dumps({"port": emu.port, "pid": os.getpid()}), flush=True)
        done.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

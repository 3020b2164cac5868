"""Benchmark of the serial odometry adapter over the odometry board emulator (pseudo-terminal).

Prints one JSON object:
- ``throughput_lines_per_s``: lines per second the adapter parses and integrates when the
  emulator (another process) writes as fast as the adapter takes them (median of repeats);
- ``cpu_fraction``: CPU seconds per wall second of this process with the adapter on a normal
  50 Hz stream, and with the adapter on a silent port.

Usage: ``python benchmarks/bench_odometry.py [--lines 20000] [--repeats 3] [--seconds 3]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from importlib.metadata import version

from drivers.serial_odometry import OdometryConfig, SerialOdometry

BLASTER = """
import json, sys
from drivers.sim.odometry_emulator import OdometryBoardEmulator
emu = OdometryBoardEmulator(link=sys.argv[1], rate_hz=float(sys.argv[3]))
emu.start(stream=sys.argv[2] == "stream")
emu.set_wheel_speeds(0.3, 0.4)
print(json.dumps({"port": emu.port}), flush=True)
for cmd in sys.stdin:
    n = int(cmd)
    if n < 0:
        break
    print(emu.blast(n), flush=True)
emu.stop()
"""


def board(link: str, mode: str, rate_hz: float = 50.0) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [sys.executable, "-c", BLASTER, link, mode, str(rate_hz)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    json.loads(proc.stdout.readline())
    return proc


def stop(proc: subprocess.Popen[str]) -> None:
    assert proc.stdin is not None
    proc.stdin.write("-1\n")
    proc.stdin.flush()
    proc.wait(5)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--lines", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=3.0)
    args = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="bench-odo-")
    link = os.path.join(tmp, "odo")

    # throughput -------------------------------------------------------------------------------
    proc = board(link, "blast")
    odo = SerialOdometry(OdometryConfig(port=link, queue_max=10 * args.lines))
    odo.open()
    rates = []
    try:
        time.sleep(0.3)  # the reader has opened the port
        assert proc.stdin is not None and proc.stdout is not None
        proc.stdin.write("1\n")  # the first line only sets the baseline: send it untimed
        proc.stdin.flush()
        assert int(proc.stdout.readline()) == 1
        time.sleep(0.1)
        for _ in range(args.repeats):
            odo.read()
            before = odo.health().counters["increments"]
            t0 = time.perf_counter()
            proc.stdin.write(f"{args.lines}\n")
            proc.stdin.flush()
            got = 0
            while got < args.lines:
                got += len(odo.read(timeout=1.0))
                if time.perf_counter() - t0 > 60:
                    break
            dt = time.perf_counter() - t0
            sent = int(proc.stdout.readline())
            assert sent == args.lines, sent
            rates.append(got / dt)
        counters = dict(odo.health().counters)
        assert counters["corrupt_lines"] == 0 and counters["gap_events"] == 0, counters
        assert counters["increments"] - before == args.lines
    finally:
        odo.close()
        stop(proc)

    # CPU on a 50 Hz stream and on a silent port ------------------------------------------------
    def cpu_with(mode: str) -> tuple[float, int]:
        p = board(link, mode)
        o = SerialOdometry(OdometryConfig(port=link))
        o.open()
        try:
            time.sleep(0.3)
            n = 0
            c0, w0 = time.process_time(), time.monotonic()
            end = w0 + args.seconds
            while time.monotonic() < end:  # a consumer reading at 30 Hz, like the daemon
                n += len(o.read(timeout=1 / 30))
                time.sleep(1 / 30)
            return (time.process_time() - c0) / (time.monotonic() - w0), n
        finally:
            o.close()
            stop(p)

    cpu_stream, n_stream = cpu_with("stream")
    cpu_silent, _ = cpu_with("blast")  # blast mode sends nothing until asked

    out = {
        "benchmark": "odometry",
        "machine": {
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "pyserial": version("pyserial"),
        },
        "transport": "pseudo-terminal, emulator in a separate process",
        "throughput_lines_per_s": {
            "lines": args.lines,
            "repeats": args.repeats,
            "median": round(statistics.median(rates)),
            "all": [round(r) for r in rates],
            "needed": 50,
        },
        "cpu_fraction": {
            "adapter_on_50hz_stream": round(cpu_stream, 4),
            "increments_received": n_stream,
            "adapter_on_silent_port": round(cpu_silent, 4),
            "seconds_each": args.seconds,
        },
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark of the pan-tilt head adapter over the Dynamixel bus emulator (pseudo-terminal).

Prints one JSON object:
- ``round_trip_ms``: one ``command`` (sync write of both goals) + one ``read`` (sync read of
  64..135 from both servos), median / p99 / mean over repeats, real dynamixel_sdk;
- ``cpu``: CPU seconds per wall second of this process (the emulator runs in another process):
  the adapter idle (no calls), the adapter polled at 50 Hz, and a silent servo pinged in a loop
  by the SDK as shipped (its reads spin) versus with the adapter's blocking read slice.

Usage: ``python benchmarks/bench_head.py [--repeats 1000] [--seconds 3]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from importlib.metadata import version

import dynamixel_sdk
import dynamixel_sdk.port_handler as sdk_port_handler
import numpy as np

from drivers.dynamixel_head import DynamixelHead, HeadConfig


def start_emulator() -> tuple[subprocess.Popen[str], str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "drivers.sim.dynamixel_emulator", "--ids", "1,2"],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    port = json.loads(proc.stdout.readline())["port"]
    return proc, port


def cpu_fraction(fn, seconds: float) -> float:  # noqa: ANN001
    c0, w0 = time.process_time(), time.monotonic()
    fn(seconds)
    return (time.process_time() - c0) / (time.monotonic() - w0)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=1000)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--latency-timer-ms", type=float, default=1.0)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    proc, port = start_emulator()
    try:
        head = DynamixelHead(
            HeadConfig(port=port, latency_timer_ms=args.latency_timer_ms, min_read_interval=0.0)
        )
        assert head.open(), head.health()
        lim = head.limits
        times = []
        for _ in range(args.repeats):
            pan = float(rng.uniform(lim.pan_min, lim.pan_max))
            tilt = float(rng.uniform(lim.tilt_min, lim.tilt_max))
            t0 = time.perf_counter()
            head.command(pan, tilt)
            state = head.read()
            times.append((time.perf_counter() - t0) * 1e3)
            assert not state.stale
        times.sort()

        def idle(seconds: float) -> None:
            time.sleep(seconds)

        def poll50(seconds: float) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                head.read()
                time.sleep(0.02)

        cpu_idle = cpu_fraction(idle, args.seconds)
        cpu_poll = cpu_fraction(poll50, args.seconds)
        health = head.health()
        head.close()

        # A servo that does not answer: the SDK as shipped (serial timeout 0: spins until its
        # packet timeout) versus the adapter's setting (blocking read slice of 1 ms).
        def silent_pings(block: float | None):  # noqa: ANN202
            def run(seconds: float) -> None:
                sdk_port_handler.LATENCY_TIMER = 16
                p = dynamixel_sdk.PortHandler(port)
                p.openPort()
                if block is not None:
                    p.ser.timeout = block
                ph = dynamixel_sdk.PacketHandler(2.0)
                end = time.monotonic() + seconds
                n = 0
                while time.monotonic() < end:
                    _, result, _ = ph.ping(p, 9)
                    assert result == dynamixel_sdk.COMM_RX_TIMEOUT
                    n += 1
                p.closePort()
                run.pings = n  # type: ignore[attr-defined]

            return run

        spin = silent_pings(None)
        cpu_spin = cpu_fraction(spin, args.seconds)
        blocked = silent_pings(0.001)
        cpu_blocked = cpu_fraction(blocked, args.seconds)
    finally:
        proc.terminate()
        proc.wait(5)

    out = {
        "benchmark": "head",
        "machine": {
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "dynamixel_sdk": version("dynamixel-sdk"),
            "pyserial": version("pyserial"),
        },
        "transport": "pseudo-terminal, emulator in a separate process",
        "latency_timer_ms": args.latency_timer_ms,
        "round_trip_ms": {
            "what": "command (sync write) + read (sync read 72 B x 2 servos)",
            "repeats": args.repeats,
            "median": round(statistics.median(times), 4),
            "p99": round(times[int(0.99 * (len(times) - 1))], 4),
            "mean": round(statistics.fmean(times), 4),
            "max": round(times[-1], 4),
        },
        "cpu_fraction": {
            "adapter_idle": round(cpu_idle, 4),
            "adapter_polled_50hz": round(cpu_poll, 4),
            "silent_servo_sdk_as_shipped": round(cpu_spin, 4),
            "silent_servo_adapter_read_slice": round(cpu_blocked, 4),
            "seconds_each": args.seconds,
        },
        "health_counters": dict(health.counters),
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

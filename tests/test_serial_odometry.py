"""SerialOdometry (real pyserial) against the odometry board emulator on a pty: integration
against closed-form arcs, counter wrap, and every injected fault."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.interfaces import HealthState, Odometry
from drivers.odometry_protocol import U32, wheel_travel
from drivers.serial_odometry import NOISE_HOLD_S, OdometryConfig, SerialOdometry
from drivers.sim.odometry_emulator import OdometryBoardEmulator
from lino_loc.poses import compose

R, N, B = 0.05, 4096.0, 0.30  # wheel radius, ticks/rev, track width
M_PER_TICK = 2 * math.pi * R / N


class Run:
    """An emulator + adapter pair, with the adapter's increments composed into a pose."""

    def __init__(self, tmp: str, rate_hz: float = 100.0, **cfg: object) -> None:
        self.link = os.path.join(tmp, "odo")
        self.emu = OdometryBoardEmulator(
            link=self.link, rate_hz=rate_hz, wheel_radius=R, ticks_per_rev=N, track_width=B
        )
        self.emu.start()
        self.start_counts = self.emu.counters()
        conf: dict[str, object] = dict(
            port=self.link, wheel_radius=R, ticks_per_rev=N, track_width=B,
            reconnect_backoff_max=0.05, stale_after=0.3,
        )  # fmt: skip
        conf.update(cfg)
        self.odo = SerialOdometry(OdometryConfig(**conf))  # type: ignore[arg-type]
        self.odo.open()
        self.pose = np.zeros(3)
        self.theta = 0.0  # unwrapped
        self.n = 0
        self.first_seq: int | None = None
        # wait for the first increment so the baseline is the emulator's state now
        self.drain(0.05)
        deadline = time.monotonic() + 2
        while self.n == 0 and time.monotonic() < deadline:
            self.drain(0.05)
        assert self.n > 0, "no increments"

    def drain(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while True:
            for inc in self.odo.read(timeout=0.02):
                if self.n == 0:
                    self.base_seq = inc.sequence
                self.pose = compose(self.pose, (inc.dx, inc.dy, inc.dtheta))
                self.theta += inc.dtheta
                self.n += 1
            if time.monotonic() >= end:
                return

    def settle(self) -> None:
        """Stop the wheels and drain until the stream is quiet (counters are final)."""
        self.emu.set_tick_rates(0.0, 0.0)
        self.drain(0.15)

    def close(self) -> None:
        self.odo.close()
        self.emu.stop()


@pytest.fixture()
def run(tmp_path: os.PathLike[str]) -> Iterator[Run]:
    r = Run(os.fspath(tmp_path))
    yield r
    r.close()


def expected_arc(run: Run, left0: int, right0: int) -> tuple[float, float, float]:
    """Closed form for constant wheel speeds: a circle of radius b/2 (dr+dl)/(dr-dl)."""
    left, right = run.emu.counters()
    dl, dr = (left - left0) * M_PER_TICK, (right - right0) * M_PER_TICK
    theta = (dr - dl) / B
    if abs(theta) < 1e-12:
        return (dl + dr) / 2, 0.0, 0.0
    radius = B / 2 * (dr + dl) / (dr - dl)
    return radius * math.sin(theta), radius * (1 - math.cos(theta)), theta


def check_arc(run: Run, counts0: tuple[int, int], tol: float = 2e-3) -> None:
    x, y, th = expected_arc(run, *counts0)
    assert run.theta == pytest.approx(th, abs=1e-9)  # heading is exact: counters are absolute
    assert run.pose[0] == pytest.approx(x, abs=tol)
    assert run.pose[1] == pytest.approx(y, abs=tol)


def baseline(run: Run) -> tuple[int, int]:
    """Counters at the adapter's current baseline (stream stopped, all drained)."""
    run.settle()
    run.pose = np.zeros(3)
    run.theta = 0.0
    return run.emu.counters()


def test_constant_wheel_speeds_trace_the_closed_form_circle(run: Run) -> None:
    assert isinstance(run.odo, Odometry)
    c0 = baseline(run)
    vl, vr = 0.3, 0.6  # m/s: radius 0.45 m, 1 rad/s
    run.emu.set_wheel_speeds(vl, vr)
    run.drain(1.0)
    run.settle()
    assert run.theta > 0.8
    check_arc(run, c0)
    assert run.odo.health().state is HealthState.OK
    h = run.odo.health().counters
    assert h["corrupt_lines"] == 0 and h["gap_events"] == 0 and h["resets"] == 0


def test_increments_carry_board_time_and_host_stamps(run: Run) -> None:
    run.emu.set_wheel_speeds(0.2, 0.2)
    time.sleep(0.1)
    run.odo.read()  # drop the increments that straddle the speed change
    time.sleep(0.2)
    incs = run.odo.read(timeout=0.5)
    assert incs
    now = time.time()
    stamps = [i.stamp for i in incs]
    assert all(now - 1.0 < s <= now + 1e-3 for s in stamps), (now, stamps)
    assert stamps == sorted(stamps)
    # 100 Hz emulator: 10 ms apart, with the jitter of a thread on a loaded host
    assert all(0.0 < i.dt < 0.5 for i in incs), [i.dt for i in incs]
    assert 0.005 < float(np.median([i.dt for i in incs])) < 0.05
    for i in incs:  # straight line at 0.2 m/s
        assert i.dy == 0.0 and i.dtheta == 0.0
        # board time has 1 ms resolution, counters 1 tick
        assert i.dx == pytest.approx(0.2 * i.dt, abs=0.2 * 0.001 + 2 * M_PER_TICK)


def test_counter_wrap_forward_and_backward(run: Run) -> None:
    run.emu.set_counters(U32 - 1000, U32 - 500)  # both wrap within the run
    c0 = baseline(run)
    assert run.odo.health().counters["resets"] == 1  # the jump itself is re-baselined
    run.emu.set_wheel_speeds(0.4, 0.4)
    run.drain(0.5)
    run.settle()
    assert run.emu.counters()[0] > U32  # really wrapped
    check_arc(run, c0)
    assert run.pose[0] > 0.15
    # backwards through zero
    run.emu.set_counters(500, 700)
    c0 = baseline(run)
    run.emu.set_wheel_speeds(-0.3, -0.2)
    run.drain(0.5)
    run.settle()
    assert run.emu.counters()[0] < 0
    check_arc(run, c0)
    assert run.pose[0] < -0.1
    assert run.odo.health().counters["resets"] == 2


def _counters_of(odo: SerialOdometry, timeout: float = 2.0):
    deadline = time.monotonic() + timeout
    while odo.counters() is None and time.monotonic() < deadline:
        odo.read(timeout=0.05)
    c = odo.counters()
    assert c is not None, "no counters"
    return c


def test_absolute_counters_outlive_the_driver_and_show_a_board_restart(run: Run) -> None:
    """The counters a driver read before it closed (a daemon killed) and those a new driver
    reads (the next daemon) give the wheels' net travel in between, the motion included while
    no driver ran; after a board restart, the reason instead. The board has been up ten
    minutes: a restart within the clock tolerance of the board's start cannot be told from
    no restart, by design."""
    run.emu.set_counters(*run.emu.counters(), t_ms=600_000)
    run.settle()
    before = _counters_of(run.odo)
    deadline = time.monotonic() + 2.0
    while before.board_ms < 600_000 and time.monotonic() < deadline:
        run.odo.read(timeout=0.05)
        before = _counters_of(run.odo)
    assert before.board_ms >= 600_000, before
    assert before.left_m_per_tick == pytest.approx(M_PER_TICK) and before.track_width == B
    assert abs(before.stamp - time.time()) < 1.0
    run.odo.close()  # the daemon is down; the board keeps counting
    run.emu.set_wheel_speeds(0.5, 0.3)
    time.sleep(0.4)
    run.emu.set_wheel_speeds(0.0, 0.0)
    run.odo = SerialOdometry(OdometryConfig(port=run.link, wheel_radius=R, ticks_per_rev=N, track_width=B))
    run.odo.open()
    after = _counters_of(run.odo)
    travel = wheel_travel(before, after)
    assert not isinstance(travel, str), travel
    assert travel[0] == pytest.approx((after.left - before.left) * M_PER_TICK)
    assert 0.1 < travel[0] < 0.3 and 0.05 < travel[1] < 0.2, travel
    assert wheel_travel(after, after) == (0.0, 0.0)
    run.emu.reboot()
    time.sleep(0.2)
    rebooted = _counters_of(run.odo)
    deadline = time.monotonic() + 2.0
    while rebooted.board_ms >= after.board_ms and time.monotonic() < deadline:
        run.odo.read(timeout=0.05)
        rebooted = _counters_of(run.odo)
    why = wheel_travel(before, rebooted)
    assert isinstance(why, str) and "board restarted" in why, why


def test_garbage_dropped_corrupt_and_split_lines(run: Run) -> None:
    c0 = baseline(run)
    run.emu.set_wheel_speeds(0.25, 0.35)
    for _ in range(3):
        run.emu.inject_garbage(40)
        run.emu.drop_lines(4)
        run.emu.corrupt_lines(2)
        run.emu.split_lines(3)
        run.drain(0.2)
    run.settle()
    h = run.odo.health()
    c = h.counters
    assert c["garbage_bytes"] >= 3 * 40
    assert c["corrupt_lines"] >= 3 * 2  # corrupted (+ lines of pure noise)
    assert c["gap_events"] >= 3 and c["lines_missed"] >= 3 * (4 + 2)
    assert c["resets"] == 0
    assert run.emu.lines_dropped == 12
    # no motion lost: the counters are absolute
    check_arc(run, c0)
    # the noise is reported while it lasts, and forgotten after NOISE_HOLD_S of clean lines
    assert h.state is HealthState.DEGRADED and (h.last_error or "").startswith("odometry: ")
    run.drain(NOISE_HOLD_S + 0.3)
    assert run.odo.health().state is HealthState.OK


def test_partial_lines_are_buffered(run: Run) -> None:
    c0 = baseline(run)
    run.emu.set_wheel_speeds(0.2, 0.1)
    run.emu.split_lines(20)
    run.drain(0.5)
    run.settle()
    c = run.odo.health().counters
    assert c["corrupt_lines"] == 0 and c["gap_events"] == 0
    check_arc(run, c0)


def test_disconnect_and_reconnect_on_a_new_pty(run: Run) -> None:
    c0 = baseline(run)
    run.emu.set_wheel_speeds(0.3, 0.2)
    run.drain(0.3)
    run.emu.disconnect()
    run.drain(0.4)  # the wheels keep turning while unplugged
    h = run.odo.health()
    assert h.state is HealthState.DEGRADED
    assert h.counters["reconnects"] == 1
    assert not os.path.exists(run.link)
    new_path = run.emu.reconnect()
    assert os.readlink(run.link) == new_path
    run.drain(0.4)
    run.settle()
    assert run.odo.health().state is HealthState.OK
    # motion during the outage is recovered from the absolute counters
    check_arc(run, c0, tol=5e-3)
    assert run.odo.health().counters["gap_events"] >= 1


def test_missing_port_at_start_is_retried(tmp_path: os.PathLike[str]) -> None:
    link = os.path.join(tmp_path, "later")
    odo = SerialOdometry(OdometryConfig(port=link, reconnect_backoff_max=0.05, stale_after=0.1))
    odo.open()
    try:
        assert odo.read(timeout=0.2) == []
        assert odo.health().state is HealthState.DEGRADED
        with OdometryBoardEmulator(link=link) as emu:
            emu.set_wheel_speeds(0.1, 0.1)
            assert odo.read(timeout=1.0) or odo.read(timeout=1.0)
            assert odo.health().state is HealthState.OK
    finally:
        odo.close()


def test_unread_increments_are_merged_without_losing_motion(tmp_path: os.PathLike[str]) -> None:
    run = Run(os.fspath(tmp_path), rate_hz=200.0, queue_max=5)
    try:
        c0 = baseline(run)
        run.emu.set_wheel_speeds(0.2, 0.5)
        time.sleep(0.4)  # nobody reads
        run.emu.set_tick_rates(0.0, 0.0)
        time.sleep(0.1)
        incs = run.odo.read()
        assert len(incs) <= 5
        for inc in incs:
            run.pose = compose(run.pose, (inc.dx, inc.dy, inc.dtheta))
            run.theta += inc.dtheta
        assert run.odo.health().counters["merged"] > 0
        check_arc(run, c0)
    finally:
        run.close()


def test_idle_adapter_uses_little_cpu(tmp_path: os.PathLike[str]) -> None:
    link = os.path.join(tmp_path, "quiet")
    with OdometryBoardEmulator(link=link).start(stream=False):
        odo = SerialOdometry(OdometryConfig(port=link))
        odo.open()
        try:
            time.sleep(0.1)
            assert odo._thread is not None and odo._thread.ident is not None
            # CPU clock of the reader thread alone (not the rest of this process)
            clock = time.pthread_getcpuclockid(odo._thread.ident)
            c0, w0 = time.clock_gettime(clock), time.monotonic()
            time.sleep(0.5)
            cpu = time.clock_gettime(clock) - c0
            assert cpu < 0.05 * (time.monotonic() - w0)
        finally:
            odo.close()

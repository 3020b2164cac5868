"""The shared reconnect backoff: d_k = min(initial * factor**k, maximum), reset on success,
and a wait that a stop event ends at once."""

from __future__ import annotations

import threading
import time

import pytest

from drivers.backoff import Backoff


def test_delays_double_up_to_the_cap() -> None:
    b = Backoff(0.05, 2.0)
    got = [b.failed() for _ in range(10)]
    assert got == [min(0.05 * 2.0**k, 2.0) for k in range(10)]
    assert got[:6] == [0.05, 0.1, 0.2, 0.4, 0.8, 1.6] and got[6:] == [2.0] * 4


def test_delay_is_the_next_wait_without_counting_a_failure() -> None:
    b = Backoff(0.5, 10.0)
    assert b.delay == b.delay == 0.5
    assert b.failed() == 0.5
    assert b.delay == 1.0 and b.failed() == 1.0


def test_cap_is_never_exceeded_and_applies_to_the_first_delay() -> None:
    b = Backoff(0.1, 0.05)
    assert [b.failed() for _ in range(3)] == [0.05, 0.05, 0.05]
    many = Backoff(1e-3, 7.0)
    delays = [many.failed() for _ in range(2000)]  # no overflow after many failures
    assert max(delays) == 7.0 and delays[-1] == 7.0


def test_other_factors() -> None:
    b = Backoff(1.0, 100.0, factor=3.0)
    assert [b.failed() for _ in range(6)] == pytest.approx([1, 3, 9, 27, 81, 100])
    constant = Backoff(0.2, 5.0, factor=1.0)
    assert [constant.failed() for _ in range(3)] == [0.2, 0.2, 0.2]


def test_reset_returns_to_the_first_delay() -> None:
    b = Backoff(0.2, 5.0)
    for _ in range(5):
        b.failed()
    b.reset()
    assert b.delay == 0.2
    assert [b.failed() for _ in range(3)] == [0.2, 0.4, 0.8]


@pytest.mark.parametrize(
    ("initial", "maximum", "factor"),
    [(0.0, 1.0, 2.0), (1.0, 0.0, 2.0), (-1.0, 1.0, 2.0), (0.1, 1.0, 0.5)],
)
def test_invalid_settings_raise(initial: float, maximum: float, factor: float) -> None:
    with pytest.raises(ValueError):
        Backoff(initial, maximum, factor)


def test_wait_sleeps_the_delay_and_counts_a_failure() -> None:
    b = Backoff(0.02, 1.0)
    stop = threading.Event()
    t0 = time.monotonic()
    assert b.wait(stop) is False
    assert time.monotonic() - t0 >= 0.02
    assert b.delay == 0.04


def test_stop_ends_a_long_wait_promptly() -> None:
    b = Backoff(30.0, 60.0)
    stop = threading.Event()
    threading.Timer(0.05, stop.set).start()
    t0 = time.monotonic()
    assert b.wait(stop) is True
    assert time.monotonic() - t0 < 2.0
    assert b.wait(stop) is True  # already set: no wait at all

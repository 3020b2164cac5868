"""When the daemon's loop dead-reckons (services/daemon.py CameraWatch)."""

from __future__ import annotations

from services.daemon import CameraWatch


def test_timeout_is_five_periods_at_least_one_second() -> None:
    assert CameraWatch.for_fps(15.0, 0.0).timeout == 1.0
    w = CameraWatch.for_fps(2.0, 0.0)
    assert w.period == 0.5 and w.timeout == 2.5


def test_due_after_the_timeout_then_once_per_period() -> None:
    w = CameraWatch.for_fps(10.0, started=100.0)
    assert not w.due(100.5, now=1000.0)  # no frame yet, counted from the start
    assert w.due(101.0, now=1000.0)
    w.last_update_stamp = 1000.0
    assert not w.due(101.05, now=1000.05)  # less than a period since the last update
    assert w.due(101.1, now=1000.1)
    w.last_frame_mono = 101.2  # a frame arrived
    assert not w.due(101.5, now=1001.0)


def test_fresh_frames_are_newer_than_the_last_update() -> None:
    w = CameraWatch.for_fps(10.0, 0.0)
    assert w.fresh(5.0)
    w.last_update_stamp = 5.0
    assert not w.fresh(5.0) and not w.fresh(4.0) and w.fresh(5.01)

"""Status reporting (services/status.py): rates and latency over a period, counters, the
message and the systemd status line."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_fakes import FakeMailbox, FakeWorker  # noqa: E402

from drivers.interfaces import HealthState
from services.messages import ActiveVisionInfo, MapInfo
from services.status import StatusReporter, StatusSources, percentile, status_line

MAP = MapInfo(path="/m.npz", n_images=3, channels=["intensity"], checksum="abc")


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _reporter(workers: dict | None = None, changes: list[int] | None = None) -> tuple[StatusReporter, Clock]:
    clock = Clock()
    counts = changes if changes is not None else [0]
    sources = StatusSources(
        state=lambda: "tracking",
        appearance_changes=lambda: counts[0],
        active_vision=lambda: ActiveVisionInfo(enabled=True),
    )
    w = workers if workers is not None else {"camera": FakeWorker(), "head": FakeWorker(), "odometry": FakeWorker()}
    return StatusReporter(FakeMailbox(received=7, dropped=2), w, MAP, simulated=True, sources=sources,
                          clock=clock), clock


def test_percentile_is_numpys_and_none_when_empty() -> None:
    assert percentile([], 50) is None
    vals = [1.0, 2.0, 3.0, 10.0]
    assert percentile(vals, 99) == pytest.approx(float(np.percentile(vals, 99)))


def test_rates_and_latency_over_one_period() -> None:
    r, clock = _reporter()
    for k in range(10):
        r.pose_published(stamp=50.0, now=50.0 + 0.001 * (k + 1))  # 1..10 ms
        r.frame_taken()
    r.frame_taken()
    clock.t += 2.0
    msg = r.publish()
    assert msg.pose_rate_hz == pytest.approx(5.0) and msg.frame_rate_hz == pytest.approx(5.5)
    assert msg.latency_ms.p50 == pytest.approx(5.5)
    assert msg.latency_ms.p99 == pytest.approx(float(np.percentile(np.arange(1, 11), 99)))
    assert r.last is msg
    # a period without poses: rates fall to 0, the latency figures stay
    clock.t += 1.0
    msg2 = r.publish()
    assert msg2.pose_rate_hz == 0.0 and msg2.latency_ms.p50 == pytest.approx(5.5)


def test_the_message_carries_counters_devices_and_sources() -> None:
    workers = {"camera": FakeWorker(counters={"dropped": 3, "frames_dropped": 1}), "head": FakeWorker(HealthState.FAILED)}
    r, clock = _reporter(workers)
    r.out_of_order()
    clock.t += 4.0
    msg = r.build()
    assert msg.state == "tracking" and msg.frames == 7
    assert msg.dropped_frames == 2 + 3 + 1 and msg.out_of_order_frames == 1
    assert msg.devices["camera"].state == "ok" and msg.devices["head"].state == "failed"
    assert msg.devices["odometry"].state == "failed" and "not started" in msg.devices["odometry"].error
    assert msg.uptime_s == pytest.approx(4.0) and msg.map == MAP and msg.simulated
    assert msg.active_vision is not None and msg.active_vision.enabled


def test_each_appearance_change_is_logged_once(caplog: pytest.LogCaptureFixture) -> None:
    changes = [0]
    r, _ = _reporter(changes=changes)
    with caplog.at_level(logging.INFO, logger="lino_loc.service"):
        assert r.check_appearance_changes() == 0
        changes[0] = 1
        r.check_appearance_changes()
        r.check_appearance_changes()
    assert sum("appearance change 1" in m for m in caplog.messages) == 1


def test_status_line() -> None:
    assert status_line(None, "tcp://x:1", False) == "serving on tcp://x:1: starting"
    r, _ = _reporter({"camera": FakeWorker(), "head": FakeWorker(HealthState.FAILED), "odometry": FakeWorker()})
    line = status_line(r.build(), "tcp://x:1", True)
    assert line.startswith("tracking at 0.0 Hz, 2 frames dropped, DEAD RECKONING")
    assert line.endswith("; head failed")


def test_the_message_carries_the_saved_pose_story() -> None:
    from services.messages import PersistenceInfo

    r, _ = _reporter()
    assert r.build().persistence is None  # a source that reports nothing
    info = PersistenceInfo(initial_belief="global localization: the saved pose was refused: old",
                           saves=3, save_error="/x/state.json: Permission denied")
    r.sources = StatusSources(state=lambda: "global", appearance_changes=lambda: 0,
                              active_vision=lambda: None, persistence=lambda: info)
    msg = r.build()
    assert msg.persistence == info
    again = type(msg).model_validate_json(msg.model_dump_json())
    assert again.persistence is not None and again.persistence.save_error == info.save_error

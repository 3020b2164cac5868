"""The fault campaign's reading of the status: what counts as a fault reported, what the status
said, the devices' state sequence and the verdict (``benchmarks/fault_campaign.py``)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import fault_campaign as fc  # noqa: E402


def status(rx: float, *, state: str = "tracking", uptime: float = 100.0, head: str = "ok",
           head_error: str | None = None, appearance_changes: int = 0, dropped_frames: int = 0,
           initial_belief: str | None = None) -> dict[str, Any]:  # fmt: skip
    ok = {"state": "ok", "error": None, "counters": {}}
    return {
        "_rx": rx,
        "state": state,
        "uptime_s": uptime,
        "appearance_changes": appearance_changes,
        "update_errors": 0,
        "dropped_frames": dropped_frames,
        "out_of_order_frames": 0,
        "devices": {"camera": ok, "odometry": ok,
                    "head": {"state": head, "error": head_error, "counters": {"reboots": 0}}},
        "persistence": {"initial_belief": initial_belief, "saves": 0, "save_error": None},
    }


def test_what_reports_a_fault() -> None:
    before = status(0.0, appearance_changes=2, dropped_frames=5)
    assert not fc.reports(before, status(1.0, uptime=101.0, appearance_changes=2))
    assert not fc.reports(before, status(1.0, uptime=101.0, dropped_frames=9))  # a busy loop
    assert fc.reports(before, status(1.0, head="degraded", head_error="servo 1 rebooted"))
    assert fc.reports(before, status(1.0, state="global"))
    assert fc.reports(before, status(1.0, appearance_changes=3))
    assert fc.reports(before, status(1.0, uptime=0.5))  # the daemon started again


def test_what_the_status_said() -> None:
    before = status(0.0)
    said = fc.said(before, [status(1.0), status(2.0, head="degraded", head_error="servo 1 rebooted")])
    assert said == "head degraded: servo 1 rebooted"
    said = fc.said(before, [status(1.0, uptime=0.4, state="global", initial_belief="the saved pose")])
    assert said is not None and "restarted" in said and "the saved pose" in said
    assert fc.said(before, [status(1.0, appearance_changes=1)]) == "state tracking, appearance_changes 1"
    assert fc.said(before, [status(1.0)]) is None


def test_the_state_sequence_keeps_the_devices_that_were_not_ok() -> None:
    statuses = [status(10.5), status(11.5, head="failed"), status(12.5, head="failed"),
                status(71.5, head="degraded"), status(76.5)]  # fmt: skip
    assert fc.sequence(statuses, 10.0) == {
        "head": [("ok", 0.5), ("failed", 1.5), ("degraded", 61.5), ("ok", 66.5)]
    }


def test_the_verdict() -> None:
    assert fc.verdict("head_crc", True, True, True, True) == "ridden through, reported, recovered"
    assert fc.verdict("head_crc", True, True, False, True) == "ridden through, NOT reported, recovered"
    assert fc.verdict("odometry_split", True, True, False, True) == (
        "ridden through, nothing to report, recovered"
    )
    assert fc.verdict("lights -> tube", True, True, False, True) == (
        "ridden through, nothing to report, recovered"
    )
    assert fc.verdict("x", False, False, True, False) == (
        "NOT ridden through (daemon dead, no pose after), reported, NOT recovered"
    )

"""The saved pose: atomic writes, round trip, and corrupt files ignored with a warning."""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path

import numpy as np
import pytest

from services.persistence import SavedState, load_state, save_state


def _state(x: float = 1.5) -> SavedState:
    cov = np.diag([0.04, 0.09, 0.01])
    cov[0, 1] = cov[1, 0] = 0.01
    return SavedState.from_estimate((x, -2.0, 3.5), cov, stamp=1.7e9, map_checksum="abc")


def test_round_trip(tmp_path: Path) -> None:
    p = tmp_path / "sub" / "state.json"  # folder created
    s = _state()
    save_state(p, s)
    got = load_state(p)
    assert got is not None
    np.testing.assert_allclose(got.mean(), [1.5, -2.0, 3.5 - 2 * math.pi])  # theta wrapped
    np.testing.assert_allclose(got.cov(), s.cov())
    assert got.stamp == 1.7e9 and got.map_checksum == "abc"
    assert json.loads(p.read_text())["format"] == "lino-loc-state"
    assert [f.name for f in p.parent.iterdir()] == ["state.json"]  # no temp file left


def test_missing_file_is_none_without_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        assert load_state(tmp_path / "nope.json") is None
    assert not caplog.records


@pytest.mark.parametrize(
    "content",
    [b"", b"{\"format\": \"lino-loc-st", b"\x00\xff garbage", b"[1, 2, 3]",
     b'{"format": "something-else", "version": 1}',
     b'{"format": "lino-loc-state", "version": 1, "stamp": 1, "saved_at": 1,'
     b' "pose": {"x": 0, "y": 0, "theta": 0}, "covariance": [1, 0, 0, 0, -1, 0, 0, 0, 1]}'],
    ids=["empty", "truncated", "binary", "not-object", "foreign", "not-psd"],
)
def test_corrupt_file_ignored_with_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, content: bytes
) -> None:
    p = tmp_path / "state.json"
    p.write_bytes(content)
    with caplog.at_level(logging.WARNING):
        assert load_state(p) is None
    assert any("ignoring it" in r.getMessage() for r in caplog.records)


def test_failed_write_keeps_the_old_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    p = tmp_path / "state.json"
    save_state(p, _state(1.0))
    before = p.read_bytes()

    def boom(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", boom)  # the atomic writer's fsync (lino_loc.atomic_file)
    with pytest.raises(OSError):
        save_state(p, _state(2.0))
    assert p.read_bytes() == before
    assert [f.name for f in tmp_path.iterdir()] == ["state.json"]
    monkeypatch.undo()
    loaded = load_state(p)
    assert loaded is not None and loaded.pose.x == 1.0


def test_replace_is_atomic_for_a_concurrent_reader(tmp_path: Path) -> None:
    """Every read during many rewrites sees one complete state (never a mixture)."""
    p = tmp_path / "state.json"
    save_state(p, _state(0.0))
    for i in range(1, 30):
        save_state(p, _state(float(i)))
        got = load_state(p)
        assert got is not None and got.pose.x == float(i)
        assert os.stat(p).st_size > 0


# ------------------------------------------------------------------ the saver thread
def test_saver_writes_the_latest_off_thread_and_reports_errors(tmp_path: Path) -> None:
    import time as _time

    from services.persistence import StateSaver

    path = tmp_path / "s.json"
    saver = StateSaver(path)
    saver.start()
    try:
        saver.submit(SavedState.from_estimate([1, 2, 3], np.eye(3), 5.0))
        deadline = _time.monotonic() + 5.0
        while saver.saves == 0:
            assert _time.monotonic() < deadline
            _time.sleep(0.01)
    finally:
        saver.stop()
    assert not saver.is_alive()
    got = load_state(path)
    assert got is not None and got.pose.x == 1.0
    blocked = StateSaver(tmp_path / "file" / "s.json")
    (tmp_path / "file").write_text("not a folder")
    assert not blocked.write(SavedState.from_estimate([0, 0, 0], np.eye(3), 1.0))
    assert blocked.last_error is not None and "file" in blocked.last_error


def test_only_a_tracking_estimate_is_saved() -> None:
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from service_fakes import estimate

    assert SavedState.of_estimate(None) is None
    assert SavedState.of_estimate(estimate("lost")) is None
    s = SavedState.of_estimate(estimate("tracking", stamp=12.0), "abc")
    assert s is not None and s.stamp == 12.0 and s.map_checksum == "abc" and s.state == "tracking"

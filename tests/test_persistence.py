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


# ----------------------------------------------------------------------- reuse checks

from services.persistence import RestoreContext, refusal  # noqa: E402

_NOW = 1.7e9 + 10.0
_BOUNDS = (-1.0, 9.0, -3.0, 5.0)


def _ctx(**kw: object) -> RestoreContext:
    base: dict[str, object] = {"now": _NOW, "map_checksum": "abc", "bounds": _BOUNDS, "max_age_s": 600.0}
    base.update(kw)
    return RestoreContext(**base)  # type: ignore[arg-type]


def _saved(**kw: object) -> SavedState:
    s = _state()
    return s.model_copy(update=kw)


def test_a_recent_tracking_state_of_this_map_is_reusable() -> None:
    assert refusal(_saved(), _ctx()) is None
    assert refusal(_saved(stamp=_NOW + 3.0), _ctx()) is None  # small clock step tolerated


@pytest.mark.parametrize(
    ("update", "ctx", "needle"),
    [
        ({"state": "lost"}, {}, "saved while 'lost'"),
        ({"state": "global"}, {}, "saved while 'global'"),
        ({"map_checksum": "other"}, {}, "another map"),
        ({"map_checksum": None}, {}, "no map checksum"),
        ({}, {"map_checksum": None}, "no map checksum"),
        ({"stamp": _NOW - 30 * 86400}, {}, "2592000 s old"),
        ({"stamp": _NOW - 601}, {}, "persistence.max_age_s = 600"),
        ({"stamp": _NOW + 10 * 365 * 86400}, {}, "in the future"),
        ({"pose": {"x": 1410.0, "y": 0.0, "theta": 0.0}}, {}, "outside the map's bounds"),
        ({"pose": {"x": 10.5, "y": 0.0, "theta": 0.0}}, {}, "outside the map's bounds"),
        ({"pose": {"x": 0.0, "y": -4.2, "theta": 0.0}}, {}, "outside the map's bounds"),
        ({"covariance": [1e6, 0, 0, 0, 1e6, 0, 0, 0, 0.01]}, {}, "position std"),
        ({"covariance": [0.01, 0, 0, 0, 0.01, 0, 0, 0, 4.0]}, {}, "heading std"),
    ],
    ids=["lost", "global", "other-map", "no-saved-checksum", "no-map-checksum", "30-days",
         "just-too-old", "future", "1410m-out", "just-outside-x", "just-outside-y", "cov-1e6",
         "heading-spread"],
)
def test_refusals_name_their_reason(update: dict[str, object], ctx: dict[str, object], needle: str) -> None:
    from services.messages import Pose2D

    if "pose" in update:
        update = {**update, "pose": Pose2D(**update["pose"])}  # type: ignore[arg-type]
    why = refusal(_saved(**update), _ctx(**ctx))
    assert why is not None and needle in why and "\n" not in why, why


def test_just_inside_the_margin_is_reusable() -> None:
    from services.messages import Pose2D

    assert refusal(_saved(pose=Pose2D(x=9.9, y=5.9, theta=0.0)), _ctx()) is None


def test_max_age_is_a_setting() -> None:
    from services.persistence import PersistenceConfig

    assert PersistenceConfig().max_age_s == 30.0
    assert PersistenceConfig(max_age_s=60).max_age_s == 60.0
    with pytest.raises(ValueError):
        PersistenceConfig(max_age_s=0)


# ----------------------------------------------------------------------- leftovers


def test_temp_files_of_dead_writers_are_removed(tmp_path: Path) -> None:
    """A writer killed between creating its temp file and renaming it leaves
    ``.<name>.tmp-<pid>-<hex>``; remove_stale_temps removes those of dead processes only, and
    nothing else."""
    import subprocess
    import sys

    from lino_loc.atomic_file import remove_stale_temps, temp_name

    target = tmp_path / "state.json"
    save_state(target, _state())
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    dead_pid = int(dead.stdout)
    stale = [tmp_path / f".state.json.tmp-{dead_pid}-{i:08x}" for i in range(3)]
    live = tmp_path / f".state.json.tmp-{os.getppid()}-0000abcd"  # the test runner's parent lives
    others = [tmp_path / ".other.json.tmp-1-00000000", tmp_path / "state.json.bak",
              tmp_path / f".state.json.tmp-{dead_pid}-xyz"]
    for f in [*stale, live, *others]:
        f.write_text("{")
    assert temp_name(target).name.startswith(f".state.json.tmp-{os.getpid()}-")
    removed = remove_stale_temps(target)
    assert sorted(removed) == sorted(stale)
    left = {f.name for f in tmp_path.iterdir()}
    assert left == {"state.json", live.name, *(o.name for o in others)}


def test_kill_9_during_saves_leaves_no_temp_file_after_a_restart(tmp_path: Path) -> None:
    """Writers killed with SIGKILL in a tight save loop: their temp files are removed at the
    next start (remove_stale_temps), the state file is whole."""
    import signal
    import subprocess
    import sys
    import time

    from lino_loc.atomic_file import remove_stale_temps

    target = tmp_path / "state.json"
    code = (
        "import sys; from services.persistence import SavedState, save_state\n"
        "s = SavedState.from_estimate((1, 2, 0), [0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.01], 1.7e9)\n"
        "while True: save_state(sys.argv[1], s)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    for i in range(5):
        before = target.stat().st_mtime_ns if target.exists() else None
        p = subprocess.Popen([sys.executable, "-c", code, str(target)], env=env)
        # killed once it is saving (its imports alone can take seconds on a loaded machine)
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and (not target.exists() or target.stat().st_mtime_ns == before):
            time.sleep(0.01)
        time.sleep(0.05 * i)
        p.send_signal(signal.SIGKILL)
        p.wait(5)
    remove_stale_temps(target)
    assert [f.name for f in tmp_path.iterdir()] == ["state.json"]
    assert load_state(target) is not None


def test_simulator_folders_of_dead_processes_are_removed(tmp_path: Path) -> None:
    import subprocess
    import sys

    from services.sim_launcher import remove_stale_sim_folders, sim_folder_prefix

    dead_pid = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                                  capture_output=True, text=True, check=True).stdout)
    stale = tmp_path / f"lino-loc-sim-{dead_pid}-ab12_cd"
    (stale / "sub").mkdir(parents=True)
    (stale / "sub" / "odometry").write_text("x")
    mine = tmp_path / f"{sim_folder_prefix()}zz99"  # this (live) process's
    old_style = tmp_path / "lino-loc-sim-k2j4h1"  # no pid: owner unknown, left alone
    other = tmp_path / f"something-{dead_pid}-ab"
    for d in (mine, old_style, other):
        d.mkdir()
    assert remove_stale_sim_folders(tmp_path) == [stale]
    assert {p.name for p in tmp_path.iterdir()} == {mine.name, old_style.name, other.name}


def test_a_restored_spread_grows_with_the_states_age() -> None:
    from services.daemon import RESTORE_MAX_STD, RESTORE_MIN_STD, restore_min_std

    np.testing.assert_allclose(restore_min_std(0.0), RESTORE_MIN_STD)
    np.testing.assert_allclose(restore_min_std(-5.0), RESTORE_MIN_STD)  # a stamp slightly ahead
    np.testing.assert_allclose(restore_min_std(1e6), RESTORE_MAX_STD)
    a, b = restore_min_std(1.0), restore_min_std(2.0)
    assert np.all(b >= a) and b[0] > a[0]
    assert restore_min_std(2.0)[0] > 0.5  # past the filter's converged_std_xy: re-converge first


# ----------------------------------------------------------------------- the board's counters


def _board(stamp: float, board_ms: int, left: int, right: int):
    from drivers.interfaces import BoardCounters

    m = 2 * math.pi * 0.05 / 4096  # the default wheel: 7.7e-5 m per tick
    return BoardCounters(stamp, board_ms, left, right, m, m, 0.30)


def _with_counters(board_ms: int = 60_000, left: int = 1_000, right: int = 2_000) -> SavedState:
    from services.persistence import SavedCounters

    return _saved(odometry=SavedCounters(stamp=_NOW - 5.0, board_ms=board_ms, left=left, right=right))


def test_the_board_says_the_robot_barely_moved_or_moved() -> None:
    from services.persistence import BARELY_MOVED_M, BARELY_TURNED_RAD, board_motion

    m = 2 * math.pi * 0.05 / 4096
    saved = _with_counters()
    still = _board(_NOW, 65_000, 1_000 + 3, 2_000 - 2)  # 5 s later by both clocks: encoder jitter
    assert refusal(saved, _ctx(odometry=still)) is None
    assert "moved 0.00 m" in board_motion(saved, still).note
    ticks = round(0.2 / m)  # 0.2 m straight: barely
    assert refusal(saved, _ctx(odometry=_board(_NOW, 65_000, 1_000 + ticks, 2_000 + ticks))) is None
    ticks = round(1.0 / m)  # 1 m straight
    why = refusal(saved, _ctx(odometry=_board(_NOW, 65_000, 1_000 + ticks, 2_000 + ticks)))
    assert why is not None and "the odometry board says the robot moved 1.00 m" in why, why
    assert f"<= {BARELY_MOVED_M:g} m" in why and "\n" not in why
    ticks = round(0.5 * 0.30 * 0.5 / m)  # turned 0.5 rad on the spot, not moved
    why = refusal(saved, _ctx(odometry=_board(_NOW, 65_000, 1_000 - ticks, 2_000 + ticks)))
    assert why is not None and "turned 0.50 rad" in why and f"{BARELY_TURNED_RAD:g} rad" in why, why
    # counters that wrapped meanwhile
    wrapped = _with_counters(left=(1 << 32) - 10, right=(1 << 32) - 10)
    assert refusal(wrapped, _ctx(odometry=_board(_NOW, 65_000, 5, 5))) is None


def test_an_unknown_motion_falls_back_to_the_other_checks_and_says_so() -> None:
    from services.persistence import board_motion

    saved = _with_counters()
    rebooted = _board(_NOW, 4_000, 0, 0)  # the board's clock went back: it restarted
    assert refusal(saved, _ctx(odometry=rebooted)) is None
    note = board_motion(saved, rebooted).note
    assert "unknown" in note and "board restarted" in note and "skipped" in note, note
    # ... and the other checks still decide
    assert "another map" in (refusal(saved.model_copy(update={"map_checksum": "x"}),
                                     _ctx(odometry=rebooted)) or "")
    old = _saved()  # a file written before the counters were saved
    assert old.odometry is None and refusal(old, _ctx(odometry=rebooted)) is None
    assert "no odometry counters (an older file)" in board_motion(old, rebooted).note
    assert "no counters from the odometry board" in board_motion(saved, None).note
    assert refusal(saved, _ctx()) is None


def test_an_older_file_without_counters_loads(tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    data = json.loads(_state().model_dump_json())
    del data["odometry"]
    path.write_text(json.dumps(data))
    loaded = load_state(path)
    assert loaded is not None and loaded.odometry is None


def test_the_saver_writes_the_boards_counters_with_the_state(tmp_path: Path) -> None:
    from services.persistence import StateSaver

    path = tmp_path / "state.json"
    saver = StateSaver(path, lambda: _board(_NOW, 123_456, 7, (1 << 32) - 1))
    assert saver.write(_state())
    saved = load_state(path)
    assert saved is not None and saved.odometry is not None
    assert (saved.odometry.board_ms, saved.odometry.left, saved.odometry.right) == (123_456, 7, (1 << 32) - 1)
    assert StateSaver(path, lambda: None).write(_state())
    assert load_state(path).odometry is None  # type: ignore[union-attr]

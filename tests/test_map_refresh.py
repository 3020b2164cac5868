"""The daemon's map refresh writer (services.map_refresh): which views it keeps, its parts
(crash-safe datasets), write errors that never reach the caller, and `map extend` of the
parts. The daemon-level test is tests/test_map_refresh_daemon.py."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from lino_loc.dataset import CameraInfo, Dataset
from lino_loc.errors import LinoLocError
from services.config import ServiceConfig
from services.map_refresh import MapRefreshConfig, MapRefreshWriter

CAM = CameraInfo(width=16, height=12, fx=10.0, fy=10.0, cx=8.0, cy=6.0)


def _img(k: int) -> np.ndarray:
    return np.full((12, 16), k % 256, dtype=np.uint8)


def _writer(tmp_path: Path, **kw: object) -> MapRefreshWriter:
    cfg = MapRefreshConfig(enabled=True, path=tmp_path / "refresh", **kw)  # type: ignore[arg-type]
    w = MapRefreshWriter(cfg, CAM, "office")
    w.start()
    return w


def _parts(w: MapRefreshWriter) -> list[Path]:
    assert w.session_dir is not None
    return sorted(w.session_dir.glob("part-*"))


def test_off_by_default_and_in_the_config() -> None:
    assert ServiceConfig().map_refresh.enabled is False
    w = MapRefreshWriter.off()
    w.start()
    assert not w.offer(0.0, _img(0), None, np.zeros(3), 0.0, 1.0, "tracking")
    w.close()
    with pytest.raises(ValidationError):
        MapRefreshConfig(min_quality=1.5)
    with pytest.raises(ValidationError):
        MapRefreshConfig(condition="a,b")


def test_keeps_confident_moving_views_only(tmp_path: Path) -> None:
    w = _writer(tmp_path, min_quality=0.8, min_distance_m=0.25, min_turn_deg=10.0)
    pose = np.array([1.0, 2.0, 0.5])
    assert not w.offer(1.0, _img(1), None, pose, 0.0, 0.79, "tracking")  # quality too low
    assert not w.offer(1.1, _img(1), None, pose, 0.0, 0.95, "global")  # not tracking
    assert not w.offer(1.2, None, None, pose, 0.0, 0.95, "tracking")  # image not used
    assert not w.offer(1.3, _img(1), None, pose, None, 0.95, "tracking")  # no pan known
    assert not w.offer(1.4, _img(1), None, np.array([np.nan, 0, 0]), 0.0, 0.95, "tracking")
    assert w.offer(2.0, _img(2), None, pose, 0.3, 0.9, "tracking")
    assert not w.offer(2.1, _img(3), None, pose + [0.1, 0, 0], 0.3, 0.9, "tracking")  # too close
    assert w.offer(2.2, _img(4), None, pose + [0.3, 0, 0], 0.3, 0.9, "tracking")  # moved
    assert w.offer(2.3, _img(5), None, pose + [0.3, 0, 0], 0.6, 0.9, "tracking")  # turned by the pan
    w.close()
    (part,) = _parts(w)
    ds = Dataset.open(part)
    assert len(ds) == 3 and ds.conditions == ["refresh"] * 3
    # the camera pose: the robot pose turned by the pan
    np.testing.assert_allclose(ds.poses[0], [1.0, 2.0, 0.8])
    np.testing.assert_allclose(ds.poses[2], [1.3, 2.0, 1.1])
    np.testing.assert_allclose(ds.stamps, [2.0, 2.2, 2.3])
    assert int(ds.image(1)[0, 0]) == 4
    assert w.info()["written"] == 3 and w.info()["errors"] == 0


def test_parts_are_finalised_by_count_and_by_time(tmp_path: Path) -> None:
    w = _writer(tmp_path, part_views=3, part_seconds=1.0, min_distance_m=0.0, min_turn_deg=0.0)
    for k in range(7):
        assert w.offer(float(k), _img(k), None, np.array([0.1 * k, 0, 0]), 0.0, 1.0, "tracking")
        time.sleep(0.02)
    deadline = time.time() + 5
    while time.time() < deadline and len([p for p in _parts(w) if (p / "dataset.json").exists()]) < 3:
        time.sleep(0.1)  # the 7th view's part is finalised after part_seconds
    done = [p for p in _parts(w) if (p / "dataset.json").exists()]
    assert [len(Dataset.open(p)) for p in done] == [3, 3, 1]
    w.close()


def test_an_open_part_is_not_a_dataset_until_finalised(tmp_path: Path) -> None:
    """What a kill -9 leaves: the open part's images without dataset.json, which no dataset
    reader takes; the finished parts are whole."""
    w = _writer(tmp_path, part_views=2, part_seconds=3600.0, min_distance_m=0.0, min_turn_deg=0.0)
    for k in range(3):
        w.offer(float(k), _img(k), None, np.array([0.5 * k, 0, 0]), 0.0, 1.0, "tracking")
    deadline = time.time() + 5
    while time.time() < deadline and w.written < 3:
        time.sleep(0.05)
    first, second = _parts(w)
    assert len(Dataset.open(first)) == 2
    assert (second / "images" / "000000.png").exists() and not (second / "dataset.json").exists()
    with pytest.raises(LinoLocError):
        Dataset.open(second)
    w.close()  # a clean stop finalises it
    assert len(Dataset.open(second)) == 1


def test_write_errors_are_counted_never_raised(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    cfg = MapRefreshConfig(enabled=True, path=blocker / "refresh", min_distance_m=0.0, min_turn_deg=0.0)
    w = MapRefreshWriter(cfg, CAM)
    w.start()
    for k in range(3):
        w.offer(float(k), _img(k), None, np.zeros(3), 0.0, 1.0, "tracking")
    # an image of another size than the map's camera, to a good folder
    w2 = _writer(tmp_path, min_distance_m=0.0, min_turn_deg=0.0)
    w2.offer(0.0, np.zeros((5, 5), np.uint8), None, np.zeros(3), 0.0, 1.0, "tracking")
    w2.offer(1.0, _img(1), None, np.ones(3), 0.0, 1.0, "tracking")
    deadline = time.time() + 5
    while time.time() < deadline and (w.errors < 3 or w2.errors < 1 or w2.written < 1):
        time.sleep(0.05)
    w.close()
    w2.close()
    assert w.errors == 3 and w.written == 0 and w.last_error
    assert w2.errors == 1 and "camera" in (w2.last_error or "")
    # the bad view ended its part; the next one is in a new part
    assert [len(Dataset.open(p)) for p in _parts(w2) if (p / "dataset.json").exists()] == [1]


def test_a_full_queue_drops_and_counts(tmp_path: Path) -> None:
    cfg = MapRefreshConfig(enabled=True, path=tmp_path / "r", queue_size=1, min_distance_m=0.0, min_turn_deg=0.0)
    w = MapRefreshWriter(cfg, CAM)  # not started: nobody empties the queue
    assert w.offer(0.0, _img(0), None, np.zeros(3), 0.0, 1.0, "tracking")
    assert not w.offer(1.0, _img(1), None, np.ones(3), 0.0, 1.0, "tracking")
    assert w.dropped == 1

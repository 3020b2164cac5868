"""The crash-safe dataset writer: every added row survives a kill, and a new writer continues."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from lino_loc.dataset import JOURNAL_FILE, CameraInfo, Dataset, DatasetMeta, DatasetWriter
from lino_loc.errors import LinoLocError

ROOT = Path(__file__).resolve().parents[1]


def _meta(width: int = 16) -> DatasetMeta:
    return DatasetMeta(name="j", camera=CameraInfo(width=width, height=12, fx=10, fy=10, cx=8, cy=6))


def _img(i: int) -> np.ndarray:
    return np.random.default_rng(i).integers(0, 256, (12, 16), dtype=np.uint8)


def test_a_killed_writer_keeps_its_rows_and_a_new_one_continues(tmp_path):
    root = tmp_path / "ds"
    script = textwrap.dedent(f"""
        import os, signal, numpy as np
        from lino_loc.dataset import CameraInfo, DatasetMeta, DatasetWriter
        w = DatasetWriter({str(root)!r}, DatasetMeta(name="j", camera=CameraInfo(width=16, height=12, fx=10,
                          fy=10, cx=8, cy=6)), journal=True)
        for i in range(3):
            img = np.random.default_rng(i).integers(0, 256, (12, 16), dtype=np.uint8)
            w.add(img, (i, 0.0, 0.1), condition="tube", stamp=100.0 + i, extra={{"stop": i}})
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, timeout=60)
    assert proc.returncode == -9
    assert not (root / "poses.csv").exists()  # never closed
    with open(root / JOURNAL_FILE, "a") as fh:  # a row torn by the kill
        fh.write('{"row": {"image": "images/000003.png", "x": "3.0"')
    w = DatasetWriter(root, _meta(), journal=True)
    assert len(w) == 3 and [e["stop"] for e in w.extras] == [0, 1, 2]
    assert w.add(_img(3), (3.0, 0.0, 0.1), condition="tube", extra={"stop": 3}) == 3
    w.close()
    ds = Dataset.open(root)
    assert len(ds) == 4
    for i in range(4):
        assert np.array_equal(ds.image(i), _img(i))
    assert ds.poses[:, 0].tolist() == [0.0, 1.0, 2.0, 3.0]
    assert ds.meta.conditions == ["tube"]
    # a later writer sees the closed dataset's rows too
    assert len(DatasetWriter(root, _meta(), journal=True)) == 4


def test_journal_refuses_another_camera_and_a_damaged_line(tmp_path):
    root = tmp_path / "ds"
    with DatasetWriter(root, _meta(), journal=True) as w:
        w.add(_img(0), (0.0, 0.0, 0.0))
    with pytest.raises(LinoLocError, match="camera"):
        DatasetWriter(root, _meta(width=20), journal=True)
    lines = (root / JOURNAL_FILE).read_text().splitlines()
    (root / JOURNAL_FILE).write_text("\n".join([lines[0], "garbage", *lines[1:]]) + "\n")
    with pytest.raises(LinoLocError, match=r"line 2: not JSON"):
        DatasetWriter(root, _meta(), journal=True)


def test_overwrite_starts_a_journal_afresh(tmp_path):
    root = tmp_path / "ds"
    with DatasetWriter(root, _meta(), journal=True) as w:
        w.add(_img(0), (0.0, 0.0, 0.0))
    with DatasetWriter(root, _meta(), overwrite=True, journal=True) as w:
        assert len(w) == 0
        w.add(_img(1), (1.0, 0.0, 0.0))
    assert len(Dataset.open(root)) == 1
    assert len((root / JOURNAL_FILE).read_text().splitlines()) == 2  # meta + one row

"""The progress line's time left leaves out what a resumed job had done before it started."""

from __future__ import annotations

import io
import time

from services.progress import Progress


def _eta(base: int) -> float:
    out = io.StringIO()
    bar = Progress("survey", stream=out, force=True)
    bar.start = time.monotonic() - 10.0  # 10 s into this run
    bar.update(6, 10, base=base)
    return float(out.getvalue().rsplit("eta", 1)[1].strip().rstrip("s"))


def test_eta_from_this_runs_rate():
    assert abs(_eta(0) - 6.7) < 0.6  # 6 of 10 in 10 s: 4 more take 6.7 s
    assert abs(_eta(4) - 20.0) < 0.6  # 2 of the 6 left in 10 s: 4 more take 20 s

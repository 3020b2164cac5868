"""The first-movement headroom report (``benchmarks/first_look_headroom.py``) against hand
computed tables: the random expectation, the strategies' picks, and the oracle scored on the
filter seeds it did not choose on."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from first_look_headroom import summarize  # noqa: E402


def _row(table: list[list[float]], a0: int, entropy: int, sweep: int, h: list[float]) -> dict:
    t = np.array(table, dtype=np.float64)
    t[:, a0] = np.nan
    return {"a0": a0, "entropy": entropy, "sweep": sweep, "h": np.array(h), "table": t}


def test_the_report_of_two_runs() -> None:
    # run 1: pan 1 always succeeds, pan 2 never, pan 3 on the first two filters only
    one = _row([[0, 1, 0, 1], [0, 1, 0, 1], [0, 1, 0, 0], [0, 1, 0, 0]], a0=0, entropy=1, sweep=3,
               h=[9.0, 1.0, 3.0, 2.0])
    # run 2: every pan alike (the choice does not matter)
    two = _row([[1, 1, 0, 1], [1, 1, 0, 1], [1, 1, 0, 1], [1, 1, 0, 1]], a0=2, entropy=0, sweep=1,
               h=[1.0, 2.0, 0.0, 3.0])
    r = summarize([one, two])
    assert r["random"] == pytest.approx(((1 + 0 + 0.5) / 3 + 1.0) / 2)
    assert r["entropy"] == pytest.approx((1.0 + 1.0) / 2)
    assert r["sweep"] == pytest.approx((0.5 + 1.0) / 2)
    # chosen on filters 0-1, run 1 ties pans 1 and 3 and takes the first (pan 1): scored on 2-3, 1;
    # chosen on 2-3: pan 1, scored on 0-1: 1. Run 2: 1 either way.
    assert r["oracle"] == pytest.approx(1.0)
    assert r["choice_matters"] == pytest.approx(0.5)
    # run 1's rates over pans 1..3 are (1, 0, 0.5) against H (1, 3, 2): perfectly anti-correlated
    assert r["corr_h"] == pytest.approx(-1.0)
    assert r["seed_variance"] == pytest.approx(0.25 / 6, abs=1e-4)  # only run 1's pan 3 varies (p = 0.5) of 6 cells
    # entropy - random: run 1 1 - 0.5, run 2 0; the two runs are two positions
    assert r["entropy_minus_random"]["difference"] == pytest.approx(0.25)
    assert r["entropy_minus_random"]["se"] == pytest.approx(np.std([0.5, 0.0], ddof=1) / np.sqrt(2), abs=1e-4)
    assert r["entropy_minus_sweep"]["difference"] == pytest.approx(0.25)


def test_the_oracle_is_not_inflated_by_noise() -> None:
    """Pans alike in truth, with outcomes that are coin flips: the maximum over the pans'
    observed rates is near 1, the honestly scored oracle near the rate itself."""
    rng = np.random.default_rng(0)
    rows = [_row(rng.random((8, 22)) < 0.5, a0=0, entropy=1, sweep=7, h=list(rng.random(22))) for _ in range(200)]
    r = summarize(rows)
    best_seen = np.mean([np.nanmax(np.mean(x["table"], axis=0)) for x in rows])
    assert best_seen > 0.8
    assert r["oracle"] == pytest.approx(0.5, abs=0.05)

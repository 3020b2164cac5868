"""The pooling of quality tables over seeds (``benchmarks/tracking_seeds.py``): frames add,
means are weighted by frames, empty bands stay None, different bands are refused."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from tracking_seeds import pool_quality  # noqa: E402

from services.evaluation.honesty import quality_table  # noqa: E402


def test_pooled_tables_equal_the_table_of_the_concatenated_runs() -> None:
    rng = np.random.default_rng(7)
    runs = []
    for n in (50, 120, 9):
        q = rng.uniform(0.0, 0.7, n)  # the top bands stay empty
        e = rng.exponential(0.8, n)
        s = list(rng.choice(["tracking", "lost", "uncertain"], n))
        runs.append((q, e, s))
    pooled = pool_quality([quality_table(q, e, s) for q, e, s in runs])
    whole = quality_table(np.concatenate([r[0] for r in runs]), np.concatenate([r[1] for r in runs]),
                          [x for r in runs for x in r[2]])
    assert [r["frames"] for r in pooled] == [r["frames"] for r in whole]
    for p, w in zip(pooled, whole, strict=True):
        for key in ("mean_error_m", "wrong_fraction", "tracking_fraction"):
            if w["frames"]:
                assert p[key] == pytest.approx(w[key])
            else:
                assert p[key] is None and w[key] is None


def test_tables_with_different_bands_are_refused() -> None:
    a = quality_table([0.1, 0.5], [0.2, 0.3])
    b = quality_table([0.1, 0.5], [0.2, 0.3], edges=(0.0, 0.5, 1.0))
    with pytest.raises(ValueError, match="different bands"):
        pool_quality([a, b])
    assert pool_quality([]) == []

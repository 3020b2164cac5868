"""Final decisions on the same filter runs (services/evaluation/decision_rules.py): the joint
likelihood's peak and the map match near the estimate, against constructed cases, and in
`eval active --decisions`."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_eval_active import TINY  # the tiny experiment of the eval-active tests

from services.cli import main
from services.evaluation.decision_rules import (
    PEAK_STEP,
    MapTable,
    decide,
    map_match,
    posterior_peak,
)


class QuadraticMixture:
    """A stand-in mixture whose log density is a quadratic bowl about the camera pose ``peak``."""

    def __init__(self, peak: np.ndarray) -> None:
        self.peak = np.asarray(peak, dtype=np.float64)

    def log_pdf(self, poses: np.ndarray) -> np.ndarray:
        d = poses - self.peak
        d[:, 2] = (d[:, 2] + math.pi) % (2 * math.pi) - math.pi
        return -np.sum(d**2, axis=1)


def _map(step: float = 0.25, n_head: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A product-grid map (positions every ``step`` m x ``n_head`` headings) whose 3 features
    are a distinct smooth function of the camera pose."""
    xs = np.arange(8) * step
    hs = np.arange(n_head) * (2 * math.pi / n_head)
    gx, gy, gh = np.meshgrid(xs, xs, hs, indexing="ij")
    poses = np.column_stack([gx.ravel(), gy.ravel(), gh.ravel()])
    feats = np.column_stack([poses[:, 0] + np.cos(poses[:, 2]), poses[:, 1] + np.sin(poses[:, 2]),
                             np.sin(3 * poses[:, 2]) + 0.5 * poses[:, 0] * poses[:, 1]])
    return poses, feats


def test_posterior_peak_finds_the_joint_maximum_near_the_estimate() -> None:
    truth = np.array([1.0, 2.0, 0.3])
    pans = (0.0, 1.2, -0.8)
    views = [(p, QuadraticMixture(truth + [0.0, 0.0, p]), np.zeros(1)) for p in pans]
    best = posterior_peak(np.array([1.2, 1.85, 0.25]), views)  # 25 cm off: within the searched lattice
    assert np.allclose(best[:2], truth[:2], atol=PEAK_STEP / 2 + 1e-9)
    assert abs(best[2] - truth[2]) <= math.radians(1.25) + 1e-9


def test_map_match_names_the_position_whose_views_match_jointly() -> None:
    poses, feats = _map()
    table = MapTable(poses, feats)
    g, head = 27, 5  # a map position and robot heading index
    pos = poses[g * 24 : (g + 1) * 24]
    assert np.allclose(pos[:, :2], pos[0, :2])
    shifts = (0, 7, -4)  # pans as multiples of the 15 deg heading step
    views = [(s * 2 * math.pi / 24, None, feats[g * 24 + (head + s) % 24]) for s in shifts]
    est = pos[0] + np.array([0.2, -0.15, 0.0])
    named = map_match(est, views, table)
    assert np.allclose(named[:2], pos[0, :2]) and named[2] == pytest.approx(head * 2 * math.pi / 24)
    assert np.array_equal(decide("map_match", est, views, table), named)
    far = np.array([10.0, 10.0, 0.0])  # no map position within the radius: the estimate stands
    assert np.array_equal(map_match(far, views, table), far)
    with pytest.raises(ValueError, match="unknown decision rule"):
        decide("vote", est, views, table)


def test_eval_active_reports_the_decisions_beside_the_estimate(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "active", "--json", *TINY, "--channels", "intensity", "--virtual-headings", "1",
                 "--decisions", "map_match,posterior_peak"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["setup"]["decisions"] == ["map_match", "posterior_peak"]
    for strat in res["strategies"].values():
        fails = strat["failure_error_m"]  # the failed runs' errors: as many as the success ratio says
        runs = res["positions"] * res["runs"]
        assert fails["count"] == [round(runs * (1.0 - v)) for v in strat["success"]]
        assert all((m is None) == (c == 0) for m, c in zip(fails["median"], fails["count"], strict=True))
        for rule in ("map_match", "posterior_peak"):
            d = strat["decisions"][rule]
            assert len(d["success"]) == 3 and all(0.0 <= v <= 1.0 for v in d["success"])
            assert len(d["success_ci95"]) == 3 and len(d["minus_estimate"]["difference"]) == 3
            for key in ("mean_error_m", "median_error_m"):  # the decided poses' distance to the truth
                assert len(d[key]) == 3 and all(np.isfinite(v) and v >= 0.0 for v in d[key])
            # the paired difference is the difference of the two success ratios
            assert np.allclose(d["minus_estimate"]["difference"],
                               np.subtract(d["success"], strat["success"]), atol=1e-4)
    assert main(["eval", "active", *TINY, "--decisions", "vote"]) == 2
    err = capsys.readouterr().err
    assert "--decisions: unknown rule 'vote'" in err and "Traceback" not in err

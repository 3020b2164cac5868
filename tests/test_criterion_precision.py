"""What section 6.1's criterion asks of an estimate, and the lattice appearance oracle
(services/evaluation/criterion_precision.py); `eval active --criterion-step`."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import norm

from drivers.sim.world import grid_poses, load_world
from lino_loc.metrics import map_positions
from services.cli import main
from services.evaluation.active_setup import ActiveSetup, paper_active_vision
from services.evaluation.criterion_precision import (
    SIGMAS,
    appearance_oracle,
    lattice,
    precision_for,
    success_under_noise,
)


def _square_grid(n: int, step: float) -> np.ndarray:
    g = np.arange(n) * step
    gx, gy = np.meshgrid(g, g, indexing="ij")
    return np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])


def _axis_success(sigma: float, s: float) -> float:
    """1-D: a truth uniform in a cell of width s stays in it under N(0, sigma^2) error."""
    val, _ = quad(lambda u: norm.cdf((s - u) / sigma) - norm.cdf(-u / sigma), 0.0, s)
    return val / s


@pytest.mark.parametrize("sigma", [0.03, 0.1, 0.2])
def test_success_under_noise_is_the_closed_form_on_an_open_square_grid(sigma: float) -> None:
    """Far from the grid's edges the two axes are independent: rate = q(sigma)^2."""
    step = 0.75
    grid = _square_grid(21, step)
    rng = np.random.default_rng(3)
    truths = np.column_stack([rng.uniform(5 * step, 15 * step, 4000), rng.uniform(5 * step, 15 * step, 4000),
                              np.zeros(4000)])
    got = success_under_noise(truths, grid, (sigma,), draws=25, seed=4)[0]
    want = _axis_success(sigma, step) ** 2
    # 100 000 draws: standard error below 0.0016
    assert abs(got - want) < 0.006, (got, want)


def test_success_under_noise_falls_with_sigma_and_is_one_without_noise() -> None:
    grid = _square_grid(8, 0.75)
    rng = np.random.default_rng(5)
    truths = np.column_stack([rng.uniform(0.5, 4.5, 300), rng.uniform(0.5, 4.5, 300), np.zeros(300)])
    rates = success_under_noise(truths, grid, (0.0, *SIGMAS), draws=20, seed=1)
    assert rates[0] == 1.0
    assert np.all(np.diff(rates) <= 0.01)  # Monte Carlo noise allowed, the trend is down
    assert rates[-1] < 0.7
    with pytest.raises(ValueError, match="negative"):
        success_under_noise(truths, grid, (-0.1,))
    with pytest.raises(ValueError, match=r"\(P, 3\)"):
        success_under_noise(np.zeros((0, 3)), grid)


def test_precision_for_interpolates_where_the_rate_crosses_the_target() -> None:
    sigmas = (0.01, 0.02, 0.04)
    assert precision_for(sigmas, np.array([0.99, 0.97, 0.93]), 0.95) == pytest.approx(0.03)
    assert precision_for(sigmas, np.array([0.94, 0.9, 0.8]), 0.95) is None
    assert precision_for(sigmas, np.array([0.99, 0.98, 0.97]), 0.95) == 0.04


def test_lattice_is_aligned_with_the_origin_and_bounded_by_the_radius() -> None:
    origin = np.array([0.25, -1.0])
    truth = np.array([1.0, 0.1, 0.3])
    ij = lattice(origin, 0.25, truth, 0.3)
    xy = origin + 0.25 * ij
    assert np.all(np.abs(xy - truth[:2]) <= 0.3 + 1e-9)
    # every lattice point within the box is there: 0.75, 1.0, 1.25 in x; 0.0, 0.25 in y
    assert sorted(map(tuple, np.round(xy, 9).tolist())) == [(x, y) for x in (0.75, 1.0, 1.25) for y in (0.0, 0.25)]
    with pytest.raises(ValueError, match="spacing"):
        lattice(origin, 0.0, truth, 0.3)


@pytest.fixture(scope="module")
def office() -> tuple[ActiveSetup, object, np.ndarray]:
    setup = ActiveSetup(world="office", runs=1, width=160, height=120, size=(40, 30), workers=1,
                        active=paper_active_vision(n_actions=8))
    world = load_world("office")
    grid = grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    return setup, world, grid


class _Identity:
    """A PCA stand-in whose features are the pixels (the oracle's two distances then agree)."""

    def project(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=np.float32)


def test_the_oracle_names_the_lattice_point_the_views_were_taken_at(office: tuple) -> None:
    """Test poses on points of the finest lattice: with its views (independent sensor noise)
    the oracle names that very point, so its error is 0 and it succeeds; the survey's own
    lattice (m = 1) can only name a survey position."""
    setup, world, grid = office
    origin = np.min(map_positions(grid), axis=0)
    spacing = setup.step / 3
    truths = np.array([[origin[0] + 7 * spacing, origin[1] + 5 * spacing, 0.4],
                       [origin[0] + 10 * spacing, origin[1] + 4 * spacing, -2.0]])
    assert world.is_free(truths[:, 0], truths[:, 1]).all()
    out = appearance_oracle(setup, world, grid, _Identity(), 0, truths, views=2, radius=0.4, refinements=(1, 3))
    assert set(out) == {"features", "pixels"} and set(out["pixels"]) == {"1", "3"}
    for dist in ("features", "pixels"):
        fine = out[dist]["3"]["2"]
        assert fine["success"].tolist() == [True, True]
        assert np.allclose(fine["error"], 0.0)
        coarse = out[dist]["1"]["2"]["error"]
        survey_xy = map_positions(grid)
        for p, e in enumerate(coarse):  # the decision is a survey position at that distance
            d = np.hypot(survey_xy[:, 0] - truths[p, 0], survey_xy[:, 1] - truths[p, 1])
            assert np.min(np.abs(d - e)) < 1e-6
    with pytest.raises(ValueError, match="divisors"):
        appearance_oracle(setup, world, grid, _Identity(), 0, truths, refinements=(2, 3))


def test_eval_active_judges_a_denser_map_on_the_criterions_grid(capsys: pytest.CaptureFixture[str]) -> None:
    """``--criterion-step``: the map every 1 m, success judged and test positions placed on a
    2 m grid: the same test positions as the 2 m map's run, and the map's own image count."""
    base = ["eval", "active", "--json", "--heading-step", "45", "--positions", "2", "--runs", "1",
            "--movements", "1", "--actions", "4", "--particles", "60", "--workers", "1", "--virtual-headings", "1"]
    assert main([*base, "--step", "2.0"]) == 0
    coarse = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert main([*base, "--step", "1.0", "--criterion-step", "2.0"]) == 0
    dense = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert dense["test_poses"] == coarse["test_poses"]
    assert dense["setup"]["criterion_step"] == 2.0 and "criterion_step" not in coarse["setup"]
    assert dense["map_images"] > 2 * coarse["map_images"]
    assert main([*base, "--step", "1.0", "--criterion-step", "-1"]) == 2
    assert "--criterion-step must be positive" in capsys.readouterr().err

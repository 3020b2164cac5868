"""Covering the cells a survey could not stand in (lino_loc/lattice_cover.py): which lattice
positions each survey position sees, against the geometry of small grids, and the survey's
translations with it (lino_loc/virtual_translations.py)."""

from __future__ import annotations

import numpy as np

from lino_loc.lattice_cover import cover_offsets
from lino_loc.virtual_translations import lattice_offsets, translate_survey

STEP = 0.75
CELL = lattice_offsets(STEP, 3)
INTR = (100.0, 100.0, 31.5, 23.5)  # fx, fy, cx, cy of a 64 x 48 image


def _grid(missing: list[tuple[int, int]], n: int = 3) -> np.ndarray:
    return np.array([[i * STEP, j * STEP] for i in range(n) for j in range(n) if (i, j) not in missing])


def _covered(survey: np.ndarray) -> list[np.ndarray]:
    return [p + cover_offsets(p, survey, STEP, CELL, reach=STEP) for p in survey]


def test_a_blocked_cell_inside_the_survey_is_covered_once_point_by_point() -> None:
    """A 3 x 3 survey without its centre: every lattice position of the centre cell is seen
    from exactly one survey position, its nearest (ties to the first in x, then y); nothing
    else inside the grid is added, only positions of the unsurveyed cells around it."""
    survey = _grid([(1, 1)])
    covered = _covered(survey)
    centre = np.array([STEP, STEP]) + CELL
    all_pts = np.concatenate(covered)
    for q in centre:  # each exactly once
        assert np.sum(np.all(np.abs(all_pts - q) < 1e-9, axis=1)) == 1, q
    for p, pts in zip(survey, covered, strict=True):
        inside = pts[np.all(np.abs(pts - STEP) <= 0.5 * STEP, axis=1)]  # those in the centre cell
        for q in inside:
            d = np.hypot(*(survey - q).T)
            assert np.hypot(*(p - q)) <= d.min() + 1e-9  # seen from its nearest survey position
    # the centre itself is 75 cm from four survey positions: the first in (x, y) order sees it
    owner = [k for k, pts in enumerate(covered) if np.any(np.all(np.abs(pts - STEP) < 1e-9, axis=1))]
    assert [tuple(survey[k]) for k in owner] == [(0.0, STEP)]


def test_a_fully_surveyed_neighbourhood_adds_nothing_and_reach_bounds_the_rest() -> None:
    survey = _grid([], n=3)
    assert cover_offsets(survey[4], survey, STEP, CELL).shape == (0, 2)  # the centre: all neighbours surveyed
    corner = cover_offsets(survey[0], survey, STEP, CELL)  # (0, 0): cells beyond the grid are unsurveyed
    assert corner.shape[0] > 0 and np.all(np.hypot(*corner.T) <= STEP + 1e-9)
    near = cover_offsets(survey[0], survey, STEP, CELL, reach=0.3)
    assert np.all(np.hypot(*near.T) <= 0.3 + 1e-9) and near.shape[0] < corner.shape[0]


def test_translate_survey_sees_the_covered_positions_with_every_heading() -> None:
    """With the survey's positions, each view is also seen from the positions its position
    covers (the floor plan's ``keep`` still drops what is not free), at the view's heading, so
    every lattice position holds all of its survey position's headings."""
    survey = _grid([(1, 1)])
    rng = np.random.default_rng(3)
    poses = np.array([[x, y, t] for x, y in survey for t in (0.0, np.pi / 2)])
    greys = rng.integers(0, 255, (poses.shape[0], 48, 64), dtype=np.uint8)
    disps = np.full((poses.shape[0], 12, 16), 100.0 * 0.075 / 3.0, dtype=np.float32)
    keep = lambda xy: np.hypot(xy[:, 0] - STEP, xy[:, 1] - STEP) > 0.1  # noqa: E731 - the obstacle at the centre
    plain = translate_survey(greys, disps, poses, INTR, 0.075, STEP, 3, keep=keep)
    moved = translate_survey(greys, disps, poses, INTR, 0.075, STEP, 3, keep=keep, survey_xy=survey)
    centre = np.all(np.abs(moved.poses[:, :2] - STEP) <= 0.25 + 1e-9, axis=1)
    assert not np.any(np.all(np.abs(plain.poses[:, :2] - STEP) <= 0.25 + 1e-9, axis=1))
    assert np.unique(np.round(moved.poses[centre, :2], 6), axis=0).shape[0] == 8  # 9 minus the blocked centre
    xy, inverse = np.unique(np.round(moved.poses[:, :2], 6), axis=0, return_inverse=True)
    for k in range(xy.shape[0]):  # every lattice position: both headings, once each
        assert sorted(moved.poses[np.ravel(inverse) == k, 2].tolist()) == [0.0, np.pi / 2]
    assert moved.images.shape[0] == moved.poses.shape[0] == moved.disparities.shape[0]


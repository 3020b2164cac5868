"""Views matched against the map's lattice near an estimate (lino_loc/view_match.py): the
table, the decision, and the expected entropy against its closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.view_match import ViewLattice, ViewMatchConfig

HEADINGS = 8  # every 45 deg


def _lattice(features: np.ndarray, xy: np.ndarray, config: ViewMatchConfig | None = None) -> ViewLattice:
    """A map of positions ``xy`` (G, 2) x HEADINGS headings with ``features`` (G, HEADINGS, d)."""
    h = np.arange(HEADINGS) * 2.0 * math.pi / HEADINGS
    entries = np.array([[x, y, t] for x, y in xy for t in h])
    return ViewLattice(entries, features.reshape(-1, features.shape[-1]), config)


def test_the_table_holds_every_entry_at_its_position_and_heading() -> None:
    rng = np.random.default_rng(0)
    xy = np.array([[0.0, 0.0], [0.25, 0.0], [0.0, 0.25]])
    f = rng.normal(size=(3, HEADINGS, 4))
    lat = _lattice(f, xy)
    assert lat.n_headings == HEADINGS and math.isclose(lat.heading_step, math.pi / 4)
    order = np.lexsort((xy[:, 1], xy[:, 0]))  # np.unique's order of the positions
    assert np.allclose(lat.table, f[order] * lat.weights, rtol=1e-15, atol=0.0)
    plain = _lattice(f, xy, ViewMatchConfig(weigh_features=False))
    assert np.array_equal(plain.table, f[order]) and np.array_equal(plain.weights, np.ones(4))
    with pytest.raises(ValueError, match="entries"):
        ViewLattice(np.zeros((3, 2)), np.zeros((3, 4)))


def test_the_decision_is_the_hypothesis_whose_stored_views_were_taken() -> None:
    rng = np.random.default_rng(1)
    xy = np.array([[x, y] for x in (0.0, 0.25, 0.5) for y in (0.0, 0.25)])
    f = rng.normal(size=(6, HEADINGS, 5))
    lat = _lattice(f, xy, ViewMatchConfig(radius=0.6, heading_span=math.pi))
    g = int(np.flatnonzero((lat.xy[:, 0] == 0.25) & (lat.xy[:, 1] == 0.25))[0])
    o = 2
    pans = np.array([0.0, math.pi / 2, -math.pi / 4])
    cols = (o + np.round(pans / lat.heading_step).astype(int)) % HEADINGS
    views = lat.table[g, cols] + 0.01 * rng.normal(size=(3, 5))
    pose = lat.match(np.array([0.1, 0.1, 0.0]), pans, views)
    assert pose is not None and np.allclose(pose, [0.25, 0.25, o * math.pi / 4])
    # no map position within the radius: no decision
    assert lat.match(np.array([9.0, 9.0, 0.0]), pans, views) is None


def test_expected_entropy_is_log_2_where_two_places_look_alike_and_0_where_they_differ() -> None:
    """Two positions, equally likely after a view they share; a pan where their stored views are
    equal leaves H = log 2, a pan where they differ by many noise scales leaves H = 0."""
    xy = np.array([[0.0, 0.0], [0.25, 0.0]])
    f = np.zeros((2, HEADINGS, 3))
    f[1, 2] = 1e3  # heading index 2 (90 deg): the second position looks different
    lat = _lattice(f, xy, ViewMatchConfig(radius=0.3, heading_span=0.0, max_hypotheses=8))
    lat.s2 = 1.0
    est = np.array([0.1, 0.0, 0.0])
    h = lat.expected_entropy(est, np.array([0.0]), np.zeros((1, 3)), np.array([0.0, math.pi / 2]))
    assert h is not None
    assert math.isclose(h[0], math.log(2.0), rel_tol=1e-9)
    assert h[1] < 1e-9


def test_expected_entropy_ignores_what_the_position_criterion_does_not_judge() -> None:
    """Hypotheses that differ only in heading at one position: the position is known, H = 0 at
    every pan, however alike their views are."""
    xy = np.array([[0.0, 0.0]])
    f = np.zeros((1, HEADINGS, 3))
    lat = _lattice(f, xy, ViewMatchConfig(radius=0.3, heading_span=math.pi / 2))
    h = lat.expected_entropy(np.zeros(3), np.array([0.0]), np.zeros((1, 3)), np.array([0.0, 1.0]))
    assert h is not None and np.allclose(h, 0.0)


def test_the_noise_scale_is_the_change_between_neighbouring_positions() -> None:
    """s^2 = noise * d * the median per-feature squared change one lattice step away."""
    xy = np.array([[0.0, 0.0], [0.25, 0.0], [0.5, 0.0]])
    f = np.zeros((3, HEADINGS, 2))
    f[:, :, 0] = np.array([0.0, 1.0, 2.0])[:, None]  # one unit per step in feature 0
    lat = _lattice(f, xy, ViewMatchConfig(noise=2.0, weigh_features=False))
    assert math.isclose(lat.neighbour_change, 0.5)  # (1^2 + 0^2) / 2
    assert math.isclose(lat.s2, 2.0 * 2 * 0.5)


def test_the_costs_are_the_summed_squared_distances_to_the_stored_views() -> None:
    """``costs`` (expanded into norms and dot products) equals the direct sum over the views of
    ``|y_i - y(g, o + u_i)|^2``, and is inf where a stored view is missing."""
    rng = np.random.default_rng(3)
    xy = np.array([[x, y] for x in (0.0, 0.25, 0.5) for y in (0.0, 0.25)])
    f = rng.normal(size=(6, HEADINGS, 5))
    f[2, 3] = np.nan  # one view the survey lacks
    lat = _lattice(f, xy, ViewMatchConfig(radius=1.0, heading_span=math.pi))
    est = np.array([0.25, 0.1, 0.0])
    g, o = lat.hypotheses(est)
    pans = np.array([0.0, math.pi / 2, -3 * math.pi / 4, math.pi])
    views = rng.normal(size=(4, 5))
    direct = np.sum((lat.predicted(g, o, pans) - lat.weigh(views)[:, None, :]) ** 2, axis=(0, 2))
    pos, heads = lat.near(est)
    c = lat.costs(pos, heads, pans, views)
    assert c.shape == (pos.size, heads.size) and pos.size * heads.size == g.size
    c = c.ravel()  # the hypotheses' order: position major
    assert np.array_equal(np.isnan(direct), np.isinf(c)) and np.isinf(c).sum() == 4  # 4 hypotheses see it
    assert np.allclose(c[np.isfinite(c)], direct[np.isfinite(direct)], rtol=1e-12, atol=1e-12)


def test_the_costs_of_a_few_positions_are_the_rows_of_the_whole_map_s() -> None:
    """A few positions' views are compared with the stored views of those positions only, most
    positions' in one product over the whole table: the same costs."""
    rng = np.random.default_rng(4)
    xy = np.array([[x, y] for x in (0.0, 0.25, 0.5) for y in (0.0, 0.25)])
    lat = _lattice(rng.normal(size=(6, HEADINGS, 5)), xy)
    heads = np.arange(HEADINGS)
    pans, views = np.array([0.0, math.pi / 4]), rng.normal(size=(2, 5))
    whole = lat.costs(np.arange(6), heads, pans, views)
    few = np.array([1, 4])
    assert np.allclose(lat.costs(few, heads, pans, views), whole[few], rtol=1e-12, atol=1e-12)


def test_weighed_costs_and_residuals_are_the_direct_sums() -> None:
    """``costs`` with view weights is ``sum_i w_i |y_i - y(g, o + u_i)|^2``; ``residuals`` at a
    pose are the terms of its nearest lattice point (inf for a missing view)."""
    rng = np.random.default_rng(8)
    xy = np.array([[x, y] for x in (0.0, 0.25, 0.5) for y in (0.0, 0.25)])
    f = rng.normal(size=(6, HEADINGS, 5))
    f[2, 3] = np.nan
    lat = _lattice(f, xy, ViewMatchConfig(radius=1.0, heading_span=math.pi))
    est = np.array([0.25, 0.1, 0.0])
    pans = np.array([0.0, math.pi / 2, -3 * math.pi / 4])
    views = rng.normal(size=(3, 5))
    w = np.array([0.5, 2.0, 0.0])
    g, o = lat.hypotheses(est)
    terms = np.sum((lat.predicted(g, o, pans) - lat.weigh(views)[:, None, :]) ** 2, axis=2)  # (k, C)
    direct = w @ np.where(np.isnan(terms), 0.0, terms)
    direct[np.isnan(terms).any(axis=0)] = np.inf
    c = lat.costs(*lat.near(est), pans, views, w).ravel()
    assert np.array_equal(np.isinf(c), np.isinf(direct))
    assert np.allclose(c[np.isfinite(c)], direct[np.isfinite(direct)], rtol=1e-12, atol=1e-12)
    i = int(np.flatnonzero(np.isfinite(direct))[3])
    pose = np.array([*lat.xy[g[i]] + 0.03, o[i] * lat.heading_step + 0.01])
    assert np.allclose(lat.residuals(pose, pans, views), terms[:, i], rtol=1e-12)
    missing = np.array([*lat.xy[2], 3 * lat.heading_step])
    assert np.isinf(lat.residuals(missing, np.array([0.0, math.pi]), views[:2])[0])


def test_best_poses_rank_each_position_by_its_best_heading_ties_to_the_first() -> None:
    """``best_poses`` against a direct ranking: each position's best heading (ties: the first
    heading), positions by that cost (ties: the earlier position), those missing every heading
    left out."""
    rng = np.random.default_rng(5)
    xy = np.array([[x, y] for x in (0.0, 0.25, 0.5) for y in (0.0, 0.25)])
    f = rng.normal(size=(6, HEADINGS, 3))
    f[1] = f[4]  # two positions alike: a tie between positions
    f[2, :, :] = f[2, 0]  # one position the same at every heading: ties between headings
    f[5] = np.nan  # one position without views
    lat = _lattice(f, xy, ViewMatchConfig(radius=1.0, heading_span=math.pi))
    est = np.array([0.25, 0.1, 0.0])
    pans = np.array([0.0, math.pi / 4])
    views = f[2, :2] + 0.3
    g, o = lat.hypotheses(est)
    direct = np.sum((lat.predicted(g, o, pans) - views[:, None, :]) ** 2, axis=(0, 2))
    expected = []
    for pos in sorted(set(g.tolist()), key=lambda p: (np.nanmin(np.where(g == p, direct, np.nan))
                                                       if np.isfinite(direct[g == p]).any() else np.inf, p)):
        at = np.flatnonzero((g == pos) & np.isfinite(direct))
        if at.size:
            best = at[np.argmin(direct[at])]
            expected.append([lat.xy[pos, 0], lat.xy[pos, 1], o[best] * lat.heading_step])
    got = lat.best_poses(est, pans, views, 10)
    assert len(got) == 5 and len(expected) == 5
    assert np.allclose(np.array(got)[:, :2], np.array(expected)[:, :2])
    assert np.allclose(np.cos(np.array(got)[:, 2] - np.array(expected)[:, 2]), 1.0)
    assert np.allclose(lat.best_poses(est, pans, views, 2), got[:2])
    assert lat.best_poses(np.array([9.0, 9.0, 0.0]), pans, views, 3) == []


def test_feature_weights_are_the_inverse_change_over_one_lattice_step() -> None:
    """Closed form on a 3 x 2 lattice of 8 headings: feature 0 changes by 1 per step in x only,
    feature 1 by 3 per step in y only, feature 2 by 2 per heading step only, feature 3 never.
    Its mean squared change over the 7 neighbouring position pairs (4 along x, 3 along y) plus
    that over the neighbouring headings gives its weight ``1 / sqrt(change)``, scaled to a mean
    squared weight of 1; the unchanging feature gets 0, and views are weighed alike."""
    xy = np.array([[x, y] for x in (0.0, 0.25, 0.5) for y in (0.0, 0.25)])
    f = np.zeros((6, HEADINGS, 4))
    f[:, :, 0] = (xy[:, 0] / 0.25)[:, None]
    f[:, :, 1] = (3.0 * xy[:, 1] / 0.25)[:, None]
    f[:, :, 2] = 2.0 * np.abs(np.arange(HEADINGS) - HEADINGS / 2)[None, :]  # cyclic: one step each way
    lat = _lattice(f, xy)
    change = np.array([4 / 7 * 1.0, 3 / 7 * 9.0, 4.0, 0.0])
    w = np.array([1 / math.sqrt(change[0]), 1 / math.sqrt(change[1]), 1 / math.sqrt(change[2]), 0.0])
    w /= math.sqrt(np.mean(w * w))
    assert np.allclose(lat.weights, w, rtol=1e-12)
    assert math.isclose(float(np.mean(lat.weights ** 2)), 1.0, rel_tol=1e-12)
    assert np.allclose(lat.weigh(np.ones((2, 4))), np.tile(w, (2, 1)))
    still = _lattice(np.ones((6, HEADINGS, 4)), xy)
    assert np.array_equal(still.weights, np.ones(4))  # nothing changes: every feature alike

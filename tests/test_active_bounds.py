"""The references of `eval active` that need no filter (services/evaluation/active_bounds.py):
the map-grid nearest-neighbour oracle on hand-made maps where the answer is known."""

from __future__ import annotations

import math

import numpy as np

from lino_loc.view_match import views_by_position
from services.evaluation.active_bounds import map_oracle_success, sweep_order
from services.evaluation.active_setup import ActiveSetup, paper_active_vision

N_HEAD = 24  # 15 deg headings


def _map(rng: np.random.Generator, xy: np.ndarray, d: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Every position at every heading, random distinct features."""
    th = np.arange(N_HEAD) * 2.0 * math.pi / N_HEAD
    poses = np.array([(x, y, t) for x, y in xy for t in th])
    return poses, rng.standard_normal((poses.shape[0], d))


def _views(entries: np.ndarray, feats: np.ndarray, at: np.ndarray, heading: float, pans: np.ndarray) -> np.ndarray:
    """The stored features of map position ``at`` at headings ``heading + pans`` (A, d)."""
    out = []
    for u in pans:
        sel = np.hypot(entries[:, 0] - at[0], entries[:, 1] - at[1]) < 1e-9
        dth = np.abs(np.angle(np.exp(1j * (entries[sel, 2] - (heading + u)))))
        out.append(feats[sel][np.argmin(dth)])
    return np.asarray(out)


def test_table_holds_every_entry_at_its_position_and_heading() -> None:
    rng = np.random.default_rng(0)
    xy = np.array([[0.0, 0.0], [0.75, 0.0]])
    entries, feats = _map(rng, xy)
    pos, table, step = views_by_position(entries, feats)
    assert table.shape == (2, N_HEAD, 5) and math.isclose(step, math.radians(15.0))
    assert not np.isnan(table).any()
    i = 2 * N_HEAD - 1  # last entry: position 1, heading 345 deg
    assert np.array_equal(table[1, N_HEAD - 1], feats[i])
    # a missing heading leaves NaN, the rest stays in place
    pos, table, _ = views_by_position(entries[1:], feats[1:])
    assert np.isnan(table[0, 0]).all() and not np.isnan(table[0, 1:]).any()


def test_oracle_finds_the_position_whose_views_are_seen() -> None:
    rng = np.random.default_rng(1)
    xy = np.array([[0.0, 0.0], [0.75, 0.0], [1.5, 0.0], [0.0, 0.75]])
    entries, feats = _map(rng, xy)
    setup = ActiveSetup(runs=3, active=paper_active_vision(n_actions=22))
    pans = setup.active.actions()
    # test positions 20 cm from map positions 0 and 2; their views are those stored at
    # positions 0 and 2 (headings 30 and -60 deg), plus a little noise
    truths = np.array([[0.2, 0.0, math.radians(30.0)], [1.5, 0.2, math.radians(-60.0)]])
    views = np.stack([_views(entries, feats, xy[0], truths[0, 2], pans),
                      _views(entries, feats, xy[2], truths[1, 2], pans)])
    views += 0.05 * rng.standard_normal(views.shape)
    res = map_oracle_success(setup, entries, entries, feats, truths, pans, views)
    assert set(res) == {"1", "2", "4", "6", "11", "22"}
    assert all(v == 1.0 for v in res.values())
    # the views of the neighbouring position: the oracle names that one, never the truth's
    wrong = np.stack([_views(entries, feats, xy[1], truths[0, 2], pans),
                      _views(entries, feats, xy[1], truths[1, 2], pans)])
    assert all(v == 0.0 for v in map_oracle_success(setup, entries, entries, feats, truths, pans, wrong).values())


def test_oracle_needs_more_views_when_positions_look_alike() -> None:
    """Two positions identical except at one heading: one view rarely tells them apart,
    all 22 always do."""
    rng = np.random.default_rng(2)
    xy = np.array([[0.0, 0.0], [0.75, 0.0]])
    entries, feats = _map(rng, xy)
    feats[N_HEAD:] = feats[:N_HEAD]
    feats[N_HEAD + 6] += 3.0  # position 1 differs only when looking at 90 deg
    setup = ActiveSetup(runs=10, active=paper_active_vision(n_actions=22))
    pans = setup.active.actions()
    truths = np.array([[0.7, 0.0, 0.0]])
    views = _views(entries, feats, xy[1], 0.0, pans)[None]
    res = map_oracle_success(setup, entries, entries, feats, truths, pans, views)
    assert res["1"] < 0.5 and res["22"] == 1.0
    assert res["1"] <= res["4"] <= res["22"]


def test_sweep_order_visits_every_pan_once() -> None:
    setup = ActiveSetup()
    order = sweep_order(setup, pos=3, run=1, n_actions=22)
    assert sorted(order) == list(range(22)) and order[1] == (order[0] + setup.sweep_stride) % 22

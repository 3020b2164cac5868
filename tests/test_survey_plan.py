"""Plans of a robot survey: CSV parsing, grids, and the head sweep of a stop."""

from __future__ import annotations

import math

import pytest

from lino_loc.errors import LinoLocError
from services.survey_plan import grid_plan, head_sweep, parse_area, parse_plan_text, read_plan_csv


def test_plan_csv_columns_comments_and_theta(tmp_path):
    p = tmp_path / "plan.csv"
    p.write_text("# survey of the lab\ny,x,theta\n0.5,1.0,0.25\n\n1.5, 2.0 ,-4.0\n")
    stops = read_plan_csv(p)
    assert [(s.x, s.y) for s in stops] == [(1.0, 0.5), (2.0, 1.5)]
    assert stops[0].theta == pytest.approx(0.25)
    assert stops[1].theta == pytest.approx(-4.0 + 2 * math.pi)  # wrapped
    assert parse_plan_text("x,y\n1,2\n", "p")[0].theta == 0.0


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("", "empty plan"),
        ("x,y\n", "no stops"),
        ("x,z\n1,2\n", "lacks column 'y'"),
        ("x,y,heading\n1,2,3\n", "unknown column 'heading'"),
        ("x,y\n1,2,3\n", "line 2: 3 fields"),
        ("x,y\n1,abc\n", "line 2, field 'y': not a number ('abc')"),
        ("x,y\n1,2\nnan,2\n", "line 3, field 'x': not finite"),
        ("x,x,y\n1,1,2\n", "named twice"),
    ],
)
def test_plan_errors_are_one_line_naming_the_place(text, needle):
    with pytest.raises(LinoLocError) as e:
        parse_plan_text(text, "plan.csv")
    msg = str(e.value)
    assert needle in msg and msg.startswith("plan.csv") and "\n" not in msg


def test_plan_file_errors(tmp_path):
    with pytest.raises(LinoLocError, match="plan file not found"):
        read_plan_csv(tmp_path / "missing.csv")
    bad = tmp_path / "bin.csv"
    bad.write_bytes(b"x,y\n\xff\xfe\n")
    with pytest.raises(LinoLocError, match="not a UTF-8"):
        read_plan_csv(bad)


def test_grid_plan_covers_the_area_row_by_row_as_a_boustrophedon():
    stops = grid_plan(0.5, (1.0, 0.0, 2.0, 0.5))
    assert [(s.x, s.y) for s in stops] == [(1.0, 0.0), (1.5, 0.0), (2.0, 0.0), (2.0, 0.5), (1.5, 0.5), (1.0, 0.5)]
    with pytest.raises(LinoLocError, match="positive"):
        grid_plan(0.0, (0, 0, 1, 1))
    with pytest.raises(LinoLocError, match="more than"):
        grid_plan(0.001, (0, 0, 1000, 1000))


@pytest.mark.parametrize(("text", "needle"), [("1,2,3", "four numbers"), ("0,0,a,1", "field 'x1'"),
                                              ("2,0,1,1", "x0 < x1")])
def test_area_errors(text, needle):
    with pytest.raises(LinoLocError, match=needle):
        parse_area(text)


@pytest.mark.parametrize(("lo", "hi"), [(-2.6, 2.6), (-3.14159, 3.14159), (-1.0, 1.0), (-0.3, 2.0)])
@pytest.mark.parametrize("step_deg", [15.0, 30.0, 45.0])
def test_head_sweep_covers_every_heading_once_within_the_head_range(lo, hi, step_deg):
    sweep = head_sweep(lo, hi, math.radians(step_deg))
    n = round(360 / step_deg)
    got = sorted(round(math.degrees(c.heading)) % 360 for c in sweep)
    assert got == [round(k * step_deg) % 360 for k in range(n)]
    assert all(lo - 1e-9 <= c.pan <= hi + 1e-9 for c in sweep)
    turns = sorted({c.turn_index for c in sweep})
    assert sweep[0].turn == 0.0
    # fewest base turns a greedy cover can need: ceil(headings / headings per range)
    per_turn = int(math.floor((hi - lo) / math.radians(step_deg) + 1e-9)) + 1
    assert len(turns) <= math.ceil(n / min(per_turn, n)) + 1
    for t in turns:  # one sweep direction per turn, alternating
        pans = [c.pan for c in sweep if c.turn_index == t]
        assert pans == sorted(pans, reverse=bool(t % 2))
    keys = [(c.turn_index, c.pan_index) for c in sweep]
    assert len(set(keys)) == len(keys)


def test_head_sweep_full_range_never_turns_the_base():
    sweep = head_sweep(-math.pi, math.pi, math.radians(15))
    assert {c.turn for c in sweep} == {0.0} and len(sweep) == 24


@pytest.mark.parametrize(("lo", "hi", "step", "needle"), [(0.0, 0.0, 15.0, "empty"), (-1, 1, 0.0, "must be in"),
                                                          (-1, 1, 7.0, "does not divide")])
def test_head_sweep_errors(lo, hi, step, needle):
    with pytest.raises(LinoLocError, match=needle):
        head_sweep(lo, hi, math.radians(step))

"""The plan of a robot survey: where the robot stops, and how the head sweeps at each stop.

A plan is a list of stops (x, y, theta): metres and radians in the map frame; theta is the
heading the robot is asked to face at the stop (0 when the plan does not say).

- :func:`read_plan_csv`: a CSV with a header row naming at least the columns ``x`` and ``y``
  (optionally ``theta``, radians); blank lines and lines starting with ``#`` are skipped.
  LinoLocError naming the file, the line and the field for anything else.
- :func:`grid_plan`: every ``step`` metres over the rectangle ``area`` = (x0, y0, x1, y1),
  rows of increasing y, driven as a boustrophedon: the first row with increasing x, the
  next with decreasing x, and so on (the robot never drives back along a whole row).

:func:`head_sweep` lists the captures of one stop: camera headings every ``heading_step``
over the full turn, relative to the stop's heading, each taken as a base turn ``b`` plus a
pan ``p`` inside the head's range [pan_min, pan_max]. With the range covering the turn
(pan_max - pan_min >= 2 pi - heading_step) the base never turns; otherwise headings are
covered greedily: base turn 0 first, then, while a heading is left, a base turn that puts
the first heading left clockwise from the lower end of the last range at pan_max, covering
every heading left that then falls inside the range. Within a base turn the pans are
ordered to sweep one way, the first turn's up and the next one's down, so that the head
goes on from where it is instead of swinging back across its range (a survey sweeps every
other stop in the reverse order, :mod:`services.robot_survey`). A capture is named in a
dataset's journal by (stop, ``turn_index``, ``pan_index``).

Usage::

    plan = read_plan_csv("plan.csv")               # or grid_plan(0.5, (0, 0, 3, 2))
    sweep = head_sweep(-2.6, 2.6, math.radians(15))
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

from lino_loc.errors import LinoLocError
from lino_loc.poses import wrap_angle

#: Largest plan accepted (stops): a grid of 10 cm over 100 x 100 m is 10^6 stops.
MAX_STOPS = 100_000


@dataclass(frozen=True)
class Stop:
    """One stop of the plan: the robot pose asked for (m, m, rad)."""

    x: float
    y: float
    theta: float = 0.0

    def as_list(self) -> list[float]:
        return [self.x, self.y, self.theta]


@dataclass(frozen=True)
class Capture:
    """One capture of a stop: the base turned by ``turn`` (rad) from the stop's heading, the
    head at ``pan`` (rad); ``heading`` = wrap(turn + pan) relative to the stop's heading.
    ``turn_index``, ``pan_index``: its place in :func:`head_sweep`'s list."""

    turn_index: int
    turn: float
    pan_index: int
    pan: float

    @property
    def heading(self) -> float:
        return float(wrap_angle(self.turn + self.pan))


def _number(cell: str, where: str, field: str) -> float:
    try:
        v = float(cell)
    except ValueError:
        raise LinoLocError(f"{where}, field '{field}': not a number ({cell!r})") from None
    if not math.isfinite(v):
        raise LinoLocError(f"{where}, field '{field}': not finite ({cell!r})")
    return v


def parse_plan_text(text: str, name: str) -> list[Stop]:
    """The stops of a plan CSV's text (``name`` is used in the error messages)."""
    lines = [(i, ln) for i, ln in enumerate(text.splitlines(), start=1)
             if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise LinoLocError(f"{name}: empty plan (expected a header row x,y[,theta] and one row per stop)")
    rows = list(csv.reader(io.StringIO("\n".join(ln for _, ln in lines))))
    header = [h.strip() for h in rows[0]]
    for col in ("x", "y"):
        if col not in header:
            raise LinoLocError(f"{name}: line {lines[0][0]}: header lacks column '{col}' (have {','.join(header)})")
    unknown = [h for h in header if h not in ("x", "y", "theta")]
    if unknown:
        raise LinoLocError(f"{name}: line {lines[0][0]}: unknown column '{unknown[0]}' (known: x, y, theta)")
    if len(set(header)) != len(header):
        raise LinoLocError(f"{name}: line {lines[0][0]}: a column is named twice")
    idx = {h: i for i, h in enumerate(header)}
    stops = []
    for (lineno, _), cells in zip(lines[1:], rows[1:], strict=True):
        where = f"{name}: line {lineno}"
        if len(cells) != len(header):
            raise LinoLocError(f"{where}: {len(cells)} fields, the header has {len(header)}")
        x = _number(cells[idx["x"]].strip(), where, "x")
        y = _number(cells[idx["y"]].strip(), where, "y")
        th = _number(cells[idx["theta"]].strip(), where, "theta") if "theta" in idx else 0.0
        stops.append(Stop(x, y, float(wrap_angle(th))))
        if len(stops) > MAX_STOPS:
            raise LinoLocError(f"{name}: more than {MAX_STOPS} stops")
    if not stops:
        raise LinoLocError(f"{name}: no stops (only a header)")
    return stops


def read_plan_csv(path: str | Path) -> list[Stop]:
    """The stops of the plan file ``path`` (see the module docstring)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise LinoLocError(f"{p}: plan file not found") from None
    except UnicodeDecodeError:
        raise LinoLocError(f"{p}: not a UTF-8 text file") from None
    except OSError as exc:
        raise LinoLocError(f"{p}: cannot read the plan: {exc.strerror or exc}") from None
    return parse_plan_text(text, str(p))


def parse_area(text: str) -> tuple[float, float, float, float]:
    """``x0,y0,x1,y1`` (metres) with x0 < x1 and y0 < y1."""
    parts = text.split(",")
    if len(parts) != 4:
        raise LinoLocError(f"--area {text!r}: expected x0,y0,x1,y1 (four numbers, metres)")
    x0, y0, x1, y1 = (_number(v.strip(), f"--area {text!r}", n) for v, n in zip(parts, ("x0", "y0", "x1", "y1"),
                                                                                  strict=True))
    if not (x0 < x1 and y0 < y1):
        raise LinoLocError(f"--area {text!r}: needs x0 < x1 and y0 < y1")
    return x0, y0, x1, y1


def grid_plan(step: float, area: tuple[float, float, float, float]) -> list[Stop]:
    """Stops every ``step`` m over ``area`` (x0, y0, x1, y1), heading 0 (module docstring)."""
    if not (math.isfinite(step) and step > 0):
        raise LinoLocError(f"--grid {step}: the step must be a positive number of metres")
    x0, y0, x1, y1 = area
    nx = int(math.floor((x1 - x0) / step + 1e-9)) + 1
    ny = int(math.floor((y1 - y0) / step + 1e-9)) + 1
    if nx * ny > MAX_STOPS:
        raise LinoLocError(f"--grid {step}: {nx * ny} stops over the area, more than {MAX_STOPS}")
    return [Stop(round(x0 + i * step, 9), round(y0 + j * step, 9))
            for j in range(ny) for i in (range(nx) if j % 2 == 0 else range(nx - 1, -1, -1))]


def head_sweep(pan_min: float, pan_max: float, heading_step: float) -> list[Capture]:
    """The captures of one stop (see the module docstring)."""
    if not (math.isfinite(heading_step) and 0 < heading_step <= math.pi):
        raise LinoLocError(f"heading step {math.degrees(heading_step):g} deg: must be in (0, 180]")
    if not pan_min < pan_max:
        raise LinoLocError(f"head pan range [{pan_min:g}, {pan_max:g}] rad is empty")
    n = int(round(2 * math.pi / heading_step))
    if abs(n * heading_step - 2 * math.pi) > 1e-6:
        raise LinoLocError(f"heading step {math.degrees(heading_step):g} deg does not divide 360 deg")
    headings = [k * heading_step for k in range(n)]  # in [0, 2 pi)
    eps = 1e-9
    left = list(range(n))
    turns: list[tuple[float, list[tuple[int, float]]]] = []
    turn = 0.0
    while left:
        covered = []
        for k in left:
            p = float(wrap_angle(headings[k] - turn))
            if pan_min - eps <= p <= pan_max + eps:
                covered.append((k, min(max(p, pan_min), pan_max)))
        if not covered:  # cannot happen for turn chosen below; guards a zero range
            raise LinoLocError(f"head pan range [{pan_min:g}, {pan_max:g}] rad covers no heading")
        turns.append((turn, sorted(covered, key=lambda kp: kp[1])))
        done = {k for k, _ in covered}
        left = [k for k in left if k not in done]
        if not left:
            break
        # the first heading left clockwise from the lower end of the first turn's range, put
        # at pan_max: the head, which ended the first sweep near pan_max, barely moves
        lower = turns[0][0] + pan_min if len(turns) == 1 else turn + pan_min
        k0 = min(left, key=lambda k: (lower - headings[k]) % (2 * math.pi))
        turn = float(wrap_angle(headings[k0] - pan_max))
    out: list[Capture] = []
    for ti, (t, pans) in enumerate(turns):
        ordered = pans if ti % 2 == 0 else list(reversed(pans))
        out += [Capture(ti, t, pi, p) for pi, (_, p) in enumerate(ordered)]
    return out

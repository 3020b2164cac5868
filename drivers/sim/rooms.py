"""Rooms joined by openings: the cells, portals, walls and lintels of a multi-room world.

A world file may describe its floor as ``rooms`` (axis-aligned rectangles, the free inside of
each room) and ``openings`` (doorways) instead of free wall segments. Two rooms joined by an
opening face each other across a wall of thickness ``gap`` (their facing sides are parallel,
``0 < gap <= MAX_WALL_M`` apart); the opening is the rectangle between them, ``width`` wide
around ``center`` (the coordinate along the wall), with a lintel box from ``height`` to the
ceiling.

:func:`build_layout` resolves rooms and openings into

- **cells**: the rooms, then one *passage* cell per opening (the doorway through the wall);
  cells are convex and their insides do not overlap;
- **walls**: every side of every room, cut at its openings, plus the two jambs of every
  passage; each wall belongs to one cell and carries that cell's inward normal. The walls of a
  cell and its portals cover the cell's boundary exactly (shared end points), which is what
  makes visibility culling sound (:mod:`drivers.sim.visibility`);
- **portals**: the open segments between a room and a passage (two per opening);
- **lintels**: boxes over the passages (identical for identical openings).

Decals and windows of a room's side are placed by ``u`` along the whole side, counter-
clockwise round the room (south side from west to east, east side from south to north, north
side from east to west, west side from north to south), as on the walls of single-room worlds;
one that straddles an opening is an error.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from drivers.sim.world_parts import Box, BoxSpec, Decal, Rect, Wall, Window, _Model

#: Thickest wall two rooms joined by an opening may have between them, metres.
MAX_WALL_M = 0.5

Side = Literal["south", "east", "north", "west"]
_SIDES: tuple[Side, ...] = ("south", "east", "north", "west")


class RoomSide(_Model):
    """One side of a room: its texture (default the room's ``wall_texture``), decals, windows."""

    texture: str | None = None
    decals: tuple[Decal, ...] = ()
    windows: tuple[Window, ...] = ()


class Room(_Model):
    """A room: the rectangle of its free floor, its wall, floor and ceiling textures (floor and
    ceiling default to the world's ``floor_texture``/``ceiling_texture``)."""

    id: str
    rect: Rect
    wall_texture: str
    floor_texture: str | None = None
    ceiling_texture: str | None = None
    sides: dict[Side, RoomSide] = {}


class Opening(_Model):
    """A doorway between rooms ``rooms[0]`` and ``rooms[1]``: ``width`` around ``center`` along
    their shared wall, open up to ``height`` (a lintel box above, unless it reaches the ceiling).
    ``texture``: jambs and lintel (default the first room's wall texture)."""

    id: str
    rooms: tuple[str, str]
    center: float
    width: float = Field(gt=0.0)
    height: float = Field(2.1, gt=0.0)
    texture: str | None = None


@dataclass(frozen=True)
class Cell:
    """A convex cell of the floor: a room or a passage, with its floor and ceiling textures."""

    id: str
    rect: tuple[float, float, float, float]  # xmin, xmax, ymin, ymax
    floor_texture: str
    ceiling_texture: str
    passage: bool


@dataclass(frozen=True)
class Portal:
    """An open segment between cells ``a`` and ``b`` (end points ``p0``, ``p1``)."""

    a: int
    b: int
    p0: tuple[float, float]
    p1: tuple[float, float]


@dataclass(frozen=True)
class Layout:
    """Resolved rooms and openings (see the module docstring). ``wall_cell[i]`` and
    ``wall_normal[i]`` (unit, into the cell) belong to ``walls[i]``."""

    cells: tuple[Cell, ...]
    portals: tuple[Portal, ...]
    walls: tuple[Wall, ...]
    wall_cell: np.ndarray  # (W,) int
    wall_normal: np.ndarray  # (W, 2)
    lintels: tuple[Box, ...]

    @property
    def rects(self) -> np.ndarray:
        """(C, 4) cell rectangles (xmin, xmax, ymin, ymax)."""
        return np.array([c.rect for c in self.cells], np.float64).reshape(-1, 4)


def _side_geometry(r: Rect, side: Side) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
    """(start, end, inward normal) of a room side, counter-clockwise round the room."""
    x0, x1, y0, y1 = r.xmin, r.xmax, r.ymin, r.ymax
    return {
        "south": ((x0, y0), (x1, y0), (0.0, 1.0)),
        "east": ((x1, y0), (x1, y1), (-1.0, 0.0)),
        "north": ((x1, y1), (x0, y1), (0.0, -1.0)),
        "west": ((x0, y1), (x0, y0), (1.0, 0.0)),
    }[side]


def _facing(a: Rect, b: Rect) -> tuple[Side, Side, float, float] | None:
    """(side of a, side of b, wall line of a, wall line of b) when a and b face each other
    across a wall of thickness in (0, MAX_WALL_M]; else None."""
    for sa, sb, la, lb in (("east", "west", a.xmax, b.xmin), ("west", "east", a.xmin, b.xmax),
                           ("north", "south", a.ymax, b.ymin), ("south", "north", a.ymin, b.ymax)):
        gap = (lb - la) if sa in ("east", "north") else (la - lb)
        if 0.0 < gap <= MAX_WALL_M + 1e-9:
            return sa, sb, la, lb
    return None


def _to_u(r: Rect, side: Side, lo: float, hi: float) -> tuple[float, float]:
    """A coordinate interval along a side (x for south/north, y for east/west) as u along it."""
    if side == "south":
        return lo - r.xmin, hi - r.xmin
    if side == "east":
        return lo - r.ymin, hi - r.ymin
    if side == "north":
        return r.xmax - hi, r.xmax - lo
    return r.ymax - hi, r.ymax - lo


def _overlap(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> bool:
    return min(a[1], b[1]) - max(a[0], b[0]) > 1e-9 and min(a[3], b[3]) - max(a[2], b[2]) > 1e-9


def build_layout(rooms: tuple[Room, ...], openings: tuple[Opening, ...], ceiling_height: float,
                 floor_texture: str, ceiling_texture: str) -> Layout:
    """Cells, portals, walls and lintels of ``rooms`` joined by ``openings``.

    Raises ValueError naming the field (``rooms.3``, ``openings.1.center``, ...) when rooms
    overlap, an opening's rooms do not face each other across one wall, an opening does not
    fit on that wall or overlaps another, or a decal or window straddles an opening."""
    index = {r.id: i for i, r in enumerate(rooms)}
    if len(index) != len(rooms):
        raise ValueError("rooms: ids must be unique")
    cells = [Cell(r.id, r.rect.as_tuple(), r.floor_texture or floor_texture, r.ceiling_texture or ceiling_texture,
                  False) for r in rooms]
    for i in range(len(rooms)):
        for j in range(i):
            if _overlap(cells[i].rect, cells[j].rect):
                raise ValueError(f"rooms.{i}: room '{rooms[i].id}' overlaps room '{rooms[j].id}'")
    cuts: dict[tuple[int, Side], list[tuple[float, float, int]]] = {}
    portals: list[Portal] = []
    walls: list[Wall] = []
    wall_cell: list[int] = []
    normals: list[tuple[float, float]] = []
    lintels: list[Box] = []
    for k, op in enumerate(openings):
        ids = []
        for name in op.rooms:
            if name not in index:
                raise ValueError(f"openings.{k}.rooms: unknown room '{name}'")
            ids.append(index[name])
        ia, ib = ids
        ra, rb = rooms[ia].rect, rooms[ib].rect
        face = _facing(ra, rb)
        if face is None:
            raise ValueError(f"openings.{k}.rooms: rooms '{op.rooms[0]}' and '{op.rooms[1]}' do not face each "
                             f"other across one wall (0 < thickness <= {MAX_WALL_M} m)")
        sa, sb, la, lb = face
        lo, hi = op.center - op.width / 2.0, op.center + op.width / 2.0
        vertical = sa in ("east", "west")  # the wall runs along y
        span = [(r.ymin, r.ymax) if vertical else (r.xmin, r.xmax) for r in (ra, rb)]
        if lo < max(s[0] for s in span) - 1e-9 or hi > min(s[1] for s in span) + 1e-9:
            raise ValueError(f"openings.{k}.center: the opening [{lo:g}, {hi:g}] does not fit on the wall "
                             f"shared by '{op.rooms[0]}' and '{op.rooms[1]}'")
        if op.height < ceiling_height - 1e-9 and op.height <= 0.5:
            raise ValueError(f"openings.{k}.height: {op.height} m is too low")
        g0, g1 = min(la, lb), max(la, lb)
        rect = (g0, g1, lo, hi) if vertical else (lo, hi, g0, g1)
        c = len(rooms) + k
        tex = op.texture or rooms[ia].wall_texture
        cells.append(Cell(op.id or f"opening{k}", rect, cells[ia].floor_texture, cells[ia].ceiling_texture, True))
        for ri, side in ((ia, sa), (ib, sb)):
            cuts.setdefault((ri, side), []).append((*_to_u(rooms[ri].rect, side, lo, hi), k, lo, hi))
        for line, ri in ((la, ia), (lb, ib)):
            p0, p1 = ((line, lo), (line, hi)) if vertical else ((lo, line), (hi, line))
            portals.append(Portal(ri, c, p0, p1))
        for v, n in ((lo, 1.0), (hi, -1.0)):  # jambs, normals into the passage
            start, end = ((g0, v), (g1, v)) if vertical else ((v, g0), (v, g1))
            walls.append(Wall(id=f"{cells[c].id}.jamb", start=start, end=end, texture=tex))
            wall_cell.append(c)
            normals.append((0.0, n) if vertical else (n, 0.0))
        if op.height < ceiling_height - 1e-9:
            cx, cy = 0.5 * (rect[0] + rect[1]), 0.5 * (rect[2] + rect[3])
            sx, sy = rect[1] - rect[0], rect[3] - rect[2]
            spec = BoxSpec(size=(sx, sy), zmin=op.height, zmax=ceiling_height, texture=tex)
            lintels.append(Box(owner=f"{cells[c].id}.lintel", cx=cx, cy=cy, hx=sx / 2, hy=sy / 2, yaw=0.0,
                               zmin=op.height, zmax=ceiling_height, spec=spec))
    for i, c in enumerate(cells[len(rooms):]):
        for d in cells[:len(rooms) + i]:
            if _overlap(c.rect, d.rect):
                raise ValueError(f"openings.{i}: its doorway overlaps '{d.id}'")
    for ri, room in enumerate(rooms):
        for side in _SIDES:
            w, n = _room_side_walls(ri, room, side, sorted(cuts.get((ri, side), [])))
            walls.extend(w)
            wall_cell.extend([ri] * len(w))
            normals.extend([n] * len(w))
    return Layout(cells=tuple(cells), portals=tuple(portals), walls=tuple(walls),
                  wall_cell=np.array(wall_cell, np.int64), wall_normal=np.array(normals, np.float64).reshape(-1, 2),
                  lintels=tuple(lintels))


def _room_side_walls(ri: int, room: Room, side: Side, cuts: list[tuple[float, float, int, float, float]]
                     ) -> tuple[list[Wall], tuple[float, float]]:
    """The wall segments of one side of a room between its openings' cuts (u intervals, with
    the opening's end coordinates along the side, so that walls and portals share end points
    exactly)."""
    start, end, normal = _side_geometry(room.rect, side)
    length = float(np.hypot(end[0] - start[0], end[1] - start[1]))
    along_x = side in ("south", "north")
    fixed = start[1] if along_x else start[0]

    def point(coord: float) -> tuple[float, float]:
        return (coord, fixed) if along_x else (fixed, coord)

    forward = side in ("south", "east")
    spec = room.sides.get(side, RoomSide())
    tex = spec.texture or room.wall_texture
    where = f"rooms.{ri}.sides.{side}"
    bounds = [0.0]
    coords = [start[0] if along_x else start[1]]
    for k, (u0, u1, op, lo, hi) in enumerate(cuts):
        if k and u0 < bounds[-1] - 1e-9:
            raise ValueError(f"openings.{op}: overlaps another opening on {where}")
        bounds += [u0, u1]
        coords += [lo, hi] if forward else [hi, lo]
    bounds.append(length)
    coords.append(end[0] if along_x else end[1])
    keep = [i for i in range(0, len(bounds), 2) if bounds[i + 1] - bounds[i] > 1e-6]
    segments = [(bounds[i], bounds[i + 1]) for i in keep]

    def place(items: tuple, name: str) -> list[list]:
        out: list[list] = [[] for _ in segments]
        for j, it in enumerate(items):
            for s, (u0, u1) in enumerate(segments):
                if it.u >= u0 - 1e-9 and it.u + it.width <= u1 + 1e-9:
                    out[s].append(it.model_copy(update={"u": it.u - u0}))
                    break
            else:
                raise ValueError(f"{where}.{name}.{j}: not on one wall segment (it straddles an opening "
                                 f"or leaves the side)")
        return out

    decals = place(spec.decals, "decals")
    windows: list[list[Window]] = place(spec.windows, "windows")
    walls = []
    for s, i in enumerate(keep):
        a, b = point(coords[i]), point(coords[i + 1])
        walls.append(Wall(id=f"{room.id}.{side}.{s}", start=a, end=b, texture=tex,
                          decals=tuple(decals[s]), windows=tuple(windows[s])))
    return walls, normal

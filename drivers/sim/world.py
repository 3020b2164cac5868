"""Simulated buildings as data: the world model, its loader, free space and the survey grid.

A world file (``config/worlds/<name>.json``) describes one floor of a building:

- ``room``: the floor rectangle (floor and ceiling cover it), ``ceiling_height``;
- ``mapped_area``: the rectangle the appearance map covers (paper sections 6.1 and 6.2);
- ``textures``: named procedural albedo textures (see :mod:`drivers.sim.textures`);
- ``walls``: floor-to-ceiling wall segments with a texture and *decals* painted on them
  (doors, posters, whiteboards, ...) and *windows* (curtains, or an outside view that
  emits light when the curtains are open); walls inside the room rectangle divide it into
  rooms (an open door is a gap between two segments, its lintel a box above the robot's
  height; they cast shadows, see :mod:`drivers.sim.lighting`);
- ``templates`` and ``furniture``: pieces of furniture made of boxes (axis-aligned or
  rotated footprints, ``zmin``/``zmax``); a template reused several times gives
  identical pieces, which is what makes single views ambiguous;
- ``lighting``: one setup per name (``tube``, ``bulb``, ``natural``) with its light sources;
- ``scene_changes``: named sets that add, move or remove furniture (``boxes``,
  ``moved_furniture``, ``people``), unknown to the map;
- ``survey`` (optional): the default grid of ``lino-loc survey`` (``step``, ``heading_step_deg``);
- ``rooms`` and ``openings`` (optional, then ``walls`` stays empty): a floor of several
  rooms, each with its own wall, floor and ceiling textures, joined by doorways; their walls,
  door jambs and lintels are generated (:mod:`drivers.sim.rooms`), and the renderer and the
  light bake cull what one room cannot see of the others (:mod:`drivers.sim.visibility`).

:func:`load_world` validates the file with pydantic; any mistake raises
:class:`lino_loc.errors.LinoLocError` naming the file and the field. :class:`World` resolves
a world plus a list of scene changes into flat geometry (wall segments, boxes) used by
the renderer, by :meth:`World.is_free` and by :func:`grid_poses`.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, ValidationError, model_validator

from drivers.sim.config_files import WORLDS_DIR
from drivers.sim.rooms import Layout, Opening, Room, build_layout
from drivers.sim.world_parts import (
    Box,
    BoxSpec,
    Decal,
    Rect,
    TextureSpec,
    Vec2,
    Vec3,
    Wall,
    Window,
    _Model,
)
from lino_loc.errors import LinoLocError

__all__ = [
    "WORLDS_DIR", "Box", "BoxSpec", "Decal", "Furniture", "Geometry", "Light", "LightingSetup", "Opening",
    "Rect", "Room", "SceneChange", "SurveyGrid", "TextureSpec", "Vec2", "Vec3", "Wall", "Window", "World", "WorldSpec",
    "grid_poses", "load_world",
]


class Furniture(_Model):
    """One piece of furniture: a ``template`` name or inline ``boxes``, at ``pose`` = (x, y, yaw_deg)."""

    id: str
    pose: Vec3 = (0.0, 0.0, 0.0)
    template: str | None = None
    boxes: tuple[BoxSpec, ...] = ()

    @model_validator(mode="after")
    def _one_of(self) -> Furniture:
        if (self.template is None) == (not self.boxes):
            raise ValueError("give exactly one of 'template' or 'boxes'")
        return self


class Light(_Model):
    """A light source.

    - ``point``: at ``position``, ``power`` (radiant intensity), optional downward lobe
      exponent ``lobe`` (0 = isotropic);
    - ``tube``: a fluorescent tube from ``start`` to ``end``, ``power`` per metre, cosine lobe
      pointing down; ``fixture`` draws its glowing diffuser on the ceiling;
    - ``sun``: parallel light of irradiance ``power`` coming from ``direction`` (pointing
      from the sun into the room), entering only through open windows.
    """

    type: Literal["point", "tube", "sun"]
    position: Vec3 | None = None
    start: Vec3 | None = None
    end: Vec3 | None = None
    direction: Vec3 | None = None
    power: float = Field(gt=0.0)
    lobe: float = Field(0.0, ge=0.0)
    samples: int = Field(4, ge=1, le=64)
    fixture: bool = True

    @model_validator(mode="after")
    def _fields(self) -> Light:
        need = {"point": ("position",), "tube": ("start", "end"), "sun": ("direction",)}[self.type]
        for name in need:
            if getattr(self, name) is None:
                raise ValueError(f"a {self.type} light needs '{name}'")
        return self


class LightingSetup(_Model):
    """Light sources of one lighting setup, plus ambient (indirect) irradiance.

    ``windows_open``: curtains open; the windows then show their view with radiance
    ``window_radiance`` and light the room as area sources.
    """

    ambient: float = Field(0.05, ge=0.0)
    lights: tuple[Light, ...] = ()
    windows_open: bool = False
    window_radiance: float = Field(0.0, ge=0.0)
    window_samples: Vec2 = (6, 3)


class SceneChange(_Model):
    """Changes the map does not know about: add furniture, move it (new pose), remove it."""

    add: tuple[Furniture, ...] = ()
    move: dict[str, Vec3] = {}
    remove: tuple[str, ...] = ()


class SurveyGrid(_Model):
    """The world's default survey grid (``lino-loc survey`` without ``--step``/``--heading-step``)."""

    step: float = Field(gt=0.0)
    heading_step_deg: float = Field(gt=0.0, le=360.0)


class WorldSpec(_Model):
    name: str
    description: str = ""
    room: Rect
    mapped_area: Rect
    ceiling_height: float = Field(gt=0.5)
    floor_texture: str
    ceiling_texture: str
    textures: dict[str, TextureSpec]
    walls: tuple[Wall, ...]
    templates: dict[str, tuple[BoxSpec, ...]] = {}
    furniture: tuple[Furniture, ...] = ()
    lighting: dict[str, LightingSetup]
    scene_changes: dict[str, SceneChange] = {}
    rooms: tuple[Room, ...] = ()
    openings: tuple[Opening, ...] = ()
    survey: SurveyGrid | None = None

    @model_validator(mode="after")
    def _references(self) -> WorldSpec:
        tex = self.textures

        def need(name: str, where: str) -> None:
            if name not in tex:
                raise ValueError(f"{where}: unknown texture '{name}'")

        need(self.floor_texture, "floor_texture")
        need(self.ceiling_texture, "ceiling_texture")
        for i, w in enumerate(self.walls):
            need(w.texture, f"walls.{i}.texture")
            for j, d in enumerate(w.decals):
                need(d.texture, f"walls.{i}.decals.{j}.texture")
            for j, win in enumerate(w.windows):
                need(win.curtain, f"walls.{i}.windows.{j}.curtain")
                need(win.view, f"walls.{i}.windows.{j}.view")

        def check_boxes(boxes: tuple[BoxSpec, ...], where: str) -> None:
            for j, b in enumerate(boxes):
                need(b.texture, f"{where}.{j}.texture")
                for face, name in b.faces.items():
                    need(name, f"{where}.{j}.faces.{face}")
                if b.zmax > self.ceiling_height + 1e-6:
                    raise ValueError(f"{where}.{j}.zmax: above the ceiling")

        for name, boxes in self.templates.items():
            check_boxes(boxes, f"templates.{name}")

        def check_furniture(items: tuple[Furniture, ...], where: str) -> None:
            for i, f in enumerate(items):
                if f.template is not None and f.template not in self.templates:
                    raise ValueError(f"{where}.{i}.template: unknown template '{f.template}'")
                check_boxes(f.boxes, f"{where}.{i}.boxes")

        check_furniture(self.furniture, "furniture")
        ids = [f.id for f in self.furniture]
        if len(set(ids)) != len(ids):
            raise ValueError("furniture: ids must be unique")
        for name, ch in self.scene_changes.items():
            check_furniture(ch.add, f"scene_changes.{name}.add")
            for fid in list(ch.move) + list(ch.remove):
                if fid not in ids:
                    raise ValueError(f"scene_changes.{name}: unknown furniture id '{fid}'")
        if not self.lighting:
            raise ValueError("lighting: at least one setup is needed")
        self._check_rooms(need)
        return self

    def _check_rooms(self, need: Any) -> None:
        """Rooms and openings: textures known, rooms inside ``room``, a consistent layout."""
        if self.openings and not self.rooms:
            raise ValueError("openings: need rooms")
        if not self.rooms:
            return
        if self.walls:
            raise ValueError("walls: a world with rooms takes its walls from its rooms (leave walls empty)")
        xmin, xmax, ymin, ymax = self.room.as_tuple()
        for i, r in enumerate(self.rooms):
            for name, t in (("wall_texture", r.wall_texture), ("floor_texture", r.floor_texture),
                            ("ceiling_texture", r.ceiling_texture)):
                if t is not None:
                    need(t, f"rooms.{i}.{name}")
            for side, rs in r.sides.items():
                where = f"rooms.{i}.sides.{side}"
                if rs.texture is not None:
                    need(rs.texture, f"{where}.texture")
                for j, d in enumerate(rs.decals):
                    need(d.texture, f"{where}.decals.{j}.texture")
                for j, win in enumerate(rs.windows):
                    need(win.curtain, f"{where}.windows.{j}.curtain")
                    need(win.view, f"{where}.windows.{j}.view")
            q = r.rect
            if q.xmin < xmin - 1e-9 or q.xmax > xmax + 1e-9 or q.ymin < ymin - 1e-9 or q.ymax > ymax + 1e-9:
                raise ValueError(f"rooms.{i}.rect: room '{r.id}' is not inside 'room'")
        for k, op in enumerate(self.openings):
            if op.texture is not None:
                need(op.texture, f"openings.{k}.texture")
        build_layout(self.rooms, self.openings, self.ceiling_height, self.floor_texture, self.ceiling_texture)


@dataclass(frozen=True)
class Geometry:
    """Flat geometry of a world with a set of scene changes applied."""

    walls: tuple[Wall, ...]
    boxes: tuple[Box, ...]
    changes: tuple[str, ...]
    layout: Layout | None = None


class World:
    """A loaded world (``spec`` is the validated :class:`WorldSpec`; ``source`` its file)."""

    def __init__(self, spec: WorldSpec, source: str = "<memory>") -> None:
        self.spec = spec
        self.source = source
        self._geometry: dict[tuple[str, ...], Geometry] = {}

    # -- simple accessors -------------------------------------------------------------
    @property
    def fingerprint(self) -> str:
        """SHA-1 of the validated world content (keys the bake cache)."""
        fp = getattr(self, "_fingerprint", None)
        if fp is None:
            # a world without rooms hashes as before rooms existed (caches stay valid)
            empty = {k for k in ("rooms", "openings", "survey") if not getattr(self.spec, k)}
            fp = hashlib.sha1(self.spec.model_dump_json(exclude=empty).encode()).hexdigest()
            self._fingerprint = fp
        return fp

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def mapped_area(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the mapped area, metres."""
        return self.spec.mapped_area.as_tuple()

    @property
    def room(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the room's floor, metres."""
        return self.spec.room.as_tuple()

    @property
    def layout(self) -> Layout | None:
        """Cells, portals, walls and lintels of the world's rooms (:mod:`drivers.sim.rooms`);
        None for a world without rooms."""
        if not self.spec.rooms:
            return None
        lay = getattr(self, "_layout", None)
        if lay is None:
            sp = self.spec
            lay = build_layout(sp.rooms, sp.openings, sp.ceiling_height, sp.floor_texture, sp.ceiling_texture)
            self._layout = lay
        return lay

    @property
    def lighting_names(self) -> tuple[str, ...]:
        return tuple(self.spec.lighting)

    @property
    def scene_change_names(self) -> tuple[str, ...]:
        return tuple(self.spec.scene_changes)

    def check_lighting(self, name: str) -> LightingSetup:
        """The lighting setup called name; LinoLocError naming the known setups otherwise."""
        if name not in self.spec.lighting:
            raise LinoLocError(
                f"world '{self.name}': unknown lighting '{name}' (have: {', '.join(self.spec.lighting)})"
            )
        return self.spec.lighting[name]

    def check_changes(self, names: tuple[str, ...] | list[str]) -> tuple[str, ...]:
        """The scene-change names in order, duplicates dropped; LinoLocError on an unknown one."""
        out = []
        for n in names:
            if n not in self.spec.scene_changes:
                have = ", ".join(self.spec.scene_changes) or "none"
                raise LinoLocError(f"world '{self.name}': unknown scene change '{n}' (have: {have})")
            if n not in out:
                out.append(n)
        return tuple(out)

    # -- geometry ---------------------------------------------------------------------
    def geometry(self, scene_changes: tuple[str, ...] | list[str] = ()) -> Geometry:
        """Walls and boxes with the named scene changes applied (in order)."""
        key = self.check_changes(tuple(scene_changes))
        if key in self._geometry:
            return self._geometry[key]
        items: dict[str, Furniture] = {f.id: f for f in self.spec.furniture}
        for name in key:
            ch = self.spec.scene_changes[name]
            for fid in ch.remove:
                items.pop(fid, None)
            for fid, pose in ch.move.items():
                if fid in items:
                    items[fid] = items[fid].model_copy(update={"pose": pose})
            for f in ch.add:
                items[f.id] = f
        boxes: list[Box] = []
        for f in items.values():
            specs = self.spec.templates[f.template] if f.template is not None else f.boxes
            px, py, pyaw = f.pose[0], f.pose[1], math.radians(f.pose[2])
            c, s = math.cos(pyaw), math.sin(pyaw)
            for b in specs:
                boxes.append(
                    Box(
                        owner=f.id,
                        cx=px + c * b.center[0] - s * b.center[1],
                        cy=py + s * b.center[0] + c * b.center[1],
                        hx=b.size[0] / 2.0,
                        hy=b.size[1] / 2.0,
                        yaw=pyaw + math.radians(b.yaw_deg),
                        zmin=b.zmin,
                        zmax=b.zmax,
                        spec=b,
                    )
                )
        lay = self.layout
        if lay is None:
            geo = Geometry(walls=self.spec.walls, boxes=tuple(boxes), changes=key)
        else:
            geo = Geometry(walls=self.spec.walls + lay.walls, boxes=tuple(boxes) + lay.lintels, changes=key,
                           layout=lay)
        self._geometry[key] = geo
        return geo

    def is_free(
        self,
        x: Any,
        y: Any,
        radius: float = 0.25,
        scene_changes: tuple[str, ...] | list[str] = (),
        robot_height: float = 1.4,
    ) -> np.ndarray:
        """True where a robot disc of ``radius`` at (x, y) is inside the room and touches no
        wall and no box whose bottom is below ``robot_height``. Vectorized over arrays."""
        px = np.asarray(x, dtype=np.float64)
        py = np.asarray(y, dtype=np.float64)
        px, py = np.broadcast_arrays(px, py)
        xmin, xmax, ymin, ymax = self.room
        free = (px - radius >= xmin) & (px + radius <= xmax) & (py - radius >= ymin) & (py + radius <= ymax)
        geo = self.geometry(scene_changes)
        for w in geo.walls:
            ax, ay = w.start
            bx, by = w.end
            ex, ey = bx - ax, by - ay
            t = np.clip(((px - ax) * ex + (py - ay) * ey) / (ex * ex + ey * ey), 0.0, 1.0)
            d = np.hypot(px - (ax + t * ex), py - (ay + t * ey))
            free &= d > radius
        for b in geo.boxes:
            if b.zmin >= robot_height:
                continue
            c, s = math.cos(b.yaw), math.sin(b.yaw)
            lx = c * (px - b.cx) + s * (py - b.cy)
            ly = -s * (px - b.cx) + c * (py - b.cy)
            dx = np.maximum(np.abs(lx) - b.hx, 0.0)
            dy = np.maximum(np.abs(ly) - b.hy, 0.0)
            free &= np.hypot(dx, dy) > radius
        return free

    def is_mapped_free(self, x: Any, y: Any) -> np.ndarray:
        """True where (x, y) is free as mapped (:meth:`is_free`, no scene changes) and inside the
        :attr:`mapped_area` (its edges included): where a map's view positions may lie.
        Vectorized over arrays."""
        px, py = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        xmin, xmax, ymin, ymax = self.mapped_area
        return self.is_free(px, py) & (px >= xmin) & (px <= xmax) & (py >= ymin) & (py <= ymax)

    # -- plotting ---------------------------------------------------------------------
    def floor_plan(self, scene_changes: tuple[str, ...] | list[str] = ()) -> dict[str, Any]:
        """Floor plan for plots: ``walls`` (M, 2, 2) segments, ``boxes`` list of (4, 2)
        footprints, ``windows`` (W, 2, 2) segments, ``mapped_area`` and ``room`` rectangles."""
        geo = self.geometry(scene_changes)
        walls = np.array([[w.start, w.end] for w in geo.walls], dtype=np.float64)
        windows = []
        for w in geo.walls:
            a = np.array(w.start)
            e = np.array(w.end) - a
            e /= np.linalg.norm(e)
            for win in w.windows:
                windows.append([a + e * win.u, a + e * (win.u + win.width)])
        return {
            "walls": walls,
            "boxes": [b.corners() for b in geo.boxes],
            "windows": np.array(windows, dtype=np.float64).reshape(-1, 2, 2),
            "mapped_area": self.mapped_area,
            "room": self.room,
        }

    def plot_floor_plan(self, ax: Any, scene_changes: tuple[str, ...] | list[str] = ()) -> None:
        """Draw the floor plan on a matplotlib axis (walls black, windows cyan, boxes grey,
        mapped area dashed)."""
        plan = self.floor_plan(scene_changes)
        for (x0, y0), (x1, y1) in plan["walls"]:
            ax.plot([x0, x1], [y0, y1], "k-", lw=2)
        for (x0, y0), (x1, y1) in plan["windows"]:
            ax.plot([x0, x1], [y0, y1], "c-", lw=4)
        for poly in plan["boxes"]:
            p = np.vstack([poly, poly[:1]])
            ax.fill(p[:, 0], p[:, 1], color="0.7", alpha=0.6)
            ax.plot(p[:, 0], p[:, 1], color="0.4", lw=0.8)
        xmin, xmax, ymin, ymax = plan["mapped_area"]
        ax.plot([xmin, xmax, xmax, xmin, xmin], [ymin, ymin, ymax, ymax, ymin], "b--", lw=1)
        ax.set_aspect("equal")


def grid_poses(
    world: World,
    step: float,
    heading_step_rad: float,
    radius: float = 0.25,
    scene_changes: tuple[str, ...] | list[str] = (),
) -> np.ndarray:
    """Survey grid: positions every ``step`` metres over the mapped area (from its minimum
    corner, both ends included), headings every ``heading_step_rad`` from 0, skipping
    positions where the robot disc of ``radius`` is not free. Returns (N, 3) float64,
    ordered by x, then y, then heading."""
    if step <= 0 or heading_step_rad <= 0:
        raise LinoLocError(f"grid step and heading step must be positive (got {step}, {heading_step_rad})")
    xmin, xmax, ymin, ymax = world.mapped_area
    xs = xmin + step * np.arange(int(math.floor((xmax - xmin) / step + 1e-9)) + 1)
    ys = ymin + step * np.arange(int(math.floor((ymax - ymin) / step + 1e-9)) + 1)
    nh = max(1, int(round(2 * math.pi / heading_step_rad)))
    if abs(nh * heading_step_rad - 2 * math.pi) > 1e-6:
        nh = int(math.floor(2 * math.pi / heading_step_rad - 1e-9)) + 1
    hs = heading_step_rad * np.arange(nh)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    gx, gy = gx.ravel(), gy.ravel()
    keep = world.is_free(gx, gy, radius, scene_changes)
    gx, gy = gx[keep], gy[keep]
    out = np.empty((gx.size * hs.size, 3))
    out[:, 0] = np.repeat(gx, hs.size)
    out[:, 1] = np.repeat(gy, hs.size)
    out[:, 2] = np.tile(np.arctan2(np.sin(hs), np.cos(hs)), gx.size)
    return out


def _error_location(err: dict[str, Any]) -> str:
    return ".".join(str(p) for p in err.get("loc", ())) or "<root>"


def load_world(name_or_path: str | Path) -> World:
    """Load a world by name (``config/worlds/<name>.json``) or by path.

    Raises :class:`LinoLocError` (one line, naming the file and the field) on a missing
    file, bad JSON or a bad field."""
    p = Path(name_or_path)
    if p.suffix == "" and not p.exists():
        p = WORLDS_DIR / f"{name_or_path}.json"
    if not p.is_file():
        have = ", ".join(sorted(q.stem for q in WORLDS_DIR.glob("*.json")))
        raise LinoLocError(f"world file {p}: not found (known worlds: {have})")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise LinoLocError(f"world file {p}: not valid JSON ({exc})") from None
    try:
        spec = WorldSpec.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        msg = str(err.get("msg", "invalid")).replace("\n", " ")
        raise LinoLocError(f"world file {p}: field {_error_location(err)}: {msg}") from None
    return World(spec, source=str(p))

"""Floor-sized worlds made of rooms: the ``floor`` world's file and the benchmark's floors.

:func:`floor_world` writes the data of ``config/worlds/floor.json`` (``scripts/make_floor_world.py``
saves it): a 40 x 25 m office floor, one east-west corridor with a row of rooms on each side,
every room opening on the corridor through a doorway, some rooms also on their neighbour.
Rooms differ (offices, meeting rooms, a lab, a kitchen; their wall, floor and ceiling
textures and furniture) and repeat as real floors do: the offices of a row are identical, with
the same furniture, posters and doors. Windows line the outer walls. The three lights of the
other worlds (``tube`` ceiling tubes, ``bulb`` desk and ceiling lamps, ``natural`` open
windows and the sun) and their scene changes (``boxes``, ``moved_furniture``, ``people``).

:func:`corridor_floor` makes the benchmark's floors of ``2 k`` identical offices along a
corridor (k a side), the same rooms whatever k, for measuring how costs grow with the number
of rooms (benchmarks/bench_render_rooms.py).

Furniture and lamps of a room are placed in the room's own frame: ``u`` along the window wall
from the room's west end (south row) or east end (north row), ``v`` from the window wall toward
the corridor; the rooms of the north row are those of the south row turned by 180 degrees, so
that identical rooms hold identical furniture.
"""

from __future__ import annotations

import json
from typing import Any

from drivers.sim.config_files import WORLDS_DIR

WALL_M = 0.15  # wall thickness between rooms
#: The floor's survey grid: the lab's spacing (benchmarks/bench_map_build.py --make-lab-survey:
#: 0.5 m, 10 deg), 3249 free positions x 36 headings = 116,964 views.
SURVEY_GRID = {"step": 0.5, "heading_step_deg": 10.0}
CEILING_M = 2.8
DOOR_W, DOOR_H = 1.0, 2.1

_TEXTURES: dict[str, dict[str, Any]] = {
    "wall_office": {"kind": "paint", "albedo": 0.74, "contrast": 0.04, "seed": 101},
    "wall_meeting": {"kind": "paint", "albedo": 0.6, "contrast": 0.06, "seed": 102},
    "wall_lab": {"kind": "paint", "albedo": 0.55, "contrast": 0.05, "seed": 103},
    "wall_kitchen": {"kind": "tiles", "albedo": 0.7, "albedo2": 0.6, "contrast": 0.08, "period": 0.2, "seed": 104},
    "wall_corridor": {"kind": "paint", "albedo": 0.68, "contrast": 0.04, "seed": 105},
    "carpet": {"kind": "carpet", "albedo": 0.32, "contrast": 0.12, "period": 0.4, "seed": 106},
    "carpet_red": {"kind": "carpet", "albedo": 0.26, "contrast": 0.16, "period": 0.3, "seed": 107},
    "lino": {"kind": "tiles", "albedo": 0.46, "albedo2": 0.36, "contrast": 0.1, "period": 0.6, "seed": 108},
    "kitchen_floor": {"kind": "tiles", "albedo": 0.55, "albedo2": 0.25, "contrast": 0.15, "period": 0.3, "seed": 109},
    "ceiling": {"kind": "ceiling_tiles", "albedo": 0.82, "albedo2": 0.62, "contrast": 0.03, "period": 0.6, "seed": 110},
    "ceiling_plain": {"kind": "paint", "albedo": 0.8, "contrast": 0.02, "seed": 111},
    "door": {"kind": "door", "albedo": 0.5, "albedo2": 0.28, "contrast": 0.12, "seed": 112},
    "door_store": {"kind": "door", "albedo": 0.35, "albedo2": 0.6, "contrast": 0.1, "seed": 113},
    "poster_a": {"kind": "poster", "albedo": 0.8, "seed": 114},
    "poster_b": {"kind": "poster", "albedo": 0.7, "seed": 115},
    "poster_c": {"kind": "poster", "albedo": 0.9, "seed": 116},
    "notice_board": {"kind": "poster", "albedo": 0.75, "seed": 117},
    "whiteboard": {"kind": "whiteboard", "albedo": 0.88, "seed": 118},
    "curtain": {"kind": "curtain", "albedo": 0.55, "contrast": 0.12, "period": 0.14, "seed": 119},
    "view": {"kind": "window_view", "albedo": 1.0, "seed": 120},
    "wood": {"kind": "wood", "albedo": 0.5, "contrast": 0.15, "period": 0.7, "seed": 121},
    "wood_dark": {"kind": "wood", "albedo": 0.3, "contrast": 0.2, "period": 0.7, "seed": 122},
    "desk_panel": {"kind": "paint", "albedo": 0.42, "contrast": 0.03, "seed": 123},
    "metal": {"kind": "metal", "albedo": 0.6, "albedo2": 0.2, "period": 0.32, "seed": 124},
    "metal_plain": {"kind": "paint", "albedo": 0.58, "contrast": 0.02, "seed": 125},
    "books": {"kind": "bookshelf", "albedo": 0.5, "albedo2": 0.45, "period": 0.36, "seed": 126},
    "books2": {"kind": "bookshelf", "albedo": 0.5, "albedo2": 0.45, "period": 0.36, "seed": 127},
    "fabric_blue": {"kind": "fabric", "albedo": 0.25, "contrast": 0.15, "period": 0.1, "seed": 128},
    "fabric_red": {"kind": "fabric", "albedo": 0.35, "contrast": 0.2, "period": 0.08, "seed": 129},
    "skin": {"kind": "paint", "albedo": 0.55, "contrast": 0.05, "seed": 130},
    "jeans": {"kind": "fabric", "albedo": 0.18, "contrast": 0.15, "period": 0.05, "seed": 131},
    "cardboard": {"kind": "cardboard", "albedo": 0.48, "contrast": 0.08, "seed": 132},
    "monitor": {"kind": "paint", "albedo": 0.06, "contrast": 0.02, "seed": 133},
    "fridge": {"kind": "paint", "albedo": 0.85, "contrast": 0.02, "seed": 134},
    "bench_top": {"kind": "paint", "albedo": 0.2, "contrast": 0.03, "seed": 135},
}


def _box(cx: float, cy: float, sx: float, sy: float, zmax: float, texture: str, zmin: float = 0.0,
         **faces: str) -> dict[str, Any]:
    b: dict[str, Any] = {"center": [cx, cy], "size": [sx, sy], "zmin": zmin, "zmax": zmax, "texture": texture}
    if faces:
        b["faces"] = faces
    return b


# templates: local +x is the front (the side a person uses)
_TEMPLATES: dict[str, list[dict[str, Any]]] = {
    "desk": [_box(0, 0, 0.7, 1.4, 0.75, "wood", zmin=0.72), _box(0, -0.68, 0.7, 0.03, 0.72, "desk_panel"),
             _box(0, 0.68, 0.7, 0.03, 0.72, "desk_panel"), _box(-0.3, 0.1, 0.05, 0.5, 1.15, "monitor", zmin=0.78)],
    "chair": [_box(0, 0, 0.08, 0.08, 0.42, "metal_plain"), _box(0, 0, 0.46, 0.46, 0.5, "fabric_blue", zmin=0.42),
              _box(-0.2, 0, 0.06, 0.46, 0.95, "fabric_blue", zmin=0.5)],
    "cabinet": [_box(0, 0, 0.5, 0.6, 1.3, "metal", top="metal_plain")],
    "shelf": [_box(0, 0, 0.35, 1.0, 1.9, "wood_dark", front="books")],
    "shelf2": [_box(0, 0, 0.35, 1.0, 1.9, "wood_dark", front="books2")],
    "table": [_box(0, 0, 1.2, 2.8, 0.75, "wood", zmin=0.72), _box(0, -1.1, 0.1, 0.1, 0.72, "metal_plain"),
              _box(0, 1.1, 0.1, 0.1, 0.72, "metal_plain")],
    "bench": [_box(0, 0, 0.9, 2.6, 0.9, "bench_top", front="metal"), _box(-0.35, 0, 0.2, 2.4, 1.6, "wood_dark",
                                                                           zmin=0.9, front="books")],
    "counter": [_box(0, 0, 0.6, 2.4, 0.9, "wood_dark", top="bench_top")],
    "fridge": [_box(0, 0, 0.65, 0.7, 1.8, "fridge")],
    "sofa": [_box(0, 0, 0.8, 1.8, 0.45, "fabric_red"), _box(-0.3, 0, 0.2, 1.8, 0.85, "fabric_red", zmin=0.45)],
    "person": [_box(0, 0, 0.22, 0.34, 0.85, "jeans"), _box(0, 0, 0.26, 0.46, 1.5, "fabric_blue", zmin=0.85),
               _box(0, 0, 0.2, 0.18, 1.75, "skin", zmin=1.5)],
    "box_big": [_box(0, 0, 0.6, 0.5, 0.5, "cardboard")],
    "box_small": [_box(0, 0, 0.4, 0.35, 0.35, "cardboard")],
}

# room kinds: textures, furniture (template, u, v, yaw_deg in the room frame), lamps (u, v, z, power, lobe)
_KINDS: dict[str, dict[str, Any]] = {
    "office": {"wall": "wall_office", "floor": "carpet", "ceiling": "ceiling",
               "furniture": [("desk", 1.6, 0.75, 90), ("chair", 1.6, 1.4, -90), ("desk", 4.0, 0.75, 90),
                             ("chair", 4.0, 1.4, -90), ("shelf", 0.25, 4.5, 0), ("cabinet", 0.3, 2.5, 0)],
               "lamps": [(1.6, 0.8, 1.15, 5.0, 2.0), (4.0, 0.8, 1.15, 5.0, 2.0)],
               "posters": [("poster_a", 1.5, 1.4, 0.6, 0.85)]},
    "meeting": {"wall": "wall_meeting", "floor": "carpet_red", "ceiling": "ceiling_plain",
                "furniture": [("table", 4.5, 4.5, 0), ("chair", 3.5, 3.5, 90), ("chair", 3.5, 5.5, 90),
                              ("chair", 5.5, 3.5, -90), ("chair", 5.5, 5.5, -90), ("shelf2", 0.25, 8.0, 0)],
                "lamps": [(4.5, 4.5, 2.4, 8.0, 0.5)],
                "posters": [("whiteboard", 2.0, 0.9, 2.0, 1.1)]},
    "lab": {"wall": "wall_lab", "floor": "lino", "ceiling": "ceiling",
            "furniture": [("bench", 3.0, 4.0, 90), ("bench", 7.0, 4.0, 90), ("cabinet", 0.3, 8.5, 0),
                          ("cabinet", 0.3, 7.8, 0), ("shelf", 9.7, 6.0, 180), ("desk", 8.5, 0.75, 90)],
            "lamps": [(3.0, 4.0, 2.2, 6.0, 1.0), (7.0, 4.0, 2.2, 6.0, 1.0), (8.5, 0.8, 1.15, 5.0, 2.0)],
            "posters": [("poster_b", 4.0, 1.4, 0.6, 0.85), ("poster_c", 6.0, 1.4, 0.6, 0.85)]},
    "kitchen": {"wall": "wall_kitchen", "floor": "kitchen_floor", "ceiling": "ceiling_plain",
                "furniture": [("counter", 0.3, 5.0, 0), ("fridge", 0.35, 7.0, 0), ("table", 6.0, 5.0, 90),
                              ("sofa", 10.0, 2.5, 180), ("chair", 5.0, 3.8, 0), ("chair", 7.0, 3.8, 0)],
                "lamps": [(6.0, 5.0, 2.3, 8.0, 0.5), (0.6, 5.0, 1.8, 4.0, 0.3)],
                "posters": [("notice_board", 3.0, 1.2, 1.2, 0.9)]},
}


def _room_xy(room: dict[str, Any], u: float, v: float) -> tuple[float, float]:
    r = room["rect"]
    if room["_row"] == "south":
        return r["xmin"] + u, r["ymin"] + v
    return r["xmax"] - u, r["ymax"] - v


def _tubes(rect: dict[str, float], along_x: bool) -> list[dict[str, Any]]:
    """Ceiling tubes (1.2 m) on a 2.4 m lattice centred in the rectangle."""
    out = []
    w, d = rect["xmax"] - rect["xmin"], rect["ymax"] - rect["ymin"]
    nx, ny = max(1, int(w // 2.4)), max(1, int(d // 2.4))
    for i in range(nx):
        for j in range(ny):
            cx = rect["xmin"] + (i + 0.5) * w / nx
            cy = rect["ymin"] + (j + 0.5) * d / ny
            a, b = ([cx - 0.6, cy], [cx + 0.6, cy]) if along_x else ([cx, cy - 0.6], [cx, cy + 0.6])
            out.append({"type": "tube", "start": [*a, CEILING_M - 0.02], "end": [*b, CEILING_M - 0.02],
                        "power": 5.0, "samples": 2})
    return out


def _build(name: str, description: str, rooms: list[dict[str, Any]], corridor: dict[str, Any],
           openings: list[dict[str, Any]], changes: dict[str, Any],
           survey: dict[str, float] | None = None) -> dict[str, Any]:
    furniture, lamps, tubes = [], [], []
    for room in rooms:
        kind = _KINDS[room["_kind"]]
        yaw0 = 0 if room["_row"] == "south" else 180
        for k, (tpl, u, v, yaw) in enumerate(kind["furniture"]):
            x, y = _room_xy(room, u, v)
            furniture.append({"id": f"{room['id']}.{tpl}{k}", "template": tpl,
                              "pose": [round(x, 4), round(y, 4), (yaw + yaw0 + 180) % 360 - 180]})
        for u, v, z, power, lobe in kind["lamps"]:
            x, y = _room_xy(room, u, v)
            lamps.append({"type": "point", "position": [round(x, 4), round(y, 4), z], "power": power, "lobe": lobe})
        tubes += _tubes(room["rect"], along_x=True)
    tubes += _tubes(corridor["rect"], along_x=False)
    c = corridor["rect"]
    for k in range(int((c["xmax"] - c["xmin"]) // 5.0)):
        x = c["xmin"] + 2.5 + 5.0 * k
        lamps.append({"type": "point", "position": [x, 0.5 * (c["ymin"] + c["ymax"]), 2.6], "power": 4.5, "lobe": 1.0})
    all_rooms = [{k: v for k, v in r.items() if not k.startswith("_")} for r in [*rooms, corridor]]
    xs = [r["rect"]["xmin"] for r in all_rooms] + [r["rect"]["xmax"] for r in all_rooms]
    ys = [r["rect"]["ymin"] for r in all_rooms] + [r["rect"]["ymax"] for r in all_rooms]
    area = {"xmin": min(xs), "xmax": max(xs), "ymin": min(ys), "ymax": max(ys)}
    return {
        "name": name, "description": description, "room": area, "mapped_area": area,
        "ceiling_height": CEILING_M, "floor_texture": "lino", "ceiling_texture": "ceiling",
        "textures": _TEXTURES, "walls": [], "templates": _TEMPLATES, "furniture": furniture,
        "rooms": all_rooms, "openings": openings,
        "lighting": {
            "tube": {"ambient": 1.5, "lights": tubes},
            "bulb": {"ambient": 0.15, "lights": lamps},
            "natural": {"ambient": 0.8, "windows_open": True, "window_radiance": 10.0, "window_samples": [4, 2],
                        "lights": [{"type": "sun", "direction": [0.3, -0.6, -0.75], "power": 15.0}]},
        },
        "scene_changes": changes,
        **({"survey": survey} if survey else {}),
    }


def _row_room(rid: str, kind: str, row: str, x0: float, width: float, y0: float, y1: float,
              door_u: float) -> dict[str, Any]:
    """A room of a row: windows on the outer side, posters on the inner, door decal texture near the door."""
    k = _KINDS[kind]
    outer, inner = ("south", "north") if row == "south" else ("north", "south")
    n_win = max(1, int(width // 2.4))
    wins = [{"u": round((i + 0.5) * width / n_win - 0.75, 4), "z": 0.95, "width": 1.5, "height": 1.6,
             "curtain": "curtain", "view": "view"} for i in range(n_win)]
    decals = []
    for tex, u, z, w, h in k["posters"]:
        # on the corridor side, ``u`` beyond the door (before it when that leaves the side)
        uu = door_u + DOOR_W / 2 + u
        if uu + w > width - 0.1:
            uu = max(0.1, door_u - DOOR_W / 2 - u - w)
        decals.append({"texture": tex, "u": round(uu, 4), "z": z, "width": w, "height": h})
    return {"id": rid, "rect": {"xmin": x0, "xmax": x0 + width, "ymin": y0, "ymax": y1}, "wall_texture": k["wall"],
            "floor_texture": k["floor"], "ceiling_texture": k["ceiling"],
            "sides": {outer: {"windows": wins}, inner: {"decals": decals}}, "_kind": kind, "_row": row}


def floor_world() -> dict[str, Any]:
    """The data of ``config/worlds/floor.json`` (see the module docstring)."""
    w = WALL_M
    ys0, ys1 = 0.0, 10.0  # south row
    yc0, yc1 = ys1 + w, ys1 + w + 2.7  # corridor
    yn0, yn1 = yc1 + w, 25.0  # north row
    south = [("s_office1", "office", 7.2), ("s_office2", "office", 7.2), ("s_office3", "office", 7.2),
             ("s_lab", "lab", 10.0), ("s_office4", "office", 7.8)]
    north = [("n_meeting1", "meeting", 9.0), ("n_meeting2", "meeting", 9.0), ("n_kitchen", "kitchen", 12.0),
             ("n_office5", "office", 9.55)]
    rooms, openings = [], []
    for row, spec, y0, y1 in (("south", south, ys0, ys1), ("north", north, yn0, yn1)):
        x = 0.0
        prev = None
        for rid, kind, width in spec:
            door_x = x + width - 1.2 if row == "south" else x + 1.2
            door_u = (door_x - x) if row == "north" else (x + width - door_x)
            room = _row_room(rid, kind, row, x, width, y0, y1, door_u)
            rooms.append(room)
            openings.append({"id": f"door_{rid}", "rooms": [rid, "corridor"], "center": round(door_x, 4),
                             "width": DOOR_W, "height": DOOR_H, "texture": "wood_dark"})
            if prev is not None and kind == prev[1]:  # identical neighbours share a connecting door
                cy = y0 + 2.0 if row == "north" else y1 - 2.0
                openings.append({"id": f"door_{prev[0]}_{rid}", "rooms": [prev[0], rid], "center": cy,
                                 "width": DOOR_W, "height": DOOR_H, "texture": "wood_dark"})
            prev = (rid, kind)
            x += width + w
    corridor = {"id": "corridor", "rect": {"xmin": 0.0, "xmax": 40.0, "ymin": yc0, "ymax": yc1},
                "wall_texture": "wall_corridor", "floor_texture": "lino", "ceiling_texture": "ceiling",
                "sides": {
                    "west": {"windows": [{"u": 0.6, "z": 0.95, "width": 1.5, "height": 1.6, "curtain": "curtain",
                                          "view": "view"}]},
                    "east": {"decals": [{"texture": "door_store", "u": 0.8, "z": 0.0, "width": 0.9, "height": 2.05}]},
                    "north": {"decals": [{"texture": "notice_board", "u": 24.0, "z": 1.2, "width": 1.2,
                                          "height": 0.9},
                                         {"texture": "door_store", "u": 14.0, "z": 0.0, "width": 0.9,
                                          "height": 2.05}]},
                    "south": {"decals": [{"texture": "poster_c", "u": 12.0, "z": 1.4, "width": 0.6, "height": 0.85},
                                         {"texture": "poster_c", "u": 34.0, "z": 1.4, "width": 0.6,
                                          "height": 0.85}]}}}
    changes = {
        "boxes": {"add": [{"id": "box_c1", "template": "box_big", "pose": [8.0, yc0 + 0.5, 10]},
                          {"id": "box_c2", "template": "box_small", "pose": [26.0, yc1 - 0.4, -20]},
                          {"id": "box_s2", "template": "box_big", "pose": [10.5, 5.0, 30]},
                          {"id": "box_n3", "template": "box_big", "pose": [25.0, 20.0, 0]}]},
        "moved_furniture": {"move": {"s_office2.desk2": [12.5, 2.5, 45], "n_meeting1.table0": [4.0, 19.0, 90],
                                     "s_lab.bench1": [30.0, 6.0, 0]}},
        "people": {"add": [{"id": "person_c", "template": "person", "pose": [15.0, 0.5 * (yc0 + yc1), 0]},
                           {"id": "person_s1", "template": "person", "pose": [3.0, 4.0, 90]},
                           {"id": "person_n2", "template": "person", "pose": [14.0, 18.0, -45]},
                           {"id": "person_k", "template": "person", "pose": [27.0, 16.0, 180]}]},
    }
    return _build("floor", "An office floor of 40 x 25 m: a corridor between a row of offices and a lab "
                  "(south) and meeting rooms, a kitchen and an office (north), joined by doorways.",
                  rooms, corridor, openings, changes, survey=SURVEY_GRID)


def corridor_floor(per_side: int, width: float = 7.2, depth: float = 6.0) -> dict[str, Any]:
    """A floor of ``2 per_side`` identical offices (``width`` x ``depth`` m) along a 2.7 m corridor,
    each opening on it; the same rooms whatever ``per_side`` (benchmarks/bench_render_rooms.py)."""
    w = WALL_M
    yc0, yc1 = depth + w, depth + w + 2.7
    rooms, openings = [], []
    for row, y0, y1 in (("south", 0.0, depth), ("north", yc1 + w, yc1 + w + depth)):
        for i in range(per_side):
            x = i * (width + w)
            door_x = x + width - 1.2 if row == "south" else x + 1.2
            rid = f"{row[0]}{i}"
            rooms.append(_row_room(rid, "office", row, x, width, y0, y1, width - 1.2 if row == "south" else 1.2))
            openings.append({"id": f"door_{rid}", "rooms": [rid, "corridor"], "center": round(door_x, 4),
                             "width": DOOR_W, "height": DOOR_H, "texture": "wood_dark"})
    length = per_side * (width + w) - w
    corridor = {"id": "corridor", "rect": {"xmin": 0.0, "xmax": round(length, 4), "ymin": yc0, "ymax": yc1},
                "wall_texture": "wall_corridor", "floor_texture": "lino", "ceiling_texture": "ceiling"}
    return _build(f"floor{2 * per_side}", f"{2 * per_side} identical offices along a corridor", rooms, corridor,
                  openings, {})


def floor_world_json() -> str:
    """``config/worlds/floor.json``'s text."""
    return json.dumps(floor_world(), indent=1) + "\n"


FLOOR_JSON = WORLDS_DIR / "floor.json"

"""Surfaces, light sources and baked radiance of a simulated world.

:func:`bake` computes, once per (world, lighting setup, scene changes), the outgoing
radiance of every surface of the world and packs it into one flat float32 *atlas*:

    radiance = albedo * E / pi + emission,

with ``albedo`` the procedural texture (:mod:`drivers.sim.textures`, 1 cm texels by default)
and ``E`` the irradiance, computed on a coarse lightmap (12 cm texels on walls, floor and
ceiling, 10 cm on furniture) and upsampled bilinearly. ``E`` sums

- point lights (bulbs, lamps) with an optional downward lobe ``cos^k``,
- fluorescent tubes (line lights, sampled into points with a cosine lobe),
- open windows (area lights of radiance ``window_radiance``, sampled into points,
  ``L cos(theta_w) cos(theta_s) dA / d^2``),
- the sun, a parallel light that enters only through open windows,
- a constant ``ambient`` term (the indirect light),

each with the cosine at the receiving surface, the inverse-square falloff and hard shadows
cast by the furniture boxes (a segment/box slab test) and by the *interior* walls, the walls
that do not lie on the room rectangle's boundary (a 2D segment crossing test: walls are floor
to ceiling). A world with only boundary walls, a single room, needs no wall test and skips it. ``emission`` is the glowing diffuser
of the ceiling tubes that are switched on, and the outside view of open windows.

The atlas holds a mip-map pyramid (texels x1, x2, x4, x8) of every surface so that the
renderer can pick a level from the pixel footprint and avoid aliasing at a distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from drivers.sim.textures import albedo_texture, texture_shape
from drivers.sim.visibility import (
    cell_sets,
    cells_at,
    oriented_portals,
    potentially_visible,
    visible_cells,
)
from drivers.sim.world import Box, Geometry, TextureSpec, Wall, World

MIP_LEVELS = 4
FIXTURE_WIDTH = 0.15  # m, width of a tube's diffuser on the ceiling
FIXTURE_SPEC = TextureSpec(kind="fixture", albedo=0.75, period=0.05)


@dataclass
class Surface:
    """A textured planar rectangle: points origin + u*eu + v*ev, 0<=u<=width, 0<=v<=height."""

    name: str
    origin: np.ndarray
    eu: np.ndarray
    ev: np.ndarray
    width: float
    height: float
    normal: np.ndarray
    albedo: np.ndarray  # (rows=v, cols=u) float32
    emission: np.ndarray | None = None
    two_sided: bool = False
    lightmap_texel: float = 0.12
    shadowed: bool = True


@dataclass
class Baked:
    """Radiance atlas and per-surface tables (see module docstring)."""

    atlas: np.ndarray  # float32 (N,)
    origin: np.ndarray  # (S, 3) float32
    eu: np.ndarray  # (S, 3)
    ev: np.ndarray  # (S, 3)
    horizontal: np.ndarray  # (S,) bool
    offset: np.ndarray  # (S * L,) int64, entry sid * L + level
    cols: np.ndarray  # (S * L,) int64
    rows: np.ndarray  # (S * L,) int64
    inv_texel: np.ndarray  # (L,) float32
    texel: float
    names: list[str] = field(default_factory=list)
    wall_sid: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    box_face_sid: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), np.int64))
    floor_sid: int = 0
    ceiling_sid: int = 1
    mean_radiance: float = 0.0
    cell_floor_sid: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # worlds with rooms
    cell_ceiling_sid: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def _paste(dst: np.ndarray, src: np.ndarray, col: int, row: int) -> None:
    h, w = src.shape
    r0, c0 = max(row, 0), max(col, 0)
    r1, c1 = min(row + h, dst.shape[0]), min(col + w, dst.shape[1])
    if r1 > r0 and c1 > c0:
        dst[r0:r1, c0:c1] = src[r0 - row: r1 - row, c0 - col: c1 - col]


def _room_normal(world: World, a: np.ndarray, e: np.ndarray) -> np.ndarray:
    n = np.array([-e[1], e[0], 0.0])
    xmin, xmax, ymin, ymax = world.room
    mid = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2])
    p = a[:2] + e[:2] * 0.5
    if np.dot(mid - p, n[:2]) < 0:
        n = -n
    return n


def _floor_ceiling(surfaces: list[Surface], world: World, lighting: str, rect: tuple[float, float, float, float],
                   floor_texture: str, ceiling_texture: str, texel: float, cell: str = "") -> None:
    """Append the floor and the ceiling over ``rect`` (the ceiling with the tube fixtures of
    every setup that fall on it, glowing only in ``lighting``'s)."""
    spec = world.spec
    tex = spec.textures
    hc = spec.ceiling_height
    xmin, xmax, ymin, ymax = rect
    tag = f":{cell}" if cell else ""

    def px(m: float) -> int:
        return int(round(m / texel))

    floor_alb = albedo_texture(tex[floor_texture], xmax - xmin, ymax - ymin, texel)
    surfaces.append(Surface("floor" + tag, np.array([xmin, ymin, 0.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                            xmax - xmin, ymax - ymin, np.array([0, 0, 1.0]), floor_alb))
    # ceiling with the tube fixtures of every setup (glowing only in the setup that has them)
    ceil = albedo_texture(tex[ceiling_texture], xmax - xmin, ymax - ymin, texel).copy()
    emis = np.zeros_like(ceil)
    for name, st in spec.lighting.items():
        for light in st.lights:
            if light.type != "tube" or not light.fixture:
                continue
            a = np.array(light.start[:2])
            b = np.array(light.end[:2])
            length = float(np.linalg.norm(b - a))
            horiz = abs(b[0] - a[0]) >= abs(b[1] - a[1])
            lo = np.minimum(a, b)
            fw, fh = (length, FIXTURE_WIDTH) if horiz else (FIXTURE_WIDTH, length)
            x0 = lo[0] - (0 if horiz else FIXTURE_WIDTH / 2)
            y0 = lo[1] - (FIXTURE_WIDTH / 2 if horiz else 0)
            fix = albedo_texture(FIXTURE_SPEC, fw, fh, texel)
            _paste(ceil, fix, px(x0 - xmin), px(y0 - ymin))
            if name == lighting:
                glow = np.full(fix.shape, light.power / (math.pi * FIXTURE_WIDTH), np.float32) * (fix / FIXTURE_SPEC.albedo)
                _paste(emis, glow, px(x0 - xmin), px(y0 - ymin))
    surfaces.append(Surface("ceiling" + tag, np.array([xmin, ymin, hc]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                            xmax - xmin, ymax - ymin, np.array([0, 0, -1.0]), ceil,
                            emission=emis if emis.any() else None, shadowed=False))


def build_surfaces(world: World, lighting: str, scene_changes: tuple[str, ...] = (), texel: float = 0.01) -> tuple[list[Surface], list[int], list[list[int]]]:
    """All surfaces: floor (0), ceiling (1), walls, then the faces of every box.

    Returns (surfaces, wall surface ids, per box the ids of its faces in the order
    front(+x), back(-x), left(+y), right(-y), top, bottom; -1 when absent)."""
    spec = world.spec
    setup = world.check_lighting(lighting)
    geo = world.geometry(scene_changes)
    tex = spec.textures
    hc = spec.ceiling_height
    xmin, xmax, ymin, ymax = world.room
    surfaces: list[Surface] = []

    def px(m: float) -> int:
        return int(round(m / texel))

    if geo.layout is None:
        _floor_ceiling(surfaces, world, lighting, (xmin, xmax, ymin, ymax), spec.floor_texture, spec.ceiling_texture,
                       texel)
    else:
        for c in geo.layout.cells:
            _floor_ceiling(surfaces, world, lighting, c.rect, c.floor_texture, c.ceiling_texture, texel, c.id)
    # walls with decals and windows
    wall_ids: list[int] = []
    for i, w in enumerate(geo.walls):
        a = np.array([w.start[0], w.start[1], 0.0])
        e = np.array([w.end[0] - w.start[0], w.end[1] - w.start[1], 0.0])
        length = float(np.linalg.norm(e))
        e /= length
        alb = albedo_texture(tex[w.texture], length, hc, texel).copy()
        k = i - (len(geo.walls) - len(geo.layout.walls)) if geo.layout is not None else -1
        normal = _room_normal(world, a, e) if k < 0 else np.array([*geo.layout.wall_normal[k], 0.0])
        # seen from the room, does u run to the viewer's left? then flip decals so that
        # posters and doors read the right way round
        flip = (e[0] * -normal[1] + e[1] * normal[0]) < 0
        em = None
        for d in w.decals:
            img = albedo_texture(tex[d.texture], d.width, d.height, texel)
            _paste(alb, img[:, ::-1] if flip else img, px(d.u), px(d.z))
        for win in w.windows:
            col, row = px(win.u), px(win.z)
            if setup.windows_open:
                view = albedo_texture(tex[win.view], win.width, win.height, texel)
                if em is None:
                    em = np.zeros_like(alb)
                _paste(em, view * setup.window_radiance, col, row)
                _paste(alb, np.full(view.shape, 0.03, np.float32), col, row)
            else:
                _paste(alb, albedo_texture(tex[win.curtain], win.width, win.height, texel), col, row)
        wall_ids.append(len(surfaces))
        surfaces.append(Surface(f"wall{i}:{w.id}", a, e, np.array([0, 0, 1.0]), length, hc,
                                normal, alb, emission=em, two_sided=True))
    # boxes
    box_faces: list[list[int]] = []
    z = np.array([0, 0, 1.0])
    for bi, b in enumerate(geo.boxes):
        c = np.array([b.cx, b.cy, 0.0])
        ax = np.array([math.cos(b.yaw), math.sin(b.yaw), 0.0])
        ay = np.array([-math.sin(b.yaw), math.cos(b.yaw), 0.0])
        zr = b.zmax - b.zmin
        zlo = np.array([0, 0, b.zmin])
        faces = b.spec.faces
        side = [
            ("front", c + b.hx * ax - b.hy * ay + zlo, ay, 2 * b.hy, ax),
            ("back", c - b.hx * ax + b.hy * ay + zlo, -ay, 2 * b.hy, -ax),
            ("left", c + b.hx * ax + b.hy * ay + zlo, -ax, 2 * b.hx, ay),
            ("right", c - b.hx * ax - b.hy * ay + zlo, ax, 2 * b.hx, -ay),
        ]
        ids = []
        for fname, org, eu, width, n in side:
            alb = albedo_texture(tex[faces.get(fname, b.spec.texture)], width, zr, texel)
            ids.append(len(surfaces))
            surfaces.append(Surface(f"box{bi}:{b.owner}:{fname}", org, eu, z, width, zr, n, alb,
                                    lightmap_texel=0.1))
        for fname, zz, n in (("top", b.zmax, z), ("bottom", b.zmin, -z)):
            if fname == "bottom" and b.zmin <= 1e-6:
                ids.append(-1)
                continue
            org = c - b.hx * ax - b.hy * ay + np.array([0, 0, zz])
            alb = albedo_texture(tex[faces.get(fname, b.spec.texture)], 2 * b.hx, 2 * b.hy, texel)
            ids.append(len(surfaces))
            surfaces.append(Surface(f"box{bi}:{b.owner}:{fname}", org, ax, ay, 2 * b.hx, 2 * b.hy, n, alb,
                                    lightmap_texel=0.1))
        box_faces.append(ids)
    return surfaces, wall_ids, box_faces


# ----------------------------------------------------------------------------------------
# irradiance


@dataclass
class _Samples:
    pos: np.ndarray  # (m, 3) emitter sample positions
    power: np.ndarray  # (m,) intensity along the emitter's axis (W/sr-like units)
    axis: np.ndarray  # (m, 3) emitter axis (unit) or zeros for isotropic
    lobe: np.ndarray  # (m,) exponent of cos(angle to axis); 0 = isotropic


def _light_samples(world: World, lighting: str, wall_normals: dict[int, np.ndarray],
                   walls: tuple[Wall, ...]) -> _Samples:
    setup = world.check_lighting(lighting)
    pos, power, axis, lobe = [], [], [], []
    for light in setup.lights:
        if light.type == "point":
            pos.append(light.position)
            power.append(light.power)
            axis.append((0.0, 0.0, -1.0))
            lobe.append(light.lobe)
        elif light.type == "tube":
            a, b = np.array(light.start), np.array(light.end)
            length = float(np.linalg.norm(b - a))
            for k in range(light.samples):
                pos.append(tuple(a + (b - a) * (k + 0.5) / light.samples))
                power.append(light.power * length / light.samples)
                axis.append((0.0, 0.0, -1.0))
                lobe.append(1.0)
    if setup.windows_open and setup.window_radiance > 0:
        nu, nv = int(setup.window_samples[0]), int(setup.window_samples[1])
        for i, w in enumerate(walls):
            if not w.windows:
                continue
            a = np.array([w.start[0], w.start[1], 0.0])
            e = np.array([w.end[0] - w.start[0], w.end[1] - w.start[1], 0.0])
            e /= np.linalg.norm(e)
            n = wall_normals[i]
            for win in w.windows:
                da = win.width * win.height / (nu * nv)
                for iu in range(nu):
                    for iv in range(nv):
                        p = a + e * (win.u + (iu + 0.5) * win.width / nu) + np.array([0, 0, win.z + (iv + 0.5) * win.height / nv])
                        pos.append(tuple(p + 0.02 * n))
                        power.append(setup.window_radiance * da)
                        axis.append(tuple(n))
                        lobe.append(1.0)
    if not pos:
        return _Samples(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0))
    return _Samples(np.array(pos, float), np.array(power, float), np.array(axis, float), np.array(lobe, float))


def _box_arrays(boxes: tuple[Box, ...]) -> np.ndarray:
    return np.array([[b.cx, b.cy, math.cos(b.yaw), math.sin(b.yaw), b.hx, b.hy, b.zmin, b.zmax] for b in boxes],
                    dtype=np.float64).reshape(-1, 8)


def _visible(p: np.ndarray, q: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Whether the segments from points p (n, 3) to light samples q (m, 3) miss every box
    (slab test in each box frame). Returns (n, m) bool."""
    n, m = len(p), len(q)
    vis = np.ones((n, m), bool)
    p32 = p.astype(np.float32)
    q32 = q.astype(np.float32)
    qz_lo, qz_hi = float(q32[:, 2].min()), float(q32[:, 2].max())
    rows_per_chunk = max(1, 32768 // max(m, 1))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for cx, cy, c, s, hx, hy, z0, z1 in boxes:
            # segments entirely above or below the box cannot cross it
            keep = ~(((p32[:, 2] > z1) & (qz_lo > z1)) | ((p32[:, 2] < z0) & (qz_hi < z0)))
            idx = np.flatnonzero(keep)
            for r0 in range(0, idx.size, rows_per_chunk):
                ii = idx[r0:r0 + rows_per_chunk]
                pp = p32[ii][:, None, :]
                d = q32[None, :, :] - pp
                px_, py_ = pp[..., 0] - np.float32(cx), pp[..., 1] - np.float32(cy)
                c32, s32 = np.float32(c), np.float32(s)
                lx = c32 * px_ + s32 * py_
                ly = c32 * py_ - s32 * px_
                dx = c32 * d[..., 0] + s32 * d[..., 1]
                dy = c32 * d[..., 1] - s32 * d[..., 0]
                tmin = np.zeros(d.shape[:2], np.float32)
                tmax = np.ones(d.shape[:2], np.float32)
                for o, dd, lo, hi in ((pp[..., 2], d[..., 2], z0, z1), (lx, dx, -hx, hx), (ly, dy, -hy, hy)):
                    inv = np.float32(1.0) / dd
                    t1 = (np.float32(lo) - o) * inv
                    t2 = (np.float32(hi) - o) * inv
                    np.fmax(tmin, np.fmin(t1, t2), out=tmin)
                    np.fmin(tmax, np.fmax(t1, t2), out=tmax)
                vis[ii] &= ~(tmin < tmax - np.float32(1e-6))
    return vis


def _visible_pairs(p: np.ndarray, q: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Whether each segment p[i] -> q[i] misses every box. Returns (n,) bool."""
    vis = np.ones(len(p), bool)
    p32, d = p.astype(np.float32), (q - p).astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for cx, cy, c, s, hx, hy, z0, z1 in boxes:
            px_, py_ = p32[:, 0] - np.float32(cx), p32[:, 1] - np.float32(cy)
            lx, ly = c * px_ + s * py_, c * py_ - s * px_
            dx, dy = c * d[:, 0] + s * d[:, 1], c * d[:, 1] - s * d[:, 0]
            tmin = np.zeros(len(p), np.float32)
            tmax = np.ones(len(p), np.float32)
            for o, dd, lo, hi in ((p32[:, 2], d[:, 2], z0, z1), (lx, dx, -hx, hx), (ly, dy, -hy, hy)):
                inv = 1.0 / dd
                t1, t2 = (lo - o) * inv, (hi - o) * inv
                tmin = np.fmax(tmin, np.fmin(t1, t2))
                tmax = np.fmin(tmax, np.fmax(t1, t2))
            vis &= ~(tmin < tmax - 1e-6)
    return vis


def interior_walls(world: World, walls: tuple[Wall, ...]) -> np.ndarray:
    """(K, 4) segments (x0, y0, x1, y1) of the walls not lying on one side of the room
    rectangle (both ends on the same side, within 1 mm): the ones that cast shadows."""
    return _wall_segments(walls)[_interior_mask(world, walls)]


def _wall_segments(walls: tuple[Wall, ...]) -> np.ndarray:
    return np.array([(*w.start, *w.end) for w in walls], np.float64).reshape(-1, 4)


def _interior_mask(world: World, walls: tuple[Wall, ...]) -> np.ndarray:
    """(W,) whether each wall is interior (see :func:`interior_walls`)."""
    xmin, xmax, ymin, ymax = world.room
    out = []
    for w in walls:
        (x0, y0), (x1, y1) = w.start, w.end
        on_side = any(abs(a - v) < 1e-3 and abs(b - v) < 1e-3
                      for a, b, v in ((x0, x1, xmin), (x0, x1, xmax), (y0, y1, ymin), (y0, y1, ymax)))
        out.append(not on_side)
    return np.array(out, bool)


_PVS_CACHE: dict[str, list[np.ndarray]] = {}


def _irradiance_culled(world: World, lighting: str, pts: np.ndarray, nrm: np.ndarray, two_sided: np.ndarray,
                       shadowed: np.ndarray, samples: _Samples, geo: Geometry, boxes: np.ndarray) -> np.ndarray:
    """:func:`_irradiance` of a world with rooms, cell by cell. The lightmap points of a cell C
    (the cell holding the point moved 1 cm off its surface, where its shadow rays start) see

    - the light samples q whose own view (:func:`drivers.sim.visibility.visible_cells` from q,
      all round) reaches C: a shadow ray to any other sample crosses a wall;
    - as occluders, the walls of the cells potentially visible from C
      (:func:`drivers.sim.visibility.potentially_visible`): a shadow ray that crosses a wall
      crosses one of these first;
    - the boxes of the cells both potentially visible from C and seen by one of its samples: a
      shadow ray that crosses no wall runs through such cells only.

    Points in no cell or in two (on a portal) and light samples in no cell or in two are traced
    against everything. The sun's windows are all kept. The result equals the unculled one up to
    the order in which the samples' contributions are summed."""
    lay = geo.layout
    assert lay is not None
    pvs = _PVS_CACHE.get(world.fingerprint)
    if pvs is None:
        pvs = _PVS_CACHE[world.fingerprint] = potentially_visible(lay)
    sets = cell_sets(lay, len(geo.walls) - len(lay.walls), geo.boxes)
    rects = lay.rects
    nc = len(rects)
    interior = _interior_mask(world, geo.walls)
    segs = _wall_segments(geo.walls)
    off = pts[:, :2] + 0.01 * nrm[:, :2]
    home = _home_cell(cells_at(rects, off[:, 0], off[:, 1]))
    s_home = _home_cell(cells_at(rects, samples.pos[:, 0], samples.pos[:, 1]))
    ports = oriented_portals(lay)
    lights = np.ones((len(samples.pos), nc), bool)  # sample q can light cell c
    for q in np.flatnonzero(s_home >= 0):
        seen = visible_cells(lay, samples.pos[q, 0], samples.pos[q, 1], -math.pi, math.pi, ports)
        lights[q] = False
        lights[q, seen] = True
    e = np.empty(len(pts), np.float64)
    for c in np.unique(home):
        idx = np.flatnonzero(home == c)
        if c < 0:
            sub, bx, wl = samples, boxes, segs[interior]
        else:
            keep = lights[:, c]
            sub = _Samples(samples.pos[keep], samples.power[keep], samples.axis[keep], samples.lobe[keep])
            w_idx, _ = sets.union(pvs[c])
            lit = lights[keep].any(axis=0)
            _, b_idx = sets.union(pvs[c][lit[pvs[c]]])
            bx, wl = boxes[b_idx], segs[w_idx[interior[w_idx]]]
        e[idx] = _irradiance(world, lighting, pts[idx], nrm[idx], two_sided[idx], shadowed[idx], sub, bx, wl,
                             geo.walls)
    return e


def _home_cell(inside: np.ndarray) -> np.ndarray:
    """(N,) the one cell each row of ``inside`` (N, C) holds, -1 for none or several."""
    one = inside.sum(axis=1) == 1
    return np.where(one, inside.argmax(axis=1), -1)


def _walls_clear(p: np.ndarray, q: np.ndarray, walls: np.ndarray, pairs: bool = False) -> np.ndarray:
    """Whether the segments from points p (n, 3) to q (m, 3) cross no wall of ``walls`` (K, 4)
    in the floor plan (a proper crossing: the segment's ends excluded, the wall's included).
    Returns (n, m) bool, or (n,) with ``pairs`` (segment p[i] -> q[i])."""
    pp = p[:, None, :2] if not pairs else p[:, :2]
    d = (q[None, :, :2] if not pairs else q[:, :2]) - pp
    clear = np.ones(d.shape[:-1], bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for x0, y0, x1, y1 in walls:
            ex, ey = x1 - x0, y1 - y0
            wx, wy = x0 - pp[..., 0], y0 - pp[..., 1]
            den = d[..., 0] * ey - d[..., 1] * ex
            t = (wx * ey - wy * ex) / den
            u = (wx * d[..., 1] - wy * d[..., 0]) / den
            clear &= ~((np.abs(den) > 1e-12) & (t > 1e-6) & (t < 1.0 - 1e-6) & (u >= 0.0) & (u <= 1.0))
    return clear


def _irradiance(world: World, lighting: str, pts: np.ndarray, nrm: np.ndarray, two_sided: np.ndarray,
                shadowed: np.ndarray, samples: _Samples, boxes: np.ndarray,
                walls: np.ndarray | None = None, windows: tuple[Wall, ...] = ()) -> np.ndarray:
    setup = world.check_lighting(lighting)
    e = np.full(len(pts), setup.ambient, np.float64)
    chunk = max(1, 200_000 // max(1, len(samples.pos)))
    for s0 in range(0, len(pts), chunk):
        p = pts[s0:s0 + chunk, None, :]
        n = nrm[s0:s0 + chunk, None, :]
        if len(samples.pos):
            d = samples.pos[None, :, :] - p
            d2 = np.maximum(np.sum(d * d, axis=-1), 1e-4)
            ldir = d / np.sqrt(d2)[..., None]
            cos_s = np.sum(ldir * n, axis=-1)
            cos_s = np.where(two_sided[s0:s0 + chunk, None], np.abs(cos_s), np.maximum(cos_s, 0.0))
            cos_l = np.maximum(-np.sum(ldir * samples.axis[None], axis=-1), 0.0)
            lobe = np.where(samples.lobe[None] > 0, cos_l ** samples.lobe[None], 1.0)
            contrib = samples.power[None] * lobe * cos_s / d2
            sh = shadowed[s0:s0 + chunk]
            if len(boxes) and sh.any():
                vis = np.ones(contrib.shape, bool)
                vis[sh] = _visible((p[sh] + 0.01 * n[sh])[:, 0, :], samples.pos, boxes)
                contrib = contrib * vis
            if walls is not None and len(walls):
                contrib = contrib * _walls_clear((p + 0.01 * n)[:, 0, :], samples.pos, walls)
            e[s0:s0 + chunk] += contrib.sum(axis=1)
        for light in setup.lights:
            if light.type == "sun" and setup.windows_open:
                e[s0:s0 + chunk] += _sun(world, light.direction, light.power, pts[s0:s0 + chunk],
                                         nrm[s0:s0 + chunk], boxes, walls, windows)
    return e


def _sun(world: World, direction: tuple[float, float, float], power: float, pts: np.ndarray, nrm: np.ndarray,
         boxes: np.ndarray, walls: np.ndarray | None = None, windows: tuple[Wall, ...] = ()) -> np.ndarray:
    d = np.array(direction, float)
    d /= np.linalg.norm(d)
    cos_s = np.maximum(-(nrm @ d), 0.0)
    lit = np.zeros(len(pts), bool)
    far = np.zeros_like(pts)
    for w in windows or world.spec.walls:
        if not w.windows:
            continue
        a = np.array([w.start[0], w.start[1], 0.0])
        e = np.array([w.end[0] - w.start[0], w.end[1] - w.start[1], 0.0])
        e /= np.linalg.norm(e)
        n = np.array([-e[1], e[0], 0.0])
        den = float(-d @ n)
        if abs(den) < 1e-9:
            continue
        t = ((a - pts) @ n) / den  # distance along -d to the wall plane
        hit = pts - t[:, None] * d
        u = (hit - a) @ e
        zz = hit[:, 2]
        for win in w.windows:
            inside = (t > 0) & (u >= win.u) & (u <= win.u + win.width) & (zz >= win.z) & (zz <= win.z + win.height)
            far[inside] = hit[inside]
            lit |= inside
    if len(boxes) and lit.any():
        idx = np.flatnonzero(lit)
        ok = np.ones(idx.size, bool)
        for k0 in range(0, idx.size, 4096):  # one light point per receiver: diagonal of (n, n)
            sl = idx[k0:k0 + 4096]
            ok[k0:k0 + 4096] = _visible_pairs(pts[sl] + 0.01 * nrm[sl], far[sl], boxes)
        lit[idx] = ok
    if walls is not None and len(walls) and lit.any():
        idx = np.flatnonzero(lit)
        lit[idx] = _walls_clear(pts[idx] + 0.01 * nrm[idx], far[idx], walls, pairs=True)
    return power * cos_s * lit


def _lightmap_points(s: Surface) -> tuple[np.ndarray, int, int]:
    rows = max(2, int(math.ceil(s.height / s.lightmap_texel)))
    cols = max(2, int(math.ceil(s.width / s.lightmap_texel)))
    u = (np.arange(cols) + 0.5) * s.width / cols
    v = (np.arange(rows) + 0.5) * s.height / rows
    uu, vv = np.meshgrid(u, v)
    pts = s.origin[None] + uu.reshape(-1, 1) * s.eu[None] + vv.reshape(-1, 1) * s.ev[None]
    return pts, rows, cols


_BAKE_CACHE: dict[tuple, Baked] = {}
# Bakes kept in memory, least recently used dropped first (a bake's size: docs/results.md).
_BAKE_CACHE_SIZE = 8


def bake(world: World, lighting: str, scene_changes: tuple[str, ...] | list[str] = (), texel: float = 0.01,
         cull: bool = True) -> Baked:
    """Radiance atlas of ``world`` under ``lighting`` with ``scene_changes`` (cached in memory).

    ``cull`` (a world with rooms): trace each cell's lightmap points only against what the cell
    can see (:func:`_irradiance_culled`); the result is the unculled one up to the order of
    summation of the light samples."""
    changes = world.check_changes(tuple(scene_changes))
    world.check_lighting(lighting)
    key = (world.fingerprint, lighting, changes, float(texel), bool(cull))
    if key in _BAKE_CACHE:
        _BAKE_CACHE[key] = _BAKE_CACHE.pop(key)  # most recently used last
        return _BAKE_CACHE[key]
    surfaces, wall_ids, box_faces = build_surfaces(world, lighting, changes, texel)
    geo = world.geometry(changes)
    boxes = _box_arrays(geo.boxes)
    wall_normals = {i: surfaces[sid].normal for i, sid in enumerate(wall_ids)}
    samples = _light_samples(world, lighting, wall_normals, geo.walls)
    # lightmap points of all surfaces at once
    pts, nrms, two, shad, shapes = [], [], [], [], []
    for s in surfaces:
        p, r, c = _lightmap_points(s)
        pts.append(p)
        nrms.append(np.broadcast_to(s.normal, p.shape))
        two.append(np.full(len(p), s.two_sided))
        shad.append(np.full(len(p), s.shadowed))
        shapes.append((r, c))
    if geo.layout is not None and cull:
        e_all = _irradiance_culled(world, lighting, np.concatenate(pts), np.concatenate(nrms), np.concatenate(two),
                                   np.concatenate(shad), samples, geo, boxes)
    else:
        e_all = _irradiance(world, lighting, np.concatenate(pts), np.concatenate(nrms), np.concatenate(two),
                            np.concatenate(shad), samples, boxes, interior_walls(world, geo.walls),
                            geo.walls if geo.layout is not None else ())
    levels: list[list[np.ndarray]] = [[] for _ in range(MIP_LEVELS)]
    k = 0
    for s, (r, c) in zip(surfaces, shapes, strict=True):
        lm = e_all[k:k + r * c].reshape(r, c).astype(np.float32)
        k += r * c
        h, w = s.albedo.shape
        irr = cv2.resize(lm, (w, h), interpolation=cv2.INTER_LINEAR)
        rad = s.albedo * irr * np.float32(1.0 / math.pi)
        if s.emission is not None:
            rad = rad + s.emission
        img = rad.astype(np.float32)
        for lev in range(MIP_LEVELS):
            levels[lev].append(img)
            nh, nw = max(1, (img.shape[0] + 1) // 2), max(1, (img.shape[1] + 1) // 2)
            img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
    nsurf = len(surfaces)
    offset = np.zeros(nsurf * MIP_LEVELS, np.int64)
    rows = np.zeros_like(offset)
    cols = np.zeros_like(offset)
    chunks = []
    pos = 0
    for sid in range(nsurf):
        for lev in range(MIP_LEVELS):
            img = levels[lev][sid]
            j = sid * MIP_LEVELS + lev
            offset[j], rows[j], cols[j] = pos, img.shape[0], img.shape[1]
            chunks.append(img.ravel())
            pos += img.size
    atlas = np.concatenate(chunks).astype(np.float32)
    area = np.array([s.width * s.height for s in surfaces])
    mean_rad = float(sum(levels[-1][i].mean() * area[i] for i in range(nsurf)) / area.sum())
    baked = Baked(
        atlas=atlas,
        origin=np.array([s.origin for s in surfaces], np.float32),
        eu=np.array([s.eu for s in surfaces], np.float32),
        ev=np.array([s.ev for s in surfaces], np.float32),
        horizontal=np.array([abs(s.normal[2]) > 0.5 for s in surfaces]),
        offset=offset, rows=rows, cols=cols,
        inv_texel=np.array([1.0 / (texel * 2 ** lev) for lev in range(MIP_LEVELS)], np.float32),
        texel=texel,
        names=[s.name for s in surfaces],
        wall_sid=np.array(wall_ids, np.int64),
        box_face_sid=np.array(box_faces, np.int64).reshape(-1, 6),
        mean_radiance=mean_rad,
    )
    if geo.layout is not None:  # per cell: floor 2 c, ceiling 2 c + 1 (build_surfaces)
        baked.cell_floor_sid = 2 * np.arange(len(geo.layout.cells), dtype=np.int64)
        baked.cell_ceiling_sid = baked.cell_floor_sid + 1
    _BAKE_CACHE[key] = baked
    while len(_BAKE_CACHE) > _BAKE_CACHE_SIZE:
        _BAKE_CACHE.pop(next(iter(_BAKE_CACHE)))
    return baked


def texture_rows_cols(width_m: float, height_m: float, texel: float) -> tuple[int, int]:
    """Shape of a surface texture (re-exported for tests)."""
    return texture_shape(width_m, height_m, texel)

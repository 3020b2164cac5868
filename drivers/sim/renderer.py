"""What the robot's stereo camera sees in a simulated world: grey image, depth, stereo pair.

:class:`Renderer` draws a world (:mod:`drivers.sim.world`) from a camera pose by ray
casting against a baked radiance atlas (:mod:`drivers.sim.lighting`):

1. once per camera resolution and tilt, per-pixel rays in the camera frame are turned into
   a relative azimuth, the slope ``s = dz / |d_xy|`` and ``1 / |d_xy|`` (``d`` has unit
   optical-axis component, so depth Z = horizontal range / |d_xy|); at tilt 0 the azimuth
   samples are exactly the image columns, otherwise 2 W samples spread over the view;
2. per view, the azimuth samples are cast in 2D against every wall segment and every box
   footprint (slab test): entry/exit ranges ``r_in``/``r_out`` and the face entered; all
   that lies behind the first (floor-to-ceiling) wall is dropped and the rest sorted;
3. per pixel, vectorized over pixels, the candidates are visited near to far: the ray
   height ``h + s r_in`` inside ``[zmin, zmax]`` hits the front face, above ``zmax`` at
   entry and below at exit hits the top face (and the mirror case the bottom); pixels
   whose ray reaches the floor or the ceiling first stop there;
4. texture coordinates come from the 3D hit point, the mip level from the pixel footprint,
   and one gather from the atlas gives the radiance;
5. the camera: auto gain (the mean grey of the left image is driven toward a target and
   clamped to a gain range, so dim light gives dark noisy images and bright windows
   saturate), shot and read noise on the linear signal, clipping, a gamma curve (as in
   real cameras) and 8-bit quantization.

Pose semantics (REP-103): (x, y, theta) is the robot pose in the map frame; the camera sits
on the robot's vertical axis at ``height`` (default ``CameraModel.height_m``); its heading is
``theta + pan``; ``tilt`` > 0 looks UP. The reference (left) camera is on the axis; the right
camera of the rectified pair is displaced by ``baseline_m`` along the camera's x axis (to
the right, i.e. -y of a robot looking along +x), with the same orientation, so that a point
at depth Z has disparity ``fx * baseline / Z`` (left column minus right column).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from drivers.sim.lighting import MIP_LEVELS, Baked, bake
from drivers.sim.visibility import cell_sets, oriented_portals, visible_cells
from drivers.sim.world import Geometry, World, load_world

_BIG = np.float32(1e4)
# surface marks of a world with rooms: a floor or ceiling hit, cell not yet known
_FLOOR, _CEILING = -10, -11


class CameraModel(BaseModel):
    """Pinhole camera of the simulated robot (rectified stereo pair, grey images).

    Either ``hfov_deg`` or the explicit ``fx, fy, cx, cy`` (pixels) set the intrinsics.
    ``gain_min``/``gain_max`` bound the auto gain (linear sensor levels, 0..255, per unit of
    radiance), ``target_grey`` is its set point for the mean output grey; ``read_noise``
    (linear levels at ``gain_ref``) and ``shot_noise`` (variance per linear level at
    ``gain_ref``) scale with the gain. The output is gamma-encoded (``gamma``, 1 = linear)
    like the images of real cameras, then quantized to 8 bits.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    width: int = Field(320, ge=8)
    height: int = Field(240, ge=8)
    hfov_deg: float = Field(70.0, gt=1.0, lt=179.0)
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    baseline_m: float = Field(0.075, ge=0.0)
    height_m: float = Field(1.1, gt=0.0)
    target_grey: float = Field(110.0, gt=0.0, lt=255.0)
    gain_min: float = Field(5.0, gt=0.0)
    gain_max: float = Field(160.0, gt=0.0)
    gain_ref: float = Field(90.0, gt=0.0)
    read_noise: float = Field(0.6, ge=0.0)
    shot_noise: float = Field(0.04, ge=0.0)
    gamma: float = Field(2.2, ge=1.0, le=3.0)

    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels; square pixels and a centred principal point by default."""
        fx = self.fx if self.fx is not None else (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)
        fy = self.fy if self.fy is not None else fx
        cx = self.cx if self.cx is not None else (self.width - 1) / 2.0
        cy = self.cy if self.cy is not None else (self.height - 1) / 2.0
        return float(fx), float(fy), float(cx), float(cy)


@dataclass
class RenderResult:
    """One rendered view. ``grey`` is the reference (left) image; ``depth`` is metres along
    the optical axis (Z) of the left camera; ``right`` is None when not rendered in stereo."""

    grey: np.ndarray
    depth: np.ndarray
    left: np.ndarray
    right: np.ndarray | None
    gain: float
    camera_pose: tuple[float, float, float]


@dataclass
class _Rays:
    az_samples: np.ndarray  # (A,) relative azimuths of the samples
    pix_sample: np.ndarray  # (P,) sample index of each pixel
    slope: np.ndarray  # (P,) dz / |d_xy|
    inv_h: np.ndarray  # (P,) 1 / |d_xy|
    ca: np.ndarray  # (P,) cos of the pixel's relative azimuth
    sa: np.ndarray  # (P,) sin
    foot_h: np.ndarray  # (P,) pixel footprint per metre of depth on a horizontal surface, in texels
    foot_v: np.ndarray  # (P,) same on a vertical surface (ignoring the azimuthal slant)


class Renderer:
    """Renders a world from camera poses. See the module docstring for the pose semantics."""

    def __init__(
        self,
        world: World | str,
        camera: CameraModel | None = None,
        lighting: str = "tube",
        scene_changes: tuple[str, ...] | list[str] = (),
        seed: int = 0,
        texel: float = 0.01,
        cull: bool = True,
    ) -> None:
        self.world = load_world(world) if isinstance(world, str) else world
        self.camera = camera if camera is not None else CameraModel()
        self.texel = texel
        self.cull = bool(cull)
        self._rng = np.random.default_rng(seed)
        self._rays: dict[float, _Rays] = {}
        self._noise_buf: np.ndarray | None = None
        self._lut: np.ndarray | None = None
        self.world.check_lighting(lighting)
        self._lighting = lighting
        self._changes = self.world.check_changes(tuple(scene_changes))
        self._load()

    # -- configuration ----------------------------------------------------------------
    @property
    def lighting(self) -> str:
        return self._lighting

    @property
    def scene_changes(self) -> tuple[str, ...]:
        return self._changes

    def set_lighting(self, name: str) -> None:
        """Switch to the lighting setup ``name`` (checked) and load its bake (cached in memory)."""
        self.world.check_lighting(name)
        self._lighting = name
        self._load()

    def set_scene_changes(self, names: tuple[str, ...] | list[str]) -> None:
        """Apply the scene changes ``names`` (checked, duplicates dropped) instead of the current
        ones, and load their bake."""
        self._changes = self.world.check_changes(tuple(names))
        self._load()

    def _load(self) -> None:
        self.baked: Baked = bake(self.world, self._lighting, self._changes, self.texel)
        b = self.baked
        if np.any(np.abs(b.eu[:, 2]) > 1e-6):
            raise ValueError("every surface needs a horizontal u axis")
        geo = self.world.geometry(self._changes)
        self._hc = np.float32(self.world.spec.ceiling_height)
        w = np.array([[*wl.start, *wl.end] for wl in geo.walls], np.float64).reshape(-1, 4)
        self._w0 = w[:, :2]
        self._we = w[:, 2:] - w[:, :2]
        self._box = np.array([[bx.cx, bx.cy, math.cos(bx.yaw), math.sin(bx.yaw), bx.hx, bx.hy, bx.zmin, bx.zmax]
                              for bx in geo.boxes], np.float64).reshape(-1, 8)
        nb, nw = len(self._box), len(self._w0)
        self._zlo = np.concatenate([np.zeros(nw), self._box[:, 6]]).astype(np.float32)
        self._zhi = np.concatenate([np.full(nw, self._hc), self._box[:, 7]]).astype(np.float32)
        bf = self.baked.box_face_sid
        self._top_sid = np.concatenate([np.full(nw, -1), bf[:, 4] if nb else np.zeros(0, np.int64)]).astype(np.int32)
        self._bot_sid = np.concatenate([np.full(nw, -1), bf[:, 5] if nb else np.zeros(0, np.int64)]).astype(np.int32)
        self._box_side_sid = bf[:, :4].astype(np.int32) if nb else np.zeros((0, 4), np.int32)
        self._box_radius = np.hypot(self._box[:, 4], self._box[:, 5])
        org, eu, ev = b.origin.astype(np.float64), b.eu.astype(np.float64), b.ev.astype(np.float64)
        k0 = 1.0 / b.texel  # metres -> level-0 texels
        self._tex = {
            "eux": (k0 * eu[:, 0]).astype(np.float32), "euy": (k0 * eu[:, 1]).astype(np.float32),
            "eu0": (-k0 * (org * eu).sum(axis=1)).astype(np.float32),
            "evx": (k0 * ev[:, 0]).astype(np.float32), "evy": (k0 * ev[:, 1]).astype(np.float32),
            "evz": (k0 * ev[:, 2]).astype(np.float32),
            "ev0": (-k0 * (org * ev).sum(axis=1)).astype(np.float32),
            "horiz": b.horizontal.astype(bool),
            "cols": b.cols.astype(np.int32), "rows": b.rows.astype(np.int32), "offset": b.offset.astype(np.int32),
        }
        self._fc_cache: dict = {}
        self._load_rooms(geo)

    def _load_rooms(self, geo: Geometry) -> None:
        """Cells, portals and per-cell wall and box sets of a world with rooms (else None)."""
        self._layout = geo.layout
        if self._layout is None:
            return
        lay = self._layout
        self._ports = oriented_portals(lay)
        self._sets = cell_sets(lay, len(geo.walls) - len(lay.walls), geo.boxes)
        self._rects = lay.rects
        self._all_cells = np.arange(len(lay.cells))
        self._cell_floor = self.baked.cell_floor_sid.astype(np.int32)
        self._cell_ceiling = self.baked.cell_ceiling_sid.astype(np.int32)

    def _selection(self, ox: float, oy: float, phi: float, rays: _Rays) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cells, walls and boxes a world with rooms traces for a view from (ox, oy): with culling
        the cells :func:`visible_cells` finds, else (or from outside every cell) all of them."""
        cells = None
        if self.cull:
            a0, a1 = float(rays.az_samples.min()), float(rays.az_samples.max())
            cells = visible_cells(self._layout, ox, oy, phi + a0, phi + a1, self._ports)
        if cells is None:
            cells = self._all_cells
            return cells, np.arange(len(self._w0)), np.arange(len(self._box))
        walls, boxes = self._sets.union(cells)
        return cells, walls, boxes

    # -- rays -------------------------------------------------------------------------
    def _rays_for(self, tilt: float) -> _Rays:
        key = round(float(tilt), 9)
        if key in self._rays:
            return self._rays[key]
        cam = self.camera
        fx, fy, cx, cy = cam.intrinsics()
        u = (np.arange(cam.width, dtype=np.float64) - cx) / fx
        v = (np.arange(cam.height, dtype=np.float64) - cy) / fy
        X, Y = np.meshgrid(u, v)  # camera frame: x right, y down, z forward (=1)
        st, ct = math.sin(tilt), math.cos(tilt)
        # world directions for heading 0: forward (ct, 0, st), right (0, -1, 0), down (st, 0, -ct)
        dx = Y * st + ct
        dy = -X
        dz = -Y * ct + st
        h = np.maximum(np.hypot(dx, dy), 1e-9)
        az = np.arctan2(dy, dx)
        if key == 0.0:
            samples = -np.arctan(u)
            pix = np.broadcast_to(np.arange(cam.width), (cam.height, cam.width))
        else:
            a0, a1 = float(az.min()), float(az.max())
            n = 2 * cam.width
            samples = np.linspace(a0, a1, n)
            pix = np.clip(np.rint((az - a0) / max(a1 - a0, 1e-12) * (n - 1)), 0, n - 1)
        norm = np.sqrt(h * h + dz * dz)
        rays = _Rays(
            az_samples=samples.astype(np.float64),
            pix_sample=np.ascontiguousarray(pix, dtype=np.int32).ravel(),
            slope=(dz / h).astype(np.float32).ravel(),
            inv_h=(1.0 / h).astype(np.float32).ravel(),
            ca=(dx / h).astype(np.float32).ravel(),
            sa=(dy / h).astype(np.float32).ravel(),
            foot_h=(1.0 / (fx * self.texel * np.maximum(np.abs(dz) / norm, 0.05))).astype(np.float32).ravel(),
            foot_v=(1.0 / (fx * self.texel * np.maximum(h / norm, 0.05))).astype(np.float32).ravel(),
        )
        if len(self._rays) >= 32:  # continuous tilts: keep the memory bounded
            self._rays.clear()
            self._fc_cache.clear()
        self._rays[key] = rays
        return rays

    # -- 2D casting ---------------------------------------------------------------------
    def _cast(self, ox: float, oy: float, phi: float, rays: _Rays,
              sel: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, ...]:
        """Candidates per azimuth sample, sorted by entry range: (r_in, r_out, zlo, zhi,
        front sid, top sid, bottom sid), each (K, A) so that row j is the j-th nearest.

        ``sel``: (wall indices, box indices), sorted, to trace instead of all (a world with
        rooms); candidates at equal range then keep the order of their indices (a stable sort),
        so that any selection containing every wall and box a ray meets gives the same result."""
        az = phi + rays.az_samples
        c, s = np.cos(az)[:, None], np.sin(az)[:, None]
        w0, we = (self._w0, self._we) if sel is None else (self._w0[sel[0]], self._we[sel[0]])
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ex, ey = we[None, :, 0], we[None, :, 1]
            wx, wy = w0[None, :, 0] - ox, w0[None, :, 1] - oy
            den = c * ey - s * ex
            r = (wx * ey - wy * ex) / den
            t = (wx * s - wy * c) / den
            rw = np.where((r > 1e-6) & (t >= -1e-9) & (t <= 1 + 1e-9), r, np.inf)
            first_wall = rw.min(axis=1, initial=np.inf)
            wall_sid = self.baked.wall_sid if sel is None else self.baked.wall_sid[sel[0]]
            wsid = np.broadcast_to(wall_sid[None, :], rw.shape)
            keep = self._visible_boxes(ox, oy, phi, rays, None if sel is None else sel[1])
            if keep.size:
                bx = self._box[keep]
                cb, sb = bx[None, :, 2], bx[None, :, 3]
                lox = cb * (ox - bx[None, :, 0]) + sb * (oy - bx[None, :, 1])
                loy = -sb * (ox - bx[None, :, 0]) + cb * (oy - bx[None, :, 1])
                ldx = cb * c + sb * s
                ldy = -sb * c + cb * s
                hx, hy = bx[None, :, 4], bx[None, :, 5]
                ix, iy = 1.0 / ldx, 1.0 / ldy
                tx1, tx2 = (-hx - lox) * ix, (hx - lox) * ix
                ty1, ty2 = (-hy - loy) * iy, (hy - loy) * iy
                txmin, txmax = np.fmin(tx1, tx2), np.fmax(tx1, tx2)
                tymin, tymax = np.fmin(ty1, ty2), np.fmax(ty1, ty2)
                rin = np.fmax(txmin, tymin)
                rout = np.fmin(txmax, tymax)
                # (a ray parallel to a slab and outside it gives NaN bounds: no hit)
                hit = (rin < rout) & (rout > 0) & (rin < first_wall[:, None])
                xface = txmin > tymin
                # faces: 0 front(+x) 1 back(-x) 2 left(+y) 3 right(-y)
                face = np.where(xface, (ldx > 0).astype(np.int64), 2 + (ldy > 0))
                bsid = self._box_side_sid[keep[None, :], face]
                rin = np.where(hit, np.maximum(rin, 0.0), np.inf)
                r_in = np.concatenate([rw, rin], axis=1)
                r_out = np.concatenate([rw, np.where(hit, rout, np.inf)], axis=1)
                fsid = np.concatenate([wsid, bsid], axis=1)
                wobj = np.arange(len(self._w0)) if sel is None else sel[0]
                obj = np.concatenate([wobj, len(self._w0) + keep])
            else:
                r_in, r_out, fsid = rw, rw, wsid
                obj = np.arange(len(self._w0)) if sel is None else sel[0]
        r_in[r_in > first_wall[:, None] + 1e-6] = np.inf
        k = max(1, int(np.isfinite(r_in).sum(axis=1).max()))
        n_obj = r_in.shape[1]
        if self._layout is not None:
            order = np.argsort(r_in, axis=1, kind="stable")[:, :k]
        elif k < n_obj:
            order = np.argpartition(r_in, k - 1, axis=1)[:, :k]
            sub = np.take_along_axis(r_in, order, 1)
            order = np.take_along_axis(order, np.argsort(sub, axis=1), 1)
        else:
            order = np.argsort(r_in, axis=1)
        order_t = np.ascontiguousarray(order.T)  # (K, A) column ids
        flat = order_t + (np.arange(order.shape[0]) * n_obj)[None, :]
        order_t = obj[order_t]  # object ids
        return (
            r_in.ravel().take(flat).astype(np.float32),
            r_out.ravel().take(flat).astype(np.float32),
            self._zlo.take(order_t),
            self._zhi.take(order_t),
            fsid.ravel().take(flat).astype(np.int32),
            self._top_sid.take(order_t),
            self._bot_sid.take(order_t),
        )

    def _visible_boxes(self, ox: float, oy: float, phi: float, rays: _Rays,
                       among: np.ndarray | None = None) -> np.ndarray:
        """Indices of the boxes (of ``among``, default all) whose bounding circle overlaps the
        view's azimuth range."""
        if among is not None:
            if not among.size:
                return np.zeros(0, np.int64)
            box, radius = self._box[among], self._box_radius[among]
        else:
            box, radius = self._box, self._box_radius
        if not len(box):
            return np.zeros(0, np.int64)
        dx = box[:, 0] - ox
        dy = box[:, 1] - oy
        dist = np.hypot(dx, dy)
        rad = radius
        a0, a1 = float(rays.az_samples.min()), float(rays.az_samples.max())
        mid, half = phi + 0.5 * (a0 + a1), 0.5 * (a1 - a0)
        if half >= math.pi - 1e-3:
            keep = np.arange(len(box))
            return keep if among is None else among[keep]
        bearing = np.arctan2(dy, dx) - mid
        bearing = (bearing + math.pi) % (2 * math.pi) - math.pi
        with np.errstate(invalid="ignore"):
            ang = np.arcsin(np.minimum(rad / np.maximum(dist, 1e-9), 1.0))
        keep = (dist <= rad) | (np.abs(bearing) <= half + ang + 1e-3)
        return np.flatnonzero(keep) if among is None else among[np.flatnonzero(keep)]

    def _floor_ceiling(self, rays: _Rays, hcam: float) -> tuple[np.ndarray, np.ndarray]:
        key = (id(rays), round(hcam, 9))
        got = self._fc_cache.get(key)
        if got is None:
            s = rays.slope.astype(np.float64)
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.where(s < 0, -hcam / s, np.where(s > 0, (float(self._hc) - hcam) / s, float(_BIG)))
            r = np.minimum(r, float(_BIG)).astype(np.float32)
            if self._layout is None:
                sid = np.where(s < 0, self.baked.floor_sid, self.baked.ceiling_sid).astype(np.int32)
            else:  # marks: the cell of the hit point decides (_room_floor_ceiling)
                sid = np.where(s < 0, _FLOOR, _CEILING).astype(np.int32)
            got = (r, sid)
            if len(self._fc_cache) > 16:
                self._fc_cache.clear()
            self._fc_cache[key] = got
        return got

    # -- per-view radiance --------------------------------------------------------------
    def _radiance(self, ox: float, oy: float, hcam: float, phi: float, rays: _Rays) -> tuple[np.ndarray, np.ndarray]:
        """Radiance (float32, P) and depth Z (float32, P) for a camera at (ox, oy, hcam), heading phi."""
        cells = None
        if self._layout is not None:
            cells, walls, boxes = self._selection(ox, oy, phi, rays)
            r_in, r_out, zlo, zhi, fsid, tsid, bsid = self._cast(ox, oy, phi, rays, (walls, boxes))
        else:
            r_in, r_out, zlo, zhi, fsid, tsid, bsid = self._cast(ox, oy, phi, rays)
        k = r_in.shape[0]
        s = rays.slope
        h = np.float32(hcam)
        r_fc, sid_fc = self._floor_ceiling(rays, hcam)
        r_hit = r_fc.copy()
        sid = sid_fc.copy()
        ps = rays.pix_sample
        n_az = r_in.shape[1]
        # per candidate rank j: the sids of its front, top and bottom faces side by side
        sid3 = np.concatenate([fsid, tsid, bsid], axis=1)  # (K, 3 A)
        with np.errstate(divide="ignore", invalid="ignore"):
            # nearest candidate, every pixel: most pixels hit its front face (or floor/ceiling)
            ri = r_in[0].take(ps)
            lo = zlo[0].take(ps)
            hi = zhi[0].take(ps)
            z_in = h + s * ri
            near = ri < r_fc
            off = (z_in > hi) | (z_in < lo)
            front = near & ~off
            r_hit = np.where(front, ri, r_fc)
            sid = np.where(front, fsid[0].take(ps), sid_fc)
            # the few that pass above or below a box at entry: top / bottom face or further
            odd = np.flatnonzero(near & off)
            if odd.size:
                pidx, st = ps[odd], s[odd]
                zi, hio, loo = z_in[odd], hi[odd], lo[odd]
                z_out = h + st * r_out[0].take(pidx)
                top = (zi > hio) & (z_out <= hio)
                bot = (zi < loo) & (z_out >= loo)
                got = top | bot
                gi = np.flatnonzero(got)
                if gi.size:
                    g = odd[gi]
                    tp = top[gi]
                    r_hit[g] = (np.where(tp, hio[gi], loo[gi]) - h) / st[gi]
                    case = np.int32(n_az) * (tp.view(np.int8) + 2 * bot[gi].view(np.int8))
                    sid[g] = sid3[0].take(pidx[gi] + case)
                todo = odd[~got]
            else:
                todo = odd
            for j in range(1, k):
                if todo.size == 0:
                    break
                pidx, st, rf = ps[todo], s[todo], r_fc[todo]
                ri = r_in[j].take(pidx)
                lo = zlo[j].take(pidx)
                hi = zhi[j].take(pidx)
                z_in = h + st * ri
                z_out = h + st * r_out[j].take(pidx)
                near = ri < rf
                above = z_in > hi
                below = z_in < lo
                top = near & above & (z_out <= hi)
                bot = near & below & (z_out >= lo)
                front = near & ~above & ~below
                got = front | top | bot
                gi = np.flatnonzero(got)
                if gi.size:
                    g = todo[gi]
                    tp, fr = top[gi], front[gi]
                    r_hit[g] = np.where(fr, ri[gi], (np.where(tp, hi[gi], lo[gi]) - h) / st[gi])
                    case = np.int32(n_az) * (tp.view(np.int8) + 2 * bot[gi].view(np.int8))
                    sid[g] = sid3[j].take(pidx[gi] + case)
                todo = todo[np.flatnonzero(near & ~got)]
        if cells is not None:
            sid = self._room_floor_ceiling(ox, oy, phi, rays, r_hit, sid, cells)
        return self._shade(ox, oy, h, phi, rays, r_hit, sid)

    def _room_floor_ceiling(self, ox: float, oy: float, phi: float, rays: _Rays, r_hit: np.ndarray,
                            sid: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """In a world with rooms every cell has its own floor and ceiling: the pixels that end on
        the floor or ceiling (``_FLOOR``/``_CEILING`` marks) get the surface of the cell of
        ``cells`` nearest their hit point (distance 0 inside; ties: the lowest cell index)."""
        fl = sid == _FLOOR
        idx = np.flatnonzero(fl | (sid == _CEILING))
        if not idx.size:
            return sid
        cphi, sphi = np.float32(math.cos(phi)), np.float32(math.sin(phi))
        ca, sa, r = rays.ca[idx], rays.sa[idx], r_hit[idx]
        x = np.float32(ox) + r * (cphi * ca - sphi * sa)
        y = np.float32(oy) + r * (sphi * ca + cphi * sa)
        rc = self._rects[cells].astype(np.float32)
        dx = np.maximum(np.maximum(rc[None, :, 0] - x[:, None], x[:, None] - rc[None, :, 1]), 0.0)
        dy = np.maximum(np.maximum(rc[None, :, 2] - y[:, None], y[:, None] - rc[None, :, 3]), 0.0)
        cell = cells[np.argmin(dx * dx + dy * dy, axis=1)]
        out = sid.copy()
        out[idx] = np.where(fl[idx], self._cell_floor[cell], self._cell_ceiling[cell])
        return out

    def _shade(self, ox: float, oy: float, h: np.float32, phi: float, rays: _Rays, r_hit: np.ndarray,
               sid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Radiance and depth from the hit range and surface of every pixel."""
        b = self.baked
        s = rays.slope
        depth = r_hit * rays.inv_h
        # texture coordinates in level-0 texels from the hit point (eu is horizontal on every
        # surface): u = r (dx eux + dy euy) + (ox eux + oy euy + eu0), v likewise (+ z evz)
        cphi, sphi = np.float32(math.cos(phi)), np.float32(math.sin(phi))
        dxw = cphi * rays.ca - sphi * rays.sa
        dyw = sphi * rays.ca + cphi * rays.sa
        t = self._tex
        cu = (np.float32(ox) * t["eux"] + np.float32(oy) * t["euy"] + t["eu0"]).take(sid)
        cv = (np.float32(ox) * t["evx"] + np.float32(oy) * t["evy"] + h * t["evz"] + t["ev0"]).take(sid)
        u = r_hit * (dxw * t["eux"].take(sid) + dyw * t["euy"].take(sid)) + cu
        v = r_hit * (dxw * t["evx"].take(sid) + dyw * t["evy"].take(sid) + s * t["evz"].take(sid)) + cv
        # mip level from the footprint of a pixel on the surface (in level-0 texels)
        foot = depth * np.where(t["horiz"].take(sid), rays.foot_h, rays.foot_v)
        lev = (foot > 1.4142135).view(np.int8) + (foot > 2.828427).view(np.int8) + (foot > 5.656854).view(np.int8)
        key = sid * MIP_LEVELS + lev
        cols = t["cols"].take(key)
        rows = t["rows"].take(key)
        iu = np.minimum(np.maximum(u, 0.0).astype(np.int32) >> lev, cols - 1)
        iv = np.minimum(np.maximum(v, 0.0).astype(np.int32) >> lev, rows - 1)
        rad = b.atlas.take(t["offset"].take(key) + iv * cols + iu)
        return rad, depth

    # -- public -------------------------------------------------------------------------
    def render(
        self,
        x: float,
        y: float,
        theta: float,
        pan: float = 0.0,
        tilt: float = 0.0,
        height: float | None = None,
        *,
        stereo: bool = True,
        noise: bool = True,
        rng: np.random.Generator | None = None,
    ) -> RenderResult:
        """Render the view of the camera on a robot at (x, y, theta) (map frame, REP-103).

        Camera heading = ``theta + pan``; ``tilt`` > 0 looks up; ``height`` is the camera
        height above the floor (default ``camera.height_m``). With ``noise=False`` the image
        is the deterministic noiseless one; otherwise noise is drawn from ``rng`` (default:
        the renderer's own generator, seeded by ``seed``)."""
        cam = self.camera
        hcam = cam.height_m if height is None else float(height)
        phi = float(theta) + float(pan)
        rays = self._rays_for(float(tilt))
        rad_l, depth = self._radiance(float(x), float(y), hcam, phi, rays)
        rad_r = None
        if stereo:
            bx, by = cam.baseline_m * math.sin(phi), -cam.baseline_m * math.cos(phi)
            rad_r, _ = self._radiance(float(x) + bx, float(y) + by, hcam, phi, rays)
        gain = self._auto_gain(rad_l)
        gen = rng if rng is not None else self._rng
        left = self._expose(rad_l, gain, noise, gen)
        right = self._expose(rad_r, gain, noise, gen) if rad_r is not None else None
        shape = (cam.height, cam.width)
        left = left.reshape(shape)
        return RenderResult(
            grey=left,
            depth=depth.reshape(shape),
            left=left,
            right=right.reshape(shape) if right is not None else None,
            gain=gain,
            camera_pose=(float(x), float(y), math.atan2(math.sin(phi), math.cos(phi))),
        )

    def radiance(
        self, x: float, y: float, theta: float, pan: float = 0.0, tilt: float = 0.0, height: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Linear scene radiance (float32 HxW, before the camera) and depth Z (float32 HxW) of
        the left camera; same pose semantics as :meth:`render`."""
        cam = self.camera
        hcam = cam.height_m if height is None else float(height)
        rad, depth = self._radiance(float(x), float(y), hcam, float(theta) + float(pan), self._rays_for(float(tilt)))
        return rad.reshape(cam.height, cam.width), depth.reshape(cam.height, cam.width)

    def _auto_gain(self, rad: np.ndarray) -> float:
        """Gain that brings the mean OUTPUT grey (after clipping and gamma) to the target,
        within [gain_min, gain_max]. With s = L^(1/gamma) on a strided pixel sample, the mean
        output is 255 mean(min(a s, 1)) with a = (gain / 255)^(1/gamma): bisection on a."""
        cam = self.camera
        inv_g = 1.0 / cam.gamma
        sub = np.power(rad[:: max(1, rad.size // 4096)], np.float32(inv_g))
        target = cam.target_grey / 255.0

        def mean_out(a: float) -> float:
            return float(np.minimum(sub * np.float32(a), np.float32(1.0)).mean())

        lo, hi = (cam.gain_min / 255.0) ** inv_g, (cam.gain_max / 255.0) ** inv_g
        if mean_out(hi) <= target:
            return cam.gain_max
        if mean_out(lo) >= target:
            return cam.gain_min
        m = float(sub.mean())
        a = min(max(target / m, lo), hi) if m > 0 else hi  # exact when nothing saturates
        if mean_out(a) >= target * (1 - 1e-4):
            lo_, hi_ = lo, a
        else:
            lo_, hi_ = a, hi
        for _ in range(20):
            mid = 0.5 * (lo_ + hi_)
            if mean_out(mid) < target:
                lo_ = mid
            else:
                hi_ = mid
            if hi_ - lo_ < 1e-4 * hi_:
                break
        return 255.0 * (0.5 * (lo_ + hi_)) ** cam.gamma

    def _normals(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n standard normal samples (float32): a window of a pre-drawn buffer (seed 12345, at
        least max(2^21, 8 n) values) at an offset and a stride of 1-3 drawn from ``rng``, its
        sign flipped with probability 1/2 (also from ``rng``). Reproducible for a given
        ``rng`` and much cheaper than fresh draws (see docs/results.md); windows of
        successive calls may overlap, which image noise does not notice."""
        if self._noise_buf is None or self._noise_buf.size < 4 * n:
            self._noise_buf = np.random.default_rng(12345).standard_normal(max(1 << 21, 8 * n), dtype=np.float32)
        buf = self._noise_buf
        step = int(rng.integers(1, 4))
        start = int(rng.integers(0, buf.size - step * n))
        out = buf[start: start + step * n: step]
        return out if rng.random() < 0.5 else -out

    def _expose(self, rad: np.ndarray, gain: float, noise: bool, rng: np.random.Generator) -> np.ndarray:
        cam = self.camera
        dn = rad * np.float32(gain)
        if noise:
            rel = np.float32(gain / cam.gain_ref)
            var = np.float32(cam.shot_noise) * rel * np.minimum(dn, 300.0) + np.float32((cam.read_noise * rel) ** 2)
            dn = dn + np.sqrt(var) * self._normals(dn.size, rng)
        if self._lut is None:
            x = (np.arange(4096, dtype=np.float64) + 0.5) / 16.0
            self._lut = np.clip(255.0 * (x / 255.0) ** (1.0 / cam.gamma) + 0.5, 0, 255).astype(np.uint8)
        code = np.minimum(np.maximum(dn * np.float32(16.0), 0.0), 4095.0).astype(np.int32)
        return self._lut.take(code)

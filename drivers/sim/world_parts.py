"""The parts of a world file that several modules share: textures, walls, boxes, rectangles.

The pydantic models of :mod:`drivers.sim.world`'s format that :mod:`drivers.sim.rooms`
also builds (walls, decals, windows, boxes, rectangles), and :class:`Box`, a box resolved into
the map frame. :mod:`drivers.sim.world` re-exports them; see it for the format.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TextureSpec(_Model):
    """A procedural albedo texture. ``kind`` selects the generator; the other fields tune it.

    Two specs with the same fields produce bit-identical textures (the ``seed`` is part of
    the spec), so repeated elements are identical.
    """

    kind: Literal[
        "paint", "wood", "poster", "door", "tiles", "carpet", "curtain", "window_view",
        "bookshelf", "whiteboard", "ceiling_tiles", "fabric", "cardboard", "metal", "fixture",
    ]
    albedo: float = Field(0.6, ge=0.0, le=1.0)
    albedo2: float | None = Field(None, ge=0.0, le=1.0)
    contrast: float = Field(0.1, ge=0.0, le=1.0)
    period: float = Field(0.3, gt=0.0)
    seed: int = 0


class Decal(_Model):
    """A flat rectangle painted on a wall: ``u`` along the wall from its start, ``z`` above the floor."""

    texture: str
    u: float
    z: float = 0.0
    width: float = Field(gt=0.0)
    height: float = Field(gt=0.0)


class Window(_Model):
    """A window in a wall: curtains (``curtain`` texture) or, when open, the ``view`` (emissive)."""

    u: float
    z: float = 0.9
    width: float = Field(gt=0.0)
    height: float = Field(gt=0.0)
    curtain: str
    view: str


class Wall(_Model):
    id: str = ""
    start: Vec2
    end: Vec2
    texture: str
    decals: tuple[Decal, ...] = ()
    windows: tuple[Window, ...] = ()

    @model_validator(mode="after")
    def _length(self) -> Wall:
        if math.dist(self.start, self.end) < 1e-3:
            raise ValueError("wall has zero length")
        return self


class BoxSpec(_Model):
    """A box in the local frame of its piece of furniture. Faces: +x local is the ``front``."""

    center: Vec2 = (0.0, 0.0)
    size: Vec2
    yaw_deg: float = 0.0
    zmin: float = Field(0.0, ge=0.0)
    zmax: float
    texture: str
    faces: dict[Literal["front", "back", "left", "right", "top", "bottom"], str] = {}

    @model_validator(mode="after")
    def _sizes(self) -> BoxSpec:
        if self.size[0] <= 0 or self.size[1] <= 0:
            raise ValueError("box size must be positive")
        if self.zmax <= self.zmin:
            raise ValueError("box zmax must be above zmin")
        return self


class Rect(_Model):
    xmin: float
    xmax: float
    ymin: float
    ymax: float

    @model_validator(mode="after")
    def _order(self) -> Rect:
        if self.xmax <= self.xmin or self.ymax <= self.ymin:
            raise ValueError("need xmin < xmax and ymin < ymax")
        return self

    def as_tuple(self) -> tuple[float, float, float, float]:
        return (self.xmin, self.xmax, self.ymin, self.ymax)


@dataclass(frozen=True)
class Box:
    """A resolved box in the map frame (footprint centre, half sizes, yaw; z range)."""

    owner: str
    cx: float
    cy: float
    hx: float
    hy: float
    yaw: float
    zmin: float
    zmax: float
    spec: BoxSpec

    def corners(self) -> np.ndarray:
        """Footprint corners (4, 2), counter-clockwise."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        local = np.array([[-self.hx, -self.hy], [self.hx, -self.hy], [self.hx, self.hy], [-self.hx, self.hy]])
        rot = np.array([[c, -s], [s, c]])
        return local @ rot.T + np.array([self.cx, self.cy])

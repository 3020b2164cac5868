"""Procedural albedo textures for the simulated building.

:func:`albedo_texture` turns a :class:`drivers.sim.world.TextureSpec` and a surface size
(metres) into a float32 albedo image in [0, 1] sampled every ``texel`` metres. Row 0 is
the *bottom* of the surface (v = 0, the floor for walls), column 0 its start (u = 0).

The generators are deterministic functions of the spec (its ``seed`` included) and the
size: two identical specs on two surfaces of the same size give bit-identical textures,
which is how the worlds get identical doors, desks and posters.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from drivers.sim.world import TextureSpec

_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _smooth_noise(rng: np.random.Generator, h: int, w: int, cell_px: float) -> np.ndarray:
    """Zero-mean, unit-ish smooth noise with features about ``cell_px`` texels wide."""
    gh = max(2, int(np.ceil(h / max(cell_px, 1.0))) + 1)
    gw = max(2, int(np.ceil(w / max(cell_px, 1.0))) + 1)
    g = rng.standard_normal((gh, gw)).astype(np.float32)
    return cv2.resize(g, (w, h), interpolation=cv2.INTER_CUBIC)


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float, value: float, thick: int) -> None:
    """Draw anti-aliased text of grey ``value`` into a float image (putText wants 8-bit)."""
    mask = np.zeros(img.shape, np.uint8)
    cv2.putText(mask, text, org, _FONT, scale, 255, thick, cv2.LINE_AA)
    m = mask.astype(np.float32) / 255.0
    img *= 1.0 - m
    img += value * m


def _px(metres: float, texel: float) -> int:
    return max(1, int(round(metres / texel)))


def _paint(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    img = spec.albedo * (1.0 + spec.contrast * 0.5 * _smooth_noise(rng, h, w, 0.6 / texel))
    img += 0.01 * spec.contrast * _smooth_noise(rng, h, w, 2.0)
    return img


def _wood(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    u = np.arange(w, dtype=np.float32)[None, :] * texel
    v = np.arange(h, dtype=np.float32)[:, None] * texel
    warp = 0.03 * _smooth_noise(rng, h, w, 0.25 / texel)
    grain = np.sin(2 * np.pi * (v + warp + 0.02 * np.sin(u * 3.0)) / 0.018)
    img = spec.albedo * (1.0 + spec.contrast * (0.5 * grain + 0.6 * _smooth_noise(rng, h, w, 0.15 / texel)))
    # planks along u every `period`
    plank = (np.mod(v, spec.period) < 0.004).astype(np.float32)
    img = img * (1.0 - 0.35 * plank)
    return np.broadcast_to(img, (h, w)).copy()


def _tiles(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    p = spec.period
    u = np.arange(w)[None, :] * texel
    v = np.arange(h)[:, None] * texel
    iu = np.floor(u / p).astype(np.int64)
    iv = np.floor(v / p).astype(np.int64)
    # per-tile variation from a hash of the tile index (no dependence on the surface size)
    hsh = np.sin(iu * 12.9898 + iv * 78.233 + spec.seed * 3.1) * 43758.5453
    var = (hsh - np.floor(hsh)) - 0.5
    img = spec.albedo * (1.0 + spec.contrast * var)
    img = img + 0.04 * spec.albedo * _smooth_noise(rng, h, w, 1.5)
    grout = (np.mod(u, p) < 0.006) | (np.mod(v, p) < 0.006)
    g2 = spec.albedo2 if spec.albedo2 is not None else spec.albedo * 0.6
    return np.where(grout, g2, img)


def _carpet(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    fine = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 1.0)
    img = spec.albedo * (1.0 + spec.contrast * (1.2 * fine + 0.5 * _smooth_noise(rng, h, w, spec.period / texel)))
    return img


def _curtain(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    u = np.arange(w, dtype=np.float32)[None, :] * texel
    folds = np.sin(2 * np.pi * u / spec.period) + 0.3 * np.sin(2 * np.pi * u / (spec.period * 0.37) + 1.0)
    img = spec.albedo * (1.0 + spec.contrast * folds) + 0.02 * _smooth_noise(rng, h, w, 0.3 / texel)
    hem = np.arange(h)[:, None] < _px(0.05, texel)
    return np.where(hem, img * 0.9, img)


def _window_view(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    v = np.arange(h, dtype=np.float32)[:, None] / max(h - 1, 1)
    sky = 0.85 + 0.15 * v  # brighter upwards
    img = np.broadcast_to(sky, (h, w)).copy()
    # skyline of trees and buildings (darker) in the lower part
    skyline = 0.35 + 0.12 * _smooth_noise(rng, 1, w, 0.4 / texel)[0]
    blocks = rng.integers(0, 2, size=max(2, w // _px(0.3, texel) + 1))
    skyline += 0.15 * np.repeat(blocks, _px(0.3, texel))[:w]
    below = v < skyline[None, :]
    ground = 0.45 + 0.1 * _smooth_noise(rng, h, w, 0.1 / texel)
    img = np.where(below, ground, img)
    # window frame and a mullion (dark)
    f = _px(0.05, texel)
    frame = np.zeros((h, w), bool)
    frame[:f, :] = frame[-f:, :] = True
    frame[:, :f] = frame[:, -f:] = True
    mid = w // 2
    frame[:, max(0, mid - f // 2): mid + f // 2 + 1] = True
    return np.where(frame, 0.12, img * spec.albedo)


def _poster(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    bg = spec.albedo
    img = np.full((h, w), bg, np.float32)
    for _ in range(int(rng.integers(3, 7))):
        x0, y0 = int(rng.integers(0, w)), int(rng.integers(0, h))
        x1, y1 = int(rng.integers(0, w)), int(rng.integers(0, h))
        cv2.rectangle(img, (x0, y0), (x1, y1), float(rng.uniform(0.05, 0.9)), -1)
    for _ in range(int(rng.integers(1, 4))):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.circle(img, c, int(rng.integers(max(2, w // 12), max(3, w // 3))), float(rng.uniform(0.05, 0.9)), -1)
    scale = max(0.3, h / 400.0)
    y = int(h * 0.1)
    letters = "ABCDEFGHIJKLMNOPQRSTUVWXYZ "
    while y < h * 0.35:
        text = "".join(letters[int(i)] for i in rng.integers(0, len(letters), 12))
        _text(img, text, (int(w * 0.05), y), scale, 0.05, max(1, int(2 * scale)))
        y += int(36 * scale) + 2
    cv2.rectangle(img, (0, 0), (w - 1, h - 1), 0.9, max(1, _px(0.01, texel)))
    return img[::-1].copy()


def _door(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    panel = _wood(spec.model_copy(update={"contrast": spec.contrast * 0.5, "period": 10.0}), h, w, texel, rng)
    frame_alb = spec.albedo2 if spec.albedo2 is not None else spec.albedo * 0.5
    f = _px(0.06, texel)
    img = panel
    img[:, :f] = frame_alb
    img[:, -f:] = frame_alb
    img[-f:, :] = frame_alb
    # handle at 1.0 m, 8 cm from the right edge of the leaf
    hy, hx = _px(1.0, texel), w - f - _px(0.1, texel)
    cv2.rectangle(img, (hx - _px(0.09, texel), hy - _px(0.015, texel)), (hx, hy + _px(0.015, texel)), 0.15, -1)
    cv2.circle(img, (hx - _px(0.01, texel), hy), _px(0.03, texel), 0.2, -1)
    # kick plate and a sign
    img[: _px(0.2, texel), f:-f] = 0.35
    sy, sx = _px(1.55, texel), w // 2
    cv2.rectangle(img, (sx - _px(0.1, texel), sy), (sx + _px(0.1, texel), sy + _px(0.07, texel)), 0.85, -1)
    return img


def _bookshelf(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    board = spec.albedo2 if spec.albedo2 is not None else spec.albedo
    img = np.full((h, w), board * 0.4, np.float32)  # dark back panel
    pitch = _px(spec.period, texel)
    bt = _px(0.02, texel)
    for y0 in range(0, h, pitch):
        img[y0: y0 + bt, :] = board
        x = _px(0.02, texel)
        top = min(h, y0 + pitch)
        while x < w - 1:
            bw = int(rng.integers(_px(0.015, texel), _px(0.06, texel) + 1))
            if rng.random() < 0.08:
                x += bw * 3
                continue
            bh = int(rng.uniform(0.55, 0.92) * (pitch - bt))
            img[y0 + bt: min(top, y0 + bt + bh), x: x + bw] = float(rng.uniform(0.05, 0.85))
            x += bw
    f = _px(0.025, texel)
    img[:, :f] = board
    img[:, -f:] = board
    return img


def _whiteboard(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    img = np.full((h, w), spec.albedo, np.float32) + 0.01 * _smooth_noise(rng, h, w, 0.5 / texel)
    for _ in range(int(rng.integers(4, 10))):
        pts = np.cumsum(rng.normal(0, max(2, w // 25), size=(8, 2)), axis=0) + [rng.integers(0, w), rng.integers(0, h)]
        cv2.polylines(img, [pts.astype(np.int32)], False, float(rng.uniform(0.1, 0.4)), max(1, _px(0.005, texel)))
    f = _px(0.02, texel)
    cv2.rectangle(img, (0, 0), (w - 1, h - 1), 0.5, f)
    return img


def _ceiling_tiles(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    img = spec.albedo * (1.0 + spec.contrast * cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 0.8))
    p = spec.period
    u = np.arange(w)[None, :] * texel
    v = np.arange(h)[:, None] * texel
    grid = (np.mod(u, p) < 0.015) | (np.mod(v, p) < 0.015)
    return np.where(grid, spec.albedo2 if spec.albedo2 is not None else spec.albedo * 0.75, img)


def _fabric(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    return spec.albedo * (1.0 + spec.contrast * (_smooth_noise(rng, h, w, spec.period / texel)
                                                 + 0.5 * _smooth_noise(rng, h, w, 0.03 / texel)))


def _cardboard(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    img = spec.albedo * (1.0 + spec.contrast * _smooth_noise(rng, h, w, 0.1 / texel))
    t = _px(0.05, texel)
    img[h // 2 - t // 2: h // 2 + t // 2 + 1, :] = spec.albedo * 1.25  # tape
    img = img.astype(np.float32)
    _text(img, "FRAGILE", (w // 6, h // 4), max(0.3, w / 500), float(spec.albedo * 0.3), max(1, w // 150))
    return img


def _metal(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    img = spec.albedo * (1.0 + 0.03 * _smooth_noise(rng, h, w, 0.2 / texel))
    pitch = _px(spec.period, texel)
    for y0 in range(0, h, pitch):  # drawer fronts with a gap and a handle
        img[y0: y0 + max(1, _px(0.006, texel)), :] = spec.albedo * 0.4
        hy = y0 + pitch // 2
        if hy < h:
            cv2.rectangle(img, (w // 2 - _px(0.06, texel), hy), (w // 2 + _px(0.06, texel), hy + _px(0.015, texel)),
                          float(spec.albedo2 if spec.albedo2 is not None else 0.2), -1)
    return img


def _fixture(spec: TextureSpec, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    img = np.full((h, w), spec.albedo, np.float32)
    u = np.arange(w)[None, :] * texel
    louvre = np.mod(u, spec.period) < 0.01
    img = np.where(louvre, spec.albedo * 0.7, img)
    f = _px(0.02, texel)
    img[:f, :] = img[-f:, :] = spec.albedo * 0.6
    return img


_GENERATORS = {
    "paint": _paint, "wood": _wood, "poster": _poster, "door": _door, "tiles": _tiles,
    "carpet": _carpet, "curtain": _curtain, "window_view": _window_view, "bookshelf": _bookshelf,
    "whiteboard": _whiteboard, "ceiling_tiles": _ceiling_tiles, "fabric": _fabric,
    "cardboard": _cardboard, "metal": _metal, "fixture": _fixture,
}


@lru_cache(maxsize=256)
def _cached(spec: TextureSpec, h: int, w: int, texel: float) -> np.ndarray:
    rng = np.random.default_rng(spec.seed)
    img = _GENERATORS[spec.kind](spec, h, w, texel, rng)
    img = np.clip(np.asarray(img, dtype=np.float32), 0.02, 0.97)
    img.setflags(write=False)
    return img


def texture_shape(width_m: float, height_m: float, texel: float) -> tuple[int, int]:
    """(rows, cols) of a texture covering width_m x height_m at ``texel`` metres."""
    return max(1, int(np.ceil(height_m / texel - 1e-6))), max(1, int(np.ceil(width_m / texel - 1e-6)))


def albedo_texture(spec: TextureSpec, width_m: float, height_m: float, texel: float = 0.01) -> np.ndarray:
    """Albedo (float32, rows = v from 0 upwards, cols = u) of a ``width_m`` x ``height_m`` surface.

    The returned array is read-only and shared between identical requests."""
    h, w = texture_shape(width_m, height_m, texel)
    return _cached(spec, h, w, float(texel))

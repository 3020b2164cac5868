"""Synthetic appearance maps of a whole floor (40 x 25 m), of any size, for the scale benchmarks.

A real map of a floor's survey (about 100k views) is not needed to measure what a map of N
entries costs the localizer: the search, the update and the memory depend on N, on the
feature dimension d and on the structure of the features (how many entries are near each
other in feature space), not on the pictures. The synthetic map reproduces that structure:

- **poses**: a survey grid over the floor, ``FLOOR_M`` = 40 x 25 m, at the spacing that gives
  N entries with ``HEADINGS`` = 36 headings per position (10 degrees, as the lab survey), each
  position jittered by up to a quarter of the spacing (a robot survey's positions are not
  exact), then N of them kept at random;
- **features**: a smooth manifold over the pose. The view at (x, y, theta) is represented by
  random Fourier features (Rahimi and Recht, "Random features for large-scale kernel
  machines", NIPS 2007) of the embedding ``(x / L, y / L, cos(theta) / S, sin(theta) / S)``
  with ``L`` = ``LENGTH_M`` (1.5 m) and ``S`` = ``HEADING_RAD`` (0.3 rad): a sample of a
  Gaussian process whose views change over about a metre of travel or 0.3 rad of turn, like the
  images of a room. They are mixed into d features with decaying scales (``k^-0.7``, the
  slowly decaying spectrum of appearance PCA), rotated to their principal axes (sorted by
  variance, as PCA features are), scaled to a total standard deviation of ``FEATURE_NORM``
  and perturbed by Gaussian noise of ``noise`` times each feature's standard deviation (image
  noise and small scene differences);
- **projection model**: an orthonormal random basis (d, 80 * 60) and a grey mean of 0.5, so
  that :func:`floor_image` can render an observation's 320 x 240 image whose projection
  (eq. 1, preprocessing ``none``) is the manifold's features at that pose: the Localizer's
  whole update path, projection included, runs on it.

Usage::

    amap = floor_map(100_000, seed=0)                 # an AppearanceMap (intensity channel)
    y = floor_features(query_poses, seed=0)            # (M, d) noise-free features
    img = floor_image(amap, y[0])                      # (240, 320) uint8
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

FLOOR_M = (40.0, 25.0)
HEADINGS = 36
LENGTH_M = 1.5
HEADING_RAD = 0.3
N_RANDOM_FEATURES = 256
FEATURE_NORM = 4.0
MAP_SIZE = (80, 60)
IMAGE_SIZE = (320, 240)
DEFAULT_DIM = 20
DEFAULT_NOISE = 0.05


def survey_poses(entries: int, seed: int = 0) -> np.ndarray:
    """(entries, 3) camera poses: a jittered grid over :data:`FLOOR_M` with :data:`HEADINGS`
    headings per position, spaced to hold at least ``entries``, a random subset of that many."""
    rng = np.random.default_rng(seed)
    w, h = FLOOR_M
    positions = math.ceil(entries / HEADINGS)
    step = math.sqrt(w * h / positions)
    nx, ny = max(1, math.ceil(w / step)), max(1, math.ceil(h / step))
    while nx * ny < positions:
        nx += 1
    xs = (np.arange(nx) + 0.5) * (w / nx)
    ys = (np.arange(ny) + 0.5) * (h / ny)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    xy += rng.uniform(-0.25, 0.25, xy.shape) * np.array([w / nx, h / ny])
    th = (np.arange(HEADINGS) * (2.0 * math.pi / HEADINGS) + math.pi) % (2.0 * math.pi) - math.pi
    poses = np.column_stack([np.repeat(xy, HEADINGS, axis=0), np.tile(th, len(xy))])
    keep = np.sort(rng.choice(len(poses), size=entries, replace=False))
    return np.ascontiguousarray(poses[keep])


class _Manifold:
    """The fixed random parts of the feature manifold for one (seed, d)."""

    def __init__(self, seed: int, dim: int) -> None:
        rng = np.random.default_rng([seed, 7919])
        self.w = rng.standard_normal((4, N_RANDOM_FEATURES))
        self.b = rng.uniform(0.0, 2.0 * math.pi, N_RANDOM_FEATURES)
        mix = rng.standard_normal((N_RANDOM_FEATURES, dim)) * (np.arange(1, dim + 1) ** -0.7)
        # principal axes and scale from a fixed sample of the floor (as a PCA of the map would)
        sample = self.raw(survey_poses(4000, seed=seed + 1)) @ mix
        mean = sample.mean(axis=0)
        evals, evecs = np.linalg.eigh(np.cov(sample, rowvar=False, bias=True))
        order = np.argsort(evals)[::-1]
        scale = FEATURE_NORM / math.sqrt(float(evals.sum()))
        self.mix = mix @ evecs[:, order] * scale
        self.mean = mean @ evecs[:, order] * scale

    def raw(self, poses: np.ndarray) -> np.ndarray:
        e = np.column_stack([poses[:, 0] / LENGTH_M, poses[:, 1] / LENGTH_M,
                             np.cos(poses[:, 2]) / HEADING_RAD, np.sin(poses[:, 2]) / HEADING_RAD])
        return math.sqrt(2.0 / N_RANDOM_FEATURES) * np.cos(e @ self.w + self.b)

    def features(self, poses: np.ndarray, block: int = 65536) -> np.ndarray:
        out = np.empty((len(poses), self.mix.shape[1]))
        for lo in range(0, len(poses), block):
            out[lo : lo + block] = self.raw(poses[lo : lo + block]) @ self.mix - self.mean
        return out


def floor_features(poses: np.ndarray, seed: int = 0, dim: int = DEFAULT_DIM, noise: float = 0.0,
                   rng: np.random.Generator | None = None) -> np.ndarray:
    """(M, dim) features of the manifold at camera poses (M, 3), plus Gaussian noise of
    ``noise`` times each feature's standard deviation (``rng``, default seeded by ``seed``)."""
    man = _Manifold(seed, dim)
    f = man.features(np.asarray(poses, dtype=np.float64))
    if noise > 0.0:
        rng = rng if rng is not None else np.random.default_rng([seed, 31])
        std = np.linalg.norm(man.mix, axis=0) * math.sqrt(0.5)  # per-feature std of the manifold
        f += noise * std * rng.standard_normal(f.shape)
    return f


def floor_map(entries: int, seed: int = 0, dim: int = DEFAULT_DIM, noise: float = DEFAULT_NOISE) -> Any:
    """An AppearanceMap of ``entries`` synthetic views of the floor (see module docstring):
    one ``intensity`` channel, features float32 as a built map holds them."""
    from lino_loc.appearance_map import AppearanceMap, ChannelMap
    from lino_loc.dataset import CameraInfo
    from lino_loc.pca import PCA

    poses = survey_poses(entries, seed)
    feats = floor_features(poses, seed, dim, noise).astype(np.float32)
    w, h = MAP_SIZE
    basis, _ = np.linalg.qr(np.random.default_rng([seed, 101]).standard_normal((w * h, dim)))
    pca = PCA(mean=np.full(w * h, 0.5, dtype=np.float32), components=np.ascontiguousarray(basis.T, dtype=np.float32),
              explained_variance=feats.var(axis=0).astype(np.float32))
    ch = ChannelMap(name="intensity", preprocess="none", size=(w, h), pca=pca, features=feats,
                    method="synthetic", params={"seed": seed, "noise": float(noise)})
    cam = CameraInfo(width=IMAGE_SIZE[0], height=IMAGE_SIZE[1], fx=277.0, fy=277.0, cx=160.0, cy=120.0)
    return AppearanceMap(poses=poses, channels={"intensity": ch}, camera=cam, source="synthetic floor",
                         name=f"floor-{entries}")


def floor_image(amap: Any, features: np.ndarray) -> np.ndarray:
    """The (240, 320) uint8 image whose projection through ``amap``'s intensity channel is
    ``features`` (up to 8-bit quantization): mean + basis^T y at 80 x 60, each pixel repeated
    4 x 4 (area averaging gives it back)."""
    ch = amap.channels["intensity"]
    w, h = ch.size
    z = ch.pca.mean + np.asarray(features, dtype=np.float32) @ ch.pca.components
    img = np.clip(np.rint(z.reshape(h, w) * 255.0), 0, 255).astype(np.uint8)
    fy, fx = IMAGE_SIZE[1] // h, IMAGE_SIZE[0] // w
    return np.repeat(np.repeat(img, fy, axis=0), fx, axis=1)

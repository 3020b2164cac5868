"""Render simulated views and turn them into the map's input vectors, on all cores.

The evaluations need thousands of views of the simulated building under several lights.
``render_vectors`` renders them in a process pool (one renderer per worker, built once) and
returns, per requested channel, the vectors that the appearance map's channels consume:
``preprocess`` + area-resize for intensity channels (lino_loc.preprocessing), and the sparse
disparity of the rendered stereo pair (lino_loc.disparity), NaN where stereo gave no value.
Every view's sensor noise is seeded by (seed, view index), so results do not depend on the
number of workers.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.world import load_world
from lino_loc.disparity import StereoConfig, compute_disparity, downsample_sparse
from lino_loc.preprocessing import preprocess, to_vector


@dataclass(frozen=True)
class ViewSpec:
    """What to render and which vectors to make of each view."""

    world: str
    lighting: str = "tube"
    scene_changes: tuple[str, ...] = ()
    width: int = 320
    height: int = 240
    size: tuple[int, int] = (80, 60)
    preprocess: tuple[str, ...] = ("none",)
    disparity: bool = False
    stereo: StereoConfig = field(default_factory=StereoConfig)
    min_valid_fraction: float = 0.25
    seed: int = 0


_worker: tuple[ViewSpec, Renderer] | None = None


def _init(spec: ViewSpec) -> None:
    global _worker
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    world = load_world(spec.world)
    camera = CameraModel(width=spec.width, height=spec.height)
    _worker = (spec, Renderer(world, camera=camera, lighting=spec.lighting, scene_changes=spec.scene_changes))


def _render_chunk(args: tuple[int, np.ndarray]) -> dict[str, np.ndarray]:
    start, poses = args
    assert _worker is not None
    spec, renderer = _worker
    out: dict[str, list[np.ndarray]] = {name: [] for name in _channels(spec)}
    for k, (x, y, theta) in enumerate(poses):
        rng = np.random.default_rng((spec.seed, start + k))
        view = renderer.render(float(x), float(y), float(theta), stereo=spec.disparity, rng=rng)
        for method in spec.preprocess:
            out[method].append(to_vector(preprocess(view.grey, method), spec.size))
        if spec.disparity:
            disp = compute_disparity(view.left, view.right, spec.stereo)
            out["disparity"].append(downsample_sparse(disp, spec.size, spec.min_valid_fraction).ravel())
    return {name: np.asarray(v, dtype=np.float32) for name, v in out.items()}


def _channels(spec: ViewSpec) -> list[str]:
    return list(spec.preprocess) + (["disparity"] if spec.disparity else [])


def render_vectors(
    spec: ViewSpec,
    poses: np.ndarray,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    chunk: int = 64,
) -> dict[str, np.ndarray]:
    """Vectors (N, w*h) per channel for robot poses (N, 3) with the camera's pan at 0."""
    poses = np.asarray(poses, dtype=np.float64)
    workers = workers or os.cpu_count() or 1
    jobs = [(i, poses[i : i + chunk]) for i in range(0, len(poses), chunk)]
    parts: list[dict[str, np.ndarray]] = []
    done = 0
    if workers == 1:
        _init(spec)
        results = map(_render_chunk, jobs)
        for part in results:
            parts.append(part)
            done += len(next(iter(part.values())))
            if progress:
                progress(done, len(poses))
    else:
        with ProcessPoolExecutor(max_workers=workers, initializer=_init, initargs=(spec,)) as pool:
            for part in pool.map(_render_chunk, jobs):
                parts.append(part)
                done += len(next(iter(part.values())))
                if progress:
                    progress(done, len(poses))
    return {name: np.concatenate([p[name] for p in parts]) for name in _channels(spec)}

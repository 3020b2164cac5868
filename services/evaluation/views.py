"""Render simulated views and turn them into the map's input vectors, on all cores.

The evaluations need thousands of views of the simulated building under several lights.
``render_vectors`` renders them in a process pool (one renderer per worker, built once) and
returns, per requested channel, the vectors that the appearance map's channels consume:
``preprocess`` + area-resize for intensity channels (lino_loc.preprocessing), and the sparse
disparity of the rendered stereo pair (lino_loc.disparity), NaN where stereo gave no value.
Every view's sensor noise is seeded by (seed, view index), so results do not depend on the
number of workers.

``render_grey`` returns the camera's uint8 grey images instead (what the Localizer takes, for
drives), and ``build_sim_maps`` turns a rendered survey grid into appearance maps (one per
preprocessing, eq. 1) kept as map files under ~/.cache/lino-loc/maps (``$LINO_LOC_CACHE``).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.sim.code_fingerprint import code_fingerprint
from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.world import grid_poses, load_world
from lino_loc.disparity import StereoConfig, compute_disparity, downsample_sparse
from lino_loc.preprocessing import preprocess, to_vector

if TYPE_CHECKING:
    from lino_loc.appearance_map import AppearanceMap


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


def _run_chunks(
    spec: ViewSpec,
    poses: np.ndarray,
    fn: Callable[[tuple[int, np.ndarray]], Any],
    workers: int | None,
    progress: Callable[[int, int], None] | None,
    chunk: int,
    count: Callable[[Any], int],
) -> list[Any]:
    """``fn`` over chunks of ``poses`` (start index, poses), in this process when one worker
    is asked for or there is one chunk, else in a pool of renderers; results in order."""
    workers = workers or os.cpu_count() or 1
    jobs = [(i, poses[i : i + chunk]) for i in range(0, len(poses), chunk)]
    parts: list[Any] = []
    done = 0

    def collect(results: Iterable[Any]) -> None:
        nonlocal done
        for part in results:
            parts.append(part)
            done += count(part)
            if progress:
                progress(done, len(poses))

    if workers == 1 or len(jobs) <= 1:
        _init(spec)
        collect(map(fn, jobs))
    else:
        with ProcessPoolExecutor(max_workers=workers, initializer=_init, initargs=(spec,)) as pool:
            collect(pool.map(fn, jobs))
    return parts


def render_vectors(
    spec: ViewSpec,
    poses: np.ndarray,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    chunk: int = 64,
) -> dict[str, np.ndarray]:
    """Vectors (N, w*h) per channel for robot poses (N, 3) with the camera's pan at 0."""
    parts = _run_chunks(spec, np.asarray(poses, dtype=np.float64), _render_chunk, workers, progress, chunk,
                        count=lambda part: len(next(iter(part.values()))))
    return {name: np.concatenate([p[name] for p in parts]) for name in _channels(spec)}


# --------------------------------------------------------------------------- grey images
# (the Localizer takes the camera's grey image)


def _render_grey_chunk(args: tuple[int, np.ndarray]) -> np.ndarray:
    start, poses = args
    assert _worker is not None
    spec, renderer = _worker
    out = np.empty((len(poses), spec.height, spec.width), dtype=np.uint8)
    for k, (x, y, theta) in enumerate(poses):
        rng = np.random.default_rng((spec.seed, start + k))
        out[k] = renderer.render(float(x), float(y), float(theta), stereo=False, rng=rng).grey
    return out


def render_grey(
    spec: ViewSpec,
    poses: np.ndarray,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    chunk: int = 32,
) -> np.ndarray:
    """The camera's grey images (N, height, width) uint8 at robot poses (N, 3), pan 0, under
    ``spec.lighting`` and ``spec.scene_changes``; noise seeded by (seed, view index)."""
    parts = _run_chunks(spec, np.asarray(poses, dtype=np.float64).reshape(-1, 3), _render_grey_chunk,
                        workers, progress, chunk, count=len)
    if not parts:
        return np.zeros((0, spec.height, spec.width), dtype=np.uint8)
    return np.concatenate(parts)


def _render_frame_chunk(args: tuple[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    start, poses = args
    assert _worker is not None
    spec, renderer = _worker
    w, h = spec.size
    grey = np.empty((len(poses), spec.height, spec.width), dtype=np.uint8)
    disp = np.empty((len(poses), h, w), dtype=np.float32)
    for k, (x, y, theta) in enumerate(poses):
        rng = np.random.default_rng((spec.seed, start + k))
        view = renderer.render(float(x), float(y), float(theta), stereo=True, rng=rng)
        grey[k] = view.grey
        d = compute_disparity(view.left, view.right, spec.stereo)
        disp[k] = downsample_sparse(d, spec.size, spec.min_valid_fraction)
    return grey, disp


def render_frames(
    spec: ViewSpec,
    poses: np.ndarray,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    chunk: int = 32,
) -> tuple[np.ndarray, np.ndarray | None]:
    """What the camera delivers at robot poses (N, 3), pan 0: the grey images (N, height,
    width) uint8 (the same as :func:`render_grey`'s: the left image of the pair) and, with
    ``spec.disparity``, the product's sparse disparity of each stereo pair
    (:func:`lino_loc.disparity.compute_disparity`, ``spec.stereo``), area-averaged to
    ``spec.size`` (N, h, w) float32, NaN = no value: the map's disparity channel averages a
    full-size map to that size with the same ``min_valid_fraction``, which leaves this one
    unchanged. Without ``spec.disparity``: (:func:`render_grey`, None)."""
    if not spec.disparity:
        return render_grey(spec, poses, workers, progress, chunk), None
    parts = _run_chunks(spec, np.asarray(poses, dtype=np.float64).reshape(-1, 3), _render_frame_chunk,
                        workers, progress, chunk, count=lambda part: len(part[0]))
    if not parts:
        w, h = spec.size
        return np.zeros((0, spec.height, spec.width), dtype=np.uint8), np.zeros((0, h, w), dtype=np.float32)
    return np.concatenate([g for g, _ in parts]), np.concatenate([d for _, d in parts])


def frame_renderer(spec: ViewSpec) -> Renderer:
    """A renderer of ``spec``'s world, light, scene changes and camera size, for
    :func:`render_frame` (the one the process pools build per worker)."""
    world = load_world(spec.world)
    return Renderer(world, camera=CameraModel(width=spec.width, height=spec.height), lighting=spec.lighting,
                    scene_changes=spec.scene_changes)


def render_frame(
    renderer: Renderer, spec: ViewSpec, pose: np.ndarray, pan: float, index: int
) -> tuple[np.ndarray, np.ndarray | None]:
    """What the camera delivers on a robot at ``pose`` (x, y, theta) with the head at ``pan``
    (rad): the grey image (height, width) uint8 and, with ``spec.disparity``, its sparse
    disparity at ``spec.size`` (NaN = no value), else None. Noise seeded by (``spec.seed``,
    ``index``): at pan 0 it is view ``index`` of :func:`render_frames` (of :func:`render_grey`
    without disparity), so a run that turns the head sees the same noise as one that does not."""
    x, y, theta = (float(v) for v in np.asarray(pose, dtype=np.float64).reshape(3))
    rng = np.random.default_rng((spec.seed, int(index)))
    view = renderer.render(x, y, theta, pan=float(pan), stereo=spec.disparity, rng=rng)
    if not spec.disparity:
        return view.grey, None
    disp = compute_disparity(view.left, view.right, spec.stereo)
    return view.grey, downsample_sparse(disp, spec.size, spec.min_valid_fraction)


# --------------------------------------------------------------------------- survey maps


def map_cache_dir() -> Path:
    """Where rendered survey maps are cached (``$LINO_LOC_CACHE`` or ~/.cache/lino-loc)/maps."""
    root = os.environ.get("LINO_LOC_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "lino-loc")
    return Path(root) / "maps"


def build_sim_maps(
    world: str,
    step: float,
    heading_step_deg: float,
    features: int,
    preprocesses: tuple[str, ...] = ("none",),
    *,
    lighting: str = "tube",
    width: int = 320,
    height: int = 240,
    size: tuple[int, int] = (80, 60),
    seed: int = 0,
    workers: int | None = None,
    cache: bool = True,
    progress: Callable[[int, int], None] | None = None,
    virtual_headings: int = 1,
    virtual_step_deg: float = 3.0,
    disparity: bool = False,
    stereo: StereoConfig | None = None,
    min_valid_fraction: float = 0.25,
    disparity_features: int | None = None,
    translations: int = 1,
    memory_budget_mb: float | None = None,
) -> dict[str, AppearanceMap]:
    """Appearance maps (eq. 1) of a simulated survey, one per preprocessing, built in memory.

    The survey is :func:`drivers.sim.world.grid_poses` (every ``step`` m and
    ``heading_step_deg``, free positions of the mapped area, no scene changes: the map knows
    the building as it was), rendered under ``lighting`` with pan 0 (camera pose = robot
    pose); the PCA is the map builder's (randomized, ``seed``). With ``cache`` each map is
    kept as a map file under :func:`map_cache_dir`, keyed by every parameter and the world's
    fingerprint, and loaded from there next time. ``virtual_headings`` > 1: every image also
    gives that many views turned ``virtual_step_deg`` apart (:mod:`lino_loc.virtual_views`).
    ``disparity``: every map also gets the disparity channel (section 5) of the same survey's
    stereo pairs, through the product's matcher (``stereo``, sparse: NaN where it found no
    match) and PCA with missing data (:func:`lino_loc.appearance_map.disparity_channel_from_vectors`)
    with ``disparity_features`` features (default ``features``). ``translations`` m > 1 (odd):
    every survey view is also seen from the lattice of spacing ``step / m`` inside its cell by
    virtual translations with its own sparse disparity
    (:func:`lino_loc.virtual_translations.translate_survey`), the disparity channel by moving
    that sparse disparity itself. ``memory_budget_mb``: the disparity EM's memory budget
    (:func:`lino_loc.appearance_map.disparity_fit_rows`; None: the map builder's default).
    """
    import math

    from lino_loc.appearance_map import (
        AppearanceMap,
        disparity_channel_from_vectors,
        intensity_channel_from_vectors,
        virtual_setup,
    )
    from lino_loc.dataset import CameraInfo
    from lino_loc.virtual_translations import as_uint8, translate_survey
    from lino_loc.virtual_views import augment_poses, offsets

    w = load_world(world)
    cam = CameraModel(width=width, height=height)
    stereo = stereo or StereoConfig()
    depth_key = ""
    if disparity:
        blob = stereo.model_dump_json() + f"|{min_valid_fraction:g}"
        depth_key = f"-disparity-{hashlib.sha256(blob.encode()).hexdigest()[:10]}"
        if disparity_features is not None and disparity_features != features:
            depth_key += f"-d{disparity_features}f"
    key = (
        f"{w.name}-{lighting}-{step:g}m-{heading_step_deg:g}deg-{features}f-{{pre}}-{width}x{height}-"
        f"{size[0]}x{size[1]}-s{seed}"
        + (f"-v{virtual_headings}x{virtual_step_deg:g}" if virtual_headings > 1 else "")
        + depth_key + (f"-t{translations}" if translations > 1 else "")
        + (f"-b{memory_budget_mb:g}" if disparity and memory_budget_mb is not None else "")
        + f"-{w.fingerprint[:10]}-c{code_fingerprint()}.npz"
    )
    out: dict[str, AppearanceMap] = {}
    missing = []
    for pre in preprocesses:
        path = map_cache_dir() / key.format(pre=pre)
        if cache and path.is_file():
            try:
                out[pre] = AppearanceMap.load(path)
                continue
            except Exception:  # a stale or broken cache file: rebuild it
                pass
        missing.append(pre)
    if not missing:
        return out
    poses = grid_poses(w, step, math.radians(heading_step_deg))
    spec = ViewSpec(world=world, lighting=lighting, width=width, height=height, size=size,
                    preprocess=tuple(missing), disparity=disparity, stereo=stereo,
                    min_valid_fraction=min_valid_fraction, seed=seed)
    fx, fy, cx, cy = cam.intrinsics()
    if translations > 1:
        greys, disps = render_frames(replace(spec, disparity=True, preprocess=()), poses, workers=workers,
                                     progress=progress)

        def vectors_of(im: np.ndarray) -> np.ndarray:  # every preprocessing's vector, side by side
            return np.concatenate([to_vector(preprocess(as_uint8(im), pre), size) for pre in missing])

        # each view warped once, whatever the number of preprocessings
        moved = translate_survey(greys, disps, poses, (fx, fy, cx, cy), cam.baseline_m, step, translations,
                                 keep=lambda xy: w.is_mapped_free(xy[:, 0], xy[:, 1]),
                                 transform=vectors_of)
        poses = moved.poses
        vectors = dict(zip(missing, np.split(moved.images, len(missing), axis=1), strict=True))
        if disparity:  # the moved disparity maps are already at the working size
            vectors["disparity"] = moved.disparities.reshape(len(poses), -1)
    else:
        vectors = render_vectors(spec, poses, workers=workers, progress=progress)
    info = CameraInfo(width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy, baseline_m=cam.baseline_m)
    virtual = None if virtual_headings <= 1 else virtual_setup(
        info, size, offsets(math.radians(virtual_step_deg), virtual_headings))
    budget = {} if memory_budget_mb is None else {"memory_budget_mb": memory_budget_mb}
    depth = None if not disparity else disparity_channel_from_vectors(
        vectors["disparity"], size, disparity_features or features, min_valid_fraction=min_valid_fraction, seed=seed,
        virtual=virtual, **budget)
    for pre in missing:
        ch = intensity_channel_from_vectors(vectors[pre], pre, size, features,  # type: ignore[arg-type]
                                            virtual=virtual, seed=seed)
        map_poses = poses.copy() if virtual is None else augment_poses(poses, virtual.offsets)
        channels = {"intensity": ch} if depth is None else {"intensity": ch, "disparity": depth}
        amap = AppearanceMap(poses=map_poses, channels=channels, camera=info,
                             source=f"sim:{w.name}", name=f"{w.name}-{lighting}", condition=lighting)
        if cache:
            path = map_cache_dir() / key.format(pre=pre)
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                amap.save(path)
            except OSError:
                pass
        out[pre] = amap
    return {pre: out[pre] for pre in preprocesses}

"""Fig. 5 of the paper: the error of the sensor model along a path under three lights (eq. 10).

Setting (paper, section 6.2): an appearance map of the simulated lab, a survey every ``step``
(50 cm) and ``heading_step_deg`` (10 deg) under the mapping light ``tube``, ``features`` (20)
features per channel:

- **intensity**: the grey images, preprocessed as the product does by default (``none``, the
  preprocessing of the tracking evaluation and of the service's configuration), area-averaged
  to 80 x 60 and compressed by PCA (eq. 1): the cached survey maps of
  :func:`services.evaluation.views.build_sim_maps`;
- **disparity**: the SPARSE disparity that the product's block matcher
  (:func:`lino_loc.disparity.compute_disparity`, default :class:`StereoConfig`) gets from each
  rendered stereo pair, NaN-aware area-averaged to 80 x 60 (``min_valid_fraction``) and
  compressed by PCA with missing data fitted by EM (:func:`lino_loc.pca_missing.fit_pca_missing`,
  as :func:`lino_loc.appearance_map.build_disparity_channel` does). The renderer's exact depth
  is never used: the map is built from the same kind of sparse disparity the robot sees.

The test path (:func:`path_poses`) is a smooth closed loop (a superellipse) off the survey grid,
derived from the world's free space alone (:func:`drivers.sim.free_space.free_loop_box`: the
longest loop inside the mapped area that keeps a robot disc of 0.25 m plus a 0.1 m margin clear of
walls and furniture, its sides a quarter of ``step`` or more off the survey grid's lines, its lattice
seeded by ``seed``; in the lab it goes round the two benches), unless
``path_box`` gives the loop's box; test poses are taken every ``spacing`` metres of arc length with
the heading along the path, and rendered under ``tube``, ``bulb`` and ``natural`` light with
sensor noise seeded apart from the map's. At each test pose the sensor model's map points are

- (a) intensity only: the J = ``j`` (10) map entries nearest in intensity feature space;
- (b) intensity + disparity, disjunctive fusion (eq. 8): ``j_intensity`` (5) entries from the
  intensity channel and ``j_disparity`` (5) from the disparity channel; the points are the
  components of the fused :class:`lino_loc.sensor_model.PoseMixture` (``lino_loc.fusion.fuse``).

and the error is eq. 10, ``e = min_n |r - n|`` over those map points, as the POSITION
distance in metres (:func:`lino_loc.metrics.sensor_model_error`). Reported per light: mean
and standard deviation (population, ddof = 0) over the test poses. Extra keys: the (x, y,
theta) variant of eq. 10 (``sqrt(dx^2 + dy^2 + wrap(dtheta)^2)``, metres and radians mixed
as in the paper's ``r = (r_x, r_y, r_phi)``), the median, the disparity channel alone with
J = ``j``, the intensity channel alone with J = ``j_intensity``, the per-pose errors, the
weighted mean distance of the fused mixture (the lambda and w weights do not change eq. 10,
which only looks at which points are in the model), and the same figures for other intensity
preprocessings (``compare_preprocess``). ``grid_limit_m`` is the mean distance from the test
positions to the nearest surveyed position: no sensor model can do better on average.
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers.sim.code_fingerprint import code_fingerprint
from drivers.sim.free_space import free_loop_box, superellipse
from drivers.sim.renderer import CameraModel
from drivers.sim.world import World, grid_poses, load_world
from lino_loc.appearance_map import DISPARITY_EM_MAX_ITER, AppearanceMap, ChannelMap
from lino_loc.dataset import CameraInfo
from lino_loc.disparity import StereoConfig
from lino_loc.errors import LinoLocError
from lino_loc.fusion import FusionConfig, fuse
from lino_loc.metrics import sensor_model_error
from lino_loc.pca_missing import fit_pca_missing
from lino_loc.poses import wrap_angle
from lino_loc.preprocessing import PREPROCESS_METHODS
from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig
from services.evaluation.tracking import DEFAULT_PREPROCESS
from services.evaluation.views import ViewSpec, build_sim_maps, map_cache_dir, render_vectors

log = logging.getLogger(__name__)

ProgressFn = Callable[[str, int, int], None]

#: Sensor noise of the test views is seeded by (seed + TEST_SEED_OFFSET, view index), apart
#: from the survey's (seed, view index).
TEST_SEED_OFFSET = 1000

#: Clearance (m) the test loop keeps beyond the robot disc (:func:`default_path_box`).
PATH_MARGIN = 0.1


def default_path_box(
    world: World, seed: int = 0, exponent: float = 4.0, grid_step: float | None = 0.5
) -> tuple[float, float, float, float]:
    """The test loop's box (xmin, xmax, ymin, ymax) in ``world``: the longest free loop of its
    free space (:func:`drivers.sim.free_space.free_loop_box`, robot radius 0.25 m plus
    :data:`PATH_MARGIN`, lattice offset from ``seed``), its sides a quarter of ``grid_step``
    or more off the survey grid's lines (None: anywhere; also when no loop fits between the
    lines of a grid coarse for the free space, which is logged)."""
    try:
        return free_loop_box(world, seed=seed, radius=0.25, margin=PATH_MARGIN, exponent=exponent,
                             grid_step=grid_step)
    except LinoLocError:
        if grid_step is None:
            raise
    log.warning("test path: no free loop between the %g m survey grid's lines in world %r; "
                "the loop may run along them", grid_step, world.name)
    return free_loop_box(world, seed=seed, radius=0.25, margin=PATH_MARGIN, exponent=exponent)


@dataclass(frozen=True)
class SensorModelSetup:
    """Parameters of the Fig. 5 experiment (defaults: the paper's lab, section 6.2)."""

    world: str = "lab"
    step: float = 0.5
    heading_step_deg: float = 10.0
    features: int = 20
    preprocess: str = DEFAULT_PREPROCESS
    compare_preprocess: tuple[str, ...] = ("histeq", "gradient")
    lights: tuple[str, ...] = ("tube", "bulb", "natural")
    j: int = 10
    j_intensity: int = 5
    j_disparity: int = 5
    w_i: float = 0.5
    w_d: float = 0.5
    spacing: float = 0.3
    path_box: tuple[float, float, float, float] | None = None  # None: derived from the free space
    path_exponent: float = 4.0
    width: int = 320
    height: int = 240
    size: tuple[int, int] = (80, 60)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    min_valid_fraction: float = 0.25
    seed: int = 0
    workers: int | None = None
    cache: bool = True


# --------------------------------------------------------------------------- the test path
def path_poses(
    world: World,
    spacing: float,
    box: tuple[float, float, float, float] | None = None,
    exponent: float = 4.0,
    radius: float = 0.25,
    samples: int = 20000,
    avoid: np.ndarray | None = None,
) -> np.ndarray:
    """Test poses every ``spacing`` m of arc length along a closed smooth loop, heading along it.

    The loop is the superellipse ``|x - cx|^p / a^p + |y - cy|^p / b^p = 1`` (p = ``exponent``)
    inscribed in ``box`` = (xmin, xmax, ymin, ymax) (default: :func:`default_path_box` with
    seed 0), driven counter-clockwise. Raises
    :class:`LinoLocError` when a test position is not free for a robot disc of ``radius``.
    ``avoid`` (K, 2+): positions the test poses should keep away from (the survey grid): the
    phase of the samples along the loop (one of 16 offsets in [0, spacing)) is the one that
    maximizes the smallest distance to them, so that no test pose sits on a map pose.
    Returns (M, 3) float64 poses (x, y, theta).
    """
    if spacing <= 0:
        raise LinoLocError(f"path spacing must be positive, got {spacing}")
    if box is None:
        box = default_path_box(world, 0, exponent)
    xmin, xmax, ymin, ymax = (float(v) for v in box)
    if xmax <= xmin or ymax <= ymin:
        raise LinoLocError(f"test path box {box} is empty")
    x, y = superellipse((xmin, xmax, ymin, ymax), exponent, samples)
    seg = np.hypot(np.diff(x), np.diff(y))
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    length = float(arc[-1])
    m = max(int(math.floor(length / spacing)), 1)
    offsets = [0.25 * spacing]
    if avoid is not None and len(avoid):
        offsets = list(np.arange(16) * spacing / 16.0)
        av = np.unique(np.round(np.asarray(avoid, dtype=np.float64)[:, :2], 6), axis=0)

        def clearance(off: float) -> float:
            tx = np.interp(off + np.arange(m) * spacing, arc, x)
            ty = np.interp(off + np.arange(m) * spacing, arc, y)
            return float(np.min(np.hypot(tx[:, None] - av[None, :, 0], ty[:, None] - av[None, :, 1])))

        offsets = [max(offsets, key=clearance)]
    targets = offsets[0] + np.arange(m) * spacing
    px = np.interp(targets, arc, x)
    py = np.interp(targets, arc, y)
    # heading along the path: the direction of the curve around each sample
    h = 0.5 * spacing * 0.1
    dx = np.interp((targets + h) % length, arc, x) - np.interp((targets - h) % length, arc, x)
    dy = np.interp((targets + h) % length, arc, y) - np.interp((targets - h) % length, arc, y)
    theta = np.arctan2(dy, dx)
    free = world.is_free(px, py, radius)
    if not np.all(free):
        k = int(np.flatnonzero(~free)[0])
        raise LinoLocError(
            f"test path: position ({px[k]:.2f}, {py[k]:.2f}) is not free in world {world.name!r} "
            f"(change the path box)"
        )
    return np.column_stack([px, py, theta])


# --------------------------------------------------------------------------- eq. 10
def errors_eq10(truths: np.ndarray, neighbour_poses: np.ndarray) -> np.ndarray:
    """Eq. 10 for each test pose: truths (M, 3), map points (M, K, 3) -> (M,) metres (position)."""
    t = np.asarray(truths, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(neighbour_poses, dtype=np.float64).reshape(t.shape[0], -1, 3)
    return np.array([sensor_model_error(t[i], n[i]) for i in range(t.shape[0])])


def errors_eq10_pose(truths: np.ndarray, neighbour_poses: np.ndarray) -> np.ndarray:
    """Eq. 10 with r and n as full poses: min_n sqrt(dx^2 + dy^2 + wrap(dtheta)^2) -> (M,)."""
    t = np.asarray(truths, dtype=np.float64).reshape(-1, 1, 3)
    n = np.asarray(neighbour_poses, dtype=np.float64).reshape(t.shape[0], -1, 3)
    d = n - t
    d[..., 2] = wrap_angle(d[..., 2])
    return np.sqrt((d * d).sum(-1)).min(axis=1)


def summary(errors: np.ndarray) -> dict[str, float | None]:
    """Mean, population standard deviation and median of per-pose errors, metres (None
    without any pose)."""
    e = np.asarray(errors, dtype=np.float64)
    if e.size == 0:
        return {"mean_m": None, "std_m": None, "median_m": None}
    return {"mean_m": float(e.mean()), "std_m": float(e.std()), "median_m": float(np.median(e))}


def grid_limit(truths: np.ndarray, map_poses: np.ndarray) -> np.ndarray:
    """Distance from each test position to the nearest surveyed position (M,), metres."""
    pos = np.unique(np.round(np.asarray(map_poses)[:, :2], 6), axis=0)
    t = np.asarray(truths)[:, None, :2]
    return np.sqrt(((t - pos[None]) ** 2).sum(-1)).min(axis=1)


# --------------------------------------------------------------------------- the map
def _stereo_key(setup: SensorModelSetup) -> str:
    blob = setup.stereo.model_dump_json() + f"|{setup.min_valid_fraction:g}"
    return hashlib.sha256(blob.encode()).hexdigest()[:10]


def _survey_key(setup: SensorModelSetup, world: World, what: str) -> str:
    w, h = int(setup.size[0]), int(setup.size[1])
    return (
        f"{world.name}-tube-{setup.step:g}m-{setup.heading_step_deg:g}deg-{what}-"
        f"{_stereo_key(setup)}-{setup.width}x{setup.height}-{w}x{h}-s{setup.seed}-{world.fingerprint[:10]}"
        f"-c{code_fingerprint()}.npz"
    )


def survey_disparity_vectors(
    setup: SensorModelSetup, world: World, poses: np.ndarray, progress: ProgressFn | None = None
) -> np.ndarray:
    """(N, w*h) float32 sparse disparity (NaN = no value) of the survey's stereo pairs under
    ``tube``: StereoBM on each rendered pair, NaN-aware area-average to ``setup.size``.
    Cached (compressed) under ``map_cache_dir()/../vectors`` when ``setup.cache``."""
    path = map_cache_dir().parent / "vectors" / _survey_key(setup, world, "disparity")
    if setup.cache and path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                if z["poses"].shape == poses.shape and np.allclose(z["poses"], poses):
                    return np.asarray(z["disparity"], dtype=np.float32)
        except (OSError, ValueError, KeyError):
            pass
    spec = ViewSpec(world=setup.world, lighting="tube", width=setup.width, height=setup.height,
                    size=(int(setup.size[0]), int(setup.size[1])), preprocess=(), disparity=True,
                    stereo=setup.stereo, min_valid_fraction=setup.min_valid_fraction, seed=setup.seed)
    X = render_vectors(spec, poses, workers=setup.workers,
                       progress=(lambda d, n: progress("map disparity", d, n)) if progress else None)["disparity"]
    if setup.cache:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp.npz")
            np.savez_compressed(tmp, poses=poses, disparity=X)
            tmp.replace(path)
        except OSError:
            pass
    return X


def disparity_map(
    setup: SensorModelSetup, world: World, poses: np.ndarray, progress: ProgressFn | None = None
) -> AppearanceMap:
    """The map's disparity channel: sparse StereoBM disparity of the survey's rendered stereo
    pairs under ``tube`` (:func:`survey_disparity_vectors`), EM-PCA with missing data (cached
    as a map file with that one channel)."""
    w, h = int(setup.size[0]), int(setup.size[1])
    path = map_cache_dir() / _survey_key(setup, world, f"{setup.features}f-disparity")
    if setup.cache and path.is_file():
        try:
            amap = AppearanceMap.load(path)
            if amap.poses.shape == poses.shape and np.allclose(amap.poses, poses):
                return amap
        except LinoLocError:
            pass
    X = survey_disparity_vectors(setup, world, poses, progress)
    model = fit_pca_missing(X, setup.features, seed=setup.seed, max_iter=DISPARITY_EM_MAX_ITER, dtype=np.float32)
    Y = np.asarray(model.project(X), dtype=np.float32)
    ch = ChannelMap(name="disparity", preprocess="none", size=(w, h), pca=model, features=Y,
                    method="em-missing",
                    params={"min_valid_fraction": float(setup.min_valid_fraction), "units": "disparity_px",
                            "seed": setup.seed, "valid_fraction": float(np.isfinite(X).mean())})
    cam = CameraModel(width=setup.width, height=setup.height)
    fx, fy, cx, cy = cam.intrinsics()
    info = CameraInfo(width=setup.width, height=setup.height, fx=fx, fy=fy, cx=cx, cy=cy,
                      baseline_m=cam.baseline_m)
    amap = AppearanceMap(poses=poses.copy(), channels={"disparity": ch}, camera=info,
                         source=f"sim:{world.name}", name=f"{world.name}-tube-disparity", condition="tube")
    if setup.cache:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            amap.save(path)
        except OSError:
            pass
    return amap


# --------------------------------------------------------------------------- one condition
def fused_points(
    model_i: NearestNeighbourSensorModel,
    model_d: NearestNeighbourSensorModel,
    y_i: np.ndarray,
    y_d: np.ndarray,
    fusion: FusionConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """The map points of the disjunctive model (eq. 8) for each test pose.

    y_i (M, d_i), y_d (M, d_d) -> (poses (M, j_i + j_d, 3), the fused mixture's normalized
    component weights (M, j_i + j_d)). The points are the
    components of ``fuse({"intensity": ..., "disparity": ...}, fusion)``: the
    ``j_intensity`` nearest entries in intensity space and the ``j_disparity`` nearest in
    disparity space (a map entry may appear twice: once per channel).
    """
    pts, wts = [], []
    for yi, yd in zip(y_i, y_d, strict=True):
        m_i = model_i.observe(yi, fusion.j_intensity)
        m_d = model_d.observe(yd, fusion.j_disparity)
        f = fuse({"intensity": m_i, "disparity": m_d}, fusion)
        pts.append(f.poses)
        w = np.exp(f.log_weights)
        wts.append(w / w.sum())
    return np.stack(pts), np.stack(wts)


def _block(errors: np.ndarray, pose_errors: np.ndarray | None = None, **extra: Any) -> dict[str, Any]:
    out: dict[str, Any] = summary(errors)
    if pose_errors is not None:
        pe = np.asarray(pose_errors, dtype=np.float64)
        out["mean_xyt"] = float(pe.mean()) if pe.size else None
        out["std_xyt"] = float(pe.std()) if pe.size else None
    out.update(extra)
    out["errors_m"] = [round(float(v), 4) for v in errors]
    return out


def evaluate_condition(
    truths: np.ndarray,
    map_poses: np.ndarray,
    feats_i: np.ndarray,
    map_feats_i: np.ndarray,
    feats_d: np.ndarray,
    map_feats_d: np.ndarray,
    setup: SensorModelSetup,
    map_rows_d: np.ndarray | None = None,
    observed_d: np.ndarray | None = None,
) -> dict[str, Any]:
    """Eq. 10 along the path for one light: intensity J = j, fused j_i + j_d, and extras.

    As in the Localizer: ``map_rows_d`` (N,) bool, the map entries the disparity channel
    observed (``ChannelMap.observed_rows``), are the only ones its model searches, and a test
    view whose disparity map has no valid block (``observed_d`` (M,) False) is not observed
    by that channel: its fused model is the intensity one (J = j), and the disparity blocks
    leave it out (``views``). None: all."""
    truths = np.asarray(truths, dtype=np.float64)
    cfg = SensorModelConfig(j=setup.j)
    model_i = NearestNeighbourSensorModel(map_poses, map_feats_i, cfg)
    keep = np.ones(len(map_poses), dtype=bool) if map_rows_d is None else np.asarray(map_rows_d, dtype=bool)
    poses_d = map_poses[keep]
    model_d = NearestNeighbourSensorModel(poses_d, map_feats_d[keep], cfg, bounds=model_i.bounds)
    fusion = FusionConfig(mode="disjunctive", w_i=setup.w_i, w_d=setup.w_d,
                          j_intensity=setup.j_intensity, j_disparity=setup.j_disparity)
    obs = np.ones(len(truths), dtype=bool) if observed_d is None else np.asarray(observed_d, dtype=bool)
    t_o = truths[obs]
    idx_i, _ = model_i.neighbours(feats_i, setup.j)
    pts_i = map_poses[idx_i]
    e_i, ep_i = errors_eq10(truths, pts_i), errors_eq10_pose(truths, pts_i)
    idx_d, _ = model_d.neighbours(feats_d[obs], setup.j) if obs.any() else (np.zeros((0, setup.j), int), None)
    pts_d = poses_d[idx_d]
    pts_f, w_f = fused_points(model_i, model_d, feats_i[obs], feats_d[obs], fusion) if obs.any() else (
        np.zeros((0, setup.j_intensity + setup.j_disparity, 3)), np.zeros((0, setup.j_intensity + setup.j_disparity)))

    def eq10(t: np.ndarray, pts: np.ndarray, pose: bool = False) -> np.ndarray:
        if not len(t):
            return np.zeros(0)
        return errors_eq10_pose(t, pts) if pose else errors_eq10(t, pts)

    e_f, ep_f = e_i.copy(), ep_i.copy()  # a view the disparity channel did not observe: intensity alone
    e_f[obs], ep_f[obs] = eq10(t_o, pts_f), eq10(t_o, pts_f, pose=True)
    dist_f = np.sqrt(((pts_f[..., :2] - t_o[:, None, :2]) ** 2).sum(-1))
    # which channel gave the fused model's nearest point (ties: intensity)
    e_fi = eq10(t_o, pts_f[:, : setup.j_intensity])
    e_fd = eq10(t_o, pts_f[:, setup.j_intensity :])
    views = int(obs.sum())
    return {
        "intensity": _block(e_i, ep_i, J=setup.j),
        "fused": _block(
            e_f,
            ep_f,
            J=[setup.j_intensity, setup.j_disparity],
            weighted_mean_distance_m=float(np.mean((w_f * dist_f).sum(1))) if views else None,
            nearest_from_disparity=float(np.mean(e_fd < e_fi)) if views else None,
            views_without_disparity=int((~obs).sum()),
        ),
        "disparity": _block(eq10(t_o, pts_d), eq10(t_o, pts_d, pose=True), J=setup.j, views=views),
        "intensity_j_split": _block(e_fi, None, J=setup.j_intensity, views=views),
        "disparity_j_split": _block(e_fd, None, J=setup.j_disparity, views=views),
    }


# --------------------------------------------------------------------------- the experiment
def run(setup: SensorModelSetup, progress: ProgressFn | None = None) -> dict[str, Any]:
    """Fig. 5 (see module docstring). Returns the JSON-ready result."""
    if setup.preprocess not in PREPROCESS_METHODS:
        raise LinoLocError(f"preprocess: unknown {setup.preprocess!r} (choose from {', '.join(PREPROCESS_METHODS)})")
    for p in setup.compare_preprocess:
        if p not in PREPROCESS_METHODS:
            raise LinoLocError(f"compare preprocess: unknown {p!r} (choose from {', '.join(PREPROCESS_METHODS)})")
    if setup.j < 1 or setup.j_intensity < 1 or setup.j_disparity < 1:
        raise LinoLocError(f"J must be at least 1 (got j={setup.j}, split {setup.j_intensity} + {setup.j_disparity})")
    world = load_world(setup.world)
    for light in setup.lights:
        world.check_lighting(light)
    pres = tuple(dict.fromkeys((setup.preprocess, *setup.compare_preprocess)))
    poses = grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    if len(poses) <= setup.features:
        raise LinoLocError(f"{len(poses)} survey poses are too few for {setup.features} features")
    if max(setup.j, setup.j_intensity, setup.j_disparity) > len(poses):
        raise LinoLocError(f"J = {setup.j} is larger than the map ({len(poses)} entries)")
    log.info("sensor model: map of %d poses, preprocess %s", len(poses), ", ".join(pres))
    maps = build_sim_maps(setup.world, setup.step, setup.heading_step_deg, setup.features, pres,
                          lighting="tube", width=setup.width, height=setup.height, size=setup.size,
                          seed=setup.seed, workers=setup.workers, cache=setup.cache,
                          progress=(lambda d, n: progress("map intensity", d, n)) if progress else None)
    dmap = disparity_map(setup, world, poses, progress)
    dch = dmap.channels["disparity"]
    for pre, amap in maps.items():
        if amap.poses.shape != poses.shape or not np.allclose(amap.poses, poses):
            raise LinoLocError(f"intensity map ({pre}) and disparity map have different poses")
    box = setup.path_box or default_path_box(world, setup.seed, setup.path_exponent, setup.step)
    truths = path_poses(world, setup.spacing, box, setup.path_exponent, avoid=poses)
    log.info("sensor model: %d test poses along the path", len(truths))
    lim = grid_limit(truths, poses)

    conditions: dict[str, Any] = {}
    by_pre: dict[str, dict[str, Any]] = {p: {} for p in pres}
    density: dict[str, float] = {}
    for light in setup.lights:
        spec = ViewSpec(world=setup.world, lighting=light, width=setup.width, height=setup.height,
                        size=setup.size, preprocess=pres, disparity=True, stereo=setup.stereo,
                        min_valid_fraction=setup.min_valid_fraction, seed=setup.seed + TEST_SEED_OFFSET)
        vec = render_vectors(spec, truths, workers=setup.workers,
                             progress=(lambda d, n, light=light: progress(f"path {light}", d, n)) if progress else None)
        Xd = vec["disparity"]
        density[light] = float(np.isfinite(Xd).mean())
        yd, has = dch.pca.project(Xd, return_valid=True)
        if not np.all(has):
            log.warning("%s: %d test disparity maps without any valid block", light, int((~has).sum()))
        for pre in pres:
            ch = maps[pre].channels["intensity"]
            yi = ch.pca.project(vec[pre])
            res = evaluate_condition(truths, poses, np.asarray(yi, dtype=np.float64),
                                     np.asarray(ch.features, dtype=np.float64), np.asarray(yd, dtype=np.float64),
                                     np.asarray(dch.features, dtype=np.float64), setup,
                                     map_rows_d=dch.observed_rows(), observed_d=has)
            by_pre[pre][light] = res
        conditions[light] = by_pre[setup.preprocess][light]

    def brief(r: dict[str, Any]) -> dict[str, Any]:
        return {k: {kk: vv for kk, vv in v.items() if kk in ("mean_m", "std_m")} for k, v in r.items()
                if k in ("intensity", "fused", "disparity")}

    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(truths[:, :2], axis=0).T))])
    return {
        "experiment": "fig5_sensor_model_error",
        "world": setup.world,
        "map": {
            "light": "tube",
            "poses": int(len(poses)),
            "step_m": setup.step,
            "heading_step_deg": setup.heading_step_deg,
            "image": [setup.width, setup.height],
            "size": [int(setup.size[0]), int(setup.size[1])],
            "preprocess": setup.preprocess,
            "disparity_valid_fraction": float(dch.params.get("valid_fraction", float("nan"))),
            "em_iterations": int(dch.pca.n_iter),
            "em_converged": bool(dch.pca.converged),
            "stereo": setup.stereo.model_dump(),
            "min_valid_fraction": setup.min_valid_fraction,
        },
        "features": setup.features,
        "J": {"intensity": setup.j, "fused": [setup.j_intensity, setup.j_disparity]},
        "fusion": {"mode": "disjunctive", "w_i": setup.w_i, "w_d": setup.w_d},
        "positions": int(len(truths)),
        "path": {
            "spacing_m": setup.spacing,
            "box": [round(float(v), 4) for v in box],
            "box_from": "given" if setup.path_box else "free space",
            "length_m": float(arc[-1]),
            "arc_m": [round(float(v), 4) for v in arc],
            "poses": [[round(float(v), 5) for v in p] for p in truths],
        },
        "grid_limit_m": summary(lim),
        "disparity_density": density,
        "conditions": conditions,
        "by_preprocess": {p: {light: brief(r) for light, r in by.items()} for p, by in by_pre.items()},
        "seed": setup.seed,
    }


# --------------------------------------------------------------------------- the figure
def plot(result: dict[str, Any], out_dir: str | Path) -> list[Path]:
    """Fig. 5 as a PNG in ``out_dir``: eq. 10 along the path per light (intensity dashed,
    fused dotted) and the mean +- std per light. Returns the files written."""
    from services.evaluation.plotting import pyplot

    plt = pyplot()

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lights = list(result["conditions"])
    arc = np.asarray(result["path"]["arc_m"])
    fig, axes = plt.subplots(len(lights) + 1, 1, figsize=(8, 2.2 * (len(lights) + 1)), constrained_layout=True)
    axes = np.atleast_1d(axes)
    for ax, light in zip(axes[:-1], lights, strict=True):
        r = result["conditions"][light]
        ax.plot(arc, r["intensity"]["errors_m"], "k--", lw=1,
                label=f"intensity J={result['J']['intensity']} (mean {r['intensity']['mean_m']:.2f} m)")
        ax.plot(arc, r["fused"]["errors_m"], "k:", lw=1.5,
                label="intensity + disparity J={}+{} (mean {:.2f} m)".format(*result["J"]["fused"],
                                                                              r["fused"]["mean_m"]))
        ax.set_title(f"{light} light")
        ax.set_ylabel("e (m)")
        ax.legend(fontsize=7, loc="upper right")
    axes[-2].set_xlabel("distance along the path (m)")
    ax = axes[-1]
    xs = np.arange(len(lights))
    for off, key, style, name in ((-0.05, "intensity", "k--", "intensity"), (0.05, "fused", "k:", "fused")):
        m = [result["conditions"][lt][key]["mean_m"] for lt in lights]
        s = [result["conditions"][lt][key]["std_m"] for lt in lights]
        ax.errorbar(xs + off, m, yerr=s, fmt=style, marker="o", capsize=3, label=name)
    ax.set_xticks(xs, lights)
    ax.set_ylabel("mean e +- std (m)")
    ax.legend(fontsize=7)
    fig.suptitle(f"Fig. 5: sensor-model error (eq. 10), {result['world']}, {result['positions']} test poses")
    path = out / "fig5_sensor_model.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]

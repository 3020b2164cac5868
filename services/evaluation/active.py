"""Active localization (paper, section 6.1, Fig. 3 and 4) in the simulated office.

The experiment: an appearance map of the office (camera poses every ``step`` metres and
``heading_step_deg`` degrees over the mapped area, ``features`` PCA features of the plain
grey images under the mapping light), a particle filter of ``particles`` particles started
from a uniform belief over the free space, the robot standing still at test positions that
are NOT on the map grid (random free positions, at least ``min_grid_distance`` from every
grid position, random headings). The first image is taken at a random candidate pan (the
same for every strategy); then the camera is moved ``movements`` times to one of
``n_actions`` pan angles over [pan_min, pan_max], chosen by

* ``entropy``: argmin H(u) of :mod:`lino_loc.active_vision` over the pans other than the
  present one (the head-movement cost breaks ties);
* ``random``: uniform over the pans other than the present one;
* ``sweep``: a fixed sweep, the pan index advancing by ``sweep_stride`` (mod n_actions) each
  time (stride 7 of 22 = 99 degrees: consecutive views overlap little and 22 movements would
  visit every pan).

After each movement the filter updates with the image at the new pan (odometry increment
zero, the pan known). After 0..movements movements the position error of the estimate and the
success of section 6.1 are recorded: ``success`` (:func:`lino_loc.metrics.success`, the
paper's words: the map position nearest to the estimated position is the one nearest to the
true position) and, beside it, the stricter ``success_pose``
(:func:`lino_loc.metrics.success_pose`: the same (x, y, theta) map cell, 75 cm / 15 deg).
Every run (position x run) starts from the same particles and first pan for all three
strategies (seeded by (seed, position, run)), so the strategies' differences are paired.

Every success ratio carries its 95 % interval and every difference entropy - other strategy
its standard error, from the two-stage bootstrap over positions then runs of
:mod:`services.evaluation.active_stats`.

Views are rendered once per test position for all candidate pans (the process pool of
:mod:`services.evaluation.views`) and reused across runs and strategies. With scene changes
(objects the map does not know) the test views are rendered again with the changes applied
and the whole experiment repeated on them; the map stays the same.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.sim.world import World, grid_poses, load_world
from lino_loc.active_vision import ActionEvaluator, ActionValues, action_evaluator, belief_entropy
from lino_loc.appearance_map import channel_margin
from lino_loc.errors import LinoLocError
from lino_loc.fusion import fuse
from lino_loc.interpolated_appearance import InterpolatedSensorModel, fuse_likelihoods
from lino_loc.metrics import nearest_map_index, position_errors, success, success_pose
from lino_loc.motion_model import OdometryMotionModel
from lino_loc.pan_reliability import PanReliability
from lino_loc.particle_filter import AuxiliaryParticleFilter
from lino_loc.poses import wrap_angle
from lino_loc.standing_match import StandingMatch, gathered
from lino_loc.view_match import ViewLattice
from lino_loc.virtual_views import crop_columns
from services.evaluation import active_stats
from services.evaluation.active_bounds import feature_diagnostics, ideal_hits, map_oracle_hits
from services.evaluation.active_setup import ActiveSetup
from services.evaluation.decision_rules import MapTable, decide
from services.evaluation.views import ViewSpec, build_sim_maps, render_vectors

log = logging.getLogger(__name__)

ProgressFn = Callable[[str, int, int], None]


# --------------------------------------------------------------------------- data


def place_test_positions(world: World, setup: ActiveSetup, grid: np.ndarray) -> np.ndarray:
    """``setup.positions`` random robot poses (P, 3): free (also with the scene changes),
    inside the mapped area, at least ``min_grid_distance`` from every grid position."""
    rng = np.random.default_rng((setup.seed, 7))
    xmin, xmax, ymin, ymax = world.mapped_area
    grid_xy = np.unique(np.round(grid[:, :2], 6), axis=0)
    out: list[np.ndarray] = []
    for _ in range(10000):
        c = np.column_stack(
            [rng.uniform(xmin, xmax, 64), rng.uniform(ymin, ymax, 64), rng.uniform(-np.pi, np.pi, 64)]
        )
        ok = world.is_free(c[:, 0], c[:, 1]) & world.is_free(
            c[:, 0], c[:, 1], scene_changes=setup.scene_changes
        )
        d = np.min(np.hypot(c[:, None, 0] - grid_xy[None, :, 0], c[:, None, 1] - grid_xy[None, :, 1]), axis=1)
        ok &= d >= setup.min_grid_distance
        out.extend(c[ok])
        if len(out) >= setup.positions:
            return np.asarray(out[: setup.positions])
    raise LinoLocError(f"active: could not place {setup.positions} test positions in world '{world.name}' "
                       f"(free, {setup.min_grid_distance} m or more from the grid)")


def build_map(setup: ActiveSetup, progress: ProgressFn | None = None) -> Any:
    """The survey map (an :class:`lino_loc.appearance_map.AppearanceMap`) as the simulated
    service builds it (:func:`services.evaluation.views.build_sim_maps`: PCA, eq. 1, of the
    grid views and their virtual headings and translations; the disparity channel with
    ``disparity`` in ``setup.channels``)."""
    return build_sim_maps(setup.world, setup.step, setup.heading_step_deg, setup.features, (setup.preprocess,),
                          lighting=setup.lighting, width=setup.width, height=setup.height, size=setup.size,
                          seed=setup.seed, workers=setup.workers,
                          progress=(lambda d, n: progress("map", d, n)) if progress else None,
                          virtual_headings=setup.virtual_headings, virtual_step_deg=setup.virtual_step_deg,
                          disparity="disparity" in setup.channels,
                          disparity_features=setup.disparity_features,
                          translations=setup.translations,
                          memory_budget_mb=setup.map_memory_budget_mb,
                          )[setup.preprocess]


def render_map(
    setup: ActiveSetup, progress: ProgressFn | None
) -> tuple[Any, np.ndarray, np.ndarray, int, tuple[Any, np.ndarray] | None]:
    """The survey map (:func:`build_map`): its PCA, the map features (N, d), the poses (N, 3)
    of the map entries, the columns cropped each side of a view, and with ``disparity`` in
    ``setup.channels`` the disparity channel's (PCA, features), else None."""
    amap = build_map(setup, progress)
    ch = amap.channels["intensity"]
    dch = amap.channels.get("disparity")
    disp = None if dch is None else (dch.pca, np.asarray(dch.features, dtype=np.float64))
    return ch.pca, np.asarray(ch.features, dtype=np.float64), np.asarray(amap.poses), channel_margin(ch), disp


def render_tests(
    setup: ActiveSetup, pca: Any, margin: int, truths: np.ndarray, pans: np.ndarray, changes: tuple[str, ...],
    progress: ProgressFn | None, disparity_pca: Any = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Features (P, A, d) of the view at every test position and candidate pan, and with
    ``disparity_pca`` those of its sparse disparity (the product's matcher), else None."""
    cams = np.repeat(truths[:, None, :], pans.size, axis=1)
    cams[:, :, 2] = cams[:, :, 2] + pans[None, :]
    spec = ViewSpec(world=setup.world, lighting=setup.lighting, scene_changes=changes, width=setup.width,
                    height=setup.height, size=setup.size, preprocess=(setup.preprocess,),
                    seed=setup.seed + 1000 + 17 * len(changes), disparity=disparity_pca is not None)
    label = "tests" + ("+" + "+".join(changes) if changes else "")
    V = render_vectors(spec, cams.reshape(-1, 3), workers=setup.workers,
                       progress=(lambda d, n: progress(label, d, n)) if progress else None)
    shape = (truths.shape[0], pans.size, -1)
    feats = np.asarray(pca.project(crop_columns(V[setup.preprocess], setup.size, margin)), dtype=np.float64)
    if disparity_pca is None:
        return feats.reshape(shape), None
    D = np.asarray(disparity_pca.project(crop_columns(V["disparity"], setup.size, margin)), dtype=np.float64)
    return feats.reshape(shape), D.reshape(shape)


# --------------------------------------------------------------------------- runs

_ctx: dict[str, Any] = {}


def init_worker(setup: ActiveSetup, entries: np.ndarray, map_features: np.ndarray, map_poses: np.ndarray,
                 disparity_features: np.ndarray | None = None) -> None:
    """``entries``: poses of the sensor model's map entries; ``map_poses``: the survey grid
    (the success criteria's training points); ``disparity_features``: the disparity channel's
    map features (the filter then fuses both channels by eq. 8; the action evaluation predicts
    views with the intensity channel alone)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    world = load_world(setup.world)
    model = setup.sensor_model_for(entries, map_features)
    model_d = None if disparity_features is None else setup.sensor_model_for(entries, disparity_features, model.bounds)
    _ctx.update(setup=setup, world=world, model=model, model_d=model_d,
                evaluator=action_evaluator(model, setup.active), map_poses=map_poses,
                map_table=MapTable(entries, map_features) if "map_match" in setup.decisions else None,
                lattice=ViewLattice(entries, map_features, setup.view_match) if "lattice" in setup.strategies else None,
                standing=_standing_match(setup, entries, map_features))


def _standing_match(setup: ActiveSetup, entries: np.ndarray, map_features: np.ndarray) -> StandingMatch | None:
    """The standing match the runs copy (None when off); the evaluation's maps are lattices."""
    if not setup.standing_match.enabled:
        return None
    match = StandingMatch.for_map(entries, map_features, setup.standing_match)
    if isinstance(match, str):
        raise LinoLocError(f"--standing-match on: {match}")
    return match


def _observe(fi: np.ndarray, fd: np.ndarray | None) -> tuple[Any, float]:
    """The sensor-model mixture of a view (intensity alone, or fused with its disparity) and
    the novelty of its intensity channel (``PoseMixture.novelty``)."""
    model = _ctx["model"]
    model_d = _ctx["model_d"]
    if model_d is None or fd is None or not np.all(np.isfinite(fd)):
        mix = model.observe(fi)
        return mix, float(mix.novelty)
    fc = _ctx["setup"].fusion
    obs = {"intensity": model.observe(fi, fc.j_intensity), "disparity": model_d.observe(fd, fc.j_disparity)}
    fused = fuse_likelihoods(obs, fc) if isinstance(model, InterpolatedSensorModel) else fuse(obs, fc)
    return fused, float(obs["intensity"].novelty)


def roughen(pf: AuxiliaryParticleFilter, setup: ActiveSetup, mixture: Any = None, pan: float = 0.0) -> None:
    """Investigation options, off by default (the paper's filter as the service runs it):
    ``inject``: after an update, resample and replace that fraction of the particles by draws
    from the image's sensor-model mixture (as the filter's AMCL-style recovery does, but at
    every update); ``roughen_xy``/``roughen_theta``: Gaussian jitter of every particle
    (roughening, Gordon, Salmond, Smith 1993). The robot stands still, so the odometry
    increment is zero and the action model adds no diversity."""
    if setup.inject > 0.0 and mixture is not None:
        n = pf.particles.shape[0]
        m = int(round(setup.inject * n))
        idx = pf.rng.choice(n, size=n, p=pf.weights)
        parts = pf.particles[idx]
        parts[pf.rng.choice(n, size=m, replace=False)] = pf.sample_from_mixture(mixture, pan, m)
        pf.set_particles(parts)
    if setup.roughen_xy <= 0.0 and setup.roughen_theta <= 0.0:
        return
    n = pf.particles.shape[0]
    jitter = pf.rng.standard_normal((n, 3)) * (setup.roughen_xy, setup.roughen_xy, setup.roughen_theta)
    pf.set_particles(pf.particles + jitter, pf.log_weights)


def _estimate(pf: AuxiliaryParticleFilter, ests: list[np.ndarray], views: list[tuple[float, Any, np.ndarray]],
              decided: dict[str, list[np.ndarray]]) -> None:
    """Append the filter's estimate to ``ests`` and each decision rule's to ``decided``
    (:mod:`services.evaluation.decision_rules`, from the ``views`` taken so far)."""
    ests.append(pf.estimate().pose)
    for rule, poses in decided.items():
        poses.append(decide(rule, ests[-1], views, _ctx["map_table"]))


def _lattice_values(pf: AuxiliaryParticleFilter, views: list[tuple[float, Any, np.ndarray]],
                    pans: np.ndarray) -> np.ndarray | None:
    """The ``lattice`` strategy's H(u) over the map-lattice hypotheses near the filter's
    estimate (:meth:`lino_loc.view_match.ViewLattice.expected_entropy`), or None while less
    than ``setup.lattice_gate`` of the particles' weight lies within the hypotheses' radius."""
    lattice: ViewLattice = _ctx["lattice"]
    est = pf.estimate().pose
    if gathered(pf.particles, pf.weights, est, lattice.config.radius, _ctx["setup"].lattice_gate) is None:
        return None
    taken = np.array([v[0] for v in views])
    return lattice.expected_entropy(est, taken, np.stack([v[2] for v in views]), pans)


def _values(pf: AuxiliaryParticleFilter, ev: ActionEvaluator, standing: StandingMatch | None,
            pans: np.ndarray, eval_ms: list[float]) -> ActionValues:
    """The entropy strategy's action values, as the service's policy gets them: the standing
    match's (the pan farthest from its views, ``StandingMatchConfig.choose_views``) once the
    belief is gathered, else the filter's H(u), whose CPU time (ms) is appended to ``eval_ms``."""
    values = None if standing is None else standing.action_values(pf.particles, pf.weights, pf.estimate().pose, pans)
    if values is None:
        t0 = time.process_time()
        values = ev.evaluate(pf.particles, pf.log_weights)
        eval_ms.append(1e3 * (time.process_time() - t0))
    return values


def new_filter(pos: int, run: int, seed: int | None = None) -> AuxiliaryParticleFilter:
    """The filter of run ``run`` at test position ``pos``: a uniform belief drawn from the seed
    (``setup.seed``, pos, run), the same for every strategy (``seed``: another draw)."""
    setup: ActiveSetup = _ctx["setup"]
    world: World = _ctx["world"]
    return AuxiliaryParticleFilter(OdometryMotionModel(setup.motion_config()), _ctx["model"].bounds,
                                   setup.filter_config(), free_space=lambda xy: world.is_free(xy[:, 0], xy[:, 1]),
                                   rng=np.random.default_rng((setup.seed, pos, run) if seed is None
                                                             else (setup.seed, pos, run, seed)))


@dataclass
class Look:
    """One run's standing robot: its filter, the standing match's views, the per-pan
    reliability (a no-op when off) and the views taken (pan, mixture, features) for the
    decision rules. :meth:`take` is one view at a candidate pan, as the service takes it."""

    pf: AuxiliaryParticleFilter
    standing: StandingMatch | None
    reliability: PanReliability
    views: list[tuple[float, Any, np.ndarray]]

    @classmethod
    def start(cls, pf: AuxiliaryParticleFilter) -> Look:
        setup: ActiveSetup = _ctx["setup"]
        base: StandingMatch | None = _ctx["standing"]  # fresh views for each run
        return cls(pf, None if base is None else StandingMatch(base.lattice, setup.standing_match),
                   PanReliability(setup.active.reliability), [])

    def take(self, a: int, feats: np.ndarray, dfeats: np.ndarray | None) -> None:
        """The view at candidate pan ``a`` (``feats``, ``dfeats``: the position's (A, d))."""
        setup: ActiveSetup = _ctx["setup"]
        pan = float(setup.active.actions()[a])
        mix, novelty = _observe(feats[a], None if dfeats is None else dfeats[a])
        self.reliability.observe(pan, novelty)
        self.pf.update(np.zeros(3), pan, mix)
        roughen(self.pf, setup, mix, pan)
        if self.standing is not None:
            self.standing.step(self.pf, np.zeros(3), pan, feats[a])
        self.views.append((pan, mix, feats[a]))

    def entropy_values(self, eval_ms: list[float]) -> ActionValues:
        """The entropy strategy's action values (:func:`_values`, discounted by the reliability)."""
        return self.reliability.discount(_values(self.pf, _ctx["evaluator"], self.standing,
                                                 _ctx["setup"].active.actions(), eval_ms))

    def entropy_choice(self, a: int, eval_ms: list[float]) -> int:
        """The entropy strategy's next pan from the present one, ``a`` (never ``a`` itself)."""
        ev: ActionEvaluator = _ctx["evaluator"]
        pans = _ctx["setup"].active.actions()
        return self.entropy_values(eval_ms).best(float(pans[a]), ev.config.move_cost, exclude=[a])


def run_position(args: tuple[int, np.ndarray, np.ndarray, np.ndarray | None]) -> dict[str, Any]:
    """All runs and strategies at one test position: errors and successes (R, moves + 1) per
    strategy, the H(u) evaluation times, and (position 0, run 0) particle snapshots."""
    pos, truth, feats, dfeats = args
    setup: ActiveSetup = _ctx["setup"]
    pans = setup.active.actions()
    n_a = pans.size
    step, hstep = setup.judged_step, math.radians(setup.heading_step_deg)
    out: dict[str, Any] = {s: {"error": [], "success": [], "success_pose": [], "heading_error": [], "pans": [],
                               "decisions": {rule: [] for rule in setup.decisions},
                               "decision_error": {rule: [] for rule in setup.decisions}}
                           for s in setup.strategies}

    eval_ms: list[float] = []
    covered: list[bool] = []
    truth_cell = nearest_map_index(truth, _ctx["map_poses"], step, hstep)[0]
    snaps: dict[str, Any] = {}
    for run in range(setup.runs):
        a0 = int(np.random.default_rng((setup.seed, pos, run, 1)).integers(n_a))
        for strat in setup.strategies:
            pf = new_filter(pos, run)
            choice_rng = np.random.default_rng((setup.seed, pos, run, 2))
            if strat == setup.strategies[0]:  # is some initial particle in the truth's map cell?
                covered.append(bool(np.any(nearest_map_index(pf.particles, _ctx["map_poses"], step, hstep)
                                           == truth_cell)))
            a = a0
            ests, seq = [], [a]
            look = Look.start(pf)
            decided: dict[str, list[np.ndarray]] = {rule: [] for rule in setup.decisions}
            look.take(a, feats, dfeats)
            _estimate(pf, ests, look.views, decided)
            if setup.snapshots and pos == 0 and run == 0 and strat == "entropy":
                snaps["start"] = (pf.particles.copy(), pf.weights.copy())
            for _ in range(setup.movements):
                if strat == "lattice" and (b := _lattice_values(pf, look.views, pans)) is not None:
                    a = int(np.argmin(np.where(np.arange(n_a) == a, np.inf, b)))
                elif strat in ("entropy", "lattice"):
                    a = look.entropy_choice(a, eval_ms)
                elif strat == "random":
                    a = int((a + 1 + choice_rng.integers(n_a - 1)) % n_a)
                else:
                    a = (a + setup.sweep_stride) % n_a
                seq.append(a)
                look.take(a, feats, dfeats)
                _estimate(pf, ests, look.views, decided)
            est = np.asarray(ests)
            truths = np.repeat(truth[None, :], len(ests), axis=0)
            out[strat]["error"].append(position_errors(est, truths))
            out[strat]["success"].append(success(est, truths, _ctx["map_poses"]))
            out[strat]["success_pose"].append(success_pose(est, truths, _ctx["map_poses"], step, hstep))
            out[strat]["heading_error"].append(np.abs(wrap_angle(est[:, 2] - truth[2])))
            out[strat]["pans"].append(seq)
            for rule, poses in decided.items():
                out[strat]["decisions"][rule].append(success(np.asarray(poses), truths, _ctx["map_poses"]))
                out[strat]["decision_error"][rule].append(position_errors(np.asarray(poses), truths))
            if setup.snapshots and pos == 0 and run == 0 and strat == "entropy":
                snaps["end"] = (pf.particles.copy(), pf.weights.copy())
                snaps["entropy_start_end"] = (
                    belief_entropy(*snaps["start"][:1], np.log(snaps["start"][1])),
                    belief_entropy(pf.particles, pf.log_weights),
                )
    for s in out.values():
        for key in ("error", "success", "success_pose", "heading_error"):
            s[key] = np.asarray(s[key])
        s["decisions"] = {rule: np.asarray(v) for rule, v in s["decisions"].items()}
        s["decision_error"] = {rule: np.asarray(v) for rule, v in s["decision_error"].items()}
    return {"pos": pos, "strategies": out, "eval_ms": eval_ms, "snapshots": snaps, "covered": covered}


#: Bands of the test position's distance to the nearest map position (m) for
#: ``success_by_grid_distance``: the section 6.1 criterion asks the estimate to fall in the
#: truth's map cell, so near a cell border (0.375 m from a grid position on a 75 cm grid) an
#: error of a few centimetres decides it.
GRID_DISTANCE_BANDS: tuple[tuple[float, float], ...] = ((0.0, 0.25), (0.25, 0.35), (0.35, math.inf))


def grid_distance(truths: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Distance (m) from each test position to the nearest map position."""
    g = np.unique(np.round(grid[:, :2], 6), axis=0)
    return np.min(np.hypot(truths[:, None, 0] - g[None, :, 0], truths[:, None, 1] - g[None, :, 1]), axis=1)


def outcomes(parts: list[dict[str, Any]], strategy: str, key: str = "success") -> np.ndarray:
    """The 0/1 outcomes (P, R, moves + 1) of one strategy over the test positions ``parts``."""
    return np.stack([p["strategies"][strategy][key] for p in parts])


def success_by_band(parts: list[dict[str, Any]], strategies: tuple[str, ...], dist: np.ndarray) -> dict[str, Any]:
    """Success ratio after each movement per strategy, and its 95 % interval (key
    ``"<strategy>_ci95"``, :mod:`services.evaluation.active_stats` over the band's positions),
    for the test positions in each band of distance to the nearest map position
    (:data:`GRID_DISTANCE_BANDS`)."""
    out: dict[str, Any] = {}
    for lo, hi in GRID_DISTANCE_BANDS:
        sel = [p for p in parts if lo <= dist[p["pos"]] < hi]
        key = f"{lo:.2f}-{hi:.2f}" if math.isfinite(hi) else f"{lo:.2f}-"
        out[key] = {"positions": len(sel)}
        if not sel:
            continue
        counts = active_stats.resample_counts(len(sel), sel[0]["strategies"][strategies[0]]["success"].shape[0])
        for s in strategies:
            suc = outcomes(sel, s)
            out[key][s] = [float(v) for v in suc.mean(axis=(0, 1))]
            out[key][f"{s}_ci95"] = active_stats.intervals_json(suc, counts)
    return out


def comparisons(parts: list[dict[str, Any]], strategies: tuple[str, ...]) -> dict[str, Any]:
    """Paired differences of success, ``"<first>-<other>"`` (the first strategy, ``entropy`` by
    default, against every other), per movement
    (:func:`services.evaluation.active_stats.paired_difference`: the runs of all strategies
    start from the same particles and first pan)."""
    if len(strategies) < 2 or not parts:
        return {}
    first = strategies[0]
    counts = active_stats.resample_counts(len(parts), parts[0]["strategies"][first]["success"].shape[0])
    out: dict[str, Any] = {"se_method": active_stats.SE_METHOD}
    for s in strategies[1:]:
        out[f"{first}-{s}"] = active_stats.paired_difference(outcomes(parts, first), outcomes(parts, s), counts)
    return out


def _failure_errors(err: np.ndarray, suc: np.ndarray) -> dict[str, list[Any]]:
    """The position errors (m) of the runs that failed the criterion, per k (runs (N, K)):
    their count, median and 90th percentile (None where none failed). Small errors say the
    estimate was near the truth but across a cell border; large ones, a wrong place."""
    out: dict[str, list[Any]] = {"count": [], "median": [], "p90": []}
    for k in range(err.shape[1]):
        e = err[~suc[:, k].astype(bool), k]
        out["count"].append(int(e.size))
        out["median"].append(float(np.median(e)) if e.size else None)
        out["p90"].append(float(np.percentile(e, 90)) if e.size else None)
    return out


def _summarize(parts: list[dict[str, Any]], strategies: tuple[str, ...]) -> dict[str, Any]:
    """Per strategy the error statistics and success ratios after each movement, the success
    ratios with their 95 % intervals (``success_ci95``, ``success_pose_ci95``, [lo, hi] per k)."""
    summary: dict[str, Any] = {}
    counts = active_stats.resample_counts(len(parts), parts[0]["strategies"][strategies[0]]["success"].shape[0])
    for s in strategies:
        err = np.concatenate([p["strategies"][s]["error"] for p in parts])  # (P*R, moves+1)
        suc = np.concatenate([p["strategies"][s]["success"] for p in parts])
        per_pos = np.array([p["strategies"][s]["success"].mean(axis=0) for p in parts])
        suc_pose = np.concatenate([p["strategies"][s]["success_pose"] for p in parts])
        herr = np.concatenate([p["strategies"][s]["heading_error"] for p in parts])
        summary[s] = {
            "mean_error_m": [float(v) for v in err.mean(axis=0)],
            "std_error_m": [float(v) for v in err.std(axis=0)],
            "median_error_m": [float(v) for v in np.median(err, axis=0)],
            "success": [float(v) for v in suc.mean(axis=0)],
            "success_ci95": active_stats.intervals_json(outcomes(parts, s), counts),
            "positions_all_success": [int(v) for v in (per_pos >= 1.0).sum(axis=0)],
            "success_pose": [float(v) for v in suc_pose.mean(axis=0)],
            "success_pose_ci95": active_stats.intervals_json(outcomes(parts, s, "success_pose"), counts),
            "median_heading_error_deg": [float(v) for v in np.degrees(np.median(herr, axis=0))],
            "failure_error_m": _failure_errors(err, suc),
        }
        rules = parts[0]["strategies"][s]["decisions"]
        if rules:  # services.evaluation.decision_rules on the same runs, with the estimate's statistics
            summary[s]["decisions"] = {}
            for rule in rules:
                hits = np.stack([p["strategies"][s]["decisions"][rule] for p in parts])
                d_err = np.concatenate([p["strategies"][s]["decision_error"][rule] for p in parts])
                summary[s]["decisions"][rule] = {
                    "mean_error_m": [float(v) for v in d_err.mean(axis=0)],
                    "median_error_m": [float(v) for v in np.median(d_err, axis=0)],
                    "success": [float(v) for v in hits.mean(axis=(0, 1))],
                    "success_ci95": active_stats.intervals_json(hits, counts),
                    "minus_estimate": active_stats.paired_difference(hits, outcomes(parts, s), counts),
                }
    return summary


def run_condition(
    setup: ActiveSetup, map_poses: np.ndarray, entries: np.ndarray, map_features: np.ndarray,
    truths: np.ndarray, feats: np.ndarray, progress: ProgressFn | None, label: str,
    disparity: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Every test position's runs (``disparity``: the map's and the tests' disparity features)."""
    dmap, dtests = (None, None) if disparity is None else disparity
    jobs = [(i, truths[i], feats[i], None if dtests is None else dtests[i]) for i in range(truths.shape[0])]
    workers = setup.workers or os.cpu_count() or 1
    parts: list[dict[str, Any]] = []
    if workers == 1:
        init_worker(setup, entries, map_features, map_poses, dmap)
        it = map(run_position, jobs)
        for part in it:
            parts.append(part)
            if progress:
                progress(label, len(parts), len(jobs))
    else:
        with ProcessPoolExecutor(max_workers=workers, initializer=init_worker,
                                 initargs=(setup, entries, map_features, map_poses, dmap)) as pool:
            for part in pool.map(run_position, jobs):
                parts.append(part)
                if progress:
                    progress(label, len(parts), len(jobs))
    parts.sort(key=lambda p: p["pos"])
    return _summarize(parts, setup.strategies), parts


def _hit_ratios(hits: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    """``{key: {"k": ratio}, key + "_ci95": {"k": [lo, hi]}}`` of per-position hits (P,) or
    (P, R) (:mod:`services.evaluation.active_stats`)."""
    out: dict[str, Any] = {key: {}, f"{key}_ci95": {}}
    for k, v in hits.items():
        h = np.asarray(v, dtype=np.float64).reshape(v.shape[0], -1)
        counts = active_stats.resample_counts(h.shape[0], h.shape[1])
        out[key][k] = float(h.mean())
        out[f"{key}_ci95"][k] = active_stats.intervals_json(h[:, :, None], counts)[0]
    return out


def diagnose(setup: ActiveSetup, grid: np.ndarray, entries: np.ndarray, map_features: np.ndarray,
             truths: np.ndarray, pans: np.ndarray, feats: np.ndarray, parts: list[dict[str, Any]]) -> dict[str, Any]:
    """One condition's diagnostics: the single-view match quality
    (:func:`services.evaluation.active_bounds.feature_diagnostics`), with ``setup.ideal`` the
    sensor model's bound and the map oracle (success ratios after k images and their 95 %
    intervals, keys ``ideal_map_estimate_success[_ci95]``, ``map_oracle_success[_ci95]``), and
    the share of runs whose initial particles cover the truth's map cell."""
    out: dict[str, Any] = feature_diagnostics(setup, grid, entries, map_features, truths, pans, feats)
    if setup.ideal:
        out.update(_hit_ratios(ideal_hits(setup, grid, entries, map_features, truths, pans, feats),
                               "ideal_map_estimate_success"))
        out.update(_hit_ratios(map_oracle_hits(setup, grid, entries, map_features, truths, pans, feats),
                               "map_oracle_success"))
    out["initial_particle_in_truth_cell"] = float(np.mean([c for p in parts for c in p["covered"]]))
    return out


def chosen_view_change(parts: list[dict[str, Any]], strategies: tuple[str, ...], mapped: np.ndarray,
                       changed: np.ndarray) -> dict[str, float]:
    """How much the scene changes spoiled the views each strategy chose: the feature distance
    between a test view with the changes and the same view as mapped, ``|f_changed - f_mapped|``
    (``mapped``, ``changed``: (P, A, d)), over the views chosen after each movement, relative to
    the mean over all candidate pans of the same position (1: as spoiled as an average view)."""
    spoil = np.linalg.norm(changed - mapped, axis=-1)  # (P, A)
    mean = spoil.mean(axis=1)
    out: dict[str, float] = {}
    for s in strategies:
        ratios = [spoil[p["pos"], seq[1:]] / mean[p["pos"]] for p in parts for seq in p["strategies"][s]["pans"]
                  if mean[p["pos"]] > 0 and len(seq) > 1]
        out[s] = float(np.mean(np.concatenate(ratios))) if ratios else math.nan
    return out


def run(setup: ActiveSetup, progress: ProgressFn | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """The experiment. Returns (the JSON-ready result, extras for plotting)."""
    t0 = time.perf_counter()
    world = load_world(setup.world)
    changes = world.check_changes(setup.scene_changes)
    grid = grid_poses(world, setup.judged_step, math.radians(setup.heading_step_deg))  # the criterion's
    pans = setup.active.actions()
    pca, map_features, entries, margin, disp = render_map(setup, progress)
    truths = place_test_positions(world, setup, grid)
    conditions: list[tuple[str, tuple[str, ...]]] = [("none", ())]
    if changes:
        conditions.append(("+".join(changes), changes))
    results: dict[str, Any] = {}
    extras: dict[str, Any] = {"world": world, "grid": grid, "truths": truths, "pans": pans}
    timing: list[float] = []
    diagnostics: dict[str, Any] = {}
    bands: dict[str, Any] = {}
    compared: dict[str, Any] = {}
    mapped_feats = np.empty(0)
    view_change: dict[str, float] = {}
    for name, ch in conditions:
        feats, dfeats = render_tests(setup, pca, margin, truths, pans, ch, progress,
                                     None if disp is None else disp[0])
        summary, parts = run_condition(setup, grid, entries, map_features, truths, feats, progress,
                                       "runs" + ("" if not ch else f" ({name})"),
                                       None if disp is None or dfeats is None else (disp[1], dfeats))
        bands[name] = success_by_band(parts, setup.strategies, grid_distance(truths, grid))
        compared[name] = comparisons(parts, setup.strategies)
        results[name] = summary
        extras[name] = parts
        diagnostics[name] = diagnose(setup, grid, entries, map_features, truths, pans, feats, parts)
        timing.extend(v for p in parts for v in p["eval_ms"])
        if not ch:
            mapped_feats = feats
        else:
            view_change = chosen_view_change(parts, setup.strategies, mapped_feats, feats)
    base = results["none"]
    out: dict[str, Any] = {
        "positions": int(truths.shape[0]),
        "runs": int(setup.runs),
        "strategies": base,
        "comparisons": compared["none"],
        "intervals": active_stats.bootstrap_report(),
        "movements": int(setup.movements),
        "setup": setup.report(),
        "map_images": int(grid.shape[0] if setup.criterion_step is None
                          else grid_poses(world, setup.step, math.radians(setup.heading_step_deg)).shape[0]),
        "map_entries": int(entries.shape[0]),
        "test_poses": [[float(v) for v in t] for t in truths],
        "success_by_grid_distance": bands["none"],
        "entropy_eval_ms_median": float(np.median(timing)) if timing else None,
        "diagnostics": diagnostics,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    if changes:
        out["scene_changes"] = {"names": list(changes), "strategies": results["+".join(changes)],
                                "comparisons": compared["+".join(changes)],
                                "success_by_grid_distance": bands["+".join(changes)],
                                "chosen_view_change": view_change}
    return out, extras


# --------------------------------------------------------------------------- plots


def plot(result: dict[str, Any], extras: dict[str, Any], out_dir: str) -> list[str]:
    """Fig. 3 (error and success against movements, all strategies, std bands on the error,
    95 % interval bands on the success) per scene condition, and Fig. 4 (particles at the start and at the end of one entropy run)."""
    from services.evaluation.plotting import pyplot

    plt = pyplot()

    os.makedirs(out_dir, exist_ok=True)
    files: list[str] = []
    conds = [("none", result["strategies"])]
    if "scene_changes" in result:
        conds.append(("+".join(result["scene_changes"]["names"]), result["scene_changes"]["strategies"]))
    colours = {"entropy": "tab:blue", "random": "tab:orange", "sweep": "tab:green", "lattice": "tab:purple"}
    fig, axes = plt.subplots(2, len(conds), figsize=(6 * len(conds), 8), squeeze=False)
    for c, (name, strategies) in enumerate(conds):
        ax, ax2 = axes[0, c], axes[1, c]
        for s, r in strategies.items():
            m = np.asarray(r["mean_error_m"])
            sd = np.asarray(r["std_error_m"])
            x = np.arange(m.size)
            ax.plot(x, m, "o-", color=colours.get(s), label=s)
            ax.fill_between(x, np.maximum(m - sd, 0), m + sd, color=colours.get(s), alpha=0.15)
            ax2.plot(x, 100 * np.asarray(r["success"]), "o-", color=colours.get(s), label=s)
            if "success_ci95" in r:
                ci = 100 * np.asarray(r["success_ci95"])
                ax2.fill_between(x, ci[:, 0], ci[:, 1], color=colours.get(s), alpha=0.12)
        ax.set_title(f"scene changes: {name}" if name != "none" else "as mapped")
        ax.set_xlabel("camera movements")
        ax.set_ylabel("position error (m), mean +- std")
        ax.legend()
        ax2.axhline(95, color="0.5", ls=":")
        ax2.set_xlabel("camera movements")
        ax2.set_ylabel("success (%), section 6.1, 95 % interval")
        ax2.set_ylim(0, 102)
        ax2.legend()
    fig.suptitle(f"Active localization, {result['positions']} positions x {result['runs']} runs (Fig. 3)")
    fig.tight_layout()
    f3 = os.path.join(out_dir, "active_fig3_error.png")
    fig.savefig(f3, dpi=110)
    plt.close(fig)
    files.append(f3)

    parts = extras.get("none") or []
    snaps = parts[0]["snapshots"] if parts else {}
    if "start" in snaps and "end" in snaps:
        world: World = extras["world"]
        truth = extras["truths"][0]
        fig, axes = plt.subplots(1, 2, figsize=(14, 4.5))
        for ax, key, title in ((axes[0], "start", "after the first image"),
                               (axes[1], "end", f"after {result['movements']} movements (entropy)")):
            world.plot_floor_plan(ax)
            p, w = snaps[key]
            shade = w / w.max()
            ax.quiver(p[:, 0], p[:, 1], np.cos(p[:, 2]), np.sin(p[:, 2]), shade, cmap="viridis",
                      scale=40, width=0.003)
            ax.plot(extras["grid"][:, 0], extras["grid"][:, 1], ".", color="0.6", ms=2)
            ax.quiver([truth[0]], [truth[1]], [math.cos(truth[2])], [math.sin(truth[2])], color="red",
                      scale=15, width=0.008)
            mean = np.average(p[:, :2], axis=0, weights=w)
            sd = math.sqrt(np.average(np.sum((p[:, :2] - mean) ** 2, axis=1), weights=w))
            ax.add_patch(plt.Circle(mean, sd, fill=False, color="magenta"))
            ax.set_title(title)
        fig.suptitle("Particles (brighter = heavier), truth in red, circle = position std (Fig. 4)")
        fig.tight_layout()
        f4 = os.path.join(out_dir, "active_fig4_particles.png")
        fig.savefig(f4, dpi=110)
        plt.close(fig)
        files.append(f4)
    return files

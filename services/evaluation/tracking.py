"""Tracking in the simulated lab under changed light and unmodelled scene changes (paper, section 7:
"localization error below 50 cm with un-modelled changes in the scene or the light").

Setting: the lab world, a map every 50 cm and 10 deg (the lab survey grid of section 6.2,
~4500 views) rendered under the mapping light ``tube`` with no scene changes; ``features``
PCA features of the preprocessed images (``none`` / ``histeq`` / ``gradient``);
``step``, ``heading_step_deg``, ``virtual_headings``, ``translations`` and
``disparity_features`` make other maps (the simulated service's: 0.75 m, 15 deg, 5, 3 and 5,
``services.evaluation.views.build_sim_maps``). The robot
drives for ``duration`` seconds along a drive plan (:mod:`drivers.sim.drive`: a
smooth path through the free space of the CHANGED scene, wheel odometry with slip, per-wheel
scale errors and a wrong wheel base), the camera fixed (pan 0), one update per camera frame
at ``rate`` Hz. The same drive is rendered under each light of ``lights`` (``tube`` is the
reference: the mapping light) with the scene changes ``scene_changes`` applied (boxes added,
furniture moved, people standing: none of it in the map).

Per condition two runs of the :class:`lino_loc.localizer.Localizer` on the same frames:

- from the KNOWN start pose (Gaussian, 10 cm / 5 deg): ``ate_rmse_m`` (RMSE of the position
  errors), ``mean_error_m``, ``median_error_m``, ``max_error_m``, ``heading_rmse_deg`` over
  every frame, and ``lost_fraction`` (frames in state ``lost``);
- from the UNIFORM (global) belief: ``converged_after_s``, the first time from which the
  position error stays below ``converged_m`` (0.5 m) for ``converged_hold_s`` (5 s), None if
  never; ``global_mean_error_m``, the mean error after that time; and
  ``converged_state_after_s``, when the filter itself first reported ``tracking``.

``without_recovery`` repeats both runs with the kidnap recovery switched off
(``filter.recovery.max_inject_fraction = 0``), to show what recovery costs or buys: under changed light
the sensor model is often wrong in a consistent way, which is why the filter only trusts
familiar views for recovery while tracking (``lino_loc.particle_filter``, see the docs).

``odometry`` gives the same errors for dead reckoning alone (integrated odometry from the
true start), to show what the camera adds.

``light_switch`` (when ``switch_lights`` = (a, b) are both among ``lights``): the lights are
switched from a to b halfway through the drive (the frames of the two renders spliced at
the middle frame), one run from the known start: the errors before and after the switch, the
share of frames after it labelled ``lost`` and how long after it the last ``lost`` frame
comes (:func:`switch_metrics`). A building's lights are switched while the robot works; the
filter's lost test calibrates itself to the light it sees (``lino_loc.lost_detection``), so
this measures what a switch costs until it has.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers.sim.drive import DriveConfig, DrivePlan, PlannerConfig, plan_drive
from drivers.sim.world import load_world
from lino_loc.disparity import StereoConfig
from lino_loc.localizer import Localizer, LocalizerConfig
from lino_loc.lost_detection import base_stands
from lino_loc.metrics import ate_rmse, heading_errors, heading_rmse, position_errors
from services.evaluation.frame_trace import frame_row, write_trace
from services.evaluation.global_loc import localizer_config
from services.evaluation.honesty import honesty_metrics, lost_delays, quality_table
from services.evaluation.trajectories import trajectory_names, write_tum
from services.evaluation.views import ViewSpec, build_sim_maps, render_frames

log = logging.getLogger(__name__)

DEFAULT_PREPROCESS = "none"  # measured: see docs/evaluations.md
DEFAULT_CHANGES = ("boxes", "moved_furniture", "people")
#: The command's channels (``--channels``): both, measured better than intensity alone under
#: the changed lights on the lab, the office and the corridor (docs/results.md). The setup's
#: own default stays intensity alone, for callers that bring an intensity-only map.
DEFAULT_CHANNELS = ("intensity", "disparity")


@dataclass(frozen=True)
class TrackingSetup:
    world: str = "lab"
    step: float = 0.5
    heading_step_deg: float = 10.0
    virtual_headings: int = 1  # map entries per survey image, turned 3 deg apart (lino_loc.virtual_views)
    translations: int = 1  # odd m > 1: the map also holds virtual translations every step / m
    disparity_features: int | None = None  # the disparity channel's features (default: features)
    features: int = 20
    preprocess: tuple[str, ...] = (DEFAULT_PREPROCESS,)
    lights: tuple[str, ...] = ("tube", "bulb", "natural")
    scene_changes: tuple[str, ...] = DEFAULT_CHANGES
    duration: float = 240.0
    rate: float = 5.0
    pause_probability: float = 0.0  # the drive planner's chance of a 0.3-2 s stop at a reached goal
    particles: int | None = None
    j: int | None = None
    start_sigma_xy: float = 0.1
    start_sigma_deg: float = 5.0
    converged_m: float = 0.5
    converged_hold_s: float = 5.0
    global_start: bool = True
    compare_recovery: bool = True
    kidnap: bool = True
    switch_lights: tuple[str, str] | None = ("tube", "bulb")
    width: int = 320
    height: int = 240
    size: tuple[int, int] = (80, 60)
    seed: int = 0
    workers: int | None = None
    channels: tuple[str, ...] = ("intensity",)
    stereo: StereoConfig = field(default_factory=StereoConfig)  # the matcher of the disparity channel

    @property
    def disparity(self) -> bool:
        """Whether the map and the frames carry the disparity channel (fused by eq. 8)."""
        return "disparity" in self.channels


def converged_after(stamps: np.ndarray, err: np.ndarray, below: float, hold_s: float) -> float | None:
    """First stamp from which the error stays below ``below`` for ``hold_s`` seconds (or to the
    end of the run, if that is shorter); None if there is none."""
    good = err < below
    n = len(err)
    # bad_after[k]: index of the first bad frame at or after k (n if none)
    bad_after = np.full(n + 1, n)
    for k in range(n - 1, -1, -1):
        bad_after[k] = bad_after[k + 1] if good[k] else k
    for k in range(n):
        if not good[k]:
            continue
        end = bad_after[k]
        if end == n or stamps[end - 1] - stamps[k] >= hold_s:
            return float(stamps[k])
    return None


@dataclass
class Run:
    """One run of the filter: estimates (K, 3), states and the estimates' quality (K,), and
    with ``trace`` the per-frame diagnostics (``frame_trace.frame_row``)."""

    est: np.ndarray
    states: list[str]
    quality: np.ndarray
    trace: list[dict[str, Any]] = field(default_factory=list)


def run_filter(
    appearance_map: Any,
    cfg: LocalizerConfig,
    plan: DrivePlan,
    images: np.ndarray,
    start: np.ndarray | None,
    start_cov: np.ndarray | None,
    seed: Any,
    frames: np.ndarray | None = None,
    disparities: np.ndarray | None = None,
    trace: bool = False,
) -> Run:
    """One run over the frames of ``plan`` (global if start is None); ``frames`` the indices
    of the frames to use, in order (default: all), each with its own odometry increment;
    ``disparities`` (K, h, w), when given, go with the images (the map's disparity channel
    observes them); ``trace``: keep every frame's diagnostics in ``Run.trace``."""
    loc = Localizer(appearance_map, cfg, rng=np.random.default_rng(seed))
    if start is None:
        loc.start_global()
    else:
        loc.set_pose(start, start_cov)
    idx = np.arange(len(plan)) if frames is None else np.asarray(frames)
    inc = plan.increments
    est = np.zeros((len(idx), 3))
    quality = np.full(len(idx), np.nan)
    states: list[str] = []
    rows: list[dict[str, Any]] = []
    for j, k in enumerate(idx):
        d = None if disparities is None else disparities[k]
        e = loc.update(inc[k], 0.0, images[k], d, stamp=float(plan.stamps[j]))
        est[j] = e.pose
        quality[j] = e.quality
        states.append(e.state)
        if trace:
            rows.append(frame_row(loc, e))
    return Run(est, states, quality, rows)


def kidnap_frames(truth: np.ndarray) -> tuple[np.ndarray, int]:
    """The frames of a kidnapping on a drive with true poses ``truth`` (n, 3): the first half
    of the drive, then the robot carried to the frame j of [5n/8, 7n/8) farthest from where it
    was (the frames between skipped), then the rest of the drive from j; and the index (in the
    new order) of the first frame after the kidnapping."""
    n = truth.shape[0]
    half, lo, hi = n // 2, (5 * n) // 8, max((7 * n) // 8, (5 * n) // 8 + 1)
    dist = np.hypot(*(truth[lo:hi, :2] - truth[half - 1, :2]).T)
    jump = lo + int(np.argmax(dist))
    return np.concatenate([np.arange(half), np.arange(jump, n)]), half


def kidnap_metrics(
    plan: DrivePlan, run: Run, frames: np.ndarray, k_jump: int
) -> dict[str, Any]:
    """How the state answered a kidnapping at ``k_jump``: where and how far the robot was
    carried, the honesty metrics of the run, and the delay of the episode of error above
    1 m that the kidnapping starts (``lino_loc``'s state against the error after the jump)."""
    truth = plan.truth[frames]
    stamps = plan.stamps[: len(frames)]
    err = position_errors(run.est, truth)
    after = lost_delays(stamps[k_jump:], err[k_jump:], run.states[k_jump:])
    return {
        "kidnap_at_s": float(stamps[k_jump]),
        "carried_m": float(np.hypot(*(truth[k_jump, :2] - truth[k_jump - 1, :2]))),
        "mean_error_after_m": float(err[k_jump:].mean()),
        **honesty_metrics(stamps, err, run.states),
        "kidnap_episode": {"delay_s": after[0][0], "caught": after[0][1]} if after else None,
    }


def switch_metrics(
    stamps: np.ndarray, est: np.ndarray, truth: np.ndarray, states: list[str], k_switch: int
) -> dict[str, Any]:
    """Errors before / after the frame ``k_switch`` where the light changed, the share of the
    frames after it in state ``lost``, and the seconds from the switch to the last ``lost``
    frame after it (0 if none)."""
    err = position_errors(est, truth)
    lost = np.array([s == "lost" for s in states])
    after = lost[k_switch:]
    last = np.flatnonzero(after)
    return {
        "switch_at_s": float(stamps[k_switch] - stamps[0]),
        "mean_error_before_m": float(err[:k_switch].mean()),
        "mean_error_after_m": float(err[k_switch:].mean()),
        "max_error_after_m": float(err[k_switch:].max()),
        "lost_fraction_before": float(lost[:k_switch].mean()),
        "lost_fraction_after": float(after.mean()),
        "last_lost_after_switch_s": float(stamps[k_switch + last[-1]] - stamps[k_switch]) if last.size else 0.0,
    }


def track_metrics(est: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    err = position_errors(est, truth)
    return {
        "ate_rmse_m": ate_rmse(est, truth),
        "mean_error_m": float(err.mean()),
        "median_error_m": float(np.median(err)),
        "max_error_m": float(err.max()),
        "heading_rmse_deg": math.degrees(heading_rmse(est, truth)),
        "median_heading_error_deg": float(np.degrees(np.median(heading_errors(est, truth)))),
    }


def run(
    setup: TrackingSetup,
    config: LocalizerConfig | None = None,
    maps: dict[str, Any] | None = None,
    trajectories: Path | str | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, Any]:
    """Run the evaluation; ``maps`` (preprocess -> map) override the rendered survey maps (tests)."""
    world = load_world(setup.world)
    changes = world.check_changes(setup.scene_changes)
    for light in setup.lights:
        world.check_lighting(light)
    cfg = localizer_config(setup, config)
    if maps is None:
        maps = build_sim_maps(
            setup.world, setup.step, setup.heading_step_deg, setup.features, tuple(setup.preprocess),
            width=setup.width, height=setup.height, size=setup.size, seed=setup.seed, workers=setup.workers,
            progress=(lambda d, n: progress("map", d, n)) if progress else None, disparity=setup.disparity,
            stereo=setup.stereo, virtual_headings=setup.virtual_headings, translations=setup.translations,
            disparity_features=setup.disparity_features,
        )
    plan = plan_drive(world, DriveConfig(duration=setup.duration, camera_rate=setup.rate, scene_changes=changes,
                                         planner=PlannerConfig(pause_probability=setup.pause_probability)),
                      seed=setup.seed + 7)
    truth = plan.truth
    odo = plan.odometry
    start_cov = np.diag([setup.start_sigma_xy**2, setup.start_sigma_xy**2, math.radians(setup.start_sigma_deg) ** 2])
    out_dir = Path(trajectories) if trajectories is not None else None
    traced = out_dir is not None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        write_tum(out_dir / "truth.tum", plan.stamps, truth, comment=f"true robot poses, world {setup.world}")
        write_tum(out_dir / "odometry.tum", plan.stamps, odo, comment="wheel odometry (dead reckoning)")
    by_pre: dict[str, dict[str, Any]] = {pre: {} for pre in setup.preprocess}
    switch = setup.switch_lights if setup.switch_lights and set(setup.switch_lights) <= set(setup.lights) else None
    kept: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    graded: list[tuple[Run, np.ndarray]] = []  # every run, for the quality table
    for light in setup.lights:
        cond = "+".join((light, *changes))
        spec = ViewSpec(world=setup.world, lighting=light, scene_changes=changes, width=setup.width,
                        height=setup.height, size=setup.size, seed=setup.seed + 11, disparity=setup.disparity,
                        stereo=setup.stereo)
        images, disps = render_frames(
            spec, truth, workers=setup.workers,
            progress=(lambda d, n, c=cond: progress(f"render {c}", d, n)) if progress else None)
        if switch is not None and light in switch:
            kept[light] = (images, disps)
        for pre in setup.preprocess:
            amap = maps[pre]
            name = light if len(setup.preprocess) == 1 else f"{light}-{pre}"
            run0 = run_filter(amap, cfg, plan, images, truth[0], start_cov, (setup.seed, 1), disparities=disps,
                              trace=traced)
            if out_dir is not None:
                write_trace(out_dir / f"{name}.trace.csv", run0.trace, truth)
            est, states = run0.est, run0.states
            res: dict[str, Any] = {"condition": cond, **track_metrics(est, truth)}
            res["lost_fraction"] = float(np.mean([s == "lost" for s in states]))
            res.update(honesty_metrics(plan.stamps, position_errors(est, truth), states))
            graded.append((run0, truth))
            if setup.global_start:
                grun = run_filter(amap, cfg, plan, images, None, None, (setup.seed, 2), disparities=disps,
                                  trace=traced)
                if out_dir is not None:
                    write_trace(out_dir / f"{name}-uniform.trace.csv", grun.trace, truth)
                gest, gstates = grun.est, grun.states
                gerr = position_errors(gest, truth)
                t_c = converged_after(plan.stamps, gerr, setup.converged_m, setup.converged_hold_s)
                res["converged_after_s"] = t_c
                res["global_mean_error_m"] = (
                    float(gerr[plan.stamps >= t_c].mean()) if t_c is not None else float(gerr.mean())
                )
                first_tr = next((float(plan.stamps[k]) for k, s in enumerate(gstates) if s == "tracking"), None)
                res["converged_state_after_s"] = first_tr
                res["global_start"] = honesty_metrics(plan.stamps, gerr, gstates)
                graded.append((grun, truth))
            if setup.kidnap and len(plan) >= 4:
                frames, k_jump = kidnap_frames(truth)
                krun = run_filter(amap, cfg, plan, images, truth[0], start_cov, (setup.seed, 3), frames=frames,
                                  disparities=disps, trace=traced)
                if out_dir is not None:
                    write_trace(out_dir / f"{name}-kidnap.trace.csv", krun.trace, truth[frames])
                res["kidnap"] = kidnap_metrics(plan, krun, frames, k_jump)
                graded.append((krun, truth[frames]))
            if setup.compare_recovery:
                cfg0 = cfg.model_copy(deep=True)
                cfg0.filter.recovery.max_inject_fraction = 0.0
                run_0 = run_filter(amap, cfg0, plan, images, truth[0], start_cov, (setup.seed, 1), disparities=disps)
                est0, states0 = run_0.est, run_0.states
                res0: dict[str, Any] = {**track_metrics(est0, truth),
                                        "lost_fraction": float(np.mean([s == "lost" for s in states0]))}
                if setup.global_start:
                    gest0 = run_filter(amap, cfg0, plan, images, None, None, (setup.seed, 2), disparities=disps).est
                    res0["converged_after_s"] = converged_after(
                        plan.stamps, position_errors(gest0, truth), setup.converged_m, setup.converged_hold_s)
                res["without_recovery"] = res0
                if out_dir is not None:
                    write_tum(out_dir / trajectory_names(name + "-no-recovery")[0], plan.stamps, est0,
                              comment=f"estimate, {cond}, preprocess {pre}, known start, no kidnap recovery")
            by_pre[pre][light] = res
            if out_dir is not None:
                est_name, _ = trajectory_names(name)
                write_tum(out_dir / est_name, plan.stamps, est,
                          comment=f"estimate, {cond}, preprocess {pre}, known start")
            log.info("tracking %s %s: mean %.3f m, max %.3f m, converged after %s s", cond, pre,
                     res["mean_error_m"], res["max_error_m"], res.get("converged_after_s"))
    head = setup.preprocess[0]
    switched: dict[str, Any] | None = None
    if switch is not None:
        k_sw = len(plan) // 2
        (ia, da), (ib, db) = kept[switch[0]], kept[switch[1]]
        images = np.concatenate([ia[:k_sw], ib[k_sw:]])
        disps = None if da is None or db is None else np.concatenate([da[:k_sw], db[k_sw:]])
        srun = run_filter(maps[head], cfg, plan, images, truth[0], start_cov, (setup.seed, 1), disparities=disps,
                          trace=traced)
        switched = {"lights": list(switch), **switch_metrics(plan.stamps, srun.est, truth, srun.states, k_sw),
                    **honesty_metrics(plan.stamps, position_errors(srun.est, truth), srun.states)}
        graded.append((srun, truth))
        if out_dir is not None:
            write_tum(out_dir / trajectory_names(f"switch-{switch[0]}-{switch[1]}")[0], plan.stamps, srun.est,
                      comment=f"estimate, lights {switch[0]} -> {switch[1]} at frame {k_sw}, known start")
            write_trace(out_dir / f"switch-{switch[0]}-{switch[1]}.trace.csv", srun.trace, truth)
        log.info("tracking, lights %s -> %s at %.0f s: mean error after %.3f m, lost after %.1f %%", *switch,
                 switched["switch_at_s"], switched["mean_error_after_m"], 100 * switched["lost_fraction_after"])
    result: dict[str, Any] = {
        "world": setup.world,
        "map_entries": int(np.asarray(maps[head].poses).shape[0]),
        "map_step_m": float(setup.step),
        "map_heading_step_deg": float(setup.heading_step_deg),
        "virtual_headings": int(setup.virtual_headings),
        "translations": int(setup.translations),
        "disparity_features": setup.disparity_features,
        "features": int(np.asarray(maps[head].channels["intensity"].features).shape[1]),
        "preprocess": head,
        "channels": list(setup.channels),
        "fusion": cfg.fusion.model_dump() if setup.disparity else None,
        "stereo": setup.stereo.model_dump() if setup.disparity else None,
        "particles": int(cfg.filter.n_particles),
        "J": int(cfg.sensor.j),
        "duration_s": float(plan.stamps[-1]),
        "rate_hz": float(setup.rate),
        "frames": len(plan),
        "path_length_m": plan.length_m,
        "pause_probability": float(setup.pause_probability),
        "standing_frames": int(sum(base_stands(d) for d in plan.increments)),
        "scene_changes": list(changes),
        "start": f"known pose (sigma {setup.start_sigma_xy:.2f} m, {setup.start_sigma_deg:.1f} deg) for the "
        "error keys; uniform (global) for converged_after_s",
        "conditions": by_pre[head],
        "odometry": track_metrics(odo, truth),
    }
    if switched is not None:
        result["light_switch"] = switched
    result["quality_table"] = quality_table(
        np.concatenate([r.quality for r, _ in graded]),
        np.concatenate([position_errors(r.est, t) for r, t in graded]),
        [s for r, _ in graded for s in r.states],
    )
    if len(setup.preprocess) > 1:
        result["by_preprocess"] = by_pre
    return result

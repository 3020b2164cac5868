"""Global localization in a simulated world (paper, section 6.1 and Fig. 3): error, success
and convergence against the number of updates, from a uniform initial belief, with the camera
fixed or turned by active vision.

Setting (section 6.1, the office by default): the world's mapped area, a map every ``step`` m
and ``heading_step_deg`` rendered under the mapping light (``tube``), ``features`` PCA
features, J = 10. For each of ``starts`` runs the robot starts at a random free pose (off the
map grid) and drives along a drive plan (:mod:`drivers.sim.drive`, with odometry noise); the
:class:`lino_loc.localizer.Localizer` starts from the uniform belief over the mapped area and
all headings and gets one (odometry increment, image) pair per update at ``rate`` Hz. The
camera (``camera``):

- ``fixed``: pan 0 throughout (the views change only because the robot drives);
- ``active``: the daemon's active-vision policy (:class:`lino_loc.active_vision.ActivePolicy`
  with the ``[active_vision]`` defaults of :class:`services.active_head.ActiveVisionSettings`)
  chooses the pan after every update from the filter's belief. The head turns at
  ``head_speed`` rad/s; a frame taken while it turns or less than ``settle_s`` after it
  stopped is used for prediction only (odometry), as the daemon does; the policy is told the
  head's readings at the command and at the stop. Frames are rendered as the run goes (the
  pan depends on the belief), with the same noise as the fixed camera's frame at that update
  (:func:`services.evaluation.views.render_frame`), so at pan 0 both see the same image.

After every update the estimate is compared with the truth:

- position error (metres) of the estimate, averaged (``mean_error_m``) and medianed
  (``median_error_m``) over the starts;
- success ratio (``success``): the fraction of starts whose estimate passes the criterion of
  section 6.1 (:func:`lino_loc.metrics.success`: the map POSITION nearest to the estimate is the
  map position nearest to the truth); ``success_pose`` the stricter (x, y, theta) cell variant
  (:func:`lino_loc.metrics.success_pose`, grid units of the map's step and heading step);
- heading error (degrees, median) and the fraction of runs whose filter state is
  ``tracking``;
- convergence: a start's ``converged_update`` is the first update (1-based) from which its
  estimate passes the section 6.1 criterion at every later update of the run (None: it does
  not pass at the last one); ``converged_by_update[k]`` the share of starts converged by update
  k + 1, and ``converge`` their median in updates and in seconds of driving (updates / rate);
  ``converged_within_step`` the same with "position error within one map step" (the survey's
  grid spacing) in place of the criterion, which flickers near the map cells' borders however
  small the error; ``final_error_m`` each start's error after the last update;
- cost: CPU milliseconds per filter update with an image (``update_cpu_ms``; rendering not
  included) and, active, per policy
  decision (``policy_cpu_ms``); the head's commands and the share of frames the filter could
  not use because the head was turning or settling.

:func:`run` runs one configuration; :func:`run_grid` runs several particle counts and both
cameras on the same starts, map and frames, interleaved start by start (paired: the same
initial particles for both cameras at a particle count).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from drivers.sim.drive import DriveConfig, DrivePlan, plan_drive
from drivers.sim.renderer import Renderer
from drivers.sim.world import World, grid_poses, load_world
from lino_loc.active_vision import ActivePolicy, ActiveVisionConfig, action_evaluator
from lino_loc.errors import LinoLocError
from lino_loc.localizer import Localizer, LocalizerConfig
from lino_loc.metrics import heading_errors, position_errors, success, success_pose
from services.active_head import ActiveVisionSettings
from services.evaluation.views import (
    ViewSpec,
    build_sim_maps,
    frame_renderer,
    render_frame,
    render_frames,
)

log = logging.getLogger(__name__)

CAMERAS: tuple[str, ...] = ("fixed", "active")

#: rad/s: the head driver's default profile velocity (``drivers.dynamixel_head.HeadConfig``).
HEAD_SPEED_RAD_S = 1.5


@dataclass(frozen=True)
class GlobalSetup:
    """The evaluation's settings (module docstring): the world and its survey map, the starts
    and updates, the camera (``fixed`` or ``active``, with the head's speed and the policy's
    settings, the daemon's by default). LinoLocError on an unknown camera or a head speed not
    above 0."""

    world: str = "office"
    step: float = 0.75
    heading_step_deg: float = 15.0
    features: int = 5
    preprocess: str = "none"
    lighting: str = "tube"
    starts: int = 20
    updates: int = 30
    rate: float = 2.0
    particles: int | None = None  # None: the LocalizerConfig's
    j: int | None = None  # None: the LocalizerConfig's
    sensor_model: str | None = None  # None: the LocalizerConfig's ("nearest_neighbour" / "interpolated")
    width: int = 320
    height: int = 240
    size: tuple[int, int] = (80, 60)
    seed: int = 0
    workers: int | None = None
    virtual_headings: int = 5  # as config/sim.toml's map (lino_loc.virtual_views); 1: images alone
    virtual_step_deg: float = 3.0
    channels: tuple[str, ...] = ("intensity",)  # with "disparity": both channels, fused (eq. 8)
    camera: str = "fixed"  # "fixed" (pan 0) or "active" (the daemon's policy turns the head)
    head_speed: float = HEAD_SPEED_RAD_S  # rad/s, active camera
    active_vision: ActiveVisionConfig = field(
        default_factory=lambda: ActiveVisionSettings().method_config(enabled=True))

    def __post_init__(self) -> None:
        if self.camera not in CAMERAS:
            raise LinoLocError(f"camera: expected one of {', '.join(CAMERAS)}, got {self.camera!r}")
        if not self.head_speed > 0.0:
            raise LinoLocError(f"head_speed: must be positive, got {self.head_speed}")


def localizer_config(setup: Any, base: LocalizerConfig | None) -> LocalizerConfig:
    """``base`` (or the defaults) with the setup's particle count, J and sensor model where it
    sets them."""
    cfg = (base or LocalizerConfig()).model_copy(deep=True)
    if setup.particles is not None:
        cfg.filter.n_particles = int(setup.particles)
    if setup.j is not None:
        cfg.sensor.j = int(setup.j)
    if getattr(setup, "sensor_model", None) is not None:
        cfg = LocalizerConfig.model_validate({**cfg.model_dump(), "sensor_model": setup.sensor_model})
    return cfg


# --------------------------------------------------------------------------- inputs


@dataclass
class Inputs:
    """What every configuration of one evaluation shares: the world, the map, the success
    criteria's training points, the drive plans and the fixed camera's frames (None until
    needed), and a renderer for the active camera (built when first needed)."""

    setup: GlobalSetup
    world: World
    appearance_map: Any
    map_poses: np.ndarray
    plans: list[DrivePlan]
    n_up: int
    spec: ViewSpec
    images: np.ndarray | None = None
    disps: np.ndarray | None = None
    renderer: Renderer | None = None
    evaluators: dict[str, Any] = field(default_factory=dict)

    def evaluator(self, loc: Localizer) -> Any:
        """The active-vision action evaluator of ``loc``'s intensity sensor model, built once
        per sensor configuration (as the daemon builds it once per map: it depends on the map
        and the sensor model, not on the particles; building it queries every map entry's J
        nearest, 8 s on the floor's 117k entries)."""
        key = loc.config.sensor.model_dump_json() + loc.config.sensor_model
        if key not in self.evaluators:
            self.evaluators[key] = action_evaluator(loc.sensor_model("intensity"), self.setup.active_vision)
        return self.evaluators[key]

    def fixed_frames(self, progress: Callable[[str, int, int], None] | None) -> None:
        """Render the fixed camera's frames of every start (once)."""
        if self.images is not None:
            return
        poses = np.concatenate([p.truth[: self.setup.updates] for p in self.plans])
        self.images, self.disps = render_frames(
            self.spec, poses, workers=self.setup.workers,
            progress=(lambda d, n: progress("drive", d, n)) if progress else None)

    def frame(self, s: int, k: int, pan: float) -> tuple[np.ndarray, np.ndarray | None]:
        """The frame of start ``s`` at update ``k`` with the head at ``pan``."""
        if self.renderer is None:
            self.renderer = frame_renderer(self.spec)
        return render_frame(self.renderer, self.spec, self.plans[s].truth[k], pan, s * self.setup.updates + k)


def prepare(setup: GlobalSetup, appearance_map: Any = None,
            progress: Callable[[str, int, int], None] | None = None) -> Inputs:
    """The map (the rendered survey's, cached by :func:`build_sim_maps`, unless
    ``appearance_map`` is given), the drive plans and the frames' view spec."""
    world = load_world(setup.world)
    given = appearance_map is not None
    if appearance_map is None:
        appearance_map = build_sim_maps(
            setup.world, setup.step, setup.heading_step_deg, setup.features, (setup.preprocess,),
            lighting=setup.lighting, width=setup.width, height=setup.height, size=setup.size,
            seed=setup.seed, workers=setup.workers,
            progress=(lambda d, n: progress("map", d, n)) if progress else None,
            virtual_headings=setup.virtual_headings, virtual_step_deg=setup.virtual_step_deg,
            disparity="disparity" in setup.channels,
        )[setup.preprocess]
    entries = np.asarray(appearance_map.poses, dtype=np.float64)
    # the success criteria's training points: the survey grid (the map's entries may add
    # virtual headings to it)
    map_poses = entries if given else grid_poses(world, setup.step, math.radians(setup.heading_step_deg))
    drive_cfg = DriveConfig(duration=max(setup.updates - 1, 1) / setup.rate, camera_rate=setup.rate)
    plans = [plan_drive(world, drive_cfg, seed=setup.seed * 100_003 + 1 + s) for s in range(setup.starts)]
    spec = ViewSpec(world=setup.world, lighting=setup.lighting, width=setup.width, height=setup.height,
                    size=setup.size, seed=setup.seed + 1, disparity="disparity" in setup.channels)
    n_up = min(setup.updates, min(len(p) for p in plans))
    return Inputs(setup, world, appearance_map, map_poses, plans, n_up, spec)


# --------------------------------------------------------------------------- one start


@dataclass
class StartRun:
    """One start's estimates (n_up, 3), whether the state was ``tracking``, the head's pan at
    each frame, whether the filter used the frame (False: the head was turning or settling,
    prediction only), update and policy CPU times (ms) and the head's commands."""

    est: np.ndarray
    tracking: np.ndarray
    pans: np.ndarray
    used: np.ndarray
    update_ms: list[float] = field(default_factory=list)
    policy_ms: list[float] = field(default_factory=list)
    commands: int = 0


def _new_run(n_up: int) -> StartRun:
    return StartRun(np.zeros((n_up, 3)), np.zeros(n_up, dtype=bool), np.zeros(n_up), np.ones(n_up, dtype=bool))


def run_fixed(inp: Inputs, loc: Localizer, s: int) -> StartRun:
    """Start ``s`` with the camera at pan 0, on the pre-rendered frames."""
    assert inp.images is not None
    out = _new_run(inp.n_up)
    inc = inp.plans[s].increments
    for k in range(inp.n_up):
        i = s * inp.setup.updates + k
        t0 = time.process_time()
        e = loc.update(inc[k], 0.0, inp.images[i], None if inp.disps is None else inp.disps[i])
        out.update_ms.append(1e3 * (time.process_time() - t0))
        out.est[k] = e.pose
        out.tracking[k] = e.state == "tracking"
    return out


@dataclass
class Head:
    """The simulated head: it turns from ``pan`` toward ``target`` at ``speed`` rad/s from
    ``t_cmd`` and arrives at ``arrive`` (s)."""

    speed: float
    pan: float = 0.0
    target: float = 0.0
    t_cmd: float = -math.inf
    arrive: float = -math.inf
    reported: bool = True  # the policy has been told of the last command's stop

    def at(self, t: float) -> tuple[float, bool]:
        """(pan, moving) at time ``t``."""
        if t >= self.arrive:
            return self.target, False
        frac = (t - self.t_cmd) / max(self.arrive - self.t_cmd, 1e-12)
        return self.pan + frac * (self.target - self.pan), True

    def command(self, t: float, goal: float) -> None:
        self.pan, _ = self.at(t)
        self.target, self.t_cmd = float(goal), t
        self.arrive = t + abs(self.target - self.pan) / self.speed
        self.reported = False


def _tell_policy(policy: ActivePolicy, head: Head, t: float) -> None:
    """The head's readings since the last decision, once per command: moving at the command,
    at rest from its arrival (the daemon reads the head far more often than it gets frames)."""
    if not head.reported and head.arrive <= t:
        policy.settle.observe(True, head.t_cmd)
        policy.settle.observe(False, head.arrive)
        head.reported = True


def run_active(inp: Inputs, loc: Localizer, s: int) -> StartRun:
    """Start ``s`` with the daemon's active-vision policy turning the head (module docstring)."""
    setup = inp.setup
    av = setup.active_vision
    policy = ActivePolicy(inp.evaluator(loc), av)
    head = Head(setup.head_speed)
    out = _new_run(inp.n_up)
    inc = inp.plans[s].increments
    used: float | None = None
    for k in range(inp.n_up):
        t = k / setup.rate
        pan, moving = head.at(t)
        at_rest = policy.settle.at_rest(t, moving, head.arrive if head.arrive > -math.inf else None)
        if at_rest:
            img, disp = inp.frame(s, k, pan)  # rendering is not the filter's cost
            t0 = time.process_time()
            e = loc.update(inc[k], pan, img, disp)
            out.update_ms.append(1e3 * (time.process_time() - t0))
            used = t
        else:
            e = loc.predict_only(inc[k])
            out.used[k] = False
        out.est[k], out.tracking[k], out.pans[k] = e.pose, e.state == "tracking", pan
        _tell_policy(policy, head, t)
        t0 = time.process_time()
        d = policy.decide(*loc.belief(), state=e.state, log_likelihood=e.log_likelihood, pan=pan,
                          moving=moving, now=t, frame_stamp=used, doubt=e.doubt)
        out.policy_ms.append(1e3 * (time.process_time() - t0))
        if d.command is not None:
            head.command(t, d.command)
            out.commands += 1
    return out


def run_start(inp: Inputs, cfg: LocalizerConfig, camera: str, s: int) -> StartRun:
    """One start from the uniform belief, the filter seeded by (seed, start): the same initial
    particles for every camera at a particle count."""
    loc = Localizer(inp.appearance_map, cfg, rng=np.random.default_rng((inp.setup.seed, s)))
    loc.start_global()
    return run_active(inp, loc, s) if camera == "active" else run_fixed(inp, loc, s)


# --------------------------------------------------------------------------- summaries


def converged_update(ok: np.ndarray) -> int | None:
    """First update (1-based) from which every later update of the row passes; None when the
    last one fails."""
    row = np.asarray(ok, dtype=bool)
    if row.size == 0 or not row[-1]:
        return None
    fails = np.flatnonzero(~row)
    return int(fails[-1]) + 2 if fails.size else 1


def _convergence(ok: np.ndarray, rate: float) -> dict[str, Any]:
    """``converged_update`` per start, the share converged by each update and the median of the
    converged starts (updates and seconds)."""
    conv = [converged_update(row) for row in ok]
    n_up = ok.shape[1]
    done = [c for c in conv if c is not None]
    med = float(np.median(done)) if done else None
    return {
        "converged_update": conv,
        "converged_by_update": [float(np.mean([c is not None and c <= k + 1 for c in conv])) for k in range(n_up)],
        "converge": {"share": float(len(done) / len(conv)) if conv else 0.0, "median_updates": med,
                     "median_s": None if med is None else med / rate},
    }


def _within_step(err: np.ndarray, step: float, rate: float) -> dict[str, Any]:
    """Convergence by position error: from which update on each start's error stays within one
    map step (the survey's grid spacing, ``step`` m), the share by each update, the median.
    (Section 6.1's criterion flickers near the borders of the map's cells however small the
    error: a run right to 6 cm fails where the truth passes within 6 cm of a border.)"""
    c = _convergence(err <= step, rate)
    return {"threshold_m": float(step), "update": c["converged_update"], "by_update": c["converged_by_update"],
            **c["converge"]}


def _cells(world: World, truths: np.ndarray) -> list[str | None]:
    """The id of the world's cell (room or doorway passage) each position lies in (None: none,
    or a world without rooms)."""
    lay = world.layout
    if lay is None:
        return [None] * len(truths)
    r = lay.rects
    out: list[str | None] = []
    for x, y, _ in truths:
        inside = np.flatnonzero((r[:, 0] <= x) & (x <= r[:, 1]) & (r[:, 2] <= y) & (y <= r[:, 3]))
        out.append(lay.cells[int(inside[0])].id if inside.size else None)
    return out


def summarize(inp: Inputs, cfg: LocalizerConfig, camera: str, runs: list[StartRun]) -> dict[str, Any]:
    """The JSON-ready result of one configuration over its starts (module docstring)."""
    setup, n_up = inp.setup, inp.n_up
    truth = np.stack([p.truth[:n_up] for p in inp.plans])
    est = np.stack([r.est for r in runs])
    err = np.stack([position_errors(e, t) for e, t in zip(est, truth, strict=True)])
    head = np.degrees(np.stack([heading_errors(e, t) for e, t in zip(est, truth, strict=True)]))
    ok = np.stack([success(e, t, inp.map_poses) for e, t in zip(est, truth, strict=True)])
    ok_pose = np.stack([success_pose(e, t, inp.map_poses, setup.step, math.radians(setup.heading_step_deg))
                        for e, t in zip(est, truth, strict=True)])
    tracking = np.stack([r.tracking for r in runs])
    upd = [v for r in runs for v in r.update_ms]
    pol = [v for r in runs for v in r.policy_ms]
    feats = np.asarray(inp.appearance_map.channels["intensity"].features)
    return {
        "world": setup.world, "starts": int(setup.starts), "updates": int(n_up), "rate_hz": float(setup.rate),
        "camera": camera, "map_images": int(inp.map_poses.shape[0]),
        "map_entries": int(np.asarray(inp.appearance_map.poses).shape[0]),
        "map_step_m": float(setup.step), "map_heading_step_deg": float(setup.heading_step_deg),
        "features": int(feats.shape[1]), "preprocess": setup.preprocess, "channels": list(setup.channels),
        "particles": int(cfg.filter.n_particles), "J": int(cfg.sensor.j), "sensor_model": cfg.sensor_model,
        "index": cfg.sensor.index, "lighting": setup.lighting,
        "mean_error_m": [float(v) for v in err.mean(axis=0)],
        "median_error_m": [float(v) for v in np.median(err, axis=0)],
        "success": [float(v) for v in ok.mean(axis=0)],
        "success_pose": [float(v) for v in ok_pose.mean(axis=0)],
        "median_heading_error_deg": [float(v) for v in np.median(head, axis=0)],
        "tracking": [float(v) for v in tracking.mean(axis=0)],
        "first_success_update": [int(np.argmax(row)) + 1 if row.any() else None for row in ok],
        **_convergence(ok, setup.rate),
        "converged_within_step": _within_step(err, setup.step, setup.rate),
        "final_error_m": [float(v) for v in err[:, -1]],
        "start_cells": _cells(inp.world, truth[:, 0]),
        "update_cpu_ms": {"median": float(np.median(upd)), "p90": float(np.percentile(upd, 90))},
        "policy_cpu_ms": {"median": float(np.median(pol)), "p90": float(np.percentile(pol, 90))} if pol else None,
        "head_commands_mean": float(np.mean([r.commands for r in runs])) if camera == "active" else 0.0,
        "unused_frame_share": float(np.mean([~r.used for r in runs])),
        "final": {"mean_error_m": float(err[:, -1].mean()), "median_error_m": float(np.median(err[:, -1])),
                  "success": float(ok[:, -1].mean()), "success_pose": float(ok_pose[:, -1].mean())},
    }


# --------------------------------------------------------------------------- runs


def run(
    setup: GlobalSetup,
    config: LocalizerConfig | None = None,
    appearance_map: Any = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, Any]:
    """Run the evaluation of ``setup.camera``; ``appearance_map`` overrides the rendered
    survey map (tests)."""
    return run_grid(setup, None, (setup.camera,), config, appearance_map, progress)["runs"][0]


def run_grid(
    setup: GlobalSetup,
    particles: tuple[int, ...] | None = None,
    cameras: tuple[str, ...] = CAMERAS,
    config: LocalizerConfig | None = None,
    appearance_map: Any = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, Any]:
    """Every particle count (None: ``setup.particles``) with every camera on the same map,
    starts and frames; for each start the configurations run one after the other (so a load
    change on a shared machine touches all alike). ``{"runs": [result per (particles,
    camera)], "seconds": wall time}``; LinoLocError on an unknown camera or a particle count
    below 1."""
    t_start = time.perf_counter()
    bad = [c for c in cameras if c not in CAMERAS]
    if bad or not cameras:
        raise LinoLocError(f"camera: expected some of {', '.join(CAMERAS)}, got {','.join(cameras) or 'none'}")
    counts: tuple[int | None, ...] = particles if particles else (setup.particles,)
    if any(n is not None and n < 1 for n in counts):
        raise LinoLocError(f"particles: each count must be at least 1, got {list(counts)}")
    inp = prepare(setup, appearance_map, progress)
    if "fixed" in cameras:
        inp.fixed_frames(progress)
    combos = [(localizer_config(replace(setup, particles=n), config), cam) for n in counts for cam in cameras]
    runs: list[list[StartRun]] = [[] for _ in combos]
    for s in range(setup.starts):
        for c, (cfg, cam) in enumerate(combos):
            runs[c].append(run_start(inp, cfg, cam, s))
        if progress:
            progress("filter", s + 1, setup.starts)
        log.debug("start %d done", s)
    results = [summarize(inp, cfg, cam, r) for (cfg, cam), r in zip(combos, runs, strict=True)]
    return {"runs": results, "seconds": round(time.perf_counter() - t_start, 1)}

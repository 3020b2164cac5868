"""The simulated robot: building, base kinematics, pan-tilt head, odometry board and camera.

:class:`SimRobot` runs, in one process, everything ``lino-loc run`` talks to on the real
robot, so that the daemon's real drivers are what runs against it:

- **base** (thread ``sim-base``, ``rate_hz`` = 50 Hz): a differential drive following a
  :class:`drivers.sim.drive.DrivePlanner` (or standing still; its settings:
  :meth:`SimRobotConfig.planner_config`). Each tick k at nominal time t_k = t_0 + k dt takes
  (v, omega) from the planner for the interval [t_k, t_k+1), sets the wheel speeds the
  encoders measure (:mod:`drivers.sim.wheel_noise` applied to the true wheel travels
  ``(v -/+ omega b / 2) dt``, b = the true track width) on the odometry board emulator and
  integrates the pose along the exact arc. A step whose end pose is not free (conservative
  raster of :meth:`World.is_free` for ``robot_radius``) is replaced by a turn in place and the
  plan picks another goal: the robot never enters a wall or a piece of furniture. The fixed
  time step makes the path a function of the seed alone. The true pose (and the head's
  present pan/tilt) of every tick goes to ``on_truth`` (50 Hz).
- **head**: a :class:`drivers.sim.dynamixel_emulator.DynamixelBusEmulator` (two X-series
  servos, Protocol 2.0 on a pseudo-terminal) for the real ``DynamixelHead`` adapter.
- **odometry**: an :class:`drivers.sim.odometry_emulator.OdometryBoardEmulator` (``$ODO``
  lines on a pseudo-terminal) whose wheel geometry (wheel radius, ticks per revolution,
  track width, encoder signs) must match the daemon's ``[devices.odometry]``.
- **camera** (thread ``sim-camera``, ``fps``): at each frame time it takes the capture stamp,
  reads the head's present pan and tilt from the emulated servos at that instant, takes the
  true pose at that stamp (the base state whose interval covers it, moved along its arc),
  renders the stereo pair (:class:`drivers.sim.renderer.Renderer`, with the lighting and the
  scene changes) and publishes it on a ZeroMQ PUB socket
  (:mod:`drivers.sim.frame_transport`). Rendering has its own thread so the base and the
  emulators keep real time; a render slower than the frame period lowers the frame rate
  (``stats()`` reports the achieved rate).
- **camera faults** (:meth:`SimRobot.set_camera_fault`, thread-safe): ``stall`` (the camera
  renders and sends nothing, the socket stays bound), ``unplug`` (the PUB socket is closed:
  subscribers lose the connection; on the way back it is bound again at the same endpoint and
  its sequence numbers restart from 0, as a replugged camera's do) and ``malformed`` (each
  frame is replaced, with a probability, by a message that is not a valid frame).

Stamps are seconds since the Unix epoch, taken from one monotonic clock anchored at start.
Nothing here imports ``services``: the command (``services/commands/sim.py``) turns the
truth callback into ``truth`` messages.

Usage::

    robot = SimRobot(SimRobotConfig(width=80, height=60, fps=5), on_truth=print).start()
    robot.head_port, robot.odometry_port, robot.camera_endpoint
    robot.stop()
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zmq
from pydantic import BaseModel, ConfigDict, Field, field_validator

from drivers.interfaces import CameraIntrinsics
from drivers.odometry_protocol import arc_step
from drivers.sim.drive import DrivePlanner, PlannerConfig
from drivers.sim.dynamixel_emulator import DynamixelBusEmulator
from drivers.sim.frame_transport import FRAME_TOPIC, encode_frame
from drivers.sim.free_space import FreeSpace
from drivers.sim.goto import PATH_CLEARANCE_M, GotoPlan, plan_path
from drivers.sim.odometry_emulator import OdometryBoardEmulator
from drivers.sim.renderer import CameraModel, Renderer
from drivers.sim.wheel_noise import WheelOdometryNoise
from drivers.sim.world import World, load_world
from lino_loc.errors import LinoLocError

log = logging.getLogger("lino_loc.drivers.sim_robot")

#: Tilt angles are rendered on this grid (radians): the renderer caches its rays per tilt.
TILT_QUANTUM = 0.01

#: The simulated base's planner settings other than speed, turn rate and clearance: bounded
#: accelerations (m/s^2, rad/s^2) and an occasional pause at a goal, like a robot doing errands.
SIM_PLANNER = PlannerConfig(accel=0.5, angular_accel=2.0, pause_probability=0.3, max_pause_s=2.0)
#: Clearance of the planner's goal segments beyond the robot's radius, m.
GOAL_CLEARANCE = 0.11
#: The camera faults :meth:`SimRobot.set_camera_fault` takes.
CAMERA_FAULTS = ("stall", "unplug", "malformed")


class SimRobotConfig(BaseModel):
    """Everything the simulated robot needs; the odometry geometry must match the daemon's."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    world: str = Field("office", description="world name (config/worlds/<name>.json) or path")
    lighting: str = "tube"
    scene_changes: tuple[str, ...] = ()
    width: int = Field(320, ge=16, le=4096)
    height: int = Field(240, ge=16, le=4096)
    hfov_deg: float = Field(70.0, gt=1.0, lt=179.0)
    baseline_m: float = Field(0.075, gt=0.0)
    fps: float = Field(15.0, gt=0.0, le=120.0)
    noise: bool = Field(True, description="camera noise (gain-dependent shot and read noise)")
    seed: int = 0
    drive: bool = True
    speed: float = Field(0.3, ge=0.0, le=2.0, description="maximum linear speed, m/s")
    turn_rate: float = Field(0.8, gt=0.0, le=6.0, description="maximum turn rate, rad/s")
    start: tuple[float, float, float] | None = Field(
        None, description="initial pose; None: centre of the mapped area"
    )
    robot_radius: float = Field(0.25, gt=0.0, description="m; the base is a disc")
    rate_hz: float = Field(50.0, gt=0.0, le=1000.0, description="base kinematics and truth rate")
    wheel_radius: float = Field(0.05, gt=0.0)
    ticks_per_rev: float = Field(4096.0, gt=0.0)
    track_width: float = Field(0.30, gt=0.0)
    left_sign: int = 1
    right_sign: int = 1
    odometry_noise: WheelOdometryNoise = Field(
        default_factory=lambda: WheelOdometryNoise(wheel_base_error=0.0),
        description="what the encoders report of the true wheel travels; its wheel_base_error makes "
        "the true track width track_width / (1 + e), track_width staying the daemon's",
    )
    odometry_rate_hz: float = Field(50.0, gt=0.0)
    pan_id: int = Field(1, ge=0, le=252)
    tilt_id: int = Field(2, ge=0, le=252)
    head_link: str | None = Field(None, description="stable symlink to create for the head's pty")
    odometry_link: str | None = Field(None, description="stable symlink for the odometry pty")
    camera_endpoint: str = Field(
        "tcp://127.0.0.1:*", description='PUB bind address; port "*" = a free one'
    )
    camera_sndhwm: int = Field(
        2, ge=1, description="frames queued per slow subscriber, then dropped"
    )

    def planner_config(self) -> PlannerConfig:
        """:data:`SIM_PLANNER` with this robot's speed, turn rate and goal clearance."""
        return SIM_PLANNER.model_copy(
            update={"speed": self.speed, "turn_rate": self.turn_rate,
                    "clearance": self.robot_radius + GOAL_CLEARANCE}
        )

    @field_validator("left_sign", "right_sign")
    @classmethod
    def _sign(cls, v: int) -> int:
        if v not in (1, -1):
            raise ValueError("must be +1 or -1")
        return v


@dataclass(frozen=True)
class TruthSample:
    """The true state at one base tick: robot pose (map frame) and the head's present angles."""

    stamp: float
    seq: int
    x: float
    y: float
    theta: float
    pan: float
    tilt: float
    v: float
    omega: float

    @property
    def pose(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.theta)


@dataclass(frozen=True)
class FrameInfo:
    """What one published frame shows: the true robot pose and head angles at its stamp."""

    seq: int
    stamp: float
    pose: tuple[float, float, float]
    pan: float
    tilt: float
    render_s: float
    sent: bool
    left: np.ndarray


@dataclass(frozen=True)
class _BaseState:
    stamp: float
    pose: tuple[float, float, float]
    v: float
    omega: float


def integrate(
    pose: tuple[float, float, float], v: float, omega: float, dt: float
) -> tuple[float, float, float]:
    """Pose after ``dt`` s at constant (v, omega): the exact arc (odometry_protocol.arc_step)."""
    dx, dy, dth = arc_step((v - 0.5 * omega) * dt, (v + 0.5 * omega) * dt, 1.0)
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    t = th + dth
    return (x + c * dx - s * dy, y + s * dx + c * dy, math.atan2(math.sin(t), math.cos(t)))


def base_step(
    pose: tuple[float, float, float], plan: Any, free: FreeSpace, dt: float
) -> tuple[float, float, tuple[float, float, float], bool]:
    """One base tick: (v, omega) from ``plan`` (None: stand still; anything with
    ``command(pose, dt)`` and ``blocked()``), the pose ``dt`` later, and whether the step was
    blocked. A step that would end outside free space becomes a turn in place (a disc turning
    on the spot stays where it is), so the base never leaves free space."""
    v, omega = plan.command(pose, dt) if plan is not None else (0.0, 0.0)
    nxt = integrate(pose, v, omega, dt)
    if v != 0.0 and not free.free_point(nxt[0], nxt[1]):
        if plan is not None:
            plan.blocked()
        return 0.0, omega, integrate(pose, 0.0, omega, dt), True
    return v, omega, nxt, False


class SimRobot:
    """The simulated robot (see the module docstring). ``start()`` / ``stop()``."""

    def __init__(
        self,
        config: SimRobotConfig | None = None,
        *,
        world: World | None = None,
        on_truth: Callable[[TruthSample], None] | None = None,
        on_frame: Callable[[FrameInfo], None] | None = None,
        context: zmq.Context | None = None,
    ) -> None:
        self.config = c = config or SimRobotConfig()
        self.world = world if world is not None else load_world(c.world)
        self.world.check_lighting(c.lighting)
        self.scene_changes = self.world.check_changes(c.scene_changes)
        self.on_truth = on_truth
        self.on_frame = on_frame
        self.camera_model = CameraModel(
            width=c.width, height=c.height, hfov_deg=c.hfov_deg, baseline_m=c.baseline_m
        )
        fx, fy, cx, cy = self.camera_model.intrinsics()
        self.intrinsics = CameraIntrinsics(fx, fy, cx, cy, c.width, c.height)
        if c.start is not None:
            self._check_start(c.start, exact=True)
        # 1 cm beyond the radius: the arc between two checked end points stays clear
        self.free = FreeSpace(self.world, c.robot_radius + 0.01, self.scene_changes)
        start = c.start if c.start is not None else self._default_start()
        self._check_start(start, exact=False)
        self._start_pose = (
            float(start[0]),
            float(start[1]),
            math.atan2(math.sin(start[2]), math.cos(start[2])),
        )
        self.plan: Any = (
            DrivePlanner(self.world, c.planner_config(), np.random.default_rng(c.seed), self.scene_changes)
            if c.drive
            else None
        )
        self.renderer: Renderer | None = None
        self._wide_free: FreeSpace | None = None
        self.head = DynamixelBusEmulator((c.pan_id, c.tilt_id), link=c.head_link)
        self.odometry = OdometryBoardEmulator(
            link=c.odometry_link,
            rate_hz=c.odometry_rate_hz,
            wheel_radius=c.wheel_radius,
            ticks_per_rev=c.ticks_per_rev,
            track_width=c.track_width,
            seed=c.seed,
        )
        self._ctx = context
        self._own_ctx = context is None
        self._sock: zmq.Socket | None = None
        self.camera_endpoint = ""
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._cond = threading.Condition()
        self._history: collections.deque[_BaseState] = collections.deque(maxlen=128)
        self._truth: TruthSample | None = None
        self._clock: tuple[float, float] = (time.time(), time.monotonic())
        self._started = False
        self._emulators_started: list[object] = []
        # statistics
        self._stats_lock = threading.Lock()
        self._ticks = 0
        self._blocked = 0
        self._late_ticks = 0
        self._resyncs = 0
        self._frames = 0
        self._frames_unsent = 0
        self._render_times: collections.deque[float] = collections.deque(maxlen=500)
        self._frame_monos: collections.deque[float] = collections.deque(maxlen=100)
        self._callback_errors = 0
        self._camera_fault: dict[str, float] = {}  # kind -> fraction (1.0 for stall, unplug)
        self._fault_rng = np.random.default_rng((c.seed, 29))
        self._malformed_sent = 0
        self._camera_seq = 0

    # ---------------------------------------------------------------------------------------
    def _check_start(self, start: tuple[float, float, float], exact: bool) -> None:
        r = self.config.robot_radius
        ok = (
            bool(self.world.is_free(start[0], start[1], r, self.scene_changes))
            if exact
            else self.free.free_point(start[0], start[1])
        )
        if not ok:
            raise LinoLocError(
                f"start pose ({start[0]:g}, {start[1]:g}) is not free space for a robot of radius "
                f"{r:g} m (plus 1 cm) in world '{self.world.name}'"
            )

    def _default_start(self) -> tuple[float, float, float]:
        """The free point nearest to the centre of the mapped area, heading 0."""
        xmin, xmax, ymin, ymax = self.world.mapped_area
        cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
        if self.free.free_point(cx, cy):
            return (cx, cy, 0.0)
        xs, ys = np.meshgrid(
            np.arange(xmin, xmax, 0.05), np.arange(ymin, ymax, 0.05), indexing="ij"
        )
        ok = self.free.is_free(xs, ys)
        if not ok.any():
            raise LinoLocError(
                f"world '{self.world.name}': no free space in the mapped area for the robot"
            )
        d = np.where(ok, np.hypot(xs - cx, ys - cy), np.inf)
        i = np.unravel_index(int(np.argmin(d)), d.shape)
        return (float(xs[i]), float(ys[i]), 0.0)

    def stamp_now(self) -> float:
        """Now on the robot's clock (s since the epoch, monotonic)."""
        e0, m0 = self._clock
        return e0 + (time.monotonic() - m0)

    # lifecycle -----------------------------------------------------------------------------------
    @property
    def head_port(self) -> str:
        return self.head.port

    @property
    def odometry_port(self) -> str:
        return self.odometry.port

    @property
    def truth(self) -> TruthSample | None:
        """The latest true state (None before the first tick)."""
        return self._truth

    def start(self) -> SimRobot:
        """Render setup (bakes the lighting: seconds), emulators, PUB socket, threads."""
        if self._started:
            return self
        c = self.config
        try:
            self.renderer = Renderer(
                self.world, self.camera_model, c.lighting, self.scene_changes, seed=c.seed
            )
            for emu, link in ((self.head, c.head_link), (self.odometry, c.odometry_link)):
                try:
                    emu.start()
                except OSError as exc:
                    emu.stop()  # closes a pty opened before the link failed
                    raise LinoLocError(
                        f"cannot create the {type(emu).__name__} pseudo-terminal"
                        + (f" with link {link}" if link else "")
                        + f": {exc.strerror or exc}"
                    ) from None
                self._emulators_started.append(emu)
            if self._ctx is None:
                self._ctx = zmq.Context()
            self._sock = self._ctx.socket(zmq.PUB)
            self._sock.setsockopt(zmq.LINGER, 0)
            self._sock.setsockopt(zmq.SNDHWM, c.camera_sndhwm)
            self.camera_endpoint = bind(self._sock, c.camera_endpoint)
        except BaseException:
            self.stop()
            raise
        self._clock = (time.time(), time.monotonic())
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._run_base, name="sim-base", daemon=True),
            threading.Thread(target=self._run_camera, name="sim-camera", daemon=True),
        ]
        self._started = True
        for t in self._threads:
            t.start()
        log.info(
            "sim robot: world %s, lighting %s, changes [%s], start (%.2f, %.2f, %.2f), %s; head %s, "
            "odometry %s, camera %s (%dx%d @ %g fps)",
            self.world.name, c.lighting, ",".join(self.scene_changes), *self._start_pose,
            f"driving at up to {c.speed:g} m/s (seed {c.seed})" if c.drive else "standing still",
            self.head_port, self.odometry_port, self.camera_endpoint, c.width, c.height, c.fps,
        )  # fmt: skip
        return self

    def stop(self) -> None:
        """Stop the threads, close the socket, close the emulators (ptys and links go away)."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads = []
        if self._sock is not None:
            self._sock.close(0)
            self._sock = None
        if self._own_ctx and self._ctx is not None:
            self._ctx.term()
            self._ctx = None
        for emu in reversed(self._emulators_started):
            try:
                emu.stop()  # type: ignore[attr-defined]
            except Exception as exc:  # noqa: BLE001 - best effort at shutdown
                log.warning("sim robot: stopping %s failed: %s", type(emu).__name__, exc)
        self._emulators_started = []
        self._started = False

    def __enter__(self) -> SimRobot:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stats(self) -> dict[str, float | int]:
        """Counters and rates: base ticks, blocked steps, frames, achieved fps, render time."""
        with self._stats_lock:
            rt = sorted(self._render_times)
            fm = list(self._frame_monos)
            out: dict[str, float | int] = {
                "ticks": self._ticks,
                "blocked_steps": self._blocked,
                "late_ticks": self._late_ticks,
                "resyncs": self._resyncs,
                "frames": self._frames,
                "frames_unsent": self._frames_unsent,
                "callback_errors": self._callback_errors,
                "malformed_frames_sent": self._malformed_sent,
                "camera_faults": len(self._camera_fault),
            }
        out["fps"] = (len(fm) - 1) / (fm[-1] - fm[0]) if len(fm) > 2 and fm[-1] > fm[0] else 0.0
        out["render_ms_p50"] = 1000.0 * rt[len(rt) // 2] if rt else 0.0
        out["render_ms_p99"] = 1000.0 * rt[min(len(rt) - 1, int(0.99 * len(rt)))] if rt else 0.0
        return out

    # base ----------------------------------------------------------------------------------------
    def _head_angles(self) -> tuple[float, float]:
        c = self.config
        return self.head.position_rad(c.pan_id), self.head.position_rad(c.tilt_id)

    def _run_base(self) -> None:
        c = self.config
        dt = 1.0 / c.rate_hz
        e0, m0 = self._clock
        pose = self._start_pose
        k = 0
        t0 = m0
        # the true track; the daemon integrates with track_width (the wheel-base error)
        half_b = 0.5 * c.track_width / (1.0 + c.odometry_noise.wheel_base_error)
        # what the encoders see is not exactly what the base did (seeded: the same run per seed)
        encoders = c.odometry_noise.start(np.random.default_rng((c.seed, 17)))

        try:
            while not self._stop.is_set():
                target = t0 + k * dt
                now = time.monotonic()
                if now < target:
                    self._stop.wait(target - now)
                    continue
                # Late ticks are caught up (the odometry board kept counting meanwhile, so the
                # truth must cover that time too); only after a long stall (process suspended)
                # does the base skip ahead, and then truth and odometry part by that stall.
                if now - target > 5.0:
                    with self._stats_lock:
                        self._resyncs += 1
                    log.warning(
                        "sim robot: base %.2f s behind real time; skipping ahead", now - target
                    )
                    k = int((now - t0) / dt)
                    target = t0 + k * dt
                elif now - target > dt:
                    with self._stats_lock:
                        self._late_ticks += 1
                stamp = e0 + (target - m0)
                v, omega, nxt, blocked = base_step(pose, self.plan, self.free, dt)
                if blocked:
                    with self._stats_lock:
                        self._blocked += 1
                ml, mr = encoders.measure((v - omega * half_b) * dt, (v + omega * half_b) * dt)
                self.odometry.set_wheel_speeds(c.left_sign * ml / dt, c.right_sign * mr / dt)
                state = _BaseState(stamp, pose, v, omega)
                with self._cond:
                    self._history.append(state)
                    self._cond.notify_all()
                pan, tilt = self._head_angles()
                truth = TruthSample(stamp, k, pose[0], pose[1], pose[2], pan, tilt, v, omega)
                self._truth = truth
                with self._stats_lock:
                    self._ticks += 1
                if self.on_truth is not None:
                    try:
                        self.on_truth(truth)
                    except Exception:  # noqa: BLE001 - a consumer's bug must not stop the robot
                        with self._stats_lock:
                            self._callback_errors += 1
                        log.exception("sim robot: truth callback failed")
                pose = nxt
                k += 1
        finally:
            self.odometry.set_wheel_speeds(0.0, 0.0)

    def pose_at(self, stamp: float, wait: float = 0.05) -> tuple[float, float, float]:
        """The true robot pose at ``stamp`` (waits up to ``wait`` s for the base to get there)."""
        dt = 1.0 / self.config.rate_hz
        deadline = time.monotonic() + wait
        with self._cond:
            while True:
                hist = self._history
                if hist and hist[-1].stamp + dt > stamp:
                    break
                left = deadline - time.monotonic()
                if left <= 0 or self._stop.is_set():
                    break
                self._cond.wait(left)
            if not hist:
                return self._start_pose
            state = hist[0]
            for s in reversed(hist):
                if s.stamp <= stamp:
                    state = s
                    break
        return integrate(state.pose, state.v, state.omega, max(0.0, stamp - state.stamp))

    def goto(self, x: float, y: float, theta: float, speed: float | None = None) -> GotoPlan:
        """Send the base to the pose (x, y, theta) (map frame; m, rad) along a path through
        free space (:mod:`drivers.sim.goto`), replacing whatever it was doing (wandering, an
        earlier goal); it stands still once there. ``speed``: top speed (m/s; default the
        configuration's). LinoLocError (one line) when the goal is not free for the base or
        cannot be reached. Thread-safe."""
        truth = self._truth
        here = truth.pose if truth is not None else self._start_pose
        if self._wide_free is None:  # the path keeps a clearance beyond the base's disc
            self._wide_free = FreeSpace(self.world, self.free.radius + PATH_CLEARANCE_M, self.scene_changes)
        path = plan_path(self.free, (here[0], here[1]), (float(x), float(y)), wide=self._wide_free)
        v = self.config.speed if speed is None else float(speed)
        plan = GotoPlan(path, float(theta), speed=v if v > 0 else 0.3, turn_rate=self.config.turn_rate)
        self.plan = plan  # the base thread reads it at its next tick
        log.info("sim robot: goto (%.3f, %.3f, %.3f) over %d waypoints", x, y, theta, len(path))
        return plan

    def where(self) -> dict[str, Any]:
        """The true pose now and the goto's goal and state (``idle`` when no goal was sent;
        else ``driving``, ``arrived`` or ``blocked``)."""
        truth = self._truth
        pose = truth.pose if truth is not None else self._start_pose
        plan = self.plan
        out: dict[str, Any] = {
            "stamp": truth.stamp if truth is not None else self.stamp_now(),
            "pose": [float(v) for v in pose],
            "state": plan.state if isinstance(plan, GotoPlan) else ("wandering" if plan is not None else "idle"),
        }
        if isinstance(plan, GotoPlan):
            out["goal"] = list(plan.goal)
        return out

    def switch_lighting(self, lighting: str) -> None:
        """Switch the building's lights while running (a light switched on or off in a real
        building). Bakes the new lighting in the calling thread (seconds); the camera renders
        under the old light until the new renderer is ready, then every frame uses it."""
        self.world.check_lighting(lighting)
        renderer = Renderer(self.world, self.camera_model, lighting, self.scene_changes, seed=self.config.seed)
        self.renderer = renderer
        log.info("sim robot: lighting switched to %s", lighting)

    # camera --------------------------------------------------------------------------------------
    def set_camera_fault(self, kind: str, on: bool, fraction: float = 1.0) -> None:
        """Start (``on``) or end a camera fault: ``stall``, ``unplug`` or ``malformed`` (each
        frame replaced with probability ``fraction``). Raises ValueError on an unknown kind."""
        if kind not in CAMERA_FAULTS:
            raise ValueError(f"unknown camera fault {kind!r} (one of {', '.join(CAMERA_FAULTS)})")
        if not 0.0 < fraction <= 1.0:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}")
        with self._stats_lock:
            if on:
                self._camera_fault[kind] = fraction
            else:
                self._camera_fault.pop(kind, None)
        log.warning("sim robot: camera %s %s", kind, "on" if on else "off")

    def camera_faults(self) -> dict[str, float]:
        """The active camera faults and their fractions."""
        with self._stats_lock:
            return dict(self._camera_fault)

    def _camera_socket(self) -> zmq.Socket | None:
        """The PUB socket, closed while the camera is unplugged and bound again (same endpoint)
        when it is plugged back; None while unplugged or not yet bound again. Camera thread only."""
        with self._stats_lock:
            unplugged = "unplug" in self._camera_fault
        if unplugged:
            if self._sock is not None:
                self._sock.close(0)
                self._sock = None
            return None
        if self._sock is None and self._ctx is not None:
            sock = self._ctx.socket(zmq.PUB)
            sock.setsockopt(zmq.LINGER, 0)
            sock.setsockopt(zmq.SNDHWM, self.config.camera_sndhwm)
            try:
                sock.bind(self.camera_endpoint)
            except zmq.ZMQError as exc:  # the port not free yet: try again at the next frame
                sock.close(0)
                log.warning("sim robot: camera cannot bind %s again yet: %s", self.camera_endpoint, exc)
                return None
            self._sock = sock
            self._camera_seq = 0
            log.info("sim robot: camera plugged back in on %s", self.camera_endpoint)
        return self._sock

    def _camera_skip(self, sock: zmq.Socket | None) -> bool:
        """True when no frame is to be rendered now (stalled or unplugged); sends a malformed
        message instead of the frame when that fault draws it (and returns True)."""
        with self._stats_lock:
            fault = dict(self._camera_fault)
        if sock is None or "stall" in fault:
            return True
        p = fault.get("malformed", 0.0)
        if p and self._fault_rng.random() < p:
            with contextlib.suppress(zmq.ZMQError):
                sock.send_multipart([FRAME_TOPIC, b'{"v": 1, "seq": "not a frame"', b"", b""], zmq.NOBLOCK)
                self._malformed_sent += 1
            return True
        return False

    def _run_camera(self) -> None:
        c = self.config
        period = 1.0 / c.fps
        assert self.renderer is not None and self._sock is not None
        next_t = time.monotonic()
        self._camera_seq = 0
        while not self._stop.is_set():
            now = time.monotonic()
            if now < next_t:
                self._stop.wait(next_t - now)
                continue
            next_t += period
            if next_t < now:
                next_t = now + period  # rendering is slower than the frame rate
            sock = self._camera_socket()
            if self._camera_skip(sock):
                continue
            assert sock is not None
            seq = self._camera_seq
            stamp = self.stamp_now()
            pan, tilt = self._head_angles()
            pose = self.pose_at(stamp)
            tilt_q = round(tilt / TILT_QUANTUM) * TILT_QUANTUM
            renderer = self.renderer  # switch_lighting may have replaced it
            t_r = time.perf_counter()
            try:
                res = renderer.render(
                    pose[0], pose[1], pose[2], pan, tilt_q, stereo=True, noise=c.noise
                )
            except Exception:  # noqa: BLE001 - keep the robot alive; the daemon sees a frame gap
                log.exception("sim robot: render failed at (%.3f, %.3f, %.3f)", *pose)
                continue
            render_s = time.perf_counter() - t_r
            assert res.right is not None
            parts = encode_frame(seq, stamp, res.left, res.right, self.intrinsics, c.baseline_m)
            sent = True
            try:
                sock.send_multipart(parts, zmq.NOBLOCK, copy=False)
            except zmq.Again:
                sent = False
            except zmq.ZMQError as exc:
                if self._stop.is_set():
                    break
                log.warning("sim robot: frame not sent: %s", exc)
                sent = False
            with self._stats_lock:
                self._frames += 1
                self._frames_unsent += 0 if sent else 1
                self._render_times.append(render_s)
                self._frame_monos.append(time.monotonic())
            if self.on_frame is not None:
                try:
                    self.on_frame(FrameInfo(seq, stamp, pose, pan, tilt, render_s, sent, res.left))
                except Exception:  # noqa: BLE001
                    with self._stats_lock:
                        self._callback_errors += 1
                    log.exception("sim robot: frame callback failed")
            self._camera_seq = seq + 1


def bind(sock: zmq.Socket, endpoint: str) -> str:
    """Bind ``sock``; ``tcp://HOST:*`` (or ``tcp://HOST:0``) takes a free port. Returns the
    endpoint as bound (with the port). Raises LinoLocError naming the endpoint on failure."""
    try:
        if endpoint.startswith("tcp://") and endpoint.rsplit(":", 1)[-1] in ("*", "0"):
            host = endpoint[len("tcp://") :].rsplit(":", 1)[0]
            port = sock.bind_to_random_port(f"tcp://{host}")
            return f"tcp://{host}:{port}"
        sock.bind(endpoint)
    except zmq.ZMQError as exc:
        raise LinoLocError(f"cannot bind ZeroMQ endpoint {endpoint!r}: {exc}") from None
    last = sock.getsockopt(zmq.LAST_ENDPOINT)
    return last.decode() if isinstance(last, bytes) else str(last)

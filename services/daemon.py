"""The localization service: devices in, poses out, at frame rate (issue 5, design.md 4.4).

:class:`Daemon` ties together the appearance map, the :class:`lino_loc.localizer.Localizer`,
the three device threads (:mod:`services.device_threads`), the pose stream
(:mod:`services.publisher`), the control socket (:mod:`services.control`), the saved pose
(:mod:`services.persistence`), active vision (:mod:`lino_loc.active_vision`) and systemd
notifications (:mod:`services.sd_notify`).

Threads::

    camera worker   --newest frame--> FrameMailbox (one slot; a replaced frame is a drop)
    odometry worker --increments----> OdometryBuffer (stamped; composed between frames)
    head worker     --present pan---> HeadHistory (interpolated at a frame's stamp)
                    <--pan goal------ (latest goal wins; all bus traffic in that thread)
    control (REP)   --set_pose, global_localization--> CommandQueue --> run by the loop
    truth relay     (simulation) SUB truth of `lino-loc sim` --> PUB topic "truth"
    state saver     writes the last pose atomically (the loop never waits on the disk)
    main thread     THE LOOP (below); it alone touches the Localizer

The loop, per camera frame: the odometry accumulated since the previous frame, composed up
to this frame's stamp (the action u_t of eq. 5), the head's pan at the frame's stamp, the
left image (and the disparity map when the map has a disparity channel) go into one
``Localizer.update`` (eq. 2-8); the pose, stamped with the frame's time, is published on
``pose``; then active vision may choose the next pan angle (paper section 4). Between frames
it runs queued control commands, and on time: ``status`` (every ``publish.status_period_s``),
``WATCHDOG=1`` (at half of ``$WATCHDOG_USEC``; from this loop, so a hung loop stops pinging),
saving the pose (every ``persistence.save_period_s``). Without frames for a while (camera
failed) it predicts from odometry alone at the camera's rate (``dead_reckoning``: the
covariance grows with the motion) and the status says so.

Starting belief: the saved pose and covariance when there is one (as AMCL does), else global
localization. A frame taken while the head turns is used for prediction only (its pan is
uncertain and the image smeared on the real camera).

Usage::

    daemon = Daemon(cfg, amap, truth_endpoint=sim_info.truth)
    daemon.start()                 # binds sockets, starts threads; raises on bind errors
    signal.signal(signal.SIGTERM, lambda *_: daemon.request_stop())
    daemon.run()                   # the loop, until request_stop(); then shut down
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from drivers.interfaces import DeviceHealth, HealthState
from lino_loc import __version__
from lino_loc.errors import LinoLocError
from lino_loc.localizer import Localizer
from lino_loc.pose_estimate import Estimate
from services import sd_notify
from services.config import ServiceConfig
from services.control import CommandQueue, ControlServer
from services.device_threads import (
    CameraWorker,
    FrameMailbox,
    HeadHistory,
    HeadWorker,
    OdometryBuffer,
    OdometryWorker,
)
from services.messages import (
    AckReply,
    ActiveVisionInfo,
    ControlStateReply,
    DeviceHealthModel,
    GetPoseReply,
    LatencyStats,
    MapInfo,
    ParticlesMessage,
    PingReply,
    PoseMessage,
    SaveStateReply,
    StatusMessage,
    StatusReply,
    TruthMessage,
    error_reply,
)
from services.persistence import SavedState, load_state, save_state
from services.publisher import Publisher, RateLimiter

log = logging.getLogger("lino_loc.service")

#: Minimum standard deviations added to a restored covariance (the robot may have been
#: pushed while the daemon was down): 0.1 m, 0.05 rad.
RESTORE_MIN_STD = (0.1, 0.1, 0.05)

DeviceFactory = Callable[[], Any]


def _percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(np.asarray(values), q)) if values else None


def default_device_factories(cfg: ServiceConfig, disparity: bool) -> dict[str, DeviceFactory]:
    """Factories of the configured drivers (ports and endpoint already resolved)."""
    d = cfg.devices
    factories: dict[str, DeviceFactory] = {}
    if d.camera.kind == "sim":
        endpoint = d.camera.sim.endpoint

        def camera() -> Any:
            from drivers.sim.camera import SimStereoCamera

            return SimStereoCamera(endpoint, compute_disparity=disparity)
    else:
        oakd_cfg = d.camera.oakd

        def camera() -> Any:
            from drivers.oakd import OakdCamera

            return OakdCamera(oakd_cfg)

    factories["camera"] = camera
    if d.head.kind != "dynamixel":
        raise LinoLocError(
            'devices.head.kind = "sim" has no in-process head in `lino-loc run`; use kind = '
            '"dynamixel" with port = "auto" (the emulator of `lino-loc sim`)'
        )
    head_cfg = d.head.driver_config()

    def head() -> Any:
        from drivers.dynamixel_head import DynamixelHead

        return DynamixelHead(head_cfg)

    factories["head"] = head
    if d.odometry.kind != "serial":
        raise LinoLocError(
            'devices.odometry.kind = "sim" has no in-process odometry in `lino-loc run`; use '
            'kind = "serial" with port = "auto" (the emulator of `lino-loc sim`)'
        )
    odo_cfg = d.odometry.driver_config()

    def odometry() -> Any:
        from drivers.serial_odometry import SerialOdometry

        return SerialOdometry(odo_cfg)

    factories["odometry"] = odometry
    return factories


def make_active_policy(cfg: ServiceConfig, localizer: Localizer, head_limits: Any) -> Any:
    """The active-vision policy (:class:`lino_loc.active_vision.ActivePolicy`), or None when
    the module is missing. This is the seam between the service and the method."""
    try:
        from lino_loc.active_vision import ActionEvaluator, ActivePolicy
    except ImportError:  # pragma: no cover - the module exists in this tree
        log.warning("active vision: lino_loc.active_vision not available; head stays at pan 0")
        return None
    # The daemon switches active vision on and off itself (``av_enabled``, the control
    # socket's set_active_vision); the policy it calls must always decide.
    av = cfg.active_vision.model_copy(update={"enabled": True})
    model = localizer.sensor_model("intensity")
    limits = None
    if head_limits is not None:
        limits = (float(head_limits.pan_min), float(head_limits.pan_max))
    else:
        limits = (cfg.devices.head.pan_min, cfg.devices.head.pan_max)
    return ActivePolicy(ActionEvaluator(model, av), av, head_limits=limits)


class _Saver(threading.Thread):
    """Writes SavedStates handed to it (latest wins), off the loop's thread."""

    def __init__(self, path: Path) -> None:
        super().__init__(name="state-saver", daemon=True)
        self.path = path
        self._cond = threading.Condition()
        self._pending: SavedState | None = None
        self._closing = False
        self.saves = 0
        self.last_error: str | None = None

    def submit(self, state: SavedState) -> None:
        with self._cond:
            self._pending = state
            self._cond.notify()

    def run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None or self._closing)
                state, self._pending = self._pending, None
                if state is None and self._closing:
                    return
            if state is not None:
                self.write(state)

    def write(self, state: SavedState) -> bool:
        try:
            save_state(self.path, state)
            self.saves += 1
            self.last_error = None
            return True
        except OSError as exc:
            self.last_error = f"{self.path}: {exc.strerror or exc}"
            log.warning("cannot save the pose: %s", self.last_error)
            return False

    def stop(self) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify()
        if self.is_alive():
            self.join(2.0)


class Daemon:
    """The localization service (see the module docstring)."""

    def __init__(
        self,
        cfg: ServiceConfig,
        amap: Any,
        *,
        truth_endpoint: str | None = None,
        device_factories: dict[str, DeviceFactory] | None = None,
        notifier: sd_notify.Notifier | None = None,
        context: zmq.Context[Any] | None = None,
    ) -> None:
        self.cfg = cfg
        self.map = amap
        self.truth_endpoint = truth_endpoint if cfg.publish.truth else None
        self.has_disparity = "disparity" in getattr(amap, "channels", {})
        self.factories = device_factories or default_device_factories(cfg, self.has_disparity)
        self.notifier = notifier or sd_notify.Notifier()
        self._own_ctx = context is None
        self.ctx = context or zmq.Context()
        self.localizer = Localizer(amap, cfg.localizer)
        self.commands = CommandQueue()
        self.mailbox: FrameMailbox[Any] = FrameMailbox()
        self.odometry = OdometryBuffer()
        self.heads = HeadHistory()
        self.workers: dict[str, Any] = {}
        self.publisher: Publisher | None = None
        self.control: ControlServer | None = None
        self._truth_thread: threading.Thread | None = None
        self._saver = _Saver(cfg.persistence.state_file)
        self._stop = threading.Event()
        self._lock = threading.Lock()  # guards the snapshots and switches below
        self._started_mono = time.monotonic()
        self._started_wall = time.time()
        # snapshots for the control thread
        self._last_pose: PoseMessage | None = None
        self._last_estimate: Estimate | None = None
        self._last_status: StatusMessage | None = None
        # switches
        self.av_enabled = bool(cfg.active_vision.enabled)
        self.av_paused = False
        self.head_paused = False
        self.policy: Any = None
        self.restored: SavedState | None = None
        # counters
        self.seq = 0
        self.poses = 0
        self.truths = 0
        self.frames_used = 0
        self.frames_skipped = 0  # out of order
        self._appearance_changes_logged = 0
        self.frames_head_moving = 0
        self.av_commands = 0
        self.av_last_decision: str | None = None
        self.av_last_command: float | None = None
        self.dead_reckoning = False
        self._last_update_stamp: float | None = None
        self._last_frame_mono: float | None = None
        self._period_poses = 0
        self._period_frames = 0
        self._period_start = time.monotonic()
        self._latencies: collections.deque[float] = collections.deque(maxlen=10000)
        self._latency_stats = LatencyStats()
        self._rates = (0.0, 0.0)
        self._map_info = self._make_map_info()
        fps = cfg.devices.camera.sim.fps if cfg.simulated else cfg.devices.camera.oakd.fps
        self.frame_period = 1.0 / float(fps)
        self.camera_timeout = max(1.0, 5.0 * self.frame_period)
        self._rng = np.random.default_rng(0)

    # ------------------------------------------------------------------------- lifecycle
    def _make_map_info(self) -> MapInfo:
        checksum = None
        try:
            checksum = self.map.meta.sha256
        except Exception:  # noqa: BLE001 - a duck-typed map may have no header
            pass
        path = getattr(self.map, "path", None) or self.cfg.map.path
        return MapInfo(
            path=str(path),
            n_images=int(np.asarray(self.map.poses).shape[0]),
            channels=sorted(self.map.channels),
            checksum=checksum,
        )

    def start(self) -> None:
        """Bind the sockets, set the initial belief, start the threads. Raises OSError when
        an endpoint cannot be bound."""
        ep = self.cfg.endpoints
        self.publisher = Publisher(self.ctx, ep.pub, ep.sndhwm)
        try:
            self.control = ControlServer(self.ctx, ep.rep, self.handle_request)
        except OSError:
            self.publisher.close()
            raise
        self._initial_belief()
        self.workers["camera"] = CameraWorker(self.factories["camera"], self.mailbox)
        self.workers["odometry"] = OdometryWorker(self.factories["odometry"], self.odometry)
        head = HeadWorker(self.factories["head"], self.heads)
        head.command(0.0, 0.0)  # start looking ahead
        self.workers["head"] = head
        for w in self.workers.values():
            w.start()
        self.control.start()
        self._saver.start()
        if self.truth_endpoint:
            self._truth_thread = threading.Thread(target=self._relay_truth, name="truth-relay", daemon=True)
            self._truth_thread.start()
        if self.av_enabled:
            try:
                self.policy = make_active_policy(self.cfg, self.localizer, None)
            except (ValueError, LinoLocError) as exc:
                log.warning("active vision disabled: %s", exc)
                self.policy = None
        self.notifier.ready(self._status_line())
        log.info("serving: poses on %s, control on %s", ep.pub, ep.rep)

    def _initial_belief(self) -> None:
        p = self.cfg.persistence
        saved = load_state(p.state_file) if p.restore else None
        if saved is not None:
            cov = saved.cov().copy()
            floor = np.square(RESTORE_MIN_STD)
            cov[np.diag_indices(3)] = np.maximum(np.diag(cov), floor)
            self.localizer.set_pose(saved.mean(), cov)
            self.restored = saved
            log.info(
                "initial belief: the saved pose (%.2f, %.2f, %.2f) from %s",
                saved.pose.x, saved.pose.y, saved.pose.theta, p.state_file,
            )
        else:
            self.localizer.start_global()
            log.info("initial belief: global localization (no saved pose)")

    def request_stop(self) -> None:
        """Ask the loop to end (safe from signal handlers and other threads)."""
        self._stop.set()
        self.mailbox.wake()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def shutdown(self) -> None:
        """Stop the threads, save the pose, close devices and sockets (idempotent)."""
        self.notifier.stopping("stopping")
        if self.control is not None:
            self.control.stop()
        self.commands.run_pending()
        for w in self.workers.values():
            w.stop()
        self._save(sync=True)
        self._saver.stop()
        if self._truth_thread is not None:
            self._truth_thread.join(2.0)
        if self.publisher is not None:
            self.publisher.close()
        if self._own_ctx:
            self.ctx.term()
        self.notifier.close()
        log.info("stopped")

    # ------------------------------------------------------------------------- the loop
    def run(self) -> int:
        """The loop (call :meth:`start` first); returns 0 after a clean shutdown."""
        wd_period = sd_notify.watchdog_period()
        next_wd = time.monotonic()
        status_every = RateLimiter.every(self.cfg.publish.status_period_s)
        save_every = RateLimiter.every(self.cfg.persistence.save_period_s)
        save_every.ready(time.monotonic())  # first save one period from now
        try:
            while not self._stop.is_set():
                self.commands.run_pending()
                frame = self.mailbox.get(timeout=0.05)
                mono = time.monotonic()
                if frame is not None:
                    self._last_frame_mono = mono
                    self._on_frame(frame)
                else:
                    self._maybe_dead_reckon(mono)
                if wd_period is not None and mono >= next_wd:
                    self.notifier.watchdog()
                    next_wd = mono + wd_period
                if status_every.ready(mono):
                    self._publish_status()
                if save_every.ready(mono):
                    self._save(sync=False)
        finally:
            self.shutdown()
        return 0

    def _on_frame(self, frame: Any) -> None:
        stamp = float(frame.stamp)
        if self._last_update_stamp is not None and stamp <= self._last_update_stamp:
            self.frames_skipped += 1
            return
        delta, _ = self.odometry.take_until(stamp)
        pan, moving = self.heads.pan_at(stamp)
        settle = self.cfg.active_vision.settle_s
        last_motion = self.heads.last_motion
        turning = moving or (last_motion is not None and 0.0 <= stamp - last_motion < settle)
        image = None if turning else frame.left
        disparity = frame.disparity if (self.has_disparity and not turning) else None
        if turning:
            self.frames_head_moving += 1
        else:
            self.frames_used += 1
        est = self.localizer.update(delta, pan, image, disparity, stamp=stamp)
        self._note_appearance_change()
        self._last_update_stamp = stamp
        if self.dead_reckoning:
            log.info("camera frames again: localizing with images")
        self.dead_reckoning = False
        self._publish_pose(est, stamp, pan)
        self._period_frames += 1
        self._active_vision(est, stamp)

    def appearance_changes(self) -> int:
        return self.localizer.appearance_changes

    def _note_appearance_change(self) -> None:
        n = self.appearance_changes()
        if n > self._appearance_changes_logged:
            self._appearance_changes_logged = n
            log.info("the views became less familiar all at once (lights switched?): the filter "
                     "relearns what they look like (appearance change %d)", n)

    def _maybe_dead_reckon(self, mono: float) -> None:
        since = self._last_frame_mono if self._last_frame_mono is not None else self._started_mono
        if mono - since < self.camera_timeout:
            return
        now = time.time()
        if self._last_update_stamp is not None and now - self._last_update_stamp < self.frame_period:
            return
        if not self.dead_reckoning:
            log.warning(
                "no camera frame for %.1f s: dead reckoning from odometry (covariance grows)",
                mono - since,
            )
        self.dead_reckoning = True
        delta, _ = self.odometry.take_until(now)
        est = self.localizer.predict_only(delta, stamp=now)
        self._last_update_stamp = now
        self._publish_pose(est, now, None)

    def _publish_pose(self, est: Estimate, stamp: float, pan: float | None) -> None:
        assert self.publisher is not None
        self.seq += 1
        try:
            msg = PoseMessage.from_estimate(
                est, stamp=stamp, seq=self.seq, pan=pan, dead_reckoning=self.dead_reckoning
            )
        except ValueError as exc:
            log.warning("pose not published (invalid estimate): %s", exc)
            return
        self.publisher.publish("pose", msg)
        latency = max(0.0, (time.time() - stamp) * 1000.0)
        with self._lock:
            self._last_pose = msg
            self._last_estimate = est
            self._latencies.append(latency)
        self.poses += 1
        self._period_poses += 1
        self._maybe_publish_particles(stamp)

    def _maybe_publish_particles(self, stamp: float) -> None:
        assert self.publisher is not None
        pc = self.cfg.publish
        limiter = getattr(self, "_particle_limiter", None)
        if limiter is None:
            limiter = self._particle_limiter = RateLimiter(pc.particles_max_rate_hz)
        if not limiter.ready(time.monotonic()) or not self.publisher.wanted("particles"):
            return
        p, w = self.localizer.particles()
        n = p.shape[0]
        if n > pc.particles_max_count:
            idx = self._rng.choice(n, size=pc.particles_max_count, replace=False)
            p, w = p[idx], w[idx]
        total = float(w.sum())
        w = w / total if total > 0 else np.full(len(w), 1.0 / max(len(w), 1))
        msg = ParticlesMessage(
            stamp=stamp,
            seq=self.seq,
            poses=[tuple(float(v) for v in row) for row in p],
            weights=[float(v) for v in w],
            n_total=n,
        )
        self.publisher.publish("particles", msg)

    def _active_vision(self, est: Estimate, stamp: float) -> None:
        with self._lock:
            active = self.av_enabled and not self.av_paused and not self.head_paused
        if not active or self.policy is None:
            return
        head = self.workers.get("head")
        state = self.heads.latest()
        if head is None or state is None:
            return
        particles, log_weights = self.localizer.belief()
        try:
            d = self.policy.decide(
                particles,
                log_weights,
                state=est.state,
                log_likelihood=est.log_likelihood,
                pan=state.pan,
                moving=state.moving,
                now=time.time(),
                frame_stamp=stamp,
                doubt=est.doubt,
            )
        except Exception as exc:  # noqa: BLE001 - active vision must not stop localization
            log.warning("active vision failed: %s: %s", type(exc).__name__, exc)
            return
        with self._lock:
            self.av_last_decision = d.reason
            if d.command is not None:
                self.av_commands += 1
                self.av_last_command = float(d.command)
        if d.command is not None:
            log.debug("active vision: pan -> %.2f rad", d.command)
            head.command(float(d.command), 0.0)

    # ------------------------------------------------------------------------- status
    def device_health(self) -> dict[str, DeviceHealth]:
        out = {}
        for name in ("camera", "head", "odometry"):
            w = self.workers.get(name)
            out[name] = (
                w.health()
                if w is not None
                else DeviceHealth(HealthState.FAILED, f"{name}: not started")
            )
        return out

    def dropped_frames(self) -> int:
        n = self.mailbox.dropped
        cam = self.workers.get("camera")
        if cam is not None:
            c = cam.health().counters
            n += int(c.get("dropped", 0)) + int(c.get("frames_dropped", 0))
        return n

    def _state(self) -> str:
        with self._lock:
            est = self._last_estimate
        return "starting" if est is None else est.state

    def build_status(self) -> StatusMessage:
        health = self.device_health()
        av = self._av_info()
        with self._lock:
            latency = self._latency_stats
            pose_rate, frame_rate = self._rates
        return StatusMessage(
            stamp=time.time(),
            state=self._state(),  # type: ignore[arg-type]
            pose_rate_hz=pose_rate,
            frame_rate_hz=frame_rate,
            frames=self.mailbox.received,
            dropped_frames=self.dropped_frames(),
            out_of_order_frames=self.frames_skipped,
            appearance_changes=self.appearance_changes(),
            latency_ms=latency,
            devices={k: DeviceHealthModel.from_health(h) for k, h in health.items()},
            uptime_s=time.monotonic() - self._started_mono,
            map=self._map_info,
            active_vision=av,
            simulated=self.cfg.simulated,
            version=__version__,
        )

    def _publish_status(self) -> None:
        mono = time.monotonic()
        dt = max(mono - self._period_start, 1e-6)
        with self._lock:
            lat = list(self._latencies)
            self._latencies.clear()
            self._rates = (self._period_poses / dt, self._period_frames / dt)
            if lat:
                self._latency_stats = LatencyStats(p50=_percentile(lat, 50), p99=_percentile(lat, 99))
        self._period_poses = self._period_frames = 0
        self._period_start = mono
        msg = self.build_status()
        with self._lock:
            self._last_status = msg
        assert self.publisher is not None
        self.publisher.publish("status", msg)
        self.notifier.status(self._status_line(msg))

    def _status_line(self, msg: StatusMessage | None = None) -> str:
        if msg is None:
            return f"serving on {self.cfg.endpoints.pub}: starting"
        bad = [f"{k} {v.state}" for k, v in msg.devices.items() if v.state != "ok"]
        text = f"{msg.state} at {msg.pose_rate_hz:.1f} Hz, {msg.dropped_frames} frames dropped"
        if self.dead_reckoning:
            text += ", DEAD RECKONING (no camera)"
        if bad:
            text += "; " + ", ".join(bad)
        return text

    # ------------------------------------------------------------------------- persistence
    def _saved_state(self) -> SavedState | None:
        with self._lock:
            est = self._last_estimate
        if est is None or est.state != "tracking":
            return None
        return SavedState.from_estimate(
            est.pose, est.covariance, est.stamp or time.time(), est.state, self._map_info.checksum
        )

    def _save(self, sync: bool) -> SavedState | None:
        state = self._saved_state()
        if state is None:
            return None
        if sync:
            return state if self._saver.write(state) else None
        self._saver.submit(state)
        return state

    # ------------------------------------------------------------------------- truth relay
    def _relay_truth(self) -> None:
        assert self.truth_endpoint is not None and self.publisher is not None
        sock = self.ctx.socket(zmq.SUB)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVHWM, 10)
        sock.setsockopt(zmq.SUBSCRIBE, b"truth")
        try:
            sock.connect(self.truth_endpoint)
            while not self._stop.is_set():
                if not sock.poll(200):
                    continue
                frames = sock.recv_multipart()
                if len(frames) != 2 or frames[0] != b"truth":
                    continue
                try:
                    TruthMessage.model_validate_json(frames[1])
                except ValueError:
                    continue
                self.publisher.send_frames([b"truth", frames[1]], "truth")
                self.truths += 1
        except zmq.ZMQError as exc:
            if not self._stop.is_set():
                log.warning("truth relay stopped: %s", exc)
        finally:
            sock.close(linger=0)

    # ------------------------------------------------------------------------- control
    def handle_request(self, req: Any) -> Any:
        """The reply to one parsed control request (called in the control thread)."""
        cmd = req.cmd
        if cmd == "ping":
            return PingReply(stamp=time.time(), version=__version__)
        if cmd == "status":
            return StatusReply(status=self.build_status())
        if cmd == "get_pose":
            with self._lock:
                return GetPoseReply(pose=self._last_pose)
        if cmd == "set_pose":
            mean = np.array(req.pose.as_tuple(), dtype=np.float64)
            cov = np.asarray(req.covariance, dtype=np.float64).reshape(3, 3)
            self.commands.call(lambda: self.localizer.set_pose(mean, cov))
            log.info("set_pose (%.2f, %.2f, %.2f) from the control socket", *mean)
            return AckReply(cmd="set_pose", message=f"belief set around ({mean[0]:.3f}, {mean[1]:.3f}, {mean[2]:.3f})")
        if cmd == "global_localization":
            self.commands.call(self.localizer.start_global)
            log.info("global localization requested on the control socket")
            return AckReply(cmd="global_localization", message="belief spread over the map")
        if cmd in ("pause", "resume"):
            with self._lock:
                value = cmd == "pause"
                if req.target == "head":
                    self.head_paused = value
                else:
                    self.av_paused = value
            return ControlStateReply(cmd=cmd, active_vision=self._av_info())
        if cmd == "set_active_vision":
            with self._lock:
                self.av_enabled = bool(req.enabled)
                head_paused = self.head_paused
            if req.enabled and self.policy is None:
                self.commands.call(self._enable_policy)
            if not req.enabled and not head_paused and "head" in self.workers:
                self.workers["head"].command(0.0, 0.0)  # look ahead again
            return ControlStateReply(cmd=cmd, active_vision=self._av_info())
        if cmd == "save_state":
            state = self._saved_state()
            if state is None:
                return error_reply(
                    f"save_state: no converged pose to save yet (state {self._state()})", cmd=cmd
                )
            if not self._saver.write(state):
                return error_reply(f"save_state: {self._saver.last_error}", cmd=cmd)
            return SaveStateReply(path=str(self.cfg.persistence.state_file), stamp=state.saved_at)
        return error_reply(f"cmd: {cmd!r} is not handled by this daemon", cmd=cmd)

    def _enable_policy(self) -> None:
        try:
            self.policy = make_active_policy(self.cfg, self.localizer, None)
        except (ValueError, LinoLocError) as exc:
            log.warning("active vision unavailable: %s", exc)

    def _av_info(self) -> ActiveVisionInfo:
        with self._lock:
            return ActiveVisionInfo(
                enabled=self.av_enabled, paused=self.av_paused, head_paused=self.head_paused,
                head_commands=self.av_commands, last_decision=self.av_last_decision,
                last_command_rad=self.av_last_command, frames_head_moving=self.frames_head_moving,
            )

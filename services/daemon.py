"""The localization service: devices in, poses out, at frame rate.

:class:`Daemon` owns the start, the loop and the shutdown; each concern around the loop is
an object of its own:

- the :class:`lino_loc.localizer.Localizer` (the only door to the filter);
- the three device threads (:mod:`services.device_threads`);
- pose and particle publishing (:class:`services.publisher.PosePublisher`);
- status reporting: rates, latency, the status message (:mod:`services.status`);
- the control socket and its handlers (:mod:`services.control`);
- active vision and the head-settle rule (:mod:`services.active_head`);
- the saved pose (:mod:`services.persistence`);
- the simulation-only truth relay (:mod:`services.truth_relay`);
- the session's recording (:mod:`services.recording.recorder`: the loop, the odometry, head
  and truth threads hand it what they get and what the Localizer was given, never waiting);
- the live view (:mod:`services.recording.live_view`: a Foxglove WebSocket server; the loop
  and the truth thread hand it what they publish, only while a client watches, never waiting);
- systemd notifications (:mod:`services.sd_notify`).

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
``pose``; then active vision may choose the next pan angle (paper section 4). A frame not
newer than the last one used is skipped. A frame taken while the head turns or settles
(:class:`lino_loc.active_vision.HeadSettle`) is used for prediction only: its pan is
uncertain and the image smeared on the real camera. Between frames the loop runs queued
control commands, and on time: ``status`` (every :data:`services.status.STATUS_PERIOD_S`), ``WATCHDOG=1``
(at half of ``$WATCHDOG_USEC``; from this loop, so a hung loop stops pinging), saving the
pose (every ``persistence.save_period_s``). Without frames for a while (:class:`CameraWatch`:
the camera failed) it predicts from odometry alone at the camera's rate (``dead_reckoning``:
the covariance grows with the motion) and the status says so. An exception in one frame's
work (the update, publishing, active vision) never ends the loop: it is logged (its
traceback once, then rate-limited), counted in ``status`` (``update_errors``) and the frame
is skipped; after :data:`RESET_AFTER_FAILED_UPDATES` failures in a row the belief restarts as
global localization.

Starting belief: the saved pose and covariance when the checks of
:func:`services.persistence.refusal` pass (the same map, recent, inside the map, a sane
covariance, saved while tracking, and barely moved since by the odometry board's counters:
the odometry worker starts first and the start waits up to :data:`ODOMETRY_WAIT_S` for
them), its standard deviations raised to at least
:func:`restore_min_std` of its age, as a belief the views must confirm (state ``global``
until they do); else global localization, with the refusal's reason in the log. Temporary
files of an interrupted save are removed first.

Usage::

    daemon = Daemon(cfg, amap, truth_endpoint=sim_info.truth)
    daemon.start()                 # binds sockets, starts threads; raises on bind errors
    signal.signal(signal.SIGTERM, lambda *_: daemon.request_stop())
    daemon.run()                   # the loop, until request_stop(); then shut down
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypedDict

import numpy as np
import zmq

from drivers.interfaces import BoardCounters, Odometry, PanTiltHead, StereoCamera, StereoFrame
from lino_loc.atomic_file import remove_stale_temps
from lino_loc.errors import LinoLocError
from lino_loc.localizer import Localizer
from lino_loc.pose_estimate import Estimate
from services import sd_notify
from services.active_head import ActiveHead
from services.config import ServiceConfig
from services.control import CommandQueue, ControlHandlers, ControlServer
from services.device_threads import (
    CameraFactory,
    CameraWorker,
    DeviceWorker,
    FrameMailbox,
    HeadFactory,
    HeadHistory,
    HeadWorker,
    OdometryBuffer,
    OdometryFactory,
    OdometryWorker,
)
from services.map_refresh import MapRefreshWriter
from services.messages import PersistenceInfo, PosePortInfo
from services.persistence import (
    RestoreContext,
    SavedState,
    StateSaver,
    board_motion,
    load_state,
    refusal,
)
from services.publisher import AnyPublisher, PosePublisher, RateLimiter, open_publisher
from services.recording.live_view import LiveView
from services.recording.recorder import Recorder, tap
from services.status import STATUS_PERIOD_S, StatusReporter, StatusSources, map_info, status_line
from services.truth_relay import TruthRelay

log = logging.getLogger("lino_loc.service")

#: Minimum standard deviations of a restored covariance (the robot may have been pushed
#: while the daemon was down): 0.1 m, 0.1 m, 0.05 rad, growing with the saved state's age
#: (the time since the save: up to ``persistence.save_period_s`` after a kill -9, plus the
#: downtime) by :data:`RESTORE_DRIFT_PER_S`, a base driving on at a typical top speed
#: (0.3 m/s, the simulated base's; 0.1 rad/s of turning), up to :data:`RESTORE_MAX_STD`.
#: (The odometry board's counters refuse a state whose robot moved more than "barely",
#: ``services.persistence.board_motion``; the spread still grows with the time, since they
#: see net wheel travel only and may be unknown.) After more than ~1.5 s the position spread
#: exceeds ``filter.estimate.converged_std_xy`` (0.5 m): the views must concentrate the
#: belief again before they confirm it (the restart table, benchmarks/restart_table.py, in
#: docs/results.md).
RESTORE_MIN_STD = (0.1, 0.1, 0.05)
RESTORE_DRIFT_PER_S = (0.3, 0.3, 0.1)  # m/s, m/s, rad/s
RESTORE_MAX_STD = (1.0, 1.0, 0.5)
#: s the start waits for the odometry board's first counters when a saved state has counters
#: to compare them with (the board sends 50 lines a second; the serial port opens in ms).
ODOMETRY_WAIT_S = 2.0


def restore_min_std(age_s: float) -> np.ndarray:
    """Floor of a restored pose's standard deviations (x, y, theta) for a state ``age_s``
    seconds old: min(RESTORE_MIN_STD + RESTORE_DRIFT_PER_S * age, RESTORE_MAX_STD)."""
    age = max(0.0, float(age_s))
    grown = np.asarray(RESTORE_MIN_STD) + np.asarray(RESTORE_DRIFT_PER_S) * age
    return np.minimum(grown, np.asarray(RESTORE_MAX_STD))

#: Frame periods without a frame before the loop dead-reckons (at least 1 s).
CAMERA_TIMEOUT_PERIODS = 5.0

#: Updates in a row that raised after which the belief is spread over the map again
#: (``start_global``): a belief that makes every update fail would otherwise never recover.
RESET_AFTER_FAILED_UPDATES = 5

class DeviceFactories(TypedDict):
    """How the daemon makes its three drivers (each worker calls its factory again after a
    failure, see ``services.device_threads``)."""

    camera: CameraFactory
    head: HeadFactory
    odometry: OdometryFactory


def default_device_factories(cfg: ServiceConfig, disparity: bool) -> DeviceFactories:
    """Factories of the configured drivers (ports and endpoint already resolved)."""
    d = cfg.devices
    camera: CameraFactory
    if d.camera.kind == "sim":
        endpoint = d.camera.sim.endpoint

        def camera() -> StereoCamera:
            from drivers.sim.camera import SimStereoCamera

            return SimStereoCamera(endpoint, compute_disparity=disparity)
    else:
        oakd_cfg = d.camera.oakd

        def camera() -> StereoCamera:
            from drivers.oakd import OakdCamera

            return OakdCamera(oakd_cfg)

    if d.head.kind != "dynamixel":
        raise LinoLocError(
            'devices.head.kind = "sim" has no in-process head in `lino-loc run`; use kind = '
            '"dynamixel" with port = "auto" (the emulator of `lino-loc sim`)'
        )
    head_cfg = d.head.driver_config()

    def head() -> PanTiltHead:
        from drivers.dynamixel_head import DynamixelHead

        return DynamixelHead(head_cfg)

    if d.odometry.kind != "serial":
        raise LinoLocError(
            'devices.odometry.kind = "sim" has no in-process odometry in `lino-loc run`; use '
            'kind = "serial" with port = "auto" (the emulator of `lino-loc sim`)'
        )
    odo_cfg = d.odometry.driver_config()

    def odometry() -> Odometry:
        from drivers.serial_odometry import SerialOdometry

        return SerialOdometry(odo_cfg)

    return DeviceFactories(camera=camera, head=head, odometry=odometry)


@dataclass
class CameraWatch:
    """When the loop predicts from odometry alone (dead reckoning).

    ``due(mono, now)``: no frame for ``timeout`` s (monotonic clock, counted from ``started``
    before the first frame) and at least one camera ``period`` since the last update (wall
    clock, the stamps' clock). ``fresh(stamp)``: a frame newer than the last update."""

    period: float
    timeout: float
    started: float
    last_frame_mono: float | None = None
    last_update_stamp: float | None = None
    dead_reckoning: bool = False

    @classmethod
    def for_fps(cls, fps: float, started: float) -> CameraWatch:
        period = 1.0 / float(fps)
        return cls(period, max(1.0, CAMERA_TIMEOUT_PERIODS * period), started)

    def fresh(self, stamp: float) -> bool:
        return self.last_update_stamp is None or stamp > self.last_update_stamp

    def silent_for(self, mono: float) -> float:
        since = self.last_frame_mono if self.last_frame_mono is not None else self.started
        return mono - since

    def due(self, mono: float, now: float) -> bool:
        if self.silent_for(mono) < self.timeout:
            return False
        return self.last_update_stamp is None or now - self.last_update_stamp >= self.period


class Daemon:
    """The localization service (see the module docstring)."""

    def __init__(
        self,
        cfg: ServiceConfig,
        amap: Any,
        *,
        truth_endpoint: str | None = None,
        device_factories: DeviceFactories | None = None,
        notifier: sd_notify.Notifier | None = None,
        context: zmq.Context[Any] | None = None,
        recorder: Recorder | None = None,
        live_view: LiveView | None = None,
    ) -> None:
        self.cfg = cfg
        self.recorder = recorder or Recorder.off()
        self.live = live_view or LiveView.off()
        self.truth_endpoint = truth_endpoint if cfg.publish.truth else None
        self.has_disparity = "disparity" in getattr(amap, "channels", {})
        factories = device_factories or default_device_factories(cfg, self.has_disparity)
        self.notifier = notifier or sd_notify.Notifier()
        self._own_ctx = context is None
        self.ctx = context or zmq.Context()
        self.localizer = Localizer(amap, cfg.localizer)
        self.commands = CommandQueue()
        self.mailbox: FrameMailbox[StereoFrame] = FrameMailbox()
        self.odometry = OdometryBuffer()
        self.heads = HeadHistory()
        if self.recorder.enabled:
            self.odometry.listener, self.heads.listener = self.recorder.odometry, self.recorder.head
        head_worker = HeadWorker(factories["head"], self.heads)
        head_worker.command(0.0, 0.0)  # start looking ahead (sent once its thread runs)
        self.workers: dict[str, DeviceWorker[Any]] = {
            "camera": CameraWorker(factories["camera"], self.mailbox),
            "odometry": OdometryWorker(factories["odometry"], self.odometry),
            "head": head_worker,
        }
        head = cfg.devices.head
        self.active = ActiveHead(
            cfg.active_vision, (head.pan_min, head.pan_max), self.localizer, self.heads, head_worker
        )
        self.saver = StateSaver(cfg.persistence.state_file, lambda: self.odometry.counters)
        self.publisher: AnyPublisher | None = None
        self.poses: PosePublisher | None = None
        self.control: ControlServer | None = None
        self.truth: TruthRelay | None = None
        self._stop = threading.Event()
        self._failed_in_a_row = 0
        self.watch = CameraWatch.for_fps(
            cfg.devices.camera.sim.fps if cfg.simulated else cfg.devices.camera.oakd.fps,
            time.monotonic(),
        )
        self.status = StatusReporter(
            self.mailbox, self.workers, map_info(amap, cfg.map.path), simulated=cfg.simulated,
            sources=StatusSources(self._state, lambda: self.localizer.appearance_changes,
                                  self.active.info, self._persistence_info, self._pose_port_info,
                                  lambda: self.control.refused_handshakes if self.control else 0,
                                  self.recorder.info, self.live.info, lambda: self.localizer.standing_matches,
                                  lambda: self.localizer.standing_relocations),
        )
        self.initial_belief: str | None = None  # how the belief started (status)
        self.refresh = MapRefreshWriter.for_map(cfg.map_refresh, amap)

    # ------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        """Bind the sockets, set the initial belief, start the threads. Raises OSError when
        an endpoint cannot be bound."""
        ep = self.cfg.endpoints
        self.publisher = open_publisher(self.ctx, ep)
        self.poses = PosePublisher(self.publisher, self.cfg.publish, self.localizer.particles)
        handlers = ControlHandlers(
            self.commands, tap(self.localizer, self.recorder, "control"), self.poses, self.status,
            self.active, self.saver, self.status.map_info.checksum,
        )
        try:
            self.control = ControlServer(self.ctx, ep.rep, handlers, ep.curve)
        except OSError:
            self.publisher.close()
            raise
        self._remove_leftovers()
        self.recorder.start()
        self.live.start()  # a port in use is logged and in the status: the daemon goes on
        self.refresh.start()
        self.workers["odometry"].start()  # its counters may decide the initial belief
        self._initial_belief()
        for name, w in self.workers.items():
            if name != "odometry":
                w.start()
        self.control.start()
        self.saver.start()
        if self.truth_endpoint:
            self.truth = TruthRelay(self.ctx, self.truth_endpoint, self.publisher, self._truth_tap())
            self.truth.start()
        self.active.start()
        self.notifier.ready(status_line(None, ep.pub, False))
        log.info("serving: poses on %s, control on %s", ep.pub, ep.rep)

    def _truth_tap(self) -> Callable[[bytes], None] | None:
        """Who gets the relayed truth besides the PUB socket: the recorder, the live view."""
        taps = [t for t, on in ((self.recorder.truth, self.recorder.enabled),
                                (self.live.truth, self.live.enabled)) if on]
        if len(taps) < 2:
            return taps[0] if taps else None

        def both(data: bytes) -> None:
            for t in taps:
                t(data)

        return both

    def _remove_leftovers(self) -> None:
        """Temporary files an interrupted save left next to the state file (kill -9 between
        writing and renaming), by :func:`lino_loc.atomic_file.remove_stale_temps`'s pattern."""
        removed = remove_stale_temps(self.cfg.persistence.state_file)
        if removed:
            log.info("removed %d temporary file(s) of an interrupted save next to %s",
                     len(removed), self.cfg.persistence.state_file)  # fmt: skip

    def _initial_belief(self) -> None:
        """The saved pose when :func:`services.persistence.refusal` finds nothing against it,
        as an UNCONFIRMED belief (``global`` until the views confirm it), its standard
        deviations raised to :func:`restore_min_std` of its age; else global localization,
        the reason logged in one line."""
        p = self.cfg.persistence
        belief = tap(self.localizer, self.recorder, "start")
        saved = load_state(p.state_file) if p.restore else None
        if saved is None:
            belief.start_global()
            self.initial_belief = "global localization: " + (
                "no saved pose" if p.restore else "persistence.restore = false")
            log.info("initial belief: %s", self.initial_belief)
            return
        b = self.localizer.bounds
        counters = self._board_counters(saved)
        now = time.time()
        why = refusal(saved, RestoreContext(
            now, self.status.map_info.checksum, (b.x_min, b.x_max, b.y_min, b.y_max), p.max_age_s,
            counters,
        ))  # fmt: skip
        if why is not None:
            belief.start_global()
            self.initial_belief = f"global localization: the saved pose was refused: {why}"
            log.warning("initial belief: global localization; saved pose in %s refused: %s",
                        p.state_file, why)  # fmt: skip
            return
        age = max(0.0, now - saved.stamp)
        cov = saved.cov().copy()
        cov[np.diag_indices(3)] = np.maximum(np.diag(cov), np.square(restore_min_std(age)))
        belief.set_pose(saved.mean(), cov, confirmed=False)
        self.initial_belief = (
            f"the saved pose ({saved.pose.x:.2f}, {saved.pose.y:.2f}, {saved.pose.theta:.2f}), "
            f"{age:.0f} s old, to be confirmed by the views; {board_motion(saved, counters).note}"
        )
        log.info("initial belief: %s from %s", self.initial_belief, p.state_file)

    def _board_counters(self, saved: SavedState) -> BoardCounters | None:
        """The odometry board's counters now, waiting up to :data:`ODOMETRY_WAIT_S` for the
        first when ``saved`` has counters to compare them with (None: none came)."""
        deadline = time.monotonic() + (ODOMETRY_WAIT_S if saved.odometry is not None else 0.0)
        while self.odometry.counters is None and time.monotonic() < deadline:
            time.sleep(0.02)
        return self.odometry.counters

    def _persistence_info(self) -> PersistenceInfo:
        return PersistenceInfo(initial_belief=self.initial_belief, saves=self.saver.saves,
                               save_error=self.saver.last_error)

    def _pose_port_info(self) -> PosePortInfo | None:
        return self.publisher.info() if self.publisher is not None else None

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
        self.saver.stop()
        if self.truth is not None:
            self.truth.stop()
        self.recorder.close()
        self.live.close()
        self.refresh.close()
        if self.refresh.enabled:
            log.info("map refresh: %s", self.refresh.info())
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
        status_every = RateLimiter.every(STATUS_PERIOD_S)
        save_every = RateLimiter.every(self.cfg.persistence.save_period_s)
        save_every.ready(time.monotonic())  # first save one period from now
        try:
            while not self._stop.is_set():
                self.commands.run_pending()
                frame = self.mailbox.get(timeout=0.05)
                mono = time.monotonic()
                if frame is not None:
                    self.watch.last_frame_mono = mono
                    self._survive(self._on_frame, frame)
                else:
                    self._survive(self._maybe_dead_reckon, mono, time.time())
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

    def _survive(self, step: Callable[..., None], *args: Any) -> None:
        """Run one frame's work; an exception is logged, counted and survived (module
        docstring). :data:`RESET_AFTER_FAILED_UPDATES` failures with no pose published in
        between reset the belief (a failure after the pose was published, in active vision
        say, does not: the belief is fine)."""
        try:
            step(*args)
        except Exception as exc:  # noqa: BLE001 - the daemon never dies on one frame
            self.status.update_failed(exc)
            self._failed_in_a_row += 1
            if self._failed_in_a_row % RESET_AFTER_FAILED_UPDATES == 0:
                log.error("%d updates in a row failed: starting global localization",
                          self._failed_in_a_row)
                try:
                    tap(self.localizer, self.recorder, "failures").start_global()
                except Exception:  # noqa: BLE001
                    log.exception("global localization failed too")

    def _on_frame(self, frame: StereoFrame) -> None:
        stamp = float(frame.stamp)
        if not self.watch.fresh(stamp):
            self.status.out_of_order()
            return
        self.watch.last_update_stamp = stamp  # also when the update fails: no frame twice
        delta, _ = self.odometry.take_until(stamp)
        pan, moving = self.heads.pan_at(stamp)
        at_rest = self.active.frame_at_rest(stamp, moving, self.heads.last_motion)
        image = frame.left if at_rest else None
        disparity = frame.disparity if (self.has_disparity and at_rest) else None
        self.recorder.frame(stamp, frame.left, frame.disparity, delta=delta.tolist(), pan=pan,
                            moving=moving, image=image is not None, disparity=disparity is not None)
        est = self.localizer.update(delta, pan, image, disparity, stamp=stamp)
        self.status.check_appearance_changes()
        if self.watch.dead_reckoning:
            log.info("camera frames again: localizing with images")
        self.watch.dead_reckoning = False
        self._publish_pose(est, stamp, pan)
        if image is not None:  # never raises, never waits (services.map_refresh)
            self.refresh.offer(stamp, frame.left, frame.disparity, est.pose, pan, est.quality, est.state)
        self.live.frame(stamp, frame.left)
        self.status.frame_taken()
        self.active.step(est, stamp, delta, pan if image is not None else None)

    def _maybe_dead_reckon(self, mono: float, now: float) -> None:
        if not self.watch.due(mono, now):
            return
        if not self.watch.dead_reckoning:
            log.warning(
                "no camera frame for %.1f s: dead reckoning from odometry (covariance grows)",
                self.watch.silent_for(mono),
            )
        self.watch.dead_reckoning = True
        self.watch.last_update_stamp = now  # also when the prediction fails: once a period
        delta, _ = self.odometry.take_until(now)
        self.recorder.call("predict", now, delta=delta.tolist())
        est = self.localizer.predict_only(delta, stamp=now)
        self._publish_pose(est, now, None)

    def _publish_pose(self, est: Estimate, stamp: float, pan: float | None) -> None:
        """Publish the pose (and maybe the particles); raises LinoLocError when the estimate
        holds a non-finite value (nothing published: a failed update)."""
        assert self.poses is not None
        msg = self.poses.publish(est, stamp=stamp, pan=pan, dead_reckoning=self.watch.dead_reckoning)
        if msg is None:
            raise LinoLocError("the estimate holds a non-finite value: no pose published")
        self.recorder.pose(msg)
        self.live.pose(msg)
        self._failed_in_a_row = 0
        self.status.pose_published(stamp)
        self.poses.publish_particles(stamp)
        self.recorder.particles(stamp, self.localizer.particles)
        self.live.particles(stamp, self.localizer.particles)

    def _state(self) -> str:
        est = self.poses.latest()[1] if self.poses is not None else None
        return "starting" if est is None else est.state

    def _publish_status(self) -> None:
        assert self.publisher is not None
        msg = self.status.publish()
        self.publisher.publish("status", msg)
        self.recorder.status(msg)
        self.live.status(msg)
        self.notifier.status(status_line(msg, self.cfg.endpoints.pub, self.watch.dead_reckoning))

    def _save(self, sync: bool) -> SavedState | None:
        est = self.poses.latest()[1] if self.poses is not None else None
        state = SavedState.of_estimate(est, self.status.map_info.checksum)
        if state is None:
            return None
        if sync:
            return state if self.saver.write(state) else None
        self.saver.submit(state)
        return state

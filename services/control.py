"""The daemon's control socket: a ZeroMQ REP server in its own thread, and its handlers.

One JSON request in, one JSON reply out. Every received message is turned by
:func:`services.messages.parse_request` into a request model or an error reply (malformed
JSON, not an object, unknown ``cmd``, bad fields, too large, several frames): the socket
always answers, and nothing a client sends can raise out of this thread or reach the
localization loop unchecked.

Valid requests go to a handler: :class:`ControlHandlers`, one method per request class
(:data:`ControlHandlers.dispatch`, keyed by the pydantic request model; a request class with
no handler gets an error reply). Requests that change the filter
(``set_pose``, ``global_localization``) must run in the loop's thread, between two
updates: the handler puts them on a :class:`CommandQueue` and waits at most
:data:`ACK_WAIT_S` for the loop to apply them (:meth:`CommandQueue.post`). The reply says
either that the belief was set, or that the request is queued and will be applied before
the next update (the loop is inside an update); a full queue gives an error reply. A
queued command that fails in the loop is logged. So no reply waits for an update. Read-only requests (``status``, ``get_pose``, ``ping``) are
answered from snapshots the loop keeps under a lock, without waiting for it.

Usage::

    handlers = ControlHandlers(commands, localizer, poses, status, active, saver, checksum)
    server = ControlServer(ctx, "tcp://127.0.0.1:5557", handler=handlers)
    server.start(); ...; server.stop()
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import TYPE_CHECKING, Any

import numpy as np
import zmq
from pydantic import BaseModel

from lino_loc import __version__
from services.curve_auth import CurveConfig, CurveKeyError, attach_server
from services.messages import (
    AckReply,
    ControlStateReply,
    ErrorReply,
    GetPoseReply,
    GetPoseRequest,
    GlobalLocalizationRequest,
    PauseRequest,
    PingReply,
    PingRequest,
    ResumeRequest,
    SaveStateReply,
    SaveStateRequest,
    SetActiveVisionRequest,
    SetPoseRequest,
    StatusReply,
    StatusRequest,
    belief_problem,
    encode_reply,
    error_reply,
    parse_request,
)
from services.persistence import SavedState
from services.subscription_guard import HANDSHAKE_FAILED

if TYPE_CHECKING:
    from lino_loc.localizer import Localizer
    from services.active_head import ActiveHead
    from services.persistence import StateSaver
    from services.publisher import PosePublisher
    from services.status import StatusReporter

log = logging.getLogger("lino_loc.service.control")

Handler = Callable[[Any], BaseModel]

#: Largest frame the control socket accepts (``ZMQ_MAXMSGSIZE``). The largest valid request
#: (a ``set_pose`` with its covariance) is a few hundred bytes; up to this size an oversized
#: request still gets the one-line error of :func:`services.messages.parse_request` (its
#: limit is ``MAX_REQUEST_BYTES``, 64 KiB). A frame announced larger than this closes that
#: client's connection before anything is allocated for it (the client's request times out).
CONTROL_MAX_FRAME_BYTES = 128 * 1024
#: Requests queued per connection (``ZMQ_RCVHWM``): a REQ client has one in flight; a client
#: that streams frames without reading the replies is held back by TCP, so what one
#: connection can make the daemon hold is bounded by CONTROL_RCVHWM x CONTROL_MAX_FRAME_BYTES.
CONTROL_RCVHWM = 2


class LoopBusy(RuntimeError):
    """The command queue is full: the loop is behind (the request is refused, not queued)."""


class CommandQueue:
    """Functions to run in the loop's thread: ``call`` from any thread, ``run_pending`` in
    the loop. Bounded: when ``maxsize`` calls wait already, ``call`` fails at once."""

    def __init__(self, maxsize: int = 16) -> None:
        self._q: queue.Queue[tuple[Callable[[], Any], Future[Any]]] = queue.Queue(maxsize)

    def submit(self, fn: Callable[[], Any]) -> Future[Any]:
        fut: Future[Any] = Future()
        try:
            self._q.put_nowait((fn, fut))
        except queue.Full:
            fut.set_exception(LoopBusy("too many pending control requests, try again"))
        return fut

    def post(self, fn: Callable[[], Any], wait: float) -> bool:
        """Queue ``fn`` for the loop's thread and wait at most ``wait`` s for it: True when it
        ran (raises its exception), False when it is still queued (an exception it raises
        later is logged). Raises :class:`LoopBusy` when the queue is full."""
        fut = self.submit(fn)
        try:
            fut.result(wait)
            return True
        except FutureTimeout:
            fut.add_done_callback(_log_failure)
            return False

    def call(self, fn: Callable[[], Any], timeout: float = 2.0) -> Any:
        """Run ``fn`` in the loop's thread and return its result (raises its exception,
        or TimeoutError when the loop did not get to it within ``timeout`` s)."""
        fut = self.submit(fn)
        try:
            return fut.result(timeout)
        except FutureTimeout:
            fut.cancel()
            raise TimeoutError(f"the localization loop did not answer within {timeout:g} s") from None

    def run_pending(self, limit: int = 16) -> int:
        """Run waiting calls (at most ``limit``); returns how many ran."""
        n = 0
        while n < limit:
            try:
                fn, fut = self._q.get_nowait()
            except queue.Empty:
                break
            n += 1
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(fn())
            except BaseException as exc:  # noqa: BLE001 - handed to the caller
                fut.set_exception(exc)
        return n


def _log_failure(fut: Future[Any]) -> None:
    if not fut.cancelled() and fut.exception() is not None:
        log.warning("a queued control command failed in the loop: %s", fut.exception())


def handle_raw(raw_frames: list[bytes], handler: Handler) -> bytes:
    """The reply bytes for one received message (never raises)."""
    try:
        if len(raw_frames) != 1:
            reply: BaseModel = error_reply(
                f"expected one frame holding a JSON object, got {len(raw_frames)} frames"
            )
        else:
            req = parse_request(raw_frames[0])
            if isinstance(req, ErrorReply):
                reply = req
            else:
                cmd = getattr(req, "cmd", None)
                try:
                    reply = handler(req)
                except (TimeoutError, LoopBusy) as exc:
                    reply = error_reply(f"{cmd}: {exc}", cmd=cmd)
                except Exception as exc:  # noqa: BLE001 - the control socket must never die
                    log.warning("control %s failed: %s: %s", cmd, type(exc).__name__, exc)
                    reply = error_reply(f"{cmd}: {type(exc).__name__}: {exc}", cmd=cmd)
        return encode_reply(reply)
    except Exception as exc:  # noqa: BLE001
        return encode_reply(error_reply(f"internal error: {type(exc).__name__}: {exc}"))


class ControlServer(threading.Thread):
    """REP socket serving :func:`handle_raw` until :meth:`stop`."""

    def __init__(
        self, ctx: zmq.Context[Any], endpoint: str, handler: Handler, curve: CurveConfig | None = None
    ) -> None:
        """Bind ``endpoint``; with ``curve`` keys, as a CURVE server (services/curve_auth.py).
        Frames over :data:`CONTROL_MAX_FRAME_BYTES` drop the connection, and at most
        :data:`CONTROL_RCVHWM` requests queue per connection. Raises OSError when the
        endpoint cannot be bound or the keys cannot be read."""
        super().__init__(name="control", daemon=True)
        self.endpoint = endpoint
        self.handler = handler
        self._stop_event = threading.Event()
        self._sock = ctx.socket(zmq.REP)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.SNDTIMEO, 1000)
        self._sock.setsockopt(zmq.MAXMSGSIZE, CONTROL_MAX_FRAME_BYTES)
        self._sock.setsockopt(zmq.RCVHWM, CONTROL_RCVHWM)
        self._release_curve: Callable[[], None] = lambda: None
        try:
            self._release_curve = attach_server(ctx, self._sock, curve)
            self._sock.bind(endpoint)
        except (zmq.ZMQError, CurveKeyError) as exc:
            self._sock.close(linger=0)
            self._release_curve()
            raise OSError(f"cannot bind the control socket to {endpoint}: {exc}") from exc
        self.requests = 0
        self.errors = 0
        self.refused_handshakes = 0  # no CURVE keys, a key not authorized, not ZeroMQ
        self._monitor = self._sock.get_monitor_socket(HANDSHAKE_FAILED)

    def run(self) -> None:
        try:
            while not self._stop_event.is_set():
                self._count_refused()
                try:
                    if not self._sock.poll(100):
                        continue
                    frames = self._sock.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    continue
                except zmq.ZMQError as exc:
                    if self._stop_event.is_set():
                        break
                    log.warning("control socket: %s", exc)
                    continue
                self.requests += 1
                reply = handle_raw(frames, self.handler)
                if reply.startswith(b'{"v":1,"ok":false') or b'"ok":false' in reply[:40]:
                    self.errors += 1
                try:
                    self._sock.send(reply)
                except zmq.ZMQError as exc:
                    log.warning("control reply not sent: %s", exc)
        finally:
            self._close()

    def _count_refused(self) -> None:
        """Count the handshakes the monitor reports refused."""
        while True:
            try:
                self._monitor.recv_multipart(zmq.NOBLOCK)
            except zmq.ZMQError:
                return
            self.refused_handshakes += 1

    def _close(self) -> None:
        if self._monitor.closed:
            return
        try:
            self._sock.disable_monitor()
        except zmq.ZMQError:
            pass
        self._monitor.close(linger=0)
        self._sock.close(linger=0)
        self._release_curve()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop_event.set()
        if self.is_alive():
            self.join(timeout)
        if not self.is_alive():  # also when never started: the socket and the ZAP handler go
            self._close()


#: Longest a ``set_pose`` / ``global_localization`` reply waits for the loop to apply it, s:
#: the loop applies queued commands between two updates, and an update may take longer.
ACK_WAIT_S = 0.02
_QUEUED = "queued, applied before the next update: belief "


class ControlHandlers:
    """The daemon's answers to the control requests, dispatched on the request's class.

    Read-only requests are answered from snapshots (the status reporter, the last published
    pose); ``set_pose`` and ``global_localization`` run in the loop's thread through
    ``commands``; ``pause``/``resume``/``set_active_vision`` flip the switches of
    :class:`services.active_head.ActiveHead`; ``save_state`` writes the last ``tracking``
    estimate synchronously (error reply when there is none or the write fails)."""

    def __init__(
        self,
        commands: CommandQueue,
        localizer: Localizer,
        poses: PosePublisher,
        status: StatusReporter,
        active: ActiveHead,
        saver: StateSaver,
        map_checksum: str | None = None,
    ) -> None:
        self.commands = commands
        self.localizer = localizer
        self.poses = poses
        self.status = status
        self.active = active
        self.saver = saver
        self.map_checksum = map_checksum
        self.dispatch: dict[type[BaseModel], Callable[[Any], BaseModel]] = {
            PingRequest: self.ping,
            StatusRequest: self.status_reply,
            GetPoseRequest: self.get_pose,
            SetPoseRequest: self.set_pose,
            GlobalLocalizationRequest: self.global_localization,
            PauseRequest: self.pause_or_resume,
            ResumeRequest: self.pause_or_resume,
            SetActiveVisionRequest: self.set_active_vision,
            SaveStateRequest: self.save_state,
        }

    def __call__(self, req: Any) -> BaseModel:
        """The reply to one parsed request (called in the control thread)."""
        handler = self.dispatch.get(type(req))
        if handler is None:
            cmd = getattr(req, "cmd", None)
            return error_reply(f"cmd: {cmd!r} is not handled by this daemon", cmd=cmd)
        return handler(req)

    def ping(self, _req: PingRequest) -> PingReply:
        return PingReply(stamp=time.time(), version=__version__)

    def status_reply(self, _req: StatusRequest) -> StatusReply:
        return StatusReply(status=self.status.build())

    def get_pose(self, _req: GetPoseRequest) -> GetPoseReply:
        return GetPoseReply(pose=self.poses.latest()[0])

    def set_pose(self, req: SetPoseRequest) -> BaseModel:
        """Belief around the requested pose; refused in one line (error reply, belief
        unchanged) when the pose or covariance does not fit the map
        (:func:`services.messages.belief_problem`: within the map's bounds plus
        :data:`services.messages.POSE_MARGIN_M`, position standard deviation at most the map's
        extent, heading standard deviation at most pi)."""
        mean = np.array(req.pose.as_tuple(), dtype=np.float64)
        cov = np.asarray(req.covariance, dtype=np.float64).reshape(3, 3)
        problem = belief_problem(mean, cov, self.localizer.bounds)
        if problem is not None:
            log.info("set_pose refused: %s", problem)
            return error_reply(f"set_pose: {problem}", cmd="set_pose")
        done = self.commands.post(lambda: self.localizer.set_pose(mean, cov), ACK_WAIT_S)
        log.info("set_pose (%.2f, %.2f, %.2f) from the control socket", *mean)
        where = f"around ({mean[0]:.3f}, {mean[1]:.3f}, {mean[2]:.3f})"
        return AckReply(cmd="set_pose", message=f"belief set {where}" if done else _QUEUED + where)

    def global_localization(self, _req: GlobalLocalizationRequest) -> AckReply:
        done = self.commands.post(self.localizer.start_global, ACK_WAIT_S)
        log.info("global localization requested on the control socket")
        where = "over the map"
        return AckReply(
            cmd="global_localization", message=f"belief spread {where}" if done else _QUEUED + where
        )

    def pause_or_resume(self, req: PauseRequest | ResumeRequest) -> ControlStateReply:
        self.active.set_paused(req.target, req.cmd == "pause")
        return ControlStateReply(cmd=req.cmd, active_vision=self.active.info())

    def set_active_vision(self, req: SetActiveVisionRequest) -> ControlStateReply:
        self.active.set_enabled(req.enabled, self.commands.call)
        return ControlStateReply(cmd=req.cmd, active_vision=self.active.info())

    def save_state(self, req: SaveStateRequest) -> BaseModel:
        est = self.poses.latest()[1]
        state = SavedState.of_estimate(est, self.map_checksum)
        if state is None:
            now = "starting" if est is None else est.state
            return error_reply(f"save_state: no converged pose to save yet (state {now})", cmd=req.cmd)
        if not self.saver.write(state):
            return error_reply(f"save_state: {self.saver.last_error}", cmd=req.cmd)
        return SaveStateReply(path=str(self.saver.path), stamp=state.saved_at)

"""The daemon's control socket: a ZeroMQ REP server in its own thread (design.md 4.4).

One JSON request in, one JSON reply out. Every received message is turned by
:func:`services.messages.parse_request` into a request model or an error reply (malformed
JSON, not an object, unknown ``cmd``, bad fields, too large, several frames): the socket
always answers, and nothing a client sends can raise out of this thread or reach the
localization loop unchecked.

Valid requests go to a handler (the daemon). Requests that change the filter
(``set_pose``, ``global_localization``) must run in the loop's thread, between two
updates: the handler puts them on a :class:`CommandQueue` and waits for the loop to apply
them (:meth:`CommandQueue.call`, bounded by a timeout, so a busy loop gives an error reply
rather than a hung client). Read-only requests (``status``, ``get_pose``, ``ping``) are
answered from snapshots the loop keeps under a lock, without waiting for it.

Usage::

    server = ControlServer(ctx, "tcp://127.0.0.1:5557", handler=daemon.handle_request)
    server.start(); ...; server.stop()
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Any

import zmq
from pydantic import BaseModel

from services.messages import ErrorReply, encode_reply, error_reply, parse_request

log = logging.getLogger("lino_loc.service.control")

Handler = Callable[[Any], BaseModel]


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
            fut.set_exception(RuntimeError("too many pending control requests"))
        return fut

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
                except TimeoutError as exc:
                    reply = error_reply(f"{cmd}: {exc}", cmd=cmd)
                except Exception as exc:  # noqa: BLE001 - the control socket must never die
                    log.warning("control %s failed: %s: %s", cmd, type(exc).__name__, exc)
                    reply = error_reply(f"{cmd}: {type(exc).__name__}: {exc}", cmd=cmd)
        return encode_reply(reply)
    except Exception as exc:  # noqa: BLE001
        return encode_reply(error_reply(f"internal error: {type(exc).__name__}: {exc}"))


class ControlServer(threading.Thread):
    """REP socket serving :func:`handle_raw` until :meth:`stop`."""

    def __init__(self, ctx: zmq.Context[Any], endpoint: str, handler: Handler) -> None:
        super().__init__(name="control", daemon=True)
        self.endpoint = endpoint
        self.handler = handler
        self._stop_event = threading.Event()
        self._sock = ctx.socket(zmq.REP)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.SNDTIMEO, 1000)
        try:
            self._sock.bind(endpoint)
        except zmq.ZMQError as exc:
            self._sock.close(linger=0)
            raise OSError(f"cannot bind the control socket to {endpoint}: {exc}") from exc
        self.requests = 0
        self.errors = 0

    def run(self) -> None:
        try:
            while not self._stop_event.is_set():
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
            self._sock.close(linger=0)

    def stop(self, timeout: float = 2.0) -> None:
        self._stop_event.set()
        if self.is_alive():
            self.join(timeout)

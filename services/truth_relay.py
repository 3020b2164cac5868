"""The simulation-only truth relay: the simulator's true pose, republished by the daemon.

``lino-loc sim`` (:mod:`services.sim_launcher`) publishes the simulated robot's true pose on
its own PUB socket, topic ``truth``. :class:`TruthRelay` subscribes to it in a thread of its
own and republishes every valid message unchanged on the daemon's PUB socket (topic
``truth``), so that a client watching the daemon sees the estimate and the truth on one
endpoint. Messages that are not two frames ``[b"truth", json]`` or that do not validate as
:class:`services.messages.TruthMessage` are dropped. The relay never blocks the daemon: it
polls every 0.2 s for :meth:`stop`, and a ZeroMQ error ends it with a warning.

Usage::

    relay = TruthRelay(ctx, sim_info.truth, publisher)
    relay.start(); ...; relay.stop()
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

import zmq

from services.messages import TruthMessage
from services.publisher import AnyPublisher

log = logging.getLogger("lino_loc.service.truth")

#: Milliseconds between two checks of the stop flag while no truth arrives.
POLL_MS = 200


class TruthRelay(threading.Thread):
    """SUB ``truth`` of the simulator -> the daemon's PUB socket (module docstring)."""

    def __init__(
        self, ctx: zmq.Context[Any], endpoint: str, publisher: AnyPublisher,
        listener: Callable[[bytes], None] | None = None,
    ) -> None:
        super().__init__(name="truth-relay", daemon=True)
        self.listener = listener  # gets every valid message's JSON (the recorder)
        self.ctx = ctx
        self.endpoint = endpoint
        self.publisher = publisher
        self.relayed = 0
        self._stop_event = threading.Event()

    def run(self) -> None:
        sock = self.ctx.socket(zmq.SUB)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVHWM, 10)
        sock.setsockopt(zmq.SUBSCRIBE, b"truth")
        try:
            sock.connect(self.endpoint)
            while not self._stop_event.is_set():
                if sock.poll(POLL_MS):
                    self.relay(sock.recv_multipart())
        except zmq.ZMQError as exc:
            if not self._stop_event.is_set():
                log.warning("truth relay stopped: %s", exc)
        finally:
            sock.close(linger=0)

    def relay(self, frames: list[bytes]) -> bool:
        """Republish one received message if it is a valid truth message; True if sent."""
        if len(frames) != 2 or frames[0] != b"truth":
            return False
        try:
            TruthMessage.model_validate_json(frames[1])
        except ValueError:
            return False
        if self.listener is not None:
            self.listener(frames[1])
        sent = self.publisher.send_frames([b"truth", frames[1]], "truth")
        self.relayed += 1
        return sent

    def stop(self, timeout: float = 2.0) -> None:
        self._stop_event.set()
        if self.is_alive():
            self.join(timeout)

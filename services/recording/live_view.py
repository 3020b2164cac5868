"""The live view: ``[live_view]`` and a Foxglove WebSocket server fed by the daemon, never waiting.

:class:`LiveView` starts foxglove-sdk's WebSocket server (``foxglove.start_server``, in a
``foxglove.Context`` of its own) and advertises the recording's channels
(:data:`services.recording.channels.TOPICS`, the same topics, encodings and schemas through
``sdk_channel_args``): a Foxglove client sees a live session as it sees a recording, and one
layout (docs/foxglove-layout.json) opens both.

The loop (and the truth thread) hand it what they publish; a hand-over looks up the set of
topics clients are subscribed to (kept by the server's listener, ``on_subscribe`` /
``on_unsubscribe``) and returns at once when no client watches them: **nothing is queued or
encoded without a subscriber**. Otherwise it is one ``put_nowait`` on a bounded queue
(:data:`MAX_QUEUED` events, :data:`MAX_QUEUED_FRAMES` camera images); a full queue drops the
event and counts it (``status.live_view.dropped``). A sender thread encodes (the encoders of
:mod:`services.recording.topic_messages`) and logs each message on its channel when the
channel has a subscriber (``Channel.has_sinks``); the server sends it to the clients, dropping
the oldest of a slow client's backlog (foxglove-sdk's ``message_backlog_size``).

What goes live: the pose (``/pose``, ``/pose/estimate``, ``/pose/ellipse``, ``/tf``: the
estimate and the head's pan), the particles (``particles_rate_hz`` sets per second of frame
stamps, every k-th beyond ``particles_max_count``), the camera image (``/camera/image``, PNG,
``image_rate_hz``), the status, in simulation the truth, and the map (``/map/survey``,
``/map/outline``): the map is sent :data:`MAP_DELAY_S` after a client subscribes to it and
every :data:`MAP_PERIOD_S` while one does, so a client that connects later still sees it.

A port that cannot be bound (in use, a bad host) is logged and reported in the status
(``live_view.error``); the daemon goes on without the live view. A host other than loopback
is served, with a warning in the log: it has no authentication.

Usage::

    live = LiveView(cfg.live_view, MapScene.of(amap, cfg))   # LiveView.off(): nothing
    live.start(); live.pose(msg); live.frame(stamp, left); ...; live.close()
"""

from __future__ import annotations

import functools
import ipaddress
import logging
import queue
import re
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from lino_loc.errors import LinoLocError
from services.messages import LiveViewInfo
from services.recording import topic_messages as tm
from services.recording.recorder import subsample

log = logging.getLogger("lino_loc.service.live_view")

#: Events the queue holds at most (poses at 15/s, particles, status, truth: about 2 s).
MAX_QUEUED = 64
#: Camera images queued at most (the sender encodes PNG; a newer image waits for none).
MAX_QUEUED_FRAMES = 2
#: s after a subscription to the map before it is sent (a message logged in the instant of
#: the subscription may miss the client); s between two sends while a client subscribes.
MAP_DELAY_S = 0.25
MAP_PERIOD_S = 10.0
#: Messages the server buffers per client before it drops that client's oldest.
BACKLOG = 256

_HOST_RE = re.compile(r"[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?")

POSE_TOPICS = frozenset({"/pose", "/pose/estimate", "/pose/ellipse", "/tf"})
MAP_TOPICS = frozenset({"/map/survey", "/map/outline"})
#: The topics a live view advertises: the recording's outputs, the camera image, the map.
LIVE_TOPICS = ("/camera/image", "/pose", "/pose/estimate", "/pose/ellipse", "/particles", "/tf",
               "/status", "/truth", "/truth/pose", "/map/survey", "/map/outline")


def is_loopback(host: str) -> bool:
    """``localhost`` or a loopback address (127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class LiveViewConfig(BaseModel):
    """The ``[live_view]`` section: a Foxglove WebSocket server in the daemon (off by default)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(False, description="serve the live view (Foxglove, ws://host:port)")
    host: str = Field(
        "127.0.0.1", description="address to bind: loopback by default (reach it over ssh -L); "
        "any other (0.0.0.0: every interface) is served unauthenticated, with a warning"
    )
    port: int = Field(8765, ge=0, le=65535, description="TCP port (0: a free one, in the status)")
    particles_rate_hz: float = Field(
        2.0, ge=0.0, le=30.0, description="particle sets sent per second of frames (0: none)"
    )
    particles_max_count: int = Field(
        500, ge=1, description="particles per set (every k-th when the filter has more)"
    )
    image_rate_hz: float = Field(
        5.0, ge=0.0, le=120.0, description="camera images sent per second of frames (0: none)"
    )

    @field_validator("host")
    @classmethod
    def _host(cls, v: str) -> str:
        v = v.strip()
        if not (_is_ip(v) or _HOST_RE.fullmatch(v)):
            raise ValueError(f"{v!r} is not a host name or IP address (e.g. 127.0.0.1)")
        return v

    @property
    def address(self) -> str:
        return f"ws://{self.host}:{self.port}"


def _is_ip(v: str) -> bool:
    try:
        ipaddress.ip_address(v)
        return True
    except ValueError:
        return False


@dataclass(frozen=True)
class MapScene:
    """What the map channels draw: the survey poses (N, 3), the outline as (M, 2, 2) segments
    and what the outline is (``walls``: the simulated world's walls and boxes; ``survey
    extent``: the rectangle around the survey poses, when there is no building plan)."""

    poses: np.ndarray
    outline: np.ndarray
    outline_what: str

    @classmethod
    def of(cls, amap: Any, cfg: Any) -> MapScene:
        """The map's poses, and the walls of ``cfg``'s simulated world (else the extent)."""
        poses = np.asarray(amap.poses, dtype=np.float64).reshape(-1, 3)
        if getattr(cfg, "simulated", False):
            from drivers.sim.world import load_world

            plan = load_world(cfg.devices.camera.sim.world).floor_plan()
            segs = [np.asarray(plan["walls"], dtype=np.float64).reshape(-1, 2, 2)]
            for corners in plan["boxes"]:
                c = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
                segs.append(np.stack([c, np.roll(c, -1, axis=0)], axis=1))
            return cls(poses, np.concatenate(segs), "walls")
        return cls(poses, extent_outline(poses), "survey extent")


def extent_outline(poses: np.ndarray) -> np.ndarray:
    """The four sides of the rectangle around the poses' positions, (4, 2, 2)."""
    if poses.shape[0] == 0:
        return np.zeros((0, 2, 2))
    (x0, y0), (x1, y1) = poses[:, :2].min(axis=0), poses[:, :2].max(axis=0)
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    return np.stack([c, np.roll(c, -1, axis=0)], axis=1)


class _Listener:
    """foxglove-sdk's ServerListener: the subscribed topics (a frozenset, replaced whole, so
    the loop reads it without a lock) and the clients with a subscription."""

    def __init__(self, on_map: Callable[[], None]) -> None:
        self.topics: frozenset[str] = frozenset()
        self._subs: dict[tuple[int, str], int] = {}
        self._lock = threading.Lock()
        self._on_map = on_map

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            key = (int(client.id), str(channel.topic))
            self._subs[key] = self._subs.get(key, 0) + 1
            self.topics = frozenset(t for _, t in self._subs)
        if channel.topic in MAP_TOPICS:
            self._on_map()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            key = (int(client.id), str(channel.topic))
            n = self._subs.pop(key, 0) - 1
            if n > 0:
                self._subs[key] = n
            self.topics = frozenset(t for _, t in self._subs)

    @property
    def clients(self) -> int:
        with self._lock:
            return len({c for c, _ in self._subs})


def _never_raises(method: Callable[..., None]) -> Callable[..., None]:
    """A hand-over that cannot fail its caller (the loop, the truth thread): an exception is
    logged (the first with its traceback) and counted as a dropped event."""
    seen: list[bool] = []

    @functools.wraps(method)
    def guarded(self: LiveView, *args: Any, **kwargs: Any) -> None:
        try:
            method(self, *args, **kwargs)
        except Exception:  # noqa: BLE001 - the live view must never stop the loop
            self.dropped += 1
            if not seen:
                seen.append(True)
                log.exception("live view: %s failed (event dropped; logged once)", method.__name__)

    return guarded


class LiveView:
    """The live view (module docstring). ``LiveView.off()`` serves nothing."""

    def __init__(self, cfg: LiveViewConfig | None, scene: MapScene | None = None) -> None:
        self.cfg = cfg or LiveViewConfig()
        self.enabled = cfg is not None and cfg.enabled
        self.scene = scene
        self.port: int | None = None
        self.error: str | None = None
        self.messages = 0
        self.dropped = 0
        self.queued = 0  # events handed over (none while nobody watches)
        self._queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(MAX_QUEUED)
        self._frames_queued = 0
        self._lock = threading.Lock()
        self._map_due: float | None = None
        self._listener = _Listener(self._map_requested)
        self._next: dict[str, float] = {}
        self._server: Any = None
        self._channels: dict[str, Any] = {}
        self._context: Any = None
        self._thread: threading.Thread | None = None

    @classmethod
    def off(cls) -> LiveView:
        return cls(None)

    # ------------------------------------------------------------------ hand-over (any thread)
    def _watched(self, topics: Iterable[str]) -> bool:
        subscribed = self._listener.topics
        return bool(subscribed) and not subscribed.isdisjoint(topics)

    def _put(self, event: tuple[Any, ...], frame: bool = False) -> None:
        with self._lock:
            if not (frame and self._frames_queued >= MAX_QUEUED_FRAMES):
                try:
                    self._queue.put_nowait((frame, *event))
                    self._frames_queued += frame
                    self.queued += 1
                    return
                except queue.Full:
                    pass
            self.dropped += 1

    def _due(self, kind: str, stamp: float, rate_hz: float) -> bool:
        """At most ``rate_hz`` per second of stamps (0: never)."""
        nxt = self._next.get(kind)
        if rate_hz <= 0 or (nxt is not None and stamp < nxt):
            return False
        self._next[kind] = stamp + 1.0 / rate_hz
        return True

    @_never_raises
    def pose(self, msg: BaseModel | None) -> None:
        """The published pose message (``/pose``, ``/pose/estimate``, ``/pose/ellipse``, ``/tf``)."""
        if msg is not None and self._watched(POSE_TOPICS):
            self._put(("pose", msg))

    @_never_raises
    def particles(self, stamp: float, particles: Callable[[], tuple[np.ndarray, np.ndarray]]) -> None:
        """The particle set, at most ``particles_rate_hz`` per second of stamps."""
        if self._watched(("/particles",)) and self._due("particles", stamp, self.cfg.particles_rate_hz):
            poses, _ = particles()
            self._put(("particles", float(stamp), subsample(np.asarray(poses), self.cfg.particles_max_count)))

    @_never_raises
    def frame(self, stamp: float, left: np.ndarray | None) -> None:
        """The camera's left image, at most ``image_rate_hz`` per second of stamps."""
        if (left is not None and self._watched(("/camera/image",))
                and self._due("image", stamp, self.cfg.image_rate_hz)):
            self._put(("frame", float(stamp), left), frame=True)

    @_never_raises
    def status(self, msg: BaseModel) -> None:
        if self._watched(("/status",)):
            self._put(("status", msg))

    @_never_raises
    def truth(self, truth_json: bytes) -> None:
        if self._watched(("/truth", "/truth/pose")):
            self._put(("truth", bytes(truth_json)))

    def _map_requested(self) -> None:
        self._map_due = time.monotonic() + MAP_DELAY_S

    def info(self) -> LiveViewInfo | None:
        """What the status says of the live view (None when off)."""
        if not self.enabled:
            return None
        port = self.port if self.port is not None else self.cfg.port
        return LiveViewInfo(
            address=f"ws://{self.cfg.host}:{port}", serving=self._server is not None,
            clients=self._listener.clients, topics=sorted(self._listener.topics),
            messages=self.messages, dropped=self.dropped, error=self.error,
        )

    # ------------------------------------------------------------------ server and sender
    def start(self) -> None:
        """Start the server and the sender thread; a failure is logged and reported
        (``error``), never raised."""
        if not self.enabled or self._thread is not None:
            return
        try:
            self._server = self._open()
        except LinoLocError as exc:  # the viz extra missing
            self.error = str(exc)
            log.warning("live view not served: %s", self.error)
            return
        except Exception as exc:  # noqa: BLE001 - no live view, the daemon goes on
            self.error = f"{self.cfg.address}: {exc}"
            log.warning("live view not served: %s (the daemon goes on)", self.error)
            return
        self.port = int(self._server.port)
        if not is_loopback(self.cfg.host):
            log.warning("live view on %s: reachable from the network, without authentication",
                        self.cfg.host)
        log.info("live view: ws://%s:%d (Foxglove: open connection, Foxglove WebSocket)",
                 self.cfg.host, self.port)
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()

    def _open(self) -> Any:
        from services.recording.channels import require_viz, sdk_channel_args

        require_viz("the live view ([live_view] enabled)")
        import foxglove

        context = self._context = foxglove.Context()  # kept: the channels die with it
        server = foxglove.start_server(
            name="lino-loc", host=self.cfg.host, port=self.cfg.port, context=context,
            server_listener=self._listener, message_backlog_size=BACKLOG,
        )
        self._channels = {t: foxglove.Channel(**sdk_channel_args(t), context=context) for t in LIVE_TOPICS}
        return server

    def close(self, timeout: float = 5.0) -> None:
        """Stop the sender and the server (idempotent)."""
        if self._thread is not None:
            try:
                self._queue.put(None, timeout=timeout)
            except queue.Full:
                log.error("live view: the sender did not drain its queue in %.0f s", timeout)
            self._thread.join(timeout)
            self._thread = None
        if self._server is not None:
            try:
                self._server.stop()
            except Exception as exc:  # noqa: BLE001 - shutting down anyway
                log.warning("live view: stopping the server: %s", exc)
            self._server = None

    def _run(self) -> None:
        next_map = time.monotonic() + MAP_PERIOD_S
        while True:
            try:
                event = self._queue.get(timeout=MAP_DELAY_S)
            except queue.Empty:
                event = ()
            if event is None:
                return
            if event:
                self._send(event)
            now = time.monotonic()
            due = self._map_due
            if (due is not None and now >= due) or (now >= next_map and self._watched(MAP_TOPICS)):
                self._map_due = None
                next_map = now + MAP_PERIOD_S
                self._send((False, "map"))

    def _send(self, event: tuple[Any, ...]) -> None:
        frame, kind, *args = event
        if frame:
            with self._lock:
                self._frames_queued -= 1
        try:
            for topic, log_ns, data in self._messages(kind, args):
                ch = self._channels[topic]
                if ch.has_sinks():
                    ch.log(data, log_time=log_ns)
                    self.messages += 1
        except Exception:  # noqa: BLE001 - one bad event never stops the live view
            self.dropped += 1
            log.exception("live view: a %s event could not be sent (dropped)", kind)

    def _messages(self, kind: str, args: list[Any]) -> tm.Messages:
        if kind == "pose":
            msg = args[0]
            return tm.pose_messages(msg.model_dump_json().encode(), msg.model_dump())
        if kind == "particles":
            return tm.particles_messages(args[0], args[1])
        if kind == "frame":
            return tm.frame_messages(args[0], args[1], None)
        if kind == "status":
            msg = args[0]
            return tm.status_messages(msg.model_dump_json().encode(), float(msg.stamp))
        if kind == "truth":
            return tm.truth_messages(args[0])
        if kind == "map" and self.scene is not None:
            s = self.scene
            return tm.map_messages(s.poses, s.outline, time.time(), s.outline_what)
        return []

"""The daemon's ZeroMQ pose stream: publishers that never block, and rate limits.

Two publishers with one interface (``send_frames``, ``publish``, ``wanted``,
``n_subscriptions``, ``info``, ``close``, ``last_endpoint``):

- :class:`services.relay_publisher.RelayedPublisher`, the default: the pose port is owned by
  the relay process (services/pose_relay.py), so that what subscribers cost never reaches the
  loop;
- :class:`Publisher` (``[endpoints.relay] enabled = false``): the daemon binds the pose port
  itself, a :class:`services.pose_port.PosePort` (an XPUB that never blocks, counts its
  subscriptions and caps their table; its docstring says how).

:func:`open_publisher` picks one from the configuration.

:class:`RateLimiter` throttles the ``particles`` topic (``publish.particles_max_rate_hz``)
and paces ``status`` (:data:`services.status.STATUS_PERIOD_S`).

:class:`PosePublisher` is what the daemon's loop calls after each filter update: it numbers
the update (``seq``), publishes its :class:`services.messages.PoseMessage` on ``pose``, keeps
it (and the estimate) as the latest for the control thread, and publishes the particle set
on ``particles`` when a subscriber wants it and the rate limit allows: a uniform random
subset of ``particles_max_count`` particles without replacement when there are more (drawn
from the publisher's own seeded generator, never the filter's), with the weights of the
subset normalised to sum to 1 (uniform when they sum to 0).

Usage::

    pub = open_publisher(zmq.Context.instance(), cfg.endpoints)
    pub.publish("pose", PoseMessage(...))
    limiter = RateLimiter(2.0)
    if limiter.ready(time.monotonic()): pub.publish("particles", msg)
    poses = PosePublisher(pub, cfg.publish, localizer.particles)
    msg = poses.publish(estimate, stamp=frame.stamp, pan=pan)   # None if invalid
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zmq
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.pose_estimate import Estimate
from services.messages import ParticlesMessage, PoseMessage, PosePortInfo, encode
from services.pose_port import MAX_SUBSCRIPTION_MESSAGES, PUB_MAX_FRAME_BYTES, PosePort
from services.relay_publisher import RelayedPublisher
from services.topics import MAX_SUBSCRIPTION_BYTES, TOPIC_PREFIXES

__all__ = [
    "MAX_SUBSCRIPTION_BYTES", "MAX_SUBSCRIPTION_MESSAGES", "PUB_MAX_FRAME_BYTES", "TOPIC_PREFIXES",
    "AnyPublisher", "PosePublisher", "PublishConfig", "Publisher", "RateLimiter", "open_publisher",
]

log = logging.getLogger("lino_loc.service.publisher")

class PublishConfig(BaseModel):
    """The service's ``[publish]`` section: what is published besides the poses."""

    model_config = ConfigDict(extra="forbid")

    particles_max_rate_hz: float = Field(2.0, ge=0.0, description="0 = never publish particles")
    particles_max_count: int = Field(500, ge=1, description="subsample the particle set to this many")
    truth: bool = Field(True, description="republish the simulator's true pose (simulation only)")


class RateLimiter:
    """``ready(now)`` is True at most ``rate_hz`` times per second (0 = never)."""

    def __init__(self, rate_hz: float) -> None:
        self.period = (1.0 / rate_hz) if rate_hz > 0 else None
        self._next: float | None = None

    @classmethod
    def every(cls, period_s: float) -> RateLimiter:
        return cls(1.0 / period_s)

    def ready(self, now: float) -> bool:
        if self.period is None:
            return False
        if self._next is None or now >= self._next:
            # schedule from the previous slot when on time (no drift), from now when late
            nxt = (self._next or now) + self.period
            self._next = nxt if nxt > now else now + self.period
            return True
        return False


class Publisher(PosePort):
    """The daemon's own pose port (no relay): a :class:`services.pose_port.PosePort` that
    publishes pydantic messages and reports its counters for the status."""

    def publish(self, topic: str, message: BaseModel) -> bool:
        """Publish a pydantic message on ``topic`` (validated against the topic's model)."""
        return self.send_frames(encode(topic, message), topic)

    def info(self) -> PosePortInfo:
        """The subscribers' counters for the status."""
        return PosePortInfo(**self.counters())


AnyPublisher = Publisher | RelayedPublisher


def open_publisher(ctx: zmq.Context[Any], endpoints: Any) -> AnyPublisher:
    """The publisher ``endpoints`` (:class:`services.config.EndpointsConfig`) asks for: through
    the relay process unless ``endpoints.relay.enabled`` is false. Raises OSError (one line)
    when the pose port cannot be bound."""
    if endpoints.relay.enabled:
        return RelayedPublisher(ctx, endpoints.pub, endpoints.sndhwm, endpoints.curve, endpoints.relay)
    return Publisher(ctx, endpoints.pub, endpoints.sndhwm, endpoints.curve)


#: Seed of the generator that picks the published subset of particles.
PARTICLE_SUBSET_SEED = 0

ParticleSource = Callable[[], tuple[np.ndarray, np.ndarray]]


class PosePublisher:
    """Poses and particles of each update on a :class:`Publisher` (module docstring).

    ``particles`` returns copies of the filter's particles (M x 3) and linear weights (M,)
    (``Localizer.particles``). :meth:`latest` may be called from any thread."""

    def __init__(self, publisher: AnyPublisher, cfg: PublishConfig, particles: ParticleSource) -> None:
        self.publisher = publisher
        self.cfg = cfg
        self.particles = particles
        self.seq = 0
        self.published = 0
        self._limiter = RateLimiter(cfg.particles_max_rate_hz)
        self._rng = np.random.default_rng(PARTICLE_SUBSET_SEED)
        self._lock = threading.Lock()
        self._last_pose: PoseMessage | None = None
        self._last_estimate: Estimate | None = None

    def latest(self) -> tuple[PoseMessage | None, Estimate | None]:
        """The last published pose message and the estimate it came from."""
        with self._lock:
            return self._last_pose, self._last_estimate

    def publish(
        self, est: Estimate, *, stamp: float, pan: float | None, dead_reckoning: bool = False
    ) -> PoseMessage | None:
        """Publish the pose of ``est`` (and maybe the particles); None when the estimate holds
        a non-finite value (logged, nothing published, ``seq`` still counts the update)."""
        self.seq += 1
        try:
            msg = PoseMessage.from_estimate(
                est, stamp=stamp, seq=self.seq, pan=pan, dead_reckoning=dead_reckoning
            )
        except ValueError as exc:
            log.warning("pose not published (invalid estimate): %s", exc)
            return None
        self.publisher.publish("pose", msg)
        with self._lock:
            self._last_pose, self._last_estimate = msg, est
        self.published += 1
        return msg

    def publish_particles(self, stamp: float) -> bool:
        """Publish the particle set of update ``seq`` if wanted and due; True if sent."""
        if not self._limiter.ready(time.monotonic()) or not self.publisher.wanted("particles"):
            return False
        return self.publisher.publish("particles", self.particles_message(stamp))

    def particles_message(self, stamp: float) -> ParticlesMessage:
        """The (maybe subsampled) particle set with normalised weights."""
        p, w = self.particles()
        n = p.shape[0]
        cap = self.cfg.particles_max_count
        if n > cap:
            idx = self._rng.choice(n, size=cap, replace=False)
            p, w = p[idx], w[idx]
        total = float(w.sum())
        w = w / total if total > 0 else np.full(len(w), 1.0 / max(len(w), 1))
        return ParticlesMessage(
            stamp=stamp,
            seq=self.seq,
            poses=[tuple(float(v) for v in row) for row in p],
            weights=[float(v) for v in w],
            n_total=n,
        )

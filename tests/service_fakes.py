"""Small stand-ins for the daemon's collaborators (shared by the service unit tests)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel

from drivers.interfaces import DeviceHealth, HealthState
from lino_loc.pose_estimate import Estimate
from lino_loc.sensor_model import Bounds


def estimate(state: str = "tracking", stamp: float | None = 10.0, pose: tuple[float, float, float] = (1.0, 2.0, 0.5),
             doubt: float = 0.0) -> Estimate:
    return Estimate(
        pose=np.array(pose), covariance=np.diag([0.01, 0.02, 0.003]), ess=100.0, n_particles=200,
        state=state,  # type: ignore[arg-type]
        cluster_weight=1.0, log_likelihood=-3.0, doubt=doubt, stamp=stamp,
    )


class FakePublisher:
    """Publisher stand-in: records what was published; ``wanted`` answers ``subscribed``."""

    def __init__(self, subscribed: bool = True) -> None:
        self.subscribed = subscribed
        self.messages: list[tuple[str, BaseModel]] = []
        self.frames: list[list[bytes]] = []

    def publish(self, topic: str, message: BaseModel) -> bool:
        self.messages.append((topic, message))
        return True

    def send_frames(self, frames: list[bytes], topic: str | None = None) -> bool:
        self.frames.append(frames)
        return True

    def wanted(self, topic: str) -> bool:
        return self.subscribed


@dataclass
class FakeWorker:
    state: HealthState = HealthState.OK
    counters: dict[str, int] = field(default_factory=dict)
    commands: list[tuple[float, float]] = field(default_factory=list)

    def health(self) -> DeviceHealth:
        return DeviceHealth(self.state, None if self.state == HealthState.OK else "broken", None, self.counters)

    def command(self, pan: float, tilt: float = 0.0) -> None:
        self.commands.append((pan, tilt))


@dataclass
class FakeMailbox:
    received: int = 0
    dropped: int = 0


@dataclass
class HeadReading:
    pan: float = 0.0
    moving: bool = False
    stamp: float = 0.0


class FakeHeads:
    def __init__(self, reading: HeadReading | None = None) -> None:
        self.reading = reading

    def latest(self) -> HeadReading | None:
        return self.reading


class FakeLocalizer:
    """Localizer stand-in: records set_pose/start_global; a uniform belief."""

    def __init__(self, n: int = 50) -> None:
        rng = np.random.default_rng(1)
        self.p = np.column_stack([rng.uniform(0, 5, n), rng.uniform(0, 3, n), rng.uniform(-math.pi, math.pi, n)])
        self.w = np.full(n, 1.0 / n)
        self.calls: list[Any] = []
        self.appearance_changes = 0
        self.bounds = Bounds(0.0, 5.0, 0.0, 3.0)  # the box of the belief above
        self.last_novelty = math.nan

    def particles(self) -> tuple[np.ndarray, np.ndarray]:
        return self.p.copy(), self.w.copy()

    def belief(self) -> tuple[np.ndarray, np.ndarray]:
        return self.p, np.log(self.w)

    def view_values(self, actions: np.ndarray) -> None:
        """No standing match: the policy's H(u) decides."""
        return None

    def set_pose(self, mean: np.ndarray, cov: np.ndarray) -> None:
        self.calls.append(("set_pose", mean.copy(), cov.copy()))

    def start_global(self) -> None:
        self.calls.append(("start_global",))

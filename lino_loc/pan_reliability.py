"""Per-pan reliability of the map's predictions, learned online from the views just taken.

Active vision (:mod:`lino_loc.active_vision`) predicts the view at a candidate pan from the
map and prefers the pans whose predicted views tell the particles apart best. When the room
has changed since the survey (objects moved, added, people standing), the views the map calls
most informative are often the ones the change spoils, and a spoiled view informs little.
This module learns, while the robot looks around, which pans the change has spoiled, and
discounts the expected entropy of those pans.

Evidence. A view's NOVELTY (``PoseMixture.novelty``: the feature distance of the view to its
nearest map entry over the map's own typical spacing, about 1 for a view like the mapped ones)
needs no pose: a view the change spoiled is far from every map entry. A camera's neighbouring
pans overlap, so a spoiled view makes its neighbours likely spoiled too. Both were measured on
the three simulated worlds (docs/results.md, "Choosing views when the room has changed").

The model. Each view taken at robot-frame pan ``u_j`` with novelty ``n_j`` is spoiled with
probability

    s_j = clip((log n_j - log n_clean) / (log n_spoiled - log n_clean), 0, 1)

(0 at or below ``novelty_clean``, 1 at or above ``novelty_spoiled``), and its evidence reaches
the pans within ``reach`` of it with a linear taper, ``rho(d) = max(0, 1 - |d| / reach)``. The
reliability of candidate pan ``u`` is the probability that no observed spoil reaches it,

    r(u) = prod_j (1 - s_j rho(u - u_j)).

A prediction that fails carries no information: with probability ``1 - r(u)`` the view leaves
the belief as it is, so the discounted expected entropy is

    H'(u) = r(u) H(u) + (1 - r(u)) H_0

where ``H_0`` is the entropy now (:meth:`PanReliability.discount`). With no spoiled view
observed, ``r = 1`` and H(u) is unchanged.

The pans are in the robot frame, which is the world's frame shifted by the robot's heading:
when the base turns by ``dtheta`` the observed pans shift by ``-dtheta``; after ``forget_xy``
metres of travel the views are of another place and everything is forgotten
(:meth:`PanReliability.move`).

Usage::

    rel = PanReliability(PanReliabilityConfig(enabled=True))
    rel.observe(pan, mixture.novelty)          # after each update with a view
    values = rel.discount(evaluator.evaluate(particles, log_weights))
    rel.move(odometry_delta)                   # when the base moves
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Protocol, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from lino_loc.poses import wrap_angle

FloatArray = NDArray[np.float64]


class _Values(Protocol):
    """What :meth:`PanReliability.discount` reads (``lino_loc.active_vision.ActionValues``, a
    frozen dataclass)."""

    actions: FloatArray
    expected_entropy: FloatArray
    current_entropy: float


V = TypeVar("V", bound=_Values)


class PanReliabilityConfig(BaseModel):
    """Settings of the per-pan reliability (``[active_vision.reliability]``; the defaults are
    chosen on the three simulated worlds together, docs/results.md)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(False, description="discount H(u) at pans near views that fit no map entry")
    novelty_clean: float = Field(0.8, gt=0.0, description="novelty at or below which a view is not spoiled")
    novelty_spoiled: float = Field(1.5, gt=0.0, description="novelty at or above which a view is spoiled")
    reach: float = Field(
        math.radians(45.0), gt=0.0, le=math.pi,
        description="radians; a spoiled view's evidence tapers linearly to zero at this pan distance",
    )
    forget_xy: float = Field(0.35, gt=0.0, description="m of base travel after which the views are forgotten")
    memory: int = Field(32, ge=1, description="most recent views kept")

    @model_validator(mode="after")
    def _order(self) -> PanReliabilityConfig:
        if not self.novelty_clean < self.novelty_spoiled:
            raise ValueError(
                f"novelty_clean ({self.novelty_clean}) must be < novelty_spoiled ({self.novelty_spoiled})"
            )
        return self


class PanReliability:
    """Spoil evidence of the views taken at the robot's present place (module docstring).
    Disabled (``config.enabled`` False) it remembers nothing and :meth:`discount` returns the
    values unchanged: callers feed it and ask it without checking."""

    def __init__(self, config: PanReliabilityConfig | None = None) -> None:
        self.config = config or PanReliabilityConfig()
        self._pans: list[float] = []
        self._spoil: list[float] = []
        self._travel = 0.0

    def reset(self) -> None:
        """Forget every view."""
        self._pans.clear()
        self._spoil.clear()
        self._travel = 0.0

    @property
    def views(self) -> int:
        """How many views are remembered."""
        return len(self._pans)

    def spoil_probability(self, novelty: float) -> float:
        """s(n) of the module docstring; 0 for a novelty that is not positive and finite."""
        c = self.config
        if not (math.isfinite(novelty) and novelty > 0.0):
            return 0.0
        t = (math.log(novelty) - math.log(c.novelty_clean)) / (
            math.log(c.novelty_spoiled) - math.log(c.novelty_clean)
        )
        return min(max(t, 0.0), 1.0)

    def observe(self, pan: float, novelty: float) -> None:
        """Record a view taken at robot-frame ``pan`` (rad) with ``novelty``. Views with an
        unknown novelty (nan) or pan are ignored."""
        if not (self.config.enabled and math.isfinite(pan) and math.isfinite(novelty)):
            return
        self._pans.append(float(pan))
        self._spoil.append(self.spoil_probability(novelty))
        if len(self._pans) > self.config.memory:
            del self._pans[0], self._spoil[0]

    def move(self, delta: ArrayLike) -> None:
        """The base moved by the odometry increment ``delta`` = (dx, dy, dtheta) in its own
        frame: the remembered pans shift by ``-dtheta``; after ``forget_xy`` of travel since the
        first view remembered, forget all (travel with no view remembered does not count)."""
        if not self._pans:
            return
        d = np.asarray(delta, dtype=np.float64).reshape(-1)
        if d.size < 3 or not np.all(np.isfinite(d)):
            return
        self._travel += math.hypot(float(d[0]), float(d[1]))
        if self._travel > self.config.forget_xy:
            self.reset()
            return
        if d[2] != 0.0:
            self._pans = [float(wrap_angle(p - d[2])) for p in self._pans]

    def reliability(self, pans: ArrayLike) -> FloatArray:
        """r(u) in [0, 1] for each robot-frame pan in ``pans``."""
        u = np.asarray(pans, dtype=np.float64).reshape(-1)
        if not self._pans:
            return np.ones_like(u)
        dist = np.abs(wrap_angle(u[:, None] - np.asarray(self._pans)[None, :]))
        rho = np.clip(1.0 - dist / self.config.reach, 0.0, 1.0)
        return np.prod(1.0 - np.asarray(self._spoil)[None, :] * rho, axis=1)

    def discount(self, values: V) -> V:
        """``values`` with H'(u) = r(u) H(u) + (1 - r(u)) H_0 (module docstring); unchanged
        when disabled."""
        if not self.config.enabled:
            return values
        r = self.reliability(values.actions)
        h = r * values.expected_entropy + (1.0 - r) * values.current_entropy
        return replace(values, expected_entropy=h)  # type: ignore[type-var]

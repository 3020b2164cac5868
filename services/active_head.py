"""The daemon's active vision: its switches, the policy it calls and the head it moves.

:class:`ActiveHead` is the part of the service that turns the camera (paper, section 4):
after each filter update the loop calls :meth:`ActiveHead.step` with the estimate; when
active vision is enabled, not paused, and the head not paused, it asks the policy
(:class:`lino_loc.active_vision.ActivePolicy`, built by :func:`make_active_policy`) for a
pan angle, from the filter's belief (``Localizer.belief``) and the head's latest reading, and
sends it to the head worker. A policy that raises is logged and skipped: active vision
never stops localization.

It also owns the head-settle rule for the frames (:meth:`frame_at_rest`,
:class:`lino_loc.active_vision.HeadSettle`, the rule the policy applies to its own readings)
and counts the frames taken while the head turned or settled.

A converged belief the views have not confirmed yet (state ``global``: a recalled pose, or a
global localization that has just converged) needs new views, and a STANDING robot gets
them only from the head; the policy's expected entropy sees no gain in looking at a
concentrated belief, so when it answers "no gain" or "stay" for such a belief on a standing
base the head makes a confirmation look instead (:meth:`ActiveHead._confirmation_look`,
reason ``confirm``): to the candidate pan of least expected entropy at least
:data:`CONFIRM_LOOK_MIN_TURN` from the present one, under the policy's interval and settle
rules. A driving base makes new views itself.

The switches are read by the loop and written by the control thread (``pause``,
``resume``, ``set_active_vision``), under a lock. Switching active vision off sends the head
back to pan 0 (looking ahead) unless the head is paused. A head command is sent under the same
lock after the switches are read again, so a decision that a switch overtook is dropped and
never undoes the switch.

Usage::

    active = ActiveHead(cfg.active_vision, (head.pan_min, head.pan_max), localizer, heads, worker)
    if active.frame_at_rest(stamp, moving, heads.last_motion): ...  # use the image
    active.step(estimate, frame_stamp)
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from lino_loc.active_vision import (
    ActivePolicy,
    ActiveVisionConfig,
    Decision,
    HeadSettle,
    action_evaluator,
)
from lino_loc.errors import LinoLocError
from lino_loc.localizer import Localizer
from lino_loc.lost_detection import VIEW_THETA, base_stands
from lino_loc.pan_reliability import PanReliabilityConfig
from lino_loc.pose_estimate import Estimate
from services.messages import ActiveVisionInfo

log = logging.getLogger("lino_loc.service")

_METHOD = ActiveVisionConfig()

#: rad: the smallest turn of a confirmation look: one independent view's worth of camera turn
#: (``lino_loc.lost_detection.VIEW_THETA``), so each look counts fully for the lost test.
CONFIRM_LOOK_MIN_TURN = VIEW_THETA

#: The method's settings the service does not expose: the policy uses the defaults of
#: lino_loc.active_vision.ActiveVisionConfig (22 candidate pans and 150 particles as in the
#: paper; the other figures are measured in docs/results.md, "Active vision").
METHOD_SETTINGS = (
    "n_actions", "max_particles", "min_entropy_gain", "trigger_entropy", "trigger_doubt",
    "min_log_likelihood", "move_cost", "pan_tolerance", "predicted_neighbours",
    "entropy_cell_xy", "entropy_cell_theta",
)


class ActiveVisionSettings(BaseModel):
    """The service's ``[active_vision]`` section: what a robot integrator sets (the head's
    range, mechanics and home). :meth:`method_config` completes it with the method's
    settings (:data:`METHOD_SETTINGS`, their defaults)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="choose the camera's pan angle (paper, section 4)")
    pan_min: float = Field(_METHOD.pan_min, ge=-math.pi, le=math.pi, description="radians; within devices.head")
    pan_max: float = Field(_METHOD.pan_max, ge=-math.pi, le=math.pi, description="radians; within devices.head")
    settle_s: float = Field(
        _METHOD.settle_s, ge=0.0,
        description="after the head stops, frames are used for prediction only this long (smear, pan uncertain)",
    )
    min_interval_s: float = Field(_METHOD.min_interval_s, ge=0.0, description="seconds between head movements")
    home_pan: float | None = Field(
        _METHOD.home_pan,
        description="radians; once localized the head returns here (0: looking ahead); unset: it stays",
    )
    reliability: PanReliabilityConfig = Field(
        default_factory=lambda: _METHOD.reliability.model_copy(),
        description="per-pan reliability learned online: avoid pans near views that fit no map entry "
        "(lino_loc.pan_reliability)",
    )

    @model_validator(mode="after")
    def _range(self) -> ActiveVisionSettings:
        if not self.pan_min < self.pan_max:
            raise ValueError(f"pan_min ({self.pan_min}) must be < pan_max ({self.pan_max})")
        return self

    def method_config(self, **update: Any) -> ActiveVisionConfig:
        """The method's configuration: these settings over the method's defaults."""
        return ActiveVisionConfig(**{**self.model_dump(), **update})


def make_active_policy(
    settings: ActiveVisionSettings, localizer: Localizer, head_limits: tuple[float, float]
) -> ActivePolicy:
    """The active-vision policy of the service: the ``[active_vision]`` settings over the
    method's defaults, the localizer's intensity sensor model, and the head's limits
    (``devices.head.pan_min/pan_max``, the limits the head driver clamps its goals to).

    The policy always decides (``enabled`` forced on): the daemon switches active vision on
    and off itself (:class:`ActiveHead`, the control socket's ``set_active_vision``). Raises
    ValueError when the pan range does not overlap the head's limits."""
    av = settings.method_config(enabled=True)
    model = localizer.sensor_model("intensity")
    return ActivePolicy(action_evaluator(model, av), av, head_limits=head_limits)


class ActiveHead:
    """Switches, policy and head commands of the daemon's active vision (module docstring)."""

    def __init__(
        self,
        settings: ActiveVisionSettings,
        head_limits: tuple[float, float],
        localizer: Localizer,
        heads: Any,
        head: Any,
    ) -> None:
        self.settings = settings
        self.head_limits = head_limits
        self.localizer = localizer
        self.heads = heads
        self.head = head
        self.settle = HeadSettle(settings.settle_s)
        self._lock = threading.Lock()
        self.enabled = bool(settings.enabled)
        self.paused = False
        self.head_paused = False
        self.policy: ActivePolicy | None = None
        self.commands = 0
        self.last_decision: str | None = None
        self.last_command: float | None = None
        self.frames_head_moving = 0

    def start(self) -> None:
        """Build the policy if active vision is enabled (a configuration the policy rejects
        disables it, with a warning)."""
        if self.enabled:
            self.ensure_policy("active vision disabled")

    def ensure_policy(self, what: str = "active vision unavailable") -> None:
        """Build the policy if there is none yet (call in the loop's thread)."""
        if self.policy is not None:
            return
        try:
            self.policy = make_active_policy(self.settings, self.localizer, self.head_limits)
        except (ValueError, LinoLocError) as exc:
            log.warning("%s: %s", what, exc)

    # ------------------------------------------------------------------ the loop
    def frame_at_rest(self, stamp: float, moving: bool, last_motion: float | None) -> bool:
        """Whether a frame taken at ``stamp`` shows the head at rest (:class:`HeadSettle`);
        counts the frames that do not."""
        at_rest = self.settle.at_rest(stamp, moving, last_motion)
        if not at_rest:
            with self._lock:
                self.frames_head_moving += 1
        return at_rest

    def step(self, est: Estimate, stamp: float, delta: Any = None, pan: float | None = None) -> float | None:
        """Ask the policy and move the head; returns the pan sent (None: no command).
        ``delta``: the base's odometry increment since the previous frame (None: unknown, no
        confirmation look); ``pan``: the head's pan of the frame the localizer just used with
        an image (None: no image), which with the localizer's ``last_novelty`` feeds the
        policy's per-pan reliability (``[active_vision.reliability]``)."""
        if self.policy is not None:
            novelty = self.localizer.last_novelty if pan is not None else math.nan
            try:
                self.policy.observe(math.nan if pan is None else float(pan), novelty, delta)
            except Exception as exc:  # noqa: BLE001 - active vision must not stop localization
                log.warning("active vision: view not recorded: %s: %s", type(exc).__name__, exc)
        with self._lock:
            active = self.enabled and not self.paused and not self.head_paused
        if not active or self.policy is None or self.head is None:
            return None
        state = self.heads.latest()
        if state is None:
            return None
        particles, log_weights = self.localizer.belief()
        try:
            d = self.policy.decide(
                particles, log_weights, state=est.state, log_likelihood=est.log_likelihood,
                pan=state.pan, moving=state.moving, now=time.time(), frame_stamp=stamp,
                doubt=est.doubt, view_values=self.localizer.view_values,
            )
            standing = delta is not None and base_stands(delta)
            look = self._confirmation_look(d, est, state.pan) if standing else None
            if look is not None:
                d = Decision(look, "confirm", d.belief_entropy, d.values)
        except Exception as exc:  # noqa: BLE001 - active vision must not stop localization
            log.warning("active vision failed: %s: %s", type(exc).__name__, exc)
            return None
        with self._lock:
            self.last_decision = d.reason
            # a switch that came while the policy decided voids the decision: checked and sent
            # under the lock, so the switch's own goal (ahead, when switched off) is the last
            if d.command is None or not (self.enabled and not self.paused and not self.head_paused):
                return None
            self.commands += 1
            self.last_command = float(d.command)
            self.head.command(float(d.command), 0.0)
        log.debug("active vision: pan -> %.2f rad", d.command)
        return float(d.command)

    def _confirmation_look(self, d: Decision, est: Estimate, pan: float) -> float | None:
        """The pan of a confirmation look (module docstring) or None: only for a ``global``
        estimate whose mode is converged (``filter.estimate``) when the policy answered "no
        gain" or "stay" (so its interval and settle rules passed); the candidate of least
        expected entropy plus move cost among those at least :data:`CONFIRM_LOOK_MIN_TURN`
        from ``pan``. Records the command as the policy's own (its interval applies)."""
        policy = self.policy
        if (policy is None or d.values is None or d.reason not in ("no gain", "stay")
                or est.state != "global" or not math.isfinite(pan)):  # fmt: skip
            return None
        if not self.localizer.config.filter.estimate.converged(est.covariance, est.cluster_weight):
            return None
        near = np.flatnonzero(np.abs(d.values.actions - pan) < CONFIRM_LOOK_MIN_TURN)
        if near.size == d.values.actions.size:
            return None
        target = policy.clamp(float(d.values.actions[d.values.best(pan, policy.config.move_cost, near)]))
        policy.last_command_time = time.time()
        policy.last_command = target
        return target

    # ------------------------------------------------------------------ the control thread
    def set_paused(self, target: str, value: bool) -> None:
        """Pause (``value`` True) or resume active vision (``target`` ``"active_vision"``) or
        every head movement (``"head"``)."""
        with self._lock:
            if target == "head":
                self.head_paused = value
            else:
                self.paused = value

    def set_enabled(self, enabled: bool, run_in_loop: Any) -> None:
        """Switch active vision on (building the policy in the loop's thread with
        ``run_in_loop``, e.g. ``CommandQueue.call``) or off (the head looks ahead again)."""
        with self._lock:
            self.enabled = bool(enabled)
            if not enabled and not self.head_paused and self.head is not None:
                self.head.command(0.0, 0.0)
        if enabled and self.policy is None:
            run_in_loop(self.ensure_policy)

    def info(self) -> ActiveVisionInfo:
        """The switches and counters, as the status and the control replies report them."""
        with self._lock:
            return ActiveVisionInfo(
                enabled=self.enabled, paused=self.paused, head_paused=self.head_paused,
                head_commands=self.commands, last_decision=self.last_decision,
                last_command_rad=self.last_command, frames_head_moving=self.frames_head_moving,
            )

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

The switches are read by the loop and written by the control thread (``pause``,
``resume``, ``set_active_vision``), under a lock. Switching active vision off sends the head
back to pan 0 (looking ahead) unless the head is paused.

Usage::

    active = ActiveHead(cfg, localizer, heads, head_worker)
    if active.frame_at_rest(stamp, moving, heads.last_motion): ...  # use the image
    active.step(estimate, frame_stamp)
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from lino_loc.active_vision import ActionEvaluator, ActivePolicy, HeadSettle
from lino_loc.errors import LinoLocError
from lino_loc.localizer import Localizer
from lino_loc.pose_estimate import Estimate
from services.config import ServiceConfig
from services.messages import ActiveVisionInfo

log = logging.getLogger("lino_loc.service")


def make_active_policy(cfg: ServiceConfig, localizer: Localizer) -> ActivePolicy:
    """The active-vision policy of the service: the ``[active_vision]`` settings, the
    localizer's intensity sensor model, and the head's limits ``devices.head.pan_min/pan_max``
    (the same limits the head driver clamps its goals to).

    The policy always decides (``enabled`` forced on): the daemon switches active vision on
    and off itself (:class:`ActiveHead`, the control socket's ``set_active_vision``). Raises
    ValueError when the pan range does not overlap the head's limits."""
    av = cfg.active_vision.model_copy(update={"enabled": True})
    head = cfg.devices.head
    model = localizer.sensor_model("intensity")
    return ActivePolicy(ActionEvaluator(model, av), av, head_limits=(head.pan_min, head.pan_max))


class ActiveHead:
    """Switches, policy and head commands of the daemon's active vision (module docstring)."""

    def __init__(self, cfg: ServiceConfig, localizer: Localizer, heads: Any, head: Any) -> None:
        self.cfg = cfg
        self.localizer = localizer
        self.heads = heads
        self.head = head
        self.settle = HeadSettle(cfg.active_vision.settle_s)
        self._lock = threading.Lock()
        self.enabled = bool(cfg.active_vision.enabled)
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
            self.policy = make_active_policy(self.cfg, self.localizer)
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

    def step(self, est: Estimate, stamp: float) -> float | None:
        """Ask the policy and move the head; returns the pan sent (None: no command)."""
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
                doubt=est.doubt,
            )
        except Exception as exc:  # noqa: BLE001 - active vision must not stop localization
            log.warning("active vision failed: %s: %s", type(exc).__name__, exc)
            return None
        with self._lock:
            self.last_decision = d.reason
            if d.command is not None:
                self.commands += 1
                self.last_command = float(d.command)
        if d.command is None:
            return None
        log.debug("active vision: pan -> %.2f rad", d.command)
        self.head.command(float(d.command), 0.0)
        return float(d.command)

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
            head_paused = self.head_paused
        if enabled and self.policy is None:
            run_in_loop(self.ensure_policy)
        if not enabled and not head_paused and self.head is not None:
            self.head.command(0.0, 0.0)

    def info(self) -> ActiveVisionInfo:
        """The switches and counters, as the status and the control replies report them."""
        with self._lock:
            return ActiveVisionInfo(
                enabled=self.enabled, paused=self.paused, head_paused=self.head_paused,
                head_commands=self.commands, last_decision=self.last_decision,
                last_command_rad=self.last_command, frames_head_moving=self.frames_head_moving,
            )

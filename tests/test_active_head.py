"""The daemon's active vision (services/active_head.py): the switches decide whether the
policy is asked, its command goes to the head, frames during head motion are counted by the
head-settle rule, and a failing policy does not stop the loop."""

from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_fakes import FakeHeads, FakeLocalizer, FakeWorker, HeadReading, estimate  # noqa: E402

from lino_loc.active_vision import Decision
from services.active_head import ActiveHead
from services.config import ServiceConfig


class FakePolicy:
    def __init__(self, command: float | None = 0.7, fail: bool = False) -> None:
        self.command, self.fail, self.calls, self.views = command, fail, [], []

    def observe(self, pan, novelty, delta=None):  # noqa: ANN001, ANN201
        self.views.append((pan, novelty, delta))

    def decide(self, particles, log_weights, **kw):  # noqa: ANN001, ANN003, ANN201
        self.calls.append(kw)
        if self.fail:
            raise RuntimeError("boom")
        return Decision(self.command, "move" if self.command is not None else "converged")


def _active(enabled: bool = True, reading: HeadReading | None = None) -> tuple[ActiveHead, FakeWorker]:
    cfg = ServiceConfig(active_vision={"enabled": enabled, "settle_s": 0.2})
    head = FakeWorker()
    a = ActiveHead(cfg.active_vision, (-2.6, 2.6), FakeLocalizer(), FakeHeads(reading or HeadReading()), head)  # type: ignore[arg-type]
    return a, head


def test_step_sends_the_policy_command_to_the_head() -> None:
    a, head = _active()
    a.policy = FakePolicy(0.7)  # type: ignore[assignment]
    assert a.step(estimate(doubt=0.3), stamp=5.0) == 0.7
    assert head.commands == [(0.7, 0.0)]
    call = a.policy.calls[0]  # type: ignore[union-attr]
    assert call["frame_stamp"] == 5.0 and call["doubt"] == 0.3 and call["state"] == "tracking"
    info = a.info()
    assert info.head_commands == 1 and info.last_command_rad == 0.7 and info.last_decision == "move"


def test_switches_gate_the_policy() -> None:
    a, head = _active()
    a.policy = FakePolicy(0.7)  # type: ignore[assignment]
    for target in ("active_vision", "head"):
        a.set_paused(target, True)
        assert a.step(estimate(), 1.0) is None
        a.set_paused(target, False)
    assert a.step(estimate(), 1.0) == 0.7
    a.set_enabled(False, run_in_loop=lambda fn: fn())
    assert head.commands[-1] == (0.0, 0.0)  # looks ahead again
    assert a.step(estimate(), 2.0) is None and not a.info().enabled


class SwitchedOffWhileDeciding(FakePolicy):
    """A policy during whose decision the control thread switches the head off (``switch``)."""

    def __init__(self, switch) -> None:  # noqa: ANN001
        super().__init__(0.99)
        self.switch = switch

    def decide(self, particles, log_weights, **kw):  # noqa: ANN001, ANN003, ANN201
        d = super().decide(particles, log_weights, **kw)
        self.switch()
        return d


def test_a_decision_overtaken_by_a_switch_does_not_move_the_head() -> None:
    # switched off (or paused) while the policy was deciding: the decision is void, and the
    # head's last goal is the one the switch gave (ahead for off, none for a pause)
    a, head = _active()
    a.policy = SwitchedOffWhileDeciding(lambda: a.set_enabled(False, run_in_loop=lambda fn: fn()))  # type: ignore[assignment]
    assert a.step(estimate(), 1.0) is None
    assert head.commands == [(0.0, 0.0)] and a.info().head_commands == 0
    for target in ("active_vision", "head"):
        a, head = _active()
        a.policy = SwitchedOffWhileDeciding(lambda t=target, a=a: a.set_paused(t, True))  # type: ignore[assignment]
        assert a.step(estimate(), 1.0) is None and head.commands == []


def test_failing_policy_is_skipped() -> None:
    a, head = _active()
    a.policy = FakePolicy(fail=True)  # type: ignore[assignment]
    assert a.step(estimate(), 1.0) is None and head.commands == []


def test_frames_while_the_head_turns_or_settles_are_counted() -> None:
    a, _ = _active()
    assert a.frame_at_rest(10.0, moving=False, last_motion=None)
    assert not a.frame_at_rest(10.0, moving=True, last_motion=None)
    assert not a.frame_at_rest(10.1, moving=False, last_motion=10.0)
    assert a.frame_at_rest(10.3, moving=False, last_motion=10.0)
    assert a.info().frames_head_moving == 2


def test_switching_on_builds_the_policy_in_the_loop() -> None:
    a, _ = _active(enabled=False)
    ran = []
    a.set_enabled(True, run_in_loop=lambda fn: ran.append(fn))
    assert a.info().enabled and ran == [a.ensure_policy]


class NoGainPolicy:
    """A policy that sees no gain anywhere (a concentrated belief): entropies rising away
    from pan 1.0."""

    def __init__(self, reason: str = "no gain") -> None:
        import math

        import numpy as np

        from lino_loc.active_vision import ActionValues

        self.reason = reason
        actions = np.linspace(-2.6, 2.6, 22)
        self.values = ActionValues(actions, 1.0 + np.abs(actions - 1.0), 1.0, 50)
        self.last_command_time, self.last_command = -math.inf, None
        from lino_loc.active_vision import ActiveVisionConfig

        self.config = ActiveVisionConfig()

    def clamp(self, pan: float) -> float:
        return pan

    def decide(self, particles, log_weights, **kw):  # noqa: ANN001, ANN003, ANN201
        return Decision(None, self.reason, 0.5, self.values)  # type: ignore[arg-type]


def test_an_unconfirmed_converged_belief_gets_a_confirmation_look() -> None:
    """state global with a converged mode on a standing base, and the policy sees no gain:
    the head turns to the least-entropy candidate at least CONFIRM_LOOK_MIN_TURN away (a
    standing robot gets new views only so); tracking, a belief not converged, or a driving
    base: nothing."""
    import dataclasses

    import numpy as np

    from lino_loc.localizer import LocalizerConfig
    from services.active_head import CONFIRM_LOOK_MIN_TURN

    for reason in ("no gain", "stay"):
        a, head = _active(reading=HeadReading(pan=1.0))
        a.localizer.config = LocalizerConfig()  # type: ignore[attr-defined]
        a.policy = NoGainPolicy(reason)  # type: ignore[assignment]
        still = np.zeros(3)
        assert a.step(estimate(state="tracking"), 5.0, still) is None
        spread = dataclasses.replace(estimate(state="global"), covariance=np.diag([1.0, 1.0, 0.3]))
        assert a.step(spread, 5.0, still) is None
        assert a.step(estimate(state="global"), 5.0, np.array([0.05, 0.0, 0.0])) is None  # driving
        assert a.step(estimate(state="global"), 5.0) is None  # the base's motion unknown
        pan = a.step(estimate(state="global"), 5.0, np.array([1e-4, 0.0, 0.0]))  # encoder jitter
        assert pan is not None and CONFIRM_LOOK_MIN_TURN <= abs(pan - 1.0) < 0.6, pan
        assert head.commands == [(pan, 0.0)]
        assert a.info().last_decision == "confirm" and a.policy.last_command == pan  # type: ignore[union-attr]


def test_the_views_used_with_an_image_reach_the_policys_reliability() -> None:
    """The frame's pan and the localizer's novelty go to the policy (lino_loc.pan_reliability);
    a frame without an image passes only the odometry (no pan, no novelty)."""
    a, _ = _active()
    a.policy = FakePolicy(None)  # type: ignore[assignment]
    a.localizer.last_novelty = 1.7  # type: ignore[attr-defined]
    a.step(estimate(), stamp=1.0, delta=[0.1, 0.0, 0.0], pan=0.4)
    a.step(estimate(), stamp=1.2, delta=[0.0, 0.0, 0.2], pan=None)
    (p1, n1, d1), (p2, n2, d2) = a.policy.views  # type: ignore[union-attr]
    assert (p1, n1, d1) == (0.4, 1.7, [0.1, 0.0, 0.0])
    assert math.isnan(p2) and math.isnan(n2) and d2 == [0.0, 0.0, 0.2]

"""A hold on the reported state: it changes only once a new state has lasted a few updates.

The filter's state (``global`` / ``tracking`` / ``lost``, ``lino_loc.particle_filter``) is
decided afresh at every update with an image, from the lost test and the view fit. Near their
thresholds it can flip for a single frame and back, which tells a pose client little and makes
a robot that stops when lost stop and go. With a hold of H updates the reported state becomes a
new state s only after H consecutive updates proposed s; any other proposal in between restarts
the count. H = 1 reports every proposal at once (the filter's default,
``FilterConfig.state_hold``).

The hold delays bad news as much as good news: a real loss is reported H - 1 updates later
(at 5 Hz and H = 2, 0.2 s). A new belief (a global start, a pose given or recalled) is
reported at once (:meth:`StateHold.reset`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lino_loc.pose_estimate import State


@dataclass
class StateHold:
    """The reported state under a hold of ``hold`` updates (see the module docstring)."""

    hold: int = 1
    reported: State = "global"
    _pending: State | None = field(default=None, init=False)
    _count: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        if self.hold < 1:
            raise ValueError(f"state hold must be at least 1 update, got {self.hold}")

    def reset(self, state: State) -> None:
        """Report ``state`` at once and forget any pending change (a new belief)."""
        self.reported = state
        self._pending = None
        self._count = 0

    def offer(self, proposed: State) -> State:
        """One update's proposed state; returns the reported state after it."""
        if proposed == self.reported:
            self._pending, self._count = None, 0
        elif proposed == self._pending:
            self._count += 1
        else:
            self._pending, self._count = proposed, 1
        if self._pending is not None and self._count >= self.hold:
            self.reset(self._pending)
        return self.reported

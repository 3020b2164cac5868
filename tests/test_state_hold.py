"""The hold on the reported state: sequences with a known answer, and the filter's use of it."""

from __future__ import annotations

import numpy as np
import pytest

from lino_loc.motion_model import OdometryMotionModel
from lino_loc.particle_filter import AuxiliaryParticleFilter, FilterConfig
from lino_loc.sensor_model import Bounds
from lino_loc.state_hold import StateHold

T, L, G = "tracking", "lost", "global"


def _run(hold: int, proposed: list[str], start: str = T) -> list[str]:
    h = StateHold(hold, start)  # type: ignore[arg-type]
    return [h.offer(s) for s in proposed]  # type: ignore[arg-type]


def test_a_hold_of_one_reports_every_proposal() -> None:
    seq = [T, L, T, T, G, L, L, T]
    assert _run(1, seq) == seq


def test_a_single_frame_flip_is_not_reported_with_a_hold_of_two() -> None:
    assert _run(2, [T, L, T, L, T, T]) == [T] * 6
    # two in a row are: the change appears on the second, H - 1 = 1 update late
    assert _run(2, [T, L, L, L, T, T, T]) == [T, T, L, L, L, T, T]


def test_another_proposal_restarts_the_count() -> None:
    # lost, global, lost: never two of the same in a row, so tracking is kept
    assert _run(2, [L, G, L, G]) == [T] * 4
    assert _run(3, [L, L, G, G, G, L]) == [T, T, T, T, G, G]


def test_reset_reports_at_once_and_forgets_the_pending_change() -> None:
    h = StateHold(3, T)
    h.offer(L)
    h.offer(L)
    h.reset(G)
    assert h.reported == G
    assert h.offer(L) == G  # the count restarted


def test_a_hold_below_one_is_refused() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        StateHold(0)


def test_filter_config_refuses_a_zero_hold() -> None:
    with pytest.raises(ValueError):
        FilterConfig(state_hold=0)


def _filter(hold: int) -> AuxiliaryParticleFilter:
    return AuxiliaryParticleFilter(
        OdometryMotionModel(), Bounds(0.0, 5.0, 0.0, 5.0), FilterConfig(n_particles=200, state_hold=hold),
        rng=np.random.default_rng(3),
    )


def test_the_filter_reports_a_new_belief_at_once_whatever_the_hold() -> None:
    pf = _filter(5)
    assert pf.state == G and pf.estimate().state == G
    pf.set_pose([1.0, 1.0, 0.0], np.diag([0.01, 0.01, 0.01]))
    assert pf.state == T  # a given pose: tracking at once, not after 5 updates
    pf.start_global()
    assert pf.state == G

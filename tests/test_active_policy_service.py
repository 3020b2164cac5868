"""The seam between the daemon and active vision (services/active_head.py ``make_active_policy``):
the policy it builds always decides; the daemon's own switch (``av_enabled``, the control
socket's ``set_active_vision``) says whether it is called. A configuration with
``[active_vision] enabled = false`` that is switched on at run time must move the head."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_localizer import _config, _world  # noqa: E402

from lino_loc.localizer import Localizer
from services.active_head import make_active_policy
from services.config import ServiceConfig


def _head_limits(cfg: ServiceConfig) -> tuple[float, float]:
    return (cfg.devices.head.pan_min, cfg.devices.head.pan_max)


def _uniform_belief(n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(0, 6, n), rng.uniform(0, 3, n), rng.uniform(-math.pi, math.pi, n)])
    return p, np.full(n, -math.log(n))


def test_policy_decides_even_when_the_file_disables_active_vision() -> None:
    m, _, _ = _world()
    cfg = ServiceConfig(active_vision={"enabled": False, "pan_min": -1.0, "pan_max": 1.0})
    policy = make_active_policy(cfg.active_vision, Localizer(m, _config()), _head_limits(cfg))
    p, lw = _uniform_belief()
    d = policy.decide(p, lw, state="global", log_likelihood=-5.0, pan=0.0, moving=False, now=100.0)
    assert d.reason != "disabled"
    assert d.command is not None and -1.0 <= d.command <= 1.0


def test_policy_keeps_inside_the_head_limits() -> None:
    m, _, _ = _world()
    cfg = ServiceConfig(
        devices={"head": {"pan_min": -0.5, "pan_max": 0.25}},
        active_vision={"pan_min": -0.5, "pan_max": 0.25},
    )
    policy = make_active_policy(cfg.active_vision, Localizer(m, _config()), _head_limits(cfg))
    assert (policy.pan_lo, policy.pan_hi) == (-0.5, 0.25)
    p, lw = _uniform_belief()
    d = policy.decide(p, lw, state="global", log_likelihood=-5.0, pan=0.0, moving=False, now=100.0)
    assert d.command is None or -0.5 <= d.command <= 0.25


def test_the_service_feeds_the_views_novelty_to_the_pan_reliability() -> None:
    """``[active_vision.reliability] enabled = true``: the localizer keeps the novelty of the
    last frame used with an image (nan without one), and ActiveHead hands it with the frame's
    pan to the policy, whose reliability then remembers the view."""
    from service_fakes import FakeHeads, FakeWorker, HeadReading

    from services.active_head import ActiveHead

    m, f_img, _ = _world()
    cfg = ServiceConfig(active_vision={"reliability": {"enabled": True}})
    loc = Localizer(m, _config())
    assert math.isnan(loc.last_novelty)
    a = ActiveHead(cfg.active_vision, _head_limits(cfg), loc, FakeHeads(HeadReading()), FakeWorker())
    a.start()
    assert a.policy is not None and a.policy.config.reliability.enabled
    est = loc.update(np.zeros(3), 0.3, f_img(np.array([[0.8, 1.2, 0.3]]))[0])
    assert math.isfinite(loc.last_novelty) and loc.last_novelty > 0.0
    a.step(est, stamp=1.0, delta=np.zeros(3), pan=0.3)
    assert a.policy.reliability.views == 1
    loc.predict_only(np.zeros(3))
    assert math.isnan(loc.last_novelty)

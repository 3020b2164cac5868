"""Do the views confirm the belief? Per channel: how able its views are to confirm a pose, and
how well the recent ones fit.

The lost test (``lino_loc.lost_detection``) looks for evidence AGAINST the belief. Where the
views say little (intensity under a light the map was not made in) a wrong belief collects
none: it hits about as often as a right one, and the test stays quiet while the estimate is
metres off. This component asks the other question, whether there is evidence FOR the belief,
and it asks it per channel of the observation (intensity; disparity too when the map has
it), so that a channel the light does not change can confirm a pose the other cannot, and a
channel whose views stop fitting is heard even when the other one fits.

Each update gives, per channel c, a hit or a miss of the belief: the channel's predictive
log-likelihood of the view exceeds the channel's outlier floor by
``lino_loc.lost_detection.HIT_NATS`` (as in the lost test). Counted per independent view
v_t (``lino_loc.lost_detection.independent_views``), two rates are kept per channel:

- rho_c, the hit rate of a trusted belief, learnt as the lost test learns its own:
  ``rho = (hits + 1/2) / (views + 1)`` (Jeffreys' prior), forgetting :data:`MEMORY` per view,
  :data:`MEMORY_SUSPECT` while the channel misfits, learnt only while ``learn`` (the belief
  is trusted), forgotten (with the recent fit) when the appearance changed (lights switched),
  except for a channel the light does not change (:data:`LIGHT_INVARIANT`). It says how able the
  channel's views are to confirm a pose here and under this light. With ``invariant_prior``
  p > 0 a light-invariant channel starts (after a reset) from p n hits in n =
  ``invariant_prior_views`` views besides Jeffreys' prior, and is heard (its misfit counts,
  below) until it has learnt n views of its own: the first belief a search converges to is
  judged by its disparity views, not only by what it teaches them (a wrong first belief
  whose disparity misses every view would otherwise teach that channel a low rate, and the
  other channel to confirm it). With p below ``informative_hit_rate`` the prior alone never
  makes the channel informative: it can refute a belief, not confirm one;
- f_c, the recent fit: ``f <- a f + (1 - a) [hit]``, ``a = FIT_MEMORY ** v_t``, from 1 for a
  new belief (it fits until its views say otherwise).

A channel is INFORMATIVE when rho_c >= ``informative_hit_rate`` (R); with
``informative_margin`` m > 0 the threshold has a hysteresis: a channel becomes informative at
rho_c >= R + m and stays so while rho_c >= R, so that a rate hovering at R does not flip the
verdict view by view. The verdict
(:meth:`ViewFit.verdict`):

- ``misfit``: some informative channel's recent views stop fitting, f_c < ``min_fit`` x
  rho_c (the recent fit of a right belief is about rho_c; a fit well below the channel's own
  rate is what a wrong one shows): evidence against the belief, also when another channel
  fits (two channels pointing at different places). With ``misfit_alpha`` alpha < 1 also
  f_c below rho_c a^k, k = log(alpha) / log(1 - rho_c) (:func:`misfit_limit`): a fit a
  right belief reaches only through a run of misses it makes with probability alpha. A
  channel below its share but above that limit makes the verdict ``uninformative`` instead
  (a channel that hits three views in four misses a few in a row by chance: the views do
  not confirm the belief, but they do not refute it either). The filter's challenge after a
  misfit counts the share alone (:meth:`ViewFit.stopped_fitting`), whatever alpha;
- ``uninformative``: no channel is informative: the views cannot confirm any pose (except
  for a pose given by the user, :meth:`ViewFit.trust`, until
  :data:`~lino_loc.lost_detection.WARMUP_VIEWS` views have been learnt: the lost test alone
  judges it until then; a belief converged from a search, or one after an appearance change,
  is uninformative until the views have proved themselves);
- ``confirmed``: otherwise (an informative channel fits, and none misfits).

The filter reports ``tracking`` only for a confirmed verdict, ``lost`` for a misfit and
``global`` (converged, not confirmed) for uninformative views (``lino_loc.particle_filter``).

Channels together (each off by default, :class:`ViewFitConfig`):

- ``joint``: with two or more channels in a view, one more channel, :data:`JOINT`, whose
  excess is the largest of the channels' (a hit when SOME channel's view fits the belief),
  learnt and judged like the others; its rho is at least every channel's. Two channels that
  each fit about half the views, not the same half, confirm a pose neither confirms alone,
  and all channels pointing away from the belief is its misfit. With ``joint = "any"`` a
  light-invariant channel, once informative, stays informative until its rho falls below
  :data:`HEARD_HIT_RATE` (hysteresis): a wrong belief teaches its channels low rates, and
  without it the joint channel, fed by the light-variant channel's chance hits under another
  light, would confirm the wrong belief the disparity channel no longer fits. A channel kept
  heard only below the informative rate can make a misfit, never a confirmation. ``"agreeing"``
  takes the smallest channel excess instead of the largest while the channels point at
  different places (overlap below :data:`MIN_OVERLAP`, below) unless all fit;
- ``split = "uninformative"``: informative channels that disagree about the belief (some
  misfit, some fit) leave it unconfirmed (``global``) instead of ``lost``; all informative
  channels misfitting is still ``misfit``;
- ``max_disagreement`` < 1: per view the channels' overlap o_t
  (``lino_loc.channel_agreement.overlap``, belief-independent) gives the recent share of
  views whose channels place the camera at different places,
  ``g <- m g + (1 - m) [o_t < MIN_OVERLAP]``, ``m = DISAGREE_MEMORY ** v_t``, from 0 for a
  new belief; a belief that would be confirmed is ``uninformative`` while g >
  ``max_disagreement``. Views without an overlap (one channel) leave g alone.

:meth:`ViewFit.support` is the views' share of the estimate's ``quality``, in [0, 1], with R =
``informative_hit_rate``:

- a misfit: 0;
- confirmed by informative channels: the smallest over them of
  ``b + (1 - b) f_c clip((rho_c - R) / (1 - R), 0, 1)``, in [b, 1] (the more reliable the
  channel and the better its recent fit, the higher), b = :data:`CONFIRMED_SUPPORT`;
- no informative channel: the largest over the channels of ``b f_c rho_c / R``, below b
  (views that cannot confirm a pose never give more support than views that do).

Observations whose channels have no finite excess are ignored; a view with v_t = 0 (the
camera did not move) changes nothing. How the defaults were chosen: docs/results.md,
"Honest states".

Usage::

    fit = ViewFit()
    fit.update({"intensity": ll_i - floor_i, "disparity": ll_d - floor_d}, views=v, learn=True)
    fit.verdict()   # "confirmed" | "uninformative" | "misfit"
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from lino_loc.lost_detection import HIT_NATS, MEMORY, MEMORY_SUSPECT, WARMUP_VIEWS

#: forgetting factor of the recent fit f_c, per independent view (about 3 views' memory: a
#: kidnapped belief under the mapping light, rho about 0.95, misfits after two missed views)
FIT_MEMORY = 0.7

#: the least support of a belief the views confirm, the most of one they cannot (chosen with the
#: error by quality band of the tracking evaluation on the lab, office and corridor worlds
#: together, docs/results.md, "Honest states")
CONFIRMED_SUPPORT = 0.3

#: channels whose views do not change with the light (the disparity of a stereo pair is its
#: geometry's): an appearance change (``lino_loc.appearance_change``) leaves their rates alone
LIGHT_INVARIANT = frozenset({"disparity"})

#: channels whose mixtures overlap less than this (``lino_loc.channel_agreement.overlap``; two
#: single kernels of width s about 3 s apart, 1 m at the sensor model's 0.35 m) place the
#: camera at different places
MIN_OVERLAP = 0.1

#: forgetting factor of the share of views whose channels disagree, per independent view
#: (about 10 views' memory: channels that KEEP pointing at different places)
DISAGREE_MEMORY = 0.9

#: the name of the channel of all channels' views together (``ViewFitConfig.joint``)
JOINT = "joint"

#: with ``joint = "any"``, a light-invariant channel once informative stays heard until its
#: learnt rate falls below this (chosen on the tracking evaluation's three worlds together:
#: docs/results.md, "Depth in the self-checks")
HEARD_HIT_RATE = 0.3

Verdict = Literal["confirmed", "uninformative", "misfit"]


class ViewFitConfig(BaseModel):
    """When the views confirm the belief, ``filter.view_fit``."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        True, description="report 'tracking' only while some channel's views are able to "
        "confirm the pose and confirm it (false: the lost test alone decides)",
    )
    informative_hit_rate: float = Field(
        0.55, ge=0.0, le=1.0, description="a channel whose learnt hit rate of a trusted belief "
        "is at least this can confirm a pose; below it its views say too little",
    )
    informative_margin: float = Field(
        0.0, ge=0.0, le=1.0, description="hysteresis: a channel becomes informative when its "
        "learnt hit rate reaches informative_hit_rate + this, and stays so until it falls below "
        "informative_hit_rate",
    )
    min_fit: float = Field(
        0.7, ge=0.0, le=1.0, description="an informative channel whose recent hit share falls "
        "below this share of its learnt hit rate no longer fits the belief: 'lost'",
    )
    misfit_alpha: float = Field(
        0.01, gt=0.0, le=1.0, description="'lost' only when the recent hit share is also one a "
        "right belief falls to with probability below this per view (misfit_limit); below "
        "min_fit but not that far, the belief is not confirmed ('global'): a channel whose "
        "views hit often but not always (rho 0.6-0.8) misses a few views in a row by chance, "
        "which does not say the belief is wrong; 1: the share alone; chosen on the tracking "
        "evaluation's three worlds (docs/results.md, 'The lost flicker')",
    )
    joint: Literal["off", "any", "agreeing"] = Field(
        "off", description="with two or more channels, their views together count as one more "
        "channel, 'joint': a hit when some channel's view fits the belief ('any'), and, "
        "'agreeing', only when the channels do not point at different places (or all fit)",
    )
    split: Literal["misfit", "uninformative"] = Field(
        "misfit", description="an informative channel that stops fitting while another "
        "informative one fits (the channels disagree about the belief): 'misfit' ('lost') or "
        "'uninformative' (not confirmed: 'global')",
    )
    max_disagreement: float = Field(
        1.0, ge=0.0, le=1.0, description="a belief is not confirmed ('global') while more than "
        "this share of the recent views had channels placing the camera at different places "
        "(lino_loc.channel_agreement overlap below MIN_OVERLAP); 1: off",
    )
    invariant_prior: float = Field(
        0.5, ge=0.0, lt=1.0, description="the hit rate a light-invariant channel (disparity) "
        "starts from after a reset, worth invariant_prior_views views; the channel is heard "
        "(its misfit counts) until it has learnt that many views of its own: the first belief a "
        "search converges to is judged by its disparity views, not only by what it teaches (a "
        "wrong belief whose disparity misses every view would otherwise teach that channel a "
        "low rate, and the other channel to confirm it); below informative_hit_rate the prior "
        "alone never confirms a pose; 0: Jeffreys' prior (1/2 of one view) alone; chosen on "
        "the tracking evaluation's three worlds (docs/results.md, 'A wrong first belief')",
    )
    invariant_prior_views: float = Field(
        10.0, ge=0.0, description="the independent views invariant_prior is worth (the learnt "
        "rate forgets them as it forgets old views)",
    )


@dataclass
class _ChannelFit:
    hits: float = 0.0
    views: float = 0.0
    fit: float = 1.0  # f_c of the current belief
    heard: bool = False  # kept informative (``joint = "any"``, light-invariant channels)
    informative: bool = False  # rho reached the informative rate (with its margin)
    own: float = 0.0  # views this channel learnt since the reset

    @property
    def rho(self) -> float:
        return (self.hits + 0.5) / (self.views + 1.0)

    def misfits(self, min_fit: float, alpha: float) -> bool:
        """Whether the recent fit is below :func:`misfit_limit` of rho."""
        return self.fit < misfit_limit(self.rho, min_fit, alpha)


def misfit_limit(rho: float, min_fit: float, alpha: float, memory: float = FIT_MEMORY) -> float:
    """The recent fit below which a channel of learnt hit rate ``rho`` misfits:
    min(``min_fit`` rho, rho a^k), a = ``memory``, k = log(alpha) / log(1 - rho).

    The recent fit f <- a f + (1 - a) [hit] of a right belief whose views hit independently
    at rate rho stays about rho; it falls from there to rho a^k only through about k missed
    views in a row, which a right belief makes with probability (1 - rho)^k = ``alpha``. So
    the second term bounds the chance that a right belief misfits at about ``alpha`` per view
    whatever rho (the share alone, ``alpha`` = 1, misfits a right belief at 2 % of the views
    when rho = 0.95 and at 20 % when rho = 0.6); the first is the share rule (a fit well
    below the channel's own rate is what a wrong belief shows)."""
    r = min(max(float(rho), 1e-9), 1.0 - 1e-9)
    k = math.log(alpha) / math.log(1.0 - r)
    return min(min_fit * r, r * memory**k)


@dataclass
class ViewFit:
    """Per-channel hit rates and recent fit of the belief (see the module docstring)."""

    config: ViewFitConfig = field(default_factory=ViewFitConfig)
    channels: dict[str, _ChannelFit] = field(default_factory=dict, init=False)
    _learnt: float = field(default=0.0, init=False)  # views learnt since reset, no forgetting
    _trusted: bool = field(default=False, init=False)
    disagreement: float = field(default=0.0, init=False)  # recent share of disagreeing views

    def reset(self) -> None:
        """Forget everything (a new start)."""
        self.channels.clear()
        self._learnt = 0.0
        self._trusted = False
        self.disagreement = 0.0

    def trust(self) -> None:
        """The belief was given by the user: confirmed until WARMUP_VIEWS views are learnt."""
        self._trusted = True

    def new_belief(self) -> None:
        """A new belief: its recent fit starts again (at 1); the rates stay."""
        for ch in self.channels.values():
            ch.fit = 1.0
        self.disagreement = 0.0

    def appearance_changed(self) -> None:
        """The appearance changed (lights switched): the learnt rates and the recent fit of
        every channel the light changes described the old light; both start again. The
        channels in :data:`LIGHT_INVARIANT` (disparity: depth from the stereo pair's geometry)
        keep theirs, and go on confirming the belief while the others relearn."""
        for name, ch in self.channels.items():
            if name not in LIGHT_INVARIANT:
                ch.hits = ch.views = 0.0
                ch.fit = 1.0
                ch.heard = False
                ch.informative = ch.rho >= self.config.informative_hit_rate + self.config.informative_margin

    def update(
        self, excess: Mapping[str, float], views: float, learn: bool = True,
        overlap: float = math.nan,
    ) -> None:
        """One observation: per channel the predictive log-likelihood minus that channel's
        outlier floor (nats; nan: the channel saw nothing this frame), ``views`` in [0, 1] its
        share of an independent view, ``learn``: the belief is trusted, ``overlap`` the
        channels' overlap (``lino_loc.channel_agreement``; nan: unknown, one channel)."""
        v = min(max(float(views), 0.0), 1.0)
        if v <= 0.0:
            return
        a = FIT_MEMORY**v
        if learn:
            self._learnt += v
        if math.isfinite(overlap):
            ad = DISAGREE_MEMORY**v
            self.disagreement = ad * self.disagreement + (1.0 - ad) * float(overlap < MIN_OVERLAP)
        seen = [x for x in excess.values() if not math.isnan(x)]
        if self.config.joint != "off" and len(seen) > 1:
            excess = {**excess, JOINT: self._joint_excess(seen, overlap)}
        for name, x in excess.items():
            if math.isnan(x):
                continue
            ch = self.channels.get(name) or self._new_channel(name)
            hit = 1.0 if x > HIT_NATS else 0.0
            suspect = ch.misfits(self.config.min_fit, 1.0)
            ch.fit = a * ch.fit + (1.0 - a) * hit
            if learn:
                ch.own += v
                m = (MEMORY_SUSPECT if suspect else MEMORY) ** v
                ch.hits = m * ch.hits + v * hit
                ch.views = m * ch.views + v
            r, m = self.config.informative_hit_rate, self.config.informative_margin
            ch.informative = ch.rho >= r + m or (ch.informative and ch.rho >= r)
            if self.config.joint == "any" and name in LIGHT_INVARIANT:
                r = ch.rho
                ch.heard = r >= self.config.informative_hit_rate or (ch.heard and r >= HEARD_HIT_RATE)

    def _new_channel(self, name: str) -> _ChannelFit:
        """A channel's first view since the reset: Jeffreys' prior, and for a light-invariant
        channel with ``invariant_prior`` p > 0 also p n hits in n = ``invariant_prior_views``
        views, heard until it has learnt n views of its own."""
        ch = _ChannelFit()
        if self._has_prior(name):
            n = self.config.invariant_prior_views
            ch.hits, ch.views = self.config.invariant_prior * n, n
        self.channels[name] = ch
        return ch

    def _has_prior(self, name: str) -> bool:
        """Whether channel ``name`` starts from ``invariant_prior`` (a light-invariant one)."""
        return self.config.invariant_prior > 0.0 and name in LIGHT_INVARIANT

    def _joint_excess(self, seen: list[float], overlap: float) -> float:
        """The joint channel's excess: the largest channel's; with ``joint = "agreeing"`` the
        smallest when the channels point at different places (overlap below MIN_OVERLAP)
        unless every channel hits."""
        apart = math.isfinite(overlap) and overlap < MIN_OVERLAP
        if self.config.joint == "agreeing" and apart and min(seen) <= HIT_NATS:
            return min(seen)
        return max(seen)

    def _informative(self) -> list[_ChannelFit]:
        return [ch for ch in self.channels.values() if ch.informative]

    def _heard(self) -> list[_ChannelFit]:
        """The channels whose misfit counts: the informative ones, those kept heard and those
        still judged by their prior."""
        n = self.config.invariant_prior_views
        return [ch for name, ch in self.channels.items()
                if ch.informative or ch.heard or (self._has_prior(name) and ch.own < n)]

    def verdict(self) -> Verdict:
        """``misfit`` / ``uninformative`` / ``confirmed`` (see the module docstring): with
        ``misfit_alpha`` < 1 a channel below its share of rho but above its
        :func:`misfit_limit` leaves the belief unconfirmed (``uninformative``), not ``misfit``."""
        v = self._verdict(self.config.misfit_alpha)
        if v == "confirmed" and self.config.misfit_alpha < 1.0 and self._verdict(1.0) != "confirmed":
            return "uninformative"
        return v

    def stopped_fitting(self) -> bool:
        """Whether the verdict by the share alone (``min_fit``; ``misfit_alpha`` = 1) is
        ``misfit``: what the filter's challenge after a misfit counts, whatever
        ``misfit_alpha``."""
        return self._verdict(1.0) == "misfit"

    def _verdict(self, alpha: float) -> Verdict:
        informative = self._informative()
        if not informative:
            warm = self._trusted and self._learnt < WARMUP_VIEWS
            return "confirmed" if warm else "uninformative"
        c = self.config
        heard = self._heard()
        misfits = sum(ch.misfits(c.min_fit, alpha) for ch in heard)
        if misfits:
            split = misfits < len(heard)
            return "uninformative" if split and c.split == "uninformative" else "misfit"
        return "uninformative" if self.disagreement > c.max_disagreement else "confirmed"

    def support(self) -> float:
        """The views' support of the belief in [0, 1] (see the module docstring); 0 before
        any view."""
        if not self.channels:
            return 0.0
        r = self.config.informative_hit_rate
        informative = self._informative()
        verdict = self.verdict()
        if verdict == "misfit":
            return 0.0
        if not informative or verdict == "uninformative":
            b = CONFIRMED_SUPPORT
            return max(b * ch.fit * min(1.0, ch.rho / max(r, 1e-9)) for ch in self.channels.values())
        span = max(1.0 - r, 1e-9)
        b = CONFIRMED_SUPPORT
        return min(b + (1.0 - b) * ch.fit * min(max((ch.rho - r) / span, 0.0), 1.0) for ch in informative)

    def hit_rates(self) -> dict[str, float]:
        """rho_c per channel seen so far."""
        return {name: ch.rho for name, ch in self.channels.items()}

"""The Localizer: one object that turns (odometry, pan, image[, disparity]) into a pose estimate.

It owns the appearance map's sensor models (one per channel: the nearest-neighbour model of
section 3, or with ``sensor_model = "interpolated"`` the map's appearance interpolated between
survey poses, ``lino_loc.interpolated_appearance``), the odometry action model, the fusion rule (eq. 7 / 8) and the auxiliary particle filter
(eq. 2-6). One call of :meth:`Localizer.update`:

1. projects the image (and the disparity map, when the map has a disparity channel) through
   the map's channels to feature vectors (eq. 1);
2. builds each channel's J-nearest-neighbour pose mixture and fuses them as configured
   (intensity alone uses J = ``sensor.j``; with disparity, ``fusion.j_intensity`` +
   ``fusion.j_disparity``);
3. runs one filter update with the odometry increment and the head's pan angle (the mixture
   lives in camera poses, the particles are robot poses);
4. returns the :class:`lino_loc.pose_estimate.Estimate` of the robot pose, stamped.

The map is duck-typed (the real one is ``lino_loc.appearance_map.AppearanceMap``): it needs
``poses`` (N, 3) camera poses and ``channels``, a mapping from channel name ("intensity",
optionally "disparity") to objects with ``features`` (N, d) and ``project(array) -> (d,)``.

Usage::

    loc = Localizer(appearance_map, LocalizerConfig())
    est = loc.update((0.1, 0.0, 0.02), pan=0.0, image=img)
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.active_vision import ActionValues
from lino_loc.errors import LinoLocError
from lino_loc.fusion import FusionConfig, fuse
from lino_loc.fusion_weights import AdaptiveFusionWeights
from lino_loc.interpolated_appearance import (
    InterpolatedSensorModel,
    InterpolationConfig,
    fuse_likelihoods,
)
from lino_loc.motion_model import MotionModelConfig, OdometryMotionModel
from lino_loc.particle_filter import AuxiliaryParticleFilter, FilterConfig, FreeSpace
from lino_loc.pose_estimate import Estimate
from lino_loc.sensor_model import (
    Bounds,
    NearestNeighbourSensorModel,
    PoseMixture,
    SensorModelConfig,
    SensorModelKind,
)
from lino_loc.standing_match import StandingMatch, StandingMatchConfig

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)


class ChannelLike(Protocol):
    features: Any

    def project(self, image: np.ndarray) -> np.ndarray: ...


class MapLike(Protocol):
    poses: Any
    channels: Mapping[str, ChannelLike]


class LocalizerConfig(BaseModel):
    """Everything the Localizer needs besides the map: action, sensor, filter and fusion."""

    model_config = ConfigDict(extra="forbid")

    motion: MotionModelConfig = Field(default_factory=MotionModelConfig)
    sensor: SensorModelConfig = Field(default_factory=SensorModelConfig)
    sensor_model: SensorModelKind = Field(
        "nearest_neighbour", description="p(y | x): the J nearest map entries (section 3, "
        "lino_loc/sensor_model.py) or the map's appearance interpolated between survey poses "
        "(lino_loc/interpolated_appearance.py; the map must be a survey lattice)",
    )
    interpolation: InterpolationConfig = Field(default_factory=InterpolationConfig)
    filter: FilterConfig = Field(default_factory=FilterConfig)
    fusion: FusionConfig = Field(default_factory=FusionConfig)
    standing_match: StandingMatchConfig = Field(
        default_factory=StandingMatchConfig, description="a standing robot's views matched jointly "
        "with the map's to place the belief (lino_loc/standing_match.py)",
    )


class Localizer:
    """The map, the models and the filter behind one ``update`` call (see module docstring)."""

    def __init__(
        self,
        appearance_map: MapLike,
        config: LocalizerConfig | None = None,
        rng: np.random.Generator | None = None,
        free_space: FreeSpace | None = None,
    ) -> None:
        self.config = config or LocalizerConfig()
        self.map = appearance_map
        poses = np.asarray(appearance_map.poses, dtype=np.float64)
        channels = dict(appearance_map.channels)
        if "intensity" not in channels:
            raise LinoLocError(f"appearance map: no 'intensity' channel (has {sorted(channels)})")
        self.bounds = Bounds.from_poses(poses, self.config.sensor.map_margin)
        self.models: dict[str, NearestNeighbourSensorModel | InterpolatedSensorModel] = {}
        for name, ch in channels.items():
            if name not in ("intensity", "disparity"):
                continue
            feats = np.asarray(ch.features)
            keep = self._searched_rows(ch, feats.shape[0])
            if not keep.any():
                log.warning("appearance map: the %s channel observed no map entry; not used", name)
                continue
            self.models[name] = self._model(poses[keep], feats[keep])
        self.channels = channels
        #: the intensity channel's novelty of the last frame used (``PoseMixture.novelty``; nan:
        #: no image, or no intensity features); read by active vision's per-pan reliability
        self.last_novelty = math.nan
        fc = self.config.fusion
        self._adaptive = (
            AdaptiveFusionWeights(fc.adaptive)
            if fc.weights == "adaptive" and "disparity" in self.models
            else None
        )
        self.standing = self._standing_match(poses, channels["intensity"])
        seed_rng = rng if rng is not None else np.random.default_rng(self.config.filter.seed)
        self.filter = AuxiliaryParticleFilter(
            OdometryMotionModel(self.config.motion),
            self.bounds,
            self.config.filter,
            free_space=free_space,
            rng=seed_rng,
        )

    def _searched_rows(self, channel: ChannelLike, n: int) -> NDArray[np.bool_]:
        """The map entries a channel's nearest-neighbour model searches: those the channel
        observed (``ChannelMap.observed_rows``: a disparity channel leaves out the entries
        with no valid stereo match, whose zero features are no observation). The interpolated
        model needs the whole survey lattice and keeps every entry."""
        rows = getattr(channel, "observed_rows", None)
        if self.config.sensor_model == "interpolated" or not callable(rows):
            return np.ones(n, dtype=bool)
        return np.asarray(rows(), dtype=bool).reshape(n)

    def _standing_match(self, poses: FloatArray, intensity: ChannelLike) -> StandingMatch | None:
        """The standing match on the map's intensity channel, None when off or when the map is
        no lattice (said once in the log)."""
        cfg = self.config.standing_match
        if not cfg.enabled:
            return None
        match = StandingMatch.for_map(poses, np.asarray(intensity.features), cfg)
        if isinstance(match, str):
            log.info("standing match off: %s", match)
            return None
        return match

    def _model(
        self, poses: FloatArray, features: FloatArray
    ) -> NearestNeighbourSensorModel | InterpolatedSensorModel:
        """One channel's sensor model, of the configured kind (``sensor_model``)."""
        c = self.config
        j = min(c.sensor.j, poses.shape[0])
        if c.sensor_model == "interpolated":
            features = np.asarray(features, dtype=np.float64)
            return InterpolatedSensorModel(poses, features, c.sensor, c.interpolation, self.bounds, j)
        # the model converts the features to float64 where its search needs it (the hnsw
        # search reads the map's own float32 rows)
        return NearestNeighbourSensorModel(poses, features, c.sensor, j=j, bounds=self.bounds)

    # ----------------------------------------------------------------- observation

    def observe(
        self, image: np.ndarray | None, disparity: np.ndarray | None = None
    ) -> PoseMixture | None:
        """The (fused) sensor-model mixture over camera poses for an image and optional
        disparity map, with the current fusion weights; None when there is nothing to observe."""
        mixtures = self.channel_mixtures(image, disparity)
        return None if mixtures is None else self._fuse(mixtures)

    def channel_mixtures(
        self, image: np.ndarray | None, disparity: np.ndarray | None = None
    ) -> dict[str, PoseMixture] | None:
        """Each observing channel's J-nearest-neighbour mixture (section 3); None when no
        channel observes anything."""
        return self._mixtures(self._features(image, disparity))

    def _features(self, image: np.ndarray | None, disparity: np.ndarray | None) -> dict[str, np.ndarray]:
        """Each observing channel's features (eq. 1); a channel with a non-finite one is left out."""
        feats: dict[str, np.ndarray] = {}
        if image is not None:
            feats["intensity"] = np.asarray(
                self.channels["intensity"].project(image), dtype=np.float64
            )
        if disparity is not None and "disparity" in self.models:
            feats["disparity"] = np.asarray(
                self.channels["disparity"].project(disparity), dtype=np.float64
            )
        for name in [n for n, y in feats.items() if not np.all(np.isfinite(y))]:
            # e.g. a disparity map with too few valid pixels: that channel observes nothing
            log.debug("channel %s: non-finite features, not used for this frame", name)
            del feats[name]
        return feats

    def _mixtures(self, feats: dict[str, np.ndarray]) -> dict[str, PoseMixture] | None:
        """The channels' mixtures for their features; None without any."""
        fc = self.config.fusion
        if not feats:
            return None
        both = len(feats) == 2
        j_of = {"intensity": fc.j_intensity, "disparity": fc.j_disparity}
        return {
            name: self.models[name].observe(y, j_of[name] if both else self.config.sensor.j)
            for name, y in feats.items()
        }

    def _fuse(self, mixtures: dict[str, PoseMixture]) -> PoseMixture:
        """Eq. 7 / 8 with the configured weights, or the adaptive ones (``fusion_weights``)."""
        fc = self.config.fusion
        if len(mixtures) == 2 and self._adaptive is not None and fc.mode == "disjunctive":
            w = self._adaptive.weights(list(mixtures))
            fc = fc.model_copy(update={"w_i": w["intensity"], "w_d": w["disparity"]})
        if self.config.sensor_model == "interpolated":
            fused = fuse_likelihoods(mixtures, fc)
        else:
            fused = fuse(mixtures, fc)
        if "intensity" in mixtures and math.isnan(fused.novelty):
            # the filter's kidnap recovery trusts the observation only when the image is
            # familiar; the intensity channel says how familiar (see PoseMixture.novelty)
            fused = replace(fused, novelty=mixtures["intensity"].novelty)
        # each channel's own mixture goes with the fused one: the filter tests the belief
        # against every channel (lino_loc.view_fit)
        return replace(fused, channels=mixtures)

    # ----------------------------------------------------------------- filter

    def update(
        self,
        odometry_delta: ArrayLike,
        pan: float,
        image: np.ndarray | None,
        disparity: np.ndarray | None = None,
        stamp: float | None = None,
    ) -> Estimate:
        """One localization step: odometry increment (dx, dy, dtheta) in the robot frame since
        the last update, the head's pan angle (rad) at the frame's time, the image (None when
        the camera failed: prediction only) and the optional disparity map."""
        feats = self._features(image, disparity)
        mixtures = self._mixtures(feats)
        self.last_novelty = (
            float(mixtures["intensity"].novelty) if mixtures and "intensity" in mixtures else math.nan
        )
        mixture = None
        if mixtures is not None:
            if self._adaptive is not None and len(mixtures) == 2:
                self._adaptive.update(mixtures, self.filter.particles, self.filter.log_weights,
                                      odometry_delta, float(pan))
            mixture = self._fuse(mixtures)
        self.filter.update(odometry_delta, float(pan), mixture)
        if self.standing is not None:
            self.standing.step(self.filter, odometry_delta, pan, feats.get("intensity"))
        return self.estimate(stamp)

    @property
    def fusion_weights(self) -> dict[str, float] | None:
        """The adaptive fusion weights now (None with fixed weights)."""
        if self._adaptive is None:
            return None
        return self._adaptive.weights([n for n in ("intensity", "disparity") if n in self.models])

    def predict_only(self, odometry_delta: ArrayLike, stamp: float | None = None) -> Estimate:
        """Propagate by odometry alone (the camera failed or no frame arrived)."""
        return self.update(odometry_delta, 0.0, None, None, stamp)

    def estimate(self, stamp: float | None = None) -> Estimate:
        """The filter's current estimate, stamped with ``stamp``."""
        return replace(self.filter.estimate(), stamp=stamp)

    def set_pose(self, mean: ArrayLike, cov: ArrayLike, confirmed: bool = True) -> None:
        """A Gaussian belief around a robot pose: ``confirmed`` (an operator's pose) starts
        ``tracking`` at once, and the standing match leaves it until the base moves;
        unconfirmed (a recalled pose) stays ``global`` until the views confirm it
        (:meth:`AuxiliaryParticleFilter.set_pose`)."""
        self.filter.set_pose(mean, cov, confirmed)
        if self.standing is not None:
            self.standing.reset()
            if confirmed:  # an operator's pose: the views of this place do not override it
                self.standing.hold()
        if self._adaptive is not None:
            self._adaptive.reset()

    def start_global(self) -> None:
        """Forget the pose: uniform belief over the mapped area and all headings."""
        self.filter.start_global()
        if self.standing is not None:
            self.standing.reset()
        if self._adaptive is not None:
            self._adaptive.reset()

    # ----------------------------------------------------------------- read-only views

    def particles(self) -> tuple[FloatArray, FloatArray]:
        """(robot poses (N, 3), normalized linear weights (N,)), copies, for viewers."""
        return self.filter.particles.copy(), self.filter.weights

    def belief(self) -> tuple[FloatArray, FloatArray]:
        """(robot poses (N, 3), normalized log-weights (N,)): the filter's own arrays, for
        readers such as active vision. Do not modify them; the next update replaces them."""
        return self.filter.particles, self.filter.log_weights

    def view_values(self, actions: ArrayLike) -> ActionValues | None:
        """Where active vision should look once the standing match has views and the belief is gathered:
        its action values of the pans ``actions`` (``StandingMatch.action_values``, the pan
        farthest from the views kept); None when it would not act or is off (the filter's
        H(u) decides)."""
        if self.standing is None:
            return None
        return self.standing.action_values(self.filter.particles, self.filter.weights,
                                           self.filter.estimate().pose, actions)

    @property
    def appearance_changes(self) -> int:
        """How many times the scene's appearance changed all at once (lights switched) since
        the start (``lino_loc.appearance_change``); 0 when that watch is switched off."""
        return self.filter.appearance_changes

    @property
    def standing_matches(self) -> int:
        """How many times the standing match moved the belief since the start
        (``lino_loc.standing_match``); 0 when it is off."""
        return 0 if self.standing is None else self.standing.matches

    @property
    def standing_relocations(self) -> int:
        """Of :attr:`standing_matches`, how many moved an unconfirmed belief to a far place whose
        views fit better (``StandingMatchConfig.relocate``)."""
        return 0 if self.standing is None else self.standing.relocations

    def sensor_model(
        self, channel: str = "intensity"
    ) -> NearestNeighbourSensorModel | InterpolatedSensorModel:
        """The sensor model of one of the map's channels (the configured kind: the
        nearest-neighbour model of section 3 by default)."""
        try:
            return self.models[channel]
        except KeyError:
            raise LinoLocError(
                f"appearance map: no {channel!r} channel (has {sorted(self.models)})"
            ) from None

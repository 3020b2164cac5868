"""The settings of the active-localization experiment (:mod:`services.evaluation.active`).

:class:`ActiveSetup` holds what the experiment varies (map, test positions, runs, strategies)
and composes the product's own configurations for the rest: the sensor model
(:class:`lino_loc.sensor_model.SensorModelConfig`) and the action evaluation
(:class:`lino_loc.active_vision.ActiveVisionConfig`). Their defaults here are the paper's
section 6.1 (:func:`paper_sensor_model`, :func:`paper_active_vision`): J = 10, kernel widths
35 cm and 0.3 rad, 22 pans over [-2.6, 2.6] rad, H(u) on up to 150 particles. The outlier
weight is 0.01 (the product's default is larger: it tracks under light and scene changes the
map does not know; the experiment's test views are taken under the mapping light).

Two configurations of the method are named here:

* :func:`product_defaults`: the method `lino-loc eval active` runs unless told otherwise (the
  command's option defaults are read from it: the one place to change them);
* :func:`paper_setup` (`eval active --paper`): the paper's section 6.1 as written: intensity
  images alone, no virtual headings, 5 PCA features, no preprocessing, the nearest-neighbour
  sensor model with J = 10, 150 particles, 22 pans, the survey every 75 cm and 15 deg
  (:data:`PAPER_METHOD`). The filter's own settings (global proposal, process-noise floor),
  which the paper does not give, are the product's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from lino_loc.active_vision import ActiveVisionConfig
from lino_loc.fusion import FusionConfig
from lino_loc.interpolated_appearance import InterpolatedSensorModel, InterpolationConfig
from lino_loc.motion_model import MotionModelConfig
from lino_loc.particle_filter import FilterConfig
from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig, SensorModelKind
from lino_loc.standing_match import StandingMatchConfig
from lino_loc.view_match import ViewMatchConfig

STRATEGIES: tuple[str, ...] = ("entropy", "random", "sweep")
#: every strategy :func:`services.evaluation.active.run_position` knows: ``lattice`` is the
#: entropy strategy that, once the belief is gathered near its estimate, chooses the pan by the
#: expected entropy of the map-lattice hypotheses there (:mod:`lino_loc.view_match`)
KNOWN_STRATEGIES: tuple[str, ...] = (*STRATEGIES, "lattice")


def paper_sensor_model(**overrides: Any) -> SensorModelConfig:
    """The experiment's sensor model: J = 10, sigma 0.35 m / 0.3 rad, outlier weight 0.01."""
    return SensorModelConfig(**{"j": 10, "sigma_xy": 0.35, "sigma_theta": 0.3, "outlier_weight": 0.01,
                                **overrides})


def paper_active_vision(**overrides: Any) -> ActiveVisionConfig:
    """The experiment's action evaluation: 22 pans over [-2.6, 2.6] rad, H(u) on <= 150
    particles, predicted observations from all J neighbours, no per-pan reliability (the
    paper's H(u); :func:`product_defaults` turns it on)."""
    return ActiveVisionConfig(**{"n_actions": 22, "pan_min": -2.6, "pan_max": 2.6, "max_particles": 150,
                                 "predicted_neighbours": "all", "reliability": {"enabled": False}, **overrides})


@dataclass(frozen=True)
class ActiveSetup:
    """Parameters of the experiment. The configurations `eval active` runs are
    :func:`product_defaults` and :func:`paper_setup`; the class defaults are the
    experiment's plain building blocks (``filter`` and ``motion`` empty: the configurations'
    own defaults)."""

    world: str = "office"
    lighting: str = "tube"
    step: float = 0.75
    heading_step_deg: float = 15.0
    virtual_headings: int = 5
    virtual_step_deg: float = 3.0
    features: int = 5
    preprocess: str = "none"
    sensor: SensorModelConfig = field(default_factory=paper_sensor_model)
    sensor_model: SensorModelKind = "nearest_neighbour"  # or "interpolated" (lino_loc.interpolated_appearance)
    interpolation: InterpolationConfig = field(default_factory=InterpolationConfig)
    particles: int = 150
    roughen_xy: float = 0.0
    roughen_theta: float = 0.0
    inject: float = 0.0
    active: ActiveVisionConfig = field(default_factory=paper_active_vision)
    positions: int = 50
    runs: int = 10
    movements: int = 10
    scene_changes: tuple[str, ...] = ()
    min_grid_distance: float = 0.15
    criterion_step: float | None = None  # the survey spacing success is judged on (None: ``step``)
    translations: int = 1  # odd m > 1: the map also holds virtual translations every step / m
    decisions: tuple[str, ...] = ()  # services.evaluation.decision_rules reported beside the estimate
    map_memory_budget_mb: float | None = None  # the map build's memory budget (None: the map builder's default)
    sweep_stride: int = 7
    width: int = 320
    height: int = 240
    size: tuple[int, int] = (80, 60)
    seed: int = 0
    workers: int | None = None
    strategies: tuple[str, ...] = STRATEGIES
    view_match: ViewMatchConfig = field(default_factory=ViewMatchConfig)  # the lattice strategy's hypotheses
    lattice_gate: float = 0.5  # the lattice strategy: weight within view_match.radius of the estimate
    standing_match: StandingMatchConfig = field(default_factory=lambda: StandingMatchConfig(enabled=False))
    snapshots: bool = True
    ideal: bool = False
    filter: dict[str, Any] = field(default_factory=dict)
    motion: dict[str, Any] = field(default_factory=dict)
    channels: tuple[str, ...] = ("intensity",)  # with "disparity": the filter fuses both (eq. 8)
    disparity_features: int | None = None  # the disparity channel's features (None: ``features``)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    paper: bool = False  # True: made by paper_setup (the result's setup says so)

    @property
    def judged_step(self) -> float:
        """The position spacing (m) of the grid section 6.1's criterion is judged on and the test
        positions are placed off: ``criterion_step``, or the map's ``step`` when None. A map
        denser than the survey the criterion names (``step`` < ``criterion_step``) is judged on
        the survey's cells."""
        return self.step if self.criterion_step is None else self.criterion_step

    def sensor_model_for(self, entries: Any, features: Any, bounds: Any = None) -> Any:
        """The sensor model :attr:`sensor_model` names over one channel's map features
        (``NearestNeighbourSensorModel`` or ``InterpolatedSensorModel``)."""
        if self.sensor_model == "interpolated":
            return InterpolatedSensorModel(entries, features, self.sensor, self.interpolation, bounds=bounds)
        return NearestNeighbourSensorModel(entries, features, self.sensor, bounds=bounds)

    def filter_config(self) -> FilterConfig:
        return FilterConfig(n_particles=self.particles, **self.filter)

    def motion_config(self) -> MotionModelConfig:
        return MotionModelConfig(**self.motion)

    def report(self) -> dict[str, Any]:
        """The result's ``setup`` object: the experiment's settings with the sensor-model and
        action-evaluation settings it varies inlined (``j``, ``sigma_xy``, ``sigma_theta``,
        ``outlier_weight``; ``eval_particles`` = max_particles, ``n_actions``,
        ``predicted_neighbours``, ``pan_min``, ``pan_max``; ``sensor_model`` and ``residual_scale``
        at the end, only for the interpolated sensor model), tuples as lists; without the
        settings that do not change the figures (workers, snapshots, ideal)."""
        s, a = self.sensor, self.active
        out: dict[str, Any] = {
            "world": self.world, "lighting": self.lighting, "step": self.step,
            "heading_step_deg": self.heading_step_deg, "virtual_headings": self.virtual_headings,
            "virtual_step_deg": self.virtual_step_deg, "features": self.features, "preprocess": self.preprocess,
            "j": s.j, "sigma_xy": s.sigma_xy, "sigma_theta": s.sigma_theta, "outlier_weight": s.outlier_weight,
            "particles": self.particles, "eval_particles": a.max_particles, "roughen_xy": self.roughen_xy,
            "roughen_theta": self.roughen_theta, "inject": self.inject, "n_actions": a.n_actions,
            "predicted_neighbours": a.predicted_neighbours, "pan_min": a.pan_min, "pan_max": a.pan_max,
            "positions": self.positions, "runs": self.runs, "movements": self.movements,
            "scene_changes": self.scene_changes, "min_grid_distance": self.min_grid_distance,
            "sweep_stride": self.sweep_stride, "width": self.width, "height": self.height, "size": self.size,
            "seed": self.seed, "strategies": self.strategies, "filter": dict(self.filter),
            "motion": dict(self.motion), "channels": list(self.channels), "paper": self.paper,
        }
        if self.disparity_features is not None:  # reported only when set
            out["disparity_features"] = self.disparity_features
        if self.criterion_step is not None:  # reported only when set
            out["criterion_step"] = self.criterion_step
        if self.translations > 1:  # reported only when set
            out["translations"] = self.translations
        if self.map_memory_budget_mb is not None:  # reported only when set
            out["map_memory_budget_mb"] = self.map_memory_budget_mb
        if self.decisions:  # reported only when set
            out["decisions"] = list(self.decisions)
        if "lattice" in self.strategies:  # its settings, reported when it runs
            out.update(lattice_gate=self.lattice_gate, view_match=self.view_match.model_dump())
        if self.standing_match.enabled:  # reported when on (lino_loc.standing_match)
            out["standing_match"] = self.standing_match.model_dump()
        if a.reliability.enabled:  # reported when on (lino_loc.pan_reliability)
            out["pan_reliability"] = a.reliability.model_dump()
        if self.sensor_model != "nearest_neighbour":  # the default's report stays as it was
            out.update(sensor_model=self.sensor_model, residual_scale=self.interpolation.residual_scale)
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in out.items()}


def product_defaults(**experiment: Any) -> ActiveSetup:
    """The method `lino-loc eval active` runs by default (its options' defaults come from
    here): the map (survey step and heading step, virtual headings, features, preprocessing,
    channels), the sensor model, the particles, the action evaluation and the filter's and
    motion model's settings. ``experiment``: any other :class:`ActiveSetup` field (world,
    positions, runs, movements, seed, ...), or a method field to override."""
    method: dict[str, Any] = {
        "step": 0.75, "heading_step_deg": 15.0, "virtual_headings": 5, "virtual_step_deg": 3.0, "features": 20,
        "disparity_features": 5, "preprocess": "none", "channels": ("intensity", "disparity"), "translations": 3,
        "sensor_model": "nearest_neighbour",
        "sensor": paper_sensor_model(), "interpolation": InterpolationConfig(), "particles": 150, "inject": 0.0,
        "active": paper_active_vision(reliability={"enabled": True}),
        "filter": {"global_proposal_fraction": 0.5},
        "motion": {"min_sigma_xy": 0.01, "min_sigma_theta": math.radians(0.5)},
        "standing_match": StandingMatchConfig(),
    }
    return ActiveSetup(**{**method, **experiment})


#: The paper's section 6.1 configuration (:func:`paper_setup`): the settings `--paper` fixes.
PAPER_METHOD: dict[str, Any] = {
    "step": 0.75, "heading_step_deg": 15.0, "virtual_headings": 1, "features": 5, "disparity_features": None,
    "preprocess": "none", "channels": ("intensity",), "sensor_model": "nearest_neighbour", "particles": 150,
    "translations": 1, "standing_match": StandingMatchConfig(enabled=False, choose_views=False),
}


def paper_setup(**experiment: Any) -> ActiveSetup:
    """The paper's configuration (:data:`PAPER_METHOD`, :func:`paper_sensor_model`: J = 10,
    :func:`paper_active_vision`: 22 pans, H(u) on <= 150 particles), the rest as :func:`product_defaults`; ``paper`` is
    True. ``experiment``: the fields the paper leaves free (world, positions, runs, ...)."""
    clash = sorted(set(experiment) & (set(PAPER_METHOD) | {"sensor", "active", "paper"}))
    if clash:
        raise ValueError(f"paper_setup: {', '.join(clash)} is fixed by the paper's configuration")
    return replace(product_defaults(**experiment), **PAPER_METHOD, sensor=paper_sensor_model(),
                   active=paper_active_vision(), paper=True)

"""`lino-loc eval active`: the paper's active-localization experiment (section 6.1, Fig. 3, 4).

The method's option defaults are :func:`services.evaluation.active_setup.product_defaults`';
``--paper`` runs :func:`services.evaluation.active_setup.paper_setup` instead, and an option it
fixes given with another value is an error (exit 2).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from pydantic import ValidationError

from lino_loc.errors import LinoLocError
from services.evaluation.active import plot, run
from services.evaluation.active_setup import (
    KNOWN_STRATEGIES,
    STRATEGIES,
    ActiveSetup,
    paper_setup,
    product_defaults,
)
from services.evaluation.commands.localization_cmd import check_translations, parse_channels
from services.evaluation.decision_rules import DECISIONS
from services.evaluation.plotting import pyplot
from services.progress import Progress

log = logging.getLogger(__name__)


def _table(result: dict) -> str:
    lines = [
        f"Active localization in the simulated {result['setup']['world']}: {result['positions']} positions x "
        f"{result['runs']} runs, {result['map_images']} map images ({result['map_entries']} map entries with "
        f"virtual headings), {result['setup']['particles']} particles, "
        f"{result['setup']['n_actions']} pans" + (" (the paper's configuration)" if result["setup"].get("paper") else "")
    ]
    blocks = [("as mapped", result["strategies"], result["success_by_grid_distance"], result.get("comparisons", {}))]
    if "scene_changes" in result:
        sc = result["scene_changes"]
        blocks.append(("scene changes " + "+".join(sc["names"]), sc["strategies"], sc["success_by_grid_distance"],
                       sc.get("comparisons", {})))
    for title, strategies, bands, compared in blocks:
        lines.extend(_block(title, strategies, bands, compared))
    for name, diag in result.get("diagnostics", {}).items():
        lines.append(f"\ndiagnostics ({name}): " + ", ".join(
            f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in diag.items()))
    if result.get("entropy_eval_ms_median") is not None:
        lines.append(f"\nH(u) evaluation: median {result['entropy_eval_ms_median']:.1f} ms CPU")
    if "intervals" in result:
        iv = result["intervals"]
        lines.append(f"95 % intervals and SE: {iv['method']} ({iv['resamples']} resamples, seed {iv['seed']})")
    return "\n".join(lines)


def _block(title: str, strategies: dict, bands: dict, compared: dict) -> list[str]:
    """One scene condition of the table: success, its 95 % interval, bands, comparisons."""
    n = len(next(iter(strategies.values()))["success"])
    lines = [f"\n{title}: success % position / pose cell (mean error m) after k movements",
             f"{'k':<10}" + "".join(f"{k:>14}" for k in range(n))]
    for s, r in strategies.items():
        lines.append(f"{s:<10}" + "".join(
            f"{100 * r['success'][k]:>5.0f}/{100 * r['success_pose'][k]:<3.0f}({r['mean_error_m'][k]:4.2f})"
            for k in range(n)))
        if "success_ci95" in r:
            lines.append(f"{'  95 %':<10}" + "".join(
                f" {f'[{100 * lo:.0f}-{100 * hi:.0f}]':<14}" for lo, hi in r["success_ci95"]))
    for band, b in bands.items():
        lines.append(f"  test positions {band} m from a map position ({b['positions']}): success % " + ", ".join(
            f"{s} " + "/".join(f"{100 * v:.0f}" for v in b[s][:4]) for s in strategies if s in b)
            + " after 0/1/2/3 movements")
    for name, c in compared.items():
        if isinstance(c, dict):
            lines.append(f"  {name.replace('-', ' - ')} (paired): " + ", ".join(
                f"k={k} {100 * c['difference'][k]:+.1f} (SE {100 * c['se'][k]:.1f})"
                + (" ahead" if c["ahead"][k] else "") for k in range(1, min(4, len(c["difference"])))) + " points")
    return lines


#: The method's options: option dest -> its value in a setup. Their defaults are
#: :func:`product_defaults`' (argparse default None = not given).
_METHOD: dict[str, Callable[[ActiveSetup], Any]] = {
    "step": lambda s: s.step,
    "heading_step": lambda s: s.heading_step_deg,
    "virtual_headings": lambda s: s.virtual_headings,
    "virtual_step": lambda s: s.virtual_step_deg,
    "features": lambda s: s.features,
    "disparity_features": lambda s: s.disparity_features,
    "preprocess": lambda s: s.preprocess,
    "channels": lambda s: ",".join(s.channels),
    "sensor_model": lambda s: s.sensor_model,
    "j": lambda s: s.sensor.j,
    "sigma_xy": lambda s: s.sensor.sigma_xy,
    "translations": lambda s: s.translations,
    "residual_scale": lambda s: s.interpolation.residual_scale,
    "particles": lambda s: s.particles,
    "eval_particles": lambda s: s.active.max_particles,
    "actions": lambda s: s.active.n_actions,
    "predicted": lambda s: s.active.predicted_neighbours,
    "pan_reliability": lambda s: "on" if s.active.reliability.enabled else "off",
    "standing_match": lambda s: "on" if s.standing_match.enabled else "off",
    "standing_subcell": lambda s: "on" if s.standing_match.subcell else "off",
    "standing_views": lambda s: "on" if s.standing_match.choose_views else "off",
    "inject": lambda s: s.inject,
    "global_proposal": lambda s: s.filter_config().global_proposal_fraction,
    "floor_xy": lambda s: s.motion_config().min_sigma_xy,
    "floor_theta": lambda s: round(math.degrees(s.motion_config().min_sigma_theta), 9),
}
#: The options `--paper` fixes (:data:`services.evaluation.active_setup.PAPER_METHOD`).
_PAPER_FIXED: tuple[str, ...] = ("step", "heading_step", "virtual_headings", "features", "disparity_features",
                                 "preprocess",
                                 "channels", "sensor_model", "j", "particles", "actions", "pan_reliability",
                                 "translations", "standing_match", "standing_subcell",
                                 "standing_views")
#: Method options mapped one to one onto an ActiveSetup field.
_FIELDS: dict[str, str] = {"step": "step", "heading_step": "heading_step_deg", "virtual_headings": "virtual_headings",
                           "virtual_step": "virtual_step_deg", "features": "features",
                           "disparity_features": "disparity_features", "preprocess": "preprocess",
                           "sensor_model": "sensor_model", "particles": "particles", "inject": "inject",
                           "translations": "translations"}


#: The options of the pydantic configurations' fields (for their validation errors).
_CONFIG_OPTIONS: dict[str, str] = {"n_actions": "--actions", "max_particles": "--eval-particles", "sigma_xy": "--sigma-xy",
                                   "predicted_neighbours": "--predicted", "j": "--j", "residual_scale": "--residual-scale"}


def _option(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def _copy(cfg: Any, **changes: Any) -> Any:
    """A pydantic configuration with ``changes``, validated again."""
    return type(cfg)(**{**cfg.model_dump(), **changes}) if changes else cfg


def with_options(base: ActiveSetup, given: dict[str, Any]) -> ActiveSetup:
    """``base`` with the method options given on the command line (keys of :data:`_METHOD`)."""
    active = {f: given[k] for k, f in (("actions", "n_actions"), ("eval_particles", "max_particles"),
                                       ("predicted", "predicted_neighbours")) if k in given}
    if "pan_reliability" in given:
        active["reliability"] = {**base.active.reliability.model_dump(), "enabled": given["pan_reliability"] == "on"}
    fields: dict[str, Any] = {}
    standing = {f: given[k] == "on" for k, f in (("standing_match", "enabled"), ("standing_subcell", "subcell"),
                                                          ("standing_views", "choose_views"))
                if k in given}
    if standing:
        fields["standing_match"] = _copy(base.standing_match, **standing)
    filt = dict(base.filter)
    if "global_proposal" in given:
        filt["global_proposal_fraction"] = given["global_proposal"]
    motion = dict(base.motion)
    if "floor_xy" in given:
        motion["min_sigma_xy"] = given["floor_xy"]
    if "floor_theta" in given:
        motion["min_sigma_theta"] = math.radians(given["floor_theta"])
    fields.update({f: given[k] for k, f in _FIELDS.items() if k in given})
    if "channels" in given:
        fields["channels"] = parse_channels(given["channels"])
    return replace(base, **fields, filter=filt, motion=motion, active=_copy(base.active, **active),
                   sensor=_copy(base.sensor, **{k: given[k] for k in ("j", "sigma_xy") if k in given}),
                   interpolation=_copy(base.interpolation, **({"residual_scale": given["residual_scale"]}
                                                              if "residual_scale" in given else {})))


def _check_paper(given: dict[str, Any]) -> None:
    """An option ``--paper`` fixes, given with another value, is an error."""
    paper = paper_setup()
    for k in _PAPER_FIXED:
        if k in given:
            v = ",".join(parse_channels(given[k])) if k == "channels" else given[k]
            if v != _METHOD[k](paper):
                raise LinoLocError(f"--paper fixes {_option(k)} {_METHOD[k](paper)} (got {given[k]})")


def _setup(args: argparse.Namespace, changes: tuple[str, ...]) -> ActiveSetup:
    """The experiment's setup from the command line: :func:`product_defaults` or with
    ``--paper`` :func:`paper_setup`, then the method options given."""
    given = {k: getattr(args, k) for k in _METHOD if getattr(args, k) is not None}
    decisions = tuple(d.strip() for d in args.decisions.split(",") if d.strip())
    unknown = [d for d in decisions if d not in DECISIONS]
    if unknown:
        raise LinoLocError(f"--decisions: unknown rule {unknown[0]!r} (known: {', '.join(DECISIONS)})")
    strategies = tuple(x.strip() for x in args.strategies.split(",") if x.strip())
    bad = [x for x in strategies if x not in KNOWN_STRATEGIES]
    if bad or len(set(strategies)) != len(strategies) or len(strategies) < 1:
        raise LinoLocError(f"--strategies: {bad[0] if bad else args.strategies!r} is not a list of distinct "
                           f"strategies of {', '.join(KNOWN_STRATEGIES)}")
    experiment = dict(world=args.world, strategies=strategies, positions=args.positions, runs=args.runs, movements=args.movements,
                      scene_changes=changes, seed=args.seed, workers=args.workers, ideal=args.ideal,
                      criterion_step=args.criterion_step, decisions=decisions,
                      map_memory_budget_mb=args.map_memory_budget)
    if args.map_memory_budget is not None and not args.map_memory_budget > 0.0:
        raise LinoLocError(f"--map-memory-budget must be positive (got {args.map_memory_budget})")
    if args.criterion_step is not None and not args.criterion_step > 0.0:
        raise LinoLocError(f"--criterion-step must be positive (got {args.criterion_step})")
    for name, value in (("--positions", args.positions), ("--runs", args.runs), ("--movements", args.movements),
                        *((_option(k), given[k]) for k in ("particles", "actions", "eval_particles",
                                                           "virtual_headings", "disparity_features") if k in given)):
        if value < 1:
            raise LinoLocError(f"{name} must be at least 1 (got {value})")
    if "residual_scale" in given and not given["residual_scale"] > 0.0:
        raise LinoLocError(f"--residual-scale must be positive (got {given['residual_scale']})")
    if "translations" in given:
        check_translations(given["translations"])
    if args.paper:
        _check_paper(given)
    try:
        setup = with_options(paper_setup(**experiment) if args.paper else product_defaults(**experiment), given)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = str(err["loc"][0]) if err["loc"] else ""
        raise LinoLocError(f"{_CONFIG_OPTIONS.get(field, field)}: {err['msg']}") from None
    return setup


def _run(args: argparse.Namespace) -> int:
    if args.plot:
        pyplot()  # fails now, in one line naming the extra, rather than after the run
    changes: tuple[str, ...] = ()
    if args.scene_changes:
        changes = tuple(c.strip() for c in args.scene_changes.split(",") if c.strip())
        if changes == ("all",):
            from drivers.sim.world import load_world

            changes = load_world(args.world).scene_change_names
    setup = _setup(args, changes)
    bar = Progress("active")
    result, extras = run(setup, progress=lambda label, d, n: bar.update(d, n, label=label))
    bar.close()
    if args.plot:
        for f in plot(result, extras, args.plot):
            log.info("wrote %s", f)
    print(json.dumps(result) if args.json else _table(result))
    return 0


def register_eval(eval_sub: argparse._SubParsersAction) -> None:
    d = product_defaults()
    dv = {k: get(d) for k, get in _METHOD.items()}
    p = eval_sub.add_parser(
        "active",
        help="Fig. 3: localization error and success against camera movements (entropy, random, sweep)",
        description="The paper's active-localization experiment (section 6.1) in a simulated world: a survey "
        "map, a filter from a uniform initial belief, test positions off the grid, strategies "
        f"{', '.join(STRATEGIES)}; success ratios with 95 % intervals and the strategies' paired differences "
        "with their standard errors (bootstrap over positions then runs). By default the product's method "
        f"(map every {dv['step']:g} m and {dv['heading_step']:g} deg, {dv['virtual_headings']} virtual headings, "
        f"{dv['features']} features, channels {dv['channels']}, {dv['sensor_model']} sensor model, "
        f"J = {dv['j']}, {dv['particles']} particles, {dv['actions']} pans); --paper: the paper's.",
    )
    p.add_argument("--paper", action="store_true",
                   help="the paper's configuration of section 6.1: intensity alone, no virtual headings, 5 features, "
                   "no preprocessing, nearest-neighbour sensor model J = 10, 150 particles, 22 pans, survey every "
                   "0.75 m / 15 deg; any of those options given with another value is an error")
    p.add_argument("--world", default=d.world)
    p.add_argument("--positions", type=int, default=d.positions, help=f"test positions (default {d.positions})")
    p.add_argument("--runs", type=int, default=d.runs, help=f"runs per position (default {d.runs})")
    p.add_argument("--movements", type=int, default=d.movements,
                   help=f"camera movements per run (default {d.movements})")
    _method_options(p, dv)
    p.add_argument("--ideal", action="store_true",
                   help="also compute the sensor model's upper bound (dense-grid posterior, no particles) and "
                   "the map oracle (the map position whose stored views best match the views taken)")
    p.add_argument("--scene-changes", default="",
                   help="also run with these scene changes of the world (comma-separated, or 'all')")
    p.add_argument("--criterion-step", type=float, default=None,
                   help="judge success (section 6.1) on a survey grid of this spacing, metres, and place the "
                   "test positions off it (default: --step); with a denser map (--step 0.375 --criterion-step "
                   "0.75) it measures what views between the survey's poses would give")
    p.add_argument("--map-memory-budget", type=float, metavar="MB",
                   help="memory budget of the map build, MiB: a disparity channel whose EM would need more is "
                   "fitted on a random sample of the views (lino_loc.appearance_map.disparity_fit_rows; default "
                   "the map builder's)")
    p.add_argument("--decisions", default="", metavar="RULES",
                   help="also judge these final decisions on the same runs, comma-separated: "
                   f"{', '.join(DECISIONS)} (services.evaluation.decision_rules)")
    p.add_argument("--strategies", default=",".join(STRATEGIES), metavar="NAMES",
                   help=f"the strategies compared, comma-separated, the first is the one compared with the others: "
                   f"{', '.join(KNOWN_STRATEGIES)} (default {','.join(STRATEGIES)})")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--plot", metavar="DIR", default=None, help="write Fig. 3 and Fig. 4 PNGs here")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run)


def _method_options(p: argparse.ArgumentParser, dv: dict[str, Any]) -> None:
    """The method's options; their defaults ``dv`` (:func:`product_defaults`' values)."""
    p.add_argument("--particles", type=int, help=f"particles of the filter (default {dv['particles']})")
    p.add_argument("--eval-particles", type=int,
                   help=f"particles used to evaluate H(u) (default {dv['eval_particles']})")
    p.add_argument("--predicted", choices=("all", "leave_one_out"),
                   help=f"sensor model of a predicted observation (see lino_loc.active_vision; default "
                   f"{dv['predicted']})")
    p.add_argument("--pan-reliability", choices=("on", "off"),
                   help="entropy strategy: discount H(u) at pans near views that fit no map entry, learned "
                   f"online (lino_loc.pan_reliability; default {dv['pan_reliability']})")
    p.add_argument("--standing-match", choices=("on", "off"),
                   help="move the belief to where the views taken so far jointly match the map's views "
                   f"(lino_loc.standing_match, as the service does; default {dv['standing_match']})")
    p.add_argument("--standing-subcell", choices=("on", "off"),
                   help="the standing match places the position between the map's lattice points "
                   f"(StandingMatchConfig.subcell; default {dv['standing_subcell']})")
    p.add_argument("--standing-views", choices=("on", "off"),
                   help="entropy strategy: once the belief is gathered near the standing match's views, look at the pan farthest from "
                   "the views taken instead of the filter's H(u) (lino_loc.view_spread; "
                   f"StandingMatchConfig.choose_views, as the service does; default {dv['standing_views']})")
    p.add_argument("--inject", type=float,
                   help="investigation: after each update replace this fraction of the particles by draws "
                   f"from the image's sensor model (default {dv['inject']:g}; 0: the filter as the service runs it)")
    p.add_argument("--global-proposal", type=float,
                   help="FilterConfig.global_proposal_fraction: share of the particles drawn from the first "
                   f"image's sensor model (0: the plain APF from the uniform set; default {dv['global_proposal']:g})")
    p.add_argument("--floor-xy", type=float,
                   help=f"MotionModelConfig.min_sigma_xy: process-noise floor per update, metres "
                   f"(default {dv['floor_xy']:g})")
    p.add_argument("--floor-theta", type=float,
                   help=f"MotionModelConfig.min_sigma_theta: process-noise floor per update, degrees "
                   f"(default {dv['floor_theta']:g})")
    p.add_argument("--step", type=float, help=f"map grid step, metres (default {dv['step']:g})")
    p.add_argument("--heading-step", type=float, help=f"map heading step, degrees (default {dv['heading_step']:g})")
    p.add_argument("--actions", type=int, help=f"candidate pan angles (default {dv['actions']})")
    p.add_argument("--virtual-headings", type=int,
                   help="views per map image, turned by multiples of --virtual-step (lino_loc.virtual_views); "
                   f"1 = the paper's plain map (default {dv['virtual_headings']})")
    p.add_argument("--virtual-step", type=float,
                   help=f"degrees between virtual headings (default {dv['virtual_step']:g})")
    p.add_argument("--features", type=int, help=f"PCA features (default {dv['features']})")
    p.add_argument("--disparity-features", type=int,
                   help="the disparity channel's PCA features (default: --features"
                   + ("" if dv["disparity_features"] is None else f"; product default {dv['disparity_features']}") + ")")
    p.add_argument("--preprocess", choices=("none", "histeq", "gradient"),
                   help=f"image preprocessing before PCA (default {dv['preprocess']}; section 6.1 names none)")
    p.add_argument("--j", type=int, help=f"nearest neighbours of the sensor model (default {dv['j']})")
    p.add_argument("--translations", type=int,
                   help="odd m > 1: the map also holds every survey view seen from a lattice every --step / m "
                   "inside its cell, synthesized from the view's sparse stereo disparity, both channels "
                   f"(lino_loc.virtual_translations; default {dv['translations']})")
    p.add_argument("--sigma-xy", type=float,
                   help=f"the sensor model's kernel width in x and y, metres (default {dv['sigma_xy']:g}; a map "
                   "denser than the survey may want a narrower one)")
    p.add_argument("--sensor-model", choices=("nearest_neighbour", "interpolated"),
                   help="p(y | x): the J nearest map entries (nearest_neighbour, section 3) or the map's appearance "
                   f"interpolated between survey poses (lino_loc.interpolated_appearance); default {dv['sensor_model']}")
    p.add_argument("--residual-scale", type=float,
                   help=f"interpolated sensor model: scale of the leave-one-out residuals (default "
                   f"{dv['residual_scale']:g})")
    p.add_argument("--channels",
                   help="the map's channels: intensity, or intensity,disparity (the filter fuses both, eq. 8; "
                   f"the views are chosen with the intensity channel's predictions; default {dv['channels']})")

"""`lino-loc eval global | tracking | leave-out`: the localization evaluations.

- ``global``: global localization in the simulated office, error and success (section 6.1)
  against the number of updates (:mod:`services.evaluation.global_loc`);
- ``tracking``: a drive of several minutes through the simulated lab under other light and
  unmodelled scene changes (:mod:`services.evaluation.tracking`);
- ``leave-out DATASET``: the sensor-model error of eq. 10 on held-out frames of a dataset,
  against its floor (:mod:`services.evaluation.leave_out`).

Each prints a short table, or with ``--json`` exactly one JSON object (keys documented in
docs/evaluations.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from typing import Any

from lino_loc.disparity import STEREO_PRESETS
from lino_loc.errors import LinoLocError
from lino_loc.preprocessing import PREPROCESS_METHODS
from services.progress import Progress


def _progress() -> tuple[Progress, object]:
    bar = Progress("eval")

    def cb(label: str, done: int, total: int) -> None:
        bar.update(done, total, label=label)

    return bar, cb


def _localizer_config(args: argparse.Namespace):  # -> LocalizerConfig
    from lino_loc.localizer import LocalizerConfig

    cfg = LocalizerConfig()
    if getattr(args, "config", None):
        from services.config import load_config

        cfg = load_config(args.config).localizer
    if getattr(args, "fusion_weights", None):
        cfg = cfg.model_copy(deep=True)
        cfg.fusion.weights = args.fusion_weights
    return cfg


def check_translations(m: int) -> int:
    """``--translations`` m: odd and positive (the lattice of virtual translations has a centre
    view, ``lino_loc.virtual_translations``), else a one-line error."""
    if m < 1 or m % 2 == 0:
        raise LinoLocError(f"--translations must be odd and positive (got {m})")
    return m


def add_tracking_map_arguments(p: argparse.ArgumentParser) -> None:
    """The map and drive options of ``eval tracking`` (and of ``benchmarks/tracking_seeds.py``),
    read back by :func:`tracking_map_settings`."""
    p.add_argument("--step", type=float, default=0.5, help="map grid step, metres (default: the lab's 0.5)")
    p.add_argument("--heading-step", type=float, default=10.0, help="map heading step, degrees (default 10)")
    p.add_argument("--virtual-headings", type=int, default=1, choices=range(1, 32), metavar="N",
                   help="map entries per survey image, turned 3 deg apart (lino_loc.virtual_views; default 1: "
                   "the images alone; config/sim.toml's map: 5)")
    p.add_argument("--translations", type=int, default=1,
                   help="odd m > 1: the map also holds virtual translations every step / m "
                   "(lino_loc.virtual_translations; default 1: none; config/sim.toml's map: 3)")
    p.add_argument("--disparity-features", type=int, default=None,
                   help="features of the disparity channel (default: --features; config/sim.toml's map: 5)")
    p.add_argument("--pauses", type=float, default=0.0, metavar="P",
                   help="chance that the drive stops 0.3-2 s at each goal it reaches (drivers.sim.drive; "
                   "default 0: it never stands; the simulated robot: 0.3)")


def tracking_map_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The ``TrackingSetup`` fields of :func:`add_tracking_map_arguments`' options, checked
    (a one-line error for a bad value)."""
    if args.step <= 0 or args.heading_step <= 0:
        raise LinoLocError("--step and --heading-step must be positive")
    check_translations(args.translations)
    if args.disparity_features is not None and args.disparity_features < 1:
        raise LinoLocError(f"--disparity-features must be positive (got {args.disparity_features})")
    if not 0.0 <= args.pauses <= 1.0:
        raise LinoLocError(f"--pauses must be a probability in [0, 1] (got {args.pauses})")
    return {"step": args.step, "heading_step_deg": args.heading_step, "virtual_headings": args.virtual_headings,
            "translations": args.translations, "disparity_features": args.disparity_features,
            "pause_probability": args.pauses}


def parse_channels(text: str) -> tuple[str, ...]:
    """``--channels``: ``intensity`` or ``intensity,disparity`` (the map's channels, fused by
    eq. 8 with the ``[localizer.fusion]`` settings when disparity is among them)."""
    names = tuple(c.strip() for c in text.split(",") if c.strip())
    unknown = [c for c in names if c not in ("intensity", "disparity")]
    if unknown or "intensity" not in names or len(set(names)) != len(names):
        raise LinoLocError(f"--channels: expected intensity or intensity,disparity, got {text!r}")
    return names


def add_channels_option(p: argparse.ArgumentParser, default: str = "intensity") -> None:
    p.add_argument("--channels", default=default, type=str,
                   help="the map's channels: intensity, or intensity,disparity (the survey's stereo "
                   f"pairs through the product's matcher, fused by eq. 8 with [localizer.fusion]; default {default})")
    p.add_argument("--stereo", default="bm", choices=tuple(STEREO_PRESETS),
                   help="the disparity channel's matcher: bm (StereoBM at the camera's size, the product's), "
                   "bm/2 (at half size), sgbm, sgbm/2 (semi-global)")
    p.add_argument("--fusion-weights", default=None, choices=("fixed", "adaptive"),
                   help="eq. 8's weights: fixed (the paper's 1/2, 1/2) or adaptive (each channel's recent "
                   "predictive likelihood); default: the configuration's")


def given_map(path: str | None, channels: tuple[str, ...]):  # -> AppearanceMap | None
    """``--map FILE``: the map to evaluate instead of the rendered survey's (None without it).
    LinoLocError (one line) when it cannot be loaded or lacks a channel of ``--channels``."""
    if not path:
        return None
    from lino_loc.appearance_map import AppearanceMap

    amap = AppearanceMap.load(path)
    missing = [c for c in channels if c not in amap.channels]
    if missing:
        raise LinoLocError(f"--map {path}: has no {', '.join(missing)} channel (it has "
                           f"{', '.join(amap.channels)}); match --channels to it")
    return amap


MAP_HELP = ("evaluate this map file (e.g. `lino-loc map build` of a `survey --robot` dataset) instead of "
            "the rendered survey's; the test views are the same; its working size and preprocessing are the map's")


def add_map_option(p: argparse.ArgumentParser, help: str = MAP_HELP) -> None:
    p.add_argument("--map", default=None, metavar="FILE", help=help)


def map_record(path: str, amap) -> dict:  # amap: AppearanceMap
    """What the JSON says of a ``--map`` file: its path and its sessions (``map extend``)."""
    return {"file": str(path), "sessions": [s.model_dump() for s in amap.session_list()]}


# --------------------------------------------------------------------------- global


def parse_counts(text: str | None) -> tuple[int, ...] | None:
    """``--particles``: one count or several, comma-separated (None: the configuration's).
    LinoLocError (one line) on a count that is not a whole number of at least 1."""
    if text is None:
        return None
    parts = [c.strip() for c in text.split(",") if c.strip()]
    try:
        counts = tuple(int(c) for c in parts)
    except ValueError:
        counts = ()
    if not counts or any(n < 1 for n in counts):
        raise LinoLocError(f"--particles: expected whole numbers of at least 1, comma-separated, got {text!r}")
    return counts


def parse_cameras(text: str) -> tuple[str, ...]:
    """``--camera``: fixed, active, or both comma-separated. LinoLocError (one line) otherwise."""
    from services.evaluation.global_loc import CAMERAS

    names = tuple(c.strip() for c in text.split(",") if c.strip())
    if not names or any(c not in CAMERAS for c in names) or len(set(names)) != len(names):
        raise LinoLocError(f"--camera: expected fixed, active or fixed,active, got {text!r}")
    return names


def _global_setup(args: argparse.Namespace):  # -> GlobalSetup
    from services.evaluation.global_loc import GlobalSetup

    if args.starts < 1 or args.updates < 1:
        raise LinoLocError("--starts and --updates must be at least 1")
    if args.step <= 0 or args.heading_step <= 0:
        raise LinoLocError("--step and --heading-step must be positive")
    if args.head_speed <= 0:
        raise LinoLocError(f"--head-speed: must be positive, got {args.head_speed}")
    return GlobalSetup(world=args.world, step=args.step, heading_step_deg=args.heading_step,
                       features=args.features, preprocess=args.preprocess,
                       starts=args.starts, updates=args.updates, rate=args.rate,
                       j=args.j, seed=args.seed, workers=args.workers, virtual_headings=args.virtual_headings,
                       channels=parse_channels(args.channels), sensor_model=args.sensor_model,
                       head_speed=args.head_speed)


def _print_global(res: dict) -> None:
    print(f"global localization, {res['world']}, camera {res['camera']}: {res['starts']} starts, map "
          f"{res['map_entries']} entries ({'+'.join(res['channels'])}), "
          f"{res['features']} features, J={res['J']}, {res['particles']} particles, {res['rate_hz']:g} Hz")
    print(f"{'update':>6} {'mean err m':>11} {'median m':>9} {'success':>8} {'converged':>10} {'tracking':>9}")
    for k in range(res["updates"]):
        print(f"{k + 1:>6} {res['mean_error_m'][k]:>11.3f} {res['median_error_m'][k]:>9.3f} "
              f"{res['success'][k]:>8.2f} {res['converged_by_update'][k]:>10.2f} {res['tracking'][k]:>9.2f}")
    c = res["converge"]
    med = "-" if c["median_s"] is None else f"{c['median_updates']:g} updates ({c['median_s']:.1f} s)"
    print(f"converged {100 * c['share']:.0f} % of starts, median {med}; filter update "
          f"{res['update_cpu_ms']['median']:.1f} ms CPU")


def _global(args: argparse.Namespace) -> int:
    from services.evaluation.global_loc import run_grid

    setup = _global_setup(args)
    cameras = parse_cameras(args.camera)
    counts = parse_counts(args.particles)
    amap = given_map(args.map, setup.channels)
    if amap is not None:
        setup = dataclasses.replace(setup, size=amap.size, preprocess=amap.preprocess)
    bar, cb = _progress()
    grid = run_grid(setup, counts, cameras, _localizer_config(args), appearance_map=amap,  # type: ignore[arg-type]
                    progress=cb)
    bar.close()
    for res in grid["runs"]:
        if amap is not None:
            res["map"] = map_record(args.map, amap)
    single = len(grid["runs"]) == 1
    if args.json:
        print(json.dumps(grid["runs"][0] if single else grid))
        return 0
    for res in grid["runs"]:
        _print_global(res)
    return 0


# --------------------------------------------------------------------------- tracking


def _switch_lights(text: str, lights: tuple[str, ...]) -> tuple[str, str] | None:
    """``--switch-lights A,B`` (``none``: no switch run); both must be among ``--lights``."""
    if text in ("", "none"):
        return None
    pair = tuple(c.strip() for c in text.split(","))
    if len(pair) != 2 or not all(pair):
        raise LinoLocError(f"--switch-lights: expected two lights A,B or none, got {text!r}")
    missing = [c for c in pair if c not in lights]
    if missing:
        raise LinoLocError(f"--switch-lights: {', '.join(missing)} not in --lights {','.join(lights)}")
    return pair[0], pair[1]


def _tracking(args: argparse.Namespace) -> int:
    from services.evaluation.tracking import TrackingSetup, run

    pre = tuple(PREPROCESS_METHODS) if args.preprocess == "all" else (args.preprocess,)
    changes = () if args.changes in ("", "none") else tuple(c for c in args.changes.split(",") if c)
    lights = tuple(c for c in args.lights.split(",") if c)
    if args.duration <= 0 or args.rate <= 0:
        raise LinoLocError("--duration and --rate must be positive")
    setup = TrackingSetup(world=args.world, features=args.features, preprocess=pre, lights=lights,
                          **tracking_map_settings(args), scene_changes=changes, duration=args.duration, rate=args.rate,
                          particles=args.particles, j=args.j, global_start=not args.no_global,
                          compare_recovery=not args.no_recovery_comparison, kidnap=not args.no_kidnap,
                          switch_lights=_switch_lights(args.switch_lights, lights),
                          seed=args.seed, workers=args.workers, channels=parse_channels(args.channels),
                          stereo=STEREO_PRESETS[args.stereo])
    amap = given_map(args.map, ())
    maps = None
    if amap is not None:  # the map's preprocessing, channels, features and camera size
        setup = dataclasses.replace(setup, preprocess=(amap.preprocess,), channels=tuple(amap.channels),
                                    features=amap.channels["intensity"].n_features, width=amap.camera.width,
                                    height=amap.camera.height, size=amap.size)
        maps = {amap.preprocess: amap}
    bar, cb = _progress()
    res = run(setup, _localizer_config(args), maps=maps, trajectories=args.trajectories,  # type: ignore[arg-type]
              progress=cb)
    bar.close()
    if amap is not None:
        res["map"] = map_record(args.map, amap)
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"tracking, {res['world']}: {res['duration_s']:.0f} s, {res['path_length_m']:.1f} m, "
          f"{res['frames']} frames, map {res['map_entries']} entries ({'+'.join(res['channels'])}), "
          f"{res['features']} features, "
          f"J={res['J']}, {res['particles']} particles; scene changes: {', '.join(res['scene_changes']) or 'none'}")
    tables = res.get("by_preprocess", {res["preprocess"]: res["conditions"]})
    for p, conds in tables.items():
        print(f"preprocess {p}:")
        print(f"  {'light':<8} {'ATE m':>7} {'mean m':>7} {'max m':>7} {'head deg':>9} {'conv s':>7}"
              f"   without recovery: {'mean m':>7} {'max m':>7} {'conv s':>7}")
        for light, r in conds.items():
            conv = r.get("converged_after_s")
            line = (f"  {light:<8} {r['ate_rmse_m']:>7.3f} {r['mean_error_m']:>7.3f} {r['max_error_m']:>7.3f} "
                    f"{r['heading_rmse_deg']:>9.2f} {'-' if conv is None else f'{conv:.1f}':>7}")
            w = r.get("without_recovery")
            if w:
                c0 = w.get("converged_after_s")
                line += (f"                     {w['mean_error_m']:>7.3f} {w['max_error_m']:>7.3f} "
                         f"{'-' if c0 is None else f'{c0:.1f}':>7}")
            print(line)
    o = res["odometry"]
    print(f"  odometry alone: ATE {o['ate_rmse_m']:.3f} m, mean {o['mean_error_m']:.3f} m, max {o['max_error_m']:.3f} m")
    sw = res.get("light_switch")
    if sw:
        print(f"  lights {' -> '.join(sw['lights'])} at {sw['switch_at_s']:.0f} s: mean error before / after "
              f"{sw['mean_error_before_m']:.3f} / {sw['mean_error_after_m']:.3f} m (max after "
              f"{sw['max_error_after_m']:.3f}), lost {100 * sw['lost_fraction_before']:.1f} / "
              f"{100 * sw['lost_fraction_after']:.1f} % of frames, last lost {sw['last_lost_after_switch_s']:.1f} s "
              "after the switch")
    return 0


# --------------------------------------------------------------------------- leave-out


def _leave_out(args: argparse.Namespace) -> int:
    from services.evaluation.leave_out import run

    res = run(args.dataset, every=args.every, features=args.features, j=args.j, preprocess=args.preprocess,
              seed=args.seed)
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"leave-out on {res['dataset']}: map {res['frames_map']} frames, {res['frames_test']} held out "
          f"(every {res['every']}), {res['features']} features, preprocess {res['preprocess']}")
    for key, label in (("error_m", f"best of J={res['J']} (eq. 10)"), ("top1_error_m", "top-1"),
                       ("floor_m", "floor (nearest map pose)"), ("random_m", "random map pose")):
        s = res[key]
        print(f"  {label:<26} mean {s['mean']:.3f} m  median {s['median']:.3f} m")
    h = res["heading_error_deg"]
    print(f"  {'top-1 heading error':<26} mean {h['mean']:.1f} deg  median {h['median']:.1f} deg")
    return 0


def register_eval(eval_sub: argparse._SubParsersAction) -> None:
    p = eval_sub.add_parser("global", help="global localization in the office: error and success per update")
    p.add_argument("--world", default="office")
    p.add_argument("--starts", type=int, default=20, help="runs from random start poses (at least 20)")
    p.add_argument("--updates", type=int, default=30, help="updates per run")
    p.add_argument("--rate", type=float, default=2.0, help="camera frames (updates) per second while driving")
    p.add_argument("--features", type=int, default=5, help="PCA features (section 6.1: 5)")
    p.add_argument("--step", type=float, default=0.75, help="map grid step, metres (section 6.1: 0.75)")
    p.add_argument("--heading-step", type=float, default=15.0, help="map heading step, degrees (section 6.1: 15)")
    p.add_argument("--preprocess", default="none", choices=PREPROCESS_METHODS)
    p.add_argument("--particles", default=None, metavar="N[,N...]",
                   help="particles (default: the localizer configuration's); several, comma-separated, run "
                   "on the same starts and frames (then --json prints {\"runs\": [...]})")
    p.add_argument("--camera", default="fixed", metavar="fixed|active|fixed,active",
                   help="the head: fixed at pan 0 (section 6.1), or turned by the daemon's active-vision "
                   "policy ([active_vision] defaults); both: run both on the same starts (default fixed)")
    from services.evaluation.global_loc import HEAD_SPEED_RAD_S

    p.add_argument("--head-speed", type=float, default=HEAD_SPEED_RAD_S,
                   help="rad/s of the head with --camera active (the head driver's default profile velocity)")
    p.add_argument("--j", type=int, default=None, help="nearest map entries J (default: configuration's)")
    p.add_argument("--sensor-model", choices=("nearest_neighbour", "interpolated"), default=None,
                   help="p(y | x) (default: the configuration's, nearest_neighbour; interpolated: "
                   "lino_loc.interpolated_appearance)")
    p.add_argument("--virtual-headings", type=int, default=5, choices=range(1, 32), metavar="N",
                   help="map entries per survey image, turned 3 deg apart (lino_loc.virtual_views), as "
                   "config/sim.toml's map; 1: the images alone (default 5)")
    add_channels_option(p)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None, help="rendering processes (default: all cores)")
    p.add_argument("--config", default=None, help="take the [localizer] settings from this configuration file")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_map_option(p)
    p.set_defaults(func=_global)

    from services.evaluation.tracking import DEFAULT_CHANGES, DEFAULT_CHANNELS, DEFAULT_PREPROCESS

    p = eval_sub.add_parser("tracking", help="a drive through the lab under other light and scene changes")
    p.add_argument("--world", default="lab")
    add_tracking_map_arguments(p)
    p.add_argument("--duration", type=float, default=240.0, help="seconds of driving")
    p.add_argument("--rate", type=float, default=5.0, help="camera frames (updates) per second")
    p.add_argument("--features", type=int, default=20)
    p.add_argument("--preprocess", default=DEFAULT_PREPROCESS, choices=(*PREPROCESS_METHODS, "all"),
                   help=f"image preprocessing of the map (default {DEFAULT_PREPROCESS}, measured best); "
                        "'all' compares the three")
    p.add_argument("--lights", default="tube,bulb,natural", help="comma-separated lighting setups")
    p.add_argument("--switch-lights", default="tube,bulb", metavar="A,B",
                   help="also a run whose light switches from A to B halfway (both in --lights; none: skip)")
    p.add_argument("--changes", default=",".join(DEFAULT_CHANGES),
                   help="comma-separated scene changes unknown to the map ('none' for none)")
    p.add_argument("--particles", type=int, default=None)
    p.add_argument("--j", type=int, default=None)
    p.add_argument("--no-global", action="store_true", help="skip the runs from the uniform belief")
    p.add_argument("--no-recovery-comparison", action="store_true",
                   help="skip the runs with kidnap recovery switched off")
    p.add_argument("--no-kidnap", action="store_true",
                   help="skip the runs with a kidnapping halfway (the robot carried a quarter of the drive ahead)")
    p.add_argument("--trajectories", default=None, metavar="DIR",
                   help="write estimated and true trajectories (TUM format) and per-frame traces of every "
                   "run (CSV: errors, state, quality and the self-checks) to DIR")
    add_channels_option(p, ",".join(DEFAULT_CHANNELS))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--config", default=None, help="take the [localizer] settings from this configuration file")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_map_option(p, "localize against this map file (e.g. one extended by `lino-loc map extend`, or built "
                   "from a `survey --robot` dataset) instead of the rendered tube survey; its preprocessing, "
                   "features, channels, camera size and working size are used (the frames are rendered at "
                   "its camera's size)")
    p.set_defaults(func=_tracking)

    p = eval_sub.add_parser("leave-out", help="sensor-model error (eq. 10) on held-out frames of a dataset")
    p.add_argument("dataset", help="dataset folder (e.g. from `lino-loc dataset import-tum`)")
    p.add_argument("--every", type=int, default=5, help="hold out every K-th frame (rows 0, K, 2K, ...)")
    p.add_argument("--features", type=int, default=20, help="PCA features D")
    p.add_argument("--j", type=int, default=10, help="nearest map entries J (paper: 10)")
    p.add_argument("--preprocess", default="none", choices=PREPROCESS_METHODS)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_leave_out)

"""`lino-loc survey --robot`: survey a building with the robot's own camera, head and odometry.

    lino-loc survey --robot [--config FILE] (--plan PLAN.csv | --grid STEP [--area x0,y0,x1,y1])
                    --out DATASET [--poses plan|stream|tum|odometry] [--pose-stream ENDPOINT]
                    [--pose-tum FILE] [--start X,Y,THETA] [--drive sim|prompt|control]
                    [--control ENDPOINT] [--sim-control ENDPOINT] [--heading-step DEG]
                    [--condition NAME] [--overwrite] [--json]

Which robot, as `lino-loc run` (:func:`services.commands.run.choose_config`): ``--config``,
else the robot's built-in defaults when its devices are attached, else the SIMULATED robot:
`lino-loc sim` started as a child process (standing still, ``--no-drive``), its "auto" ports
filled in, and the same drivers (Dynamixel head, serial odometry, camera) used over its
emulators. The devices come from the configuration's ``[devices]`` through
:func:`services.daemon.default_device_factories`, the settle time from ``[active_vision]
settle_s``, the pan range from ``[devices.head] pan_min/pan_max``.

How the robot gets to each stop (``--drive``; :mod:`services.survey_moves`): ``sim`` (the
simulated robot drives there itself, through the simulator's ``goto`` control: the one this
command started, or ``--sim-control`` of one you started), ``prompt`` (the operator, at this
terminal) or ``control`` (the operator or a program, by requests on the ``--control`` REP
socket). Default: ``sim`` when a simulator's control is known, else ``prompt``.

Where the stop pose comes from (``--poses``; :mod:`services.survey_poses`): ``plan`` (the
marked positions of the plan, as confirmed; the default), ``stream`` (the project's ``pose``
messages on ``--pose-stream``, e.g. another localization system's, interpolated at each
frame's stamp), ``tum`` (a TUM trajectory file of the base, ``--pose-tum``, read as it grows)
or ``odometry`` (dead reckoning from ``--start``: it drifts, and the survey says so).

The survey's engine, the frame rules and the resumption: :mod:`services.robot_survey`.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
from typing import Any

from lino_loc.errors import LinoLocError

log = logging.getLogger("lino_loc.survey")

POSE_MODES = ("plan", "stream", "tum", "odometry")
DRIVE_MODES = ("sim", "prompt", "control")


def _pose3(text: str) -> tuple[float, float, float]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise LinoLocError(f"--start {text!r}: expected x,y,theta (metres, metres, radians)") from None
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise LinoLocError(f"--start {text!r}: expected three finite numbers x,y,theta")
    return vals  # type: ignore[return-value]


def check_args(args: argparse.Namespace) -> None:
    """One-line errors for option combinations that cannot work (before any device starts)."""
    if (args.plan is None) == (args.grid is None):
        raise LinoLocError("survey --robot: give exactly one of --plan PLAN.csv and --grid STEP")
    if args.area is not None and args.grid is None:
        raise LinoLocError("survey --robot: --area goes with --grid")
    if args.poses == "stream" and not args.pose_stream:
        raise LinoLocError("survey --robot --poses stream: needs --pose-stream ENDPOINT")
    if args.poses == "tum" and not args.pose_tum:
        raise LinoLocError("survey --robot --poses tum: needs --pose-tum FILE")
    if args.poses == "odometry" and args.start is None:
        raise LinoLocError("survey --robot --poses odometry: needs --start X,Y,THETA (the robot's pose now)")
    if args.drive == "control" and not args.control:
        raise LinoLocError("survey --robot --drive control: needs --control ENDPOINT (e.g. tcp://127.0.0.1:5570)")
    if not (math.isfinite(args.heading_step) and args.heading_step > 0):
        raise LinoLocError(f"--heading-step {args.heading_step}: must be a positive number of degrees")


def make_stops(args: argparse.Namespace, cfg: Any) -> list[Any]:
    from services.survey_plan import grid_plan, parse_area, read_plan_csv

    if args.plan is not None:
        return read_plan_csv(args.plan)
    if args.area is not None:
        area = parse_area(args.area)
    elif cfg.simulated:
        from drivers.sim.world import load_world

        x0, x1, y0, y1 = load_world(cfg.devices.camera.sim.world).mapped_area
        area = (x0, y0, x1, y1)
    else:
        raise LinoLocError("survey --robot --grid: needs --area x0,y0,x1,y1 (metres, map frame) on a real robot")
    return grid_plan(args.grid, area)


def run_robot_survey(args: argparse.Namespace) -> int:
    import zmq

    from services.commands.run import choose_config
    from services.daemon import default_device_factories
    from services.progress import Progress
    from services.robot_survey import CaptureSettings, PlanPoses, RobotSurvey, SurveyDevices
    from services.sim_launcher import SimProcess, needs_sim, resolve_auto
    from services.survey_moves import ControlMover, PromptMover, SimMover
    from services.survey_plan import head_sweep
    from services.survey_poses import OdometryPoses, StreamPoses, TumFilePoses

    check_args(args)
    cfg, cfg_path, reason = choose_config(args.config)
    stops = make_stops(args, cfg)
    head_cfg = cfg.devices.head
    sweep = head_sweep(head_cfg.pan_min, head_cfg.pan_max, math.radians(args.heading_step))
    start = _pose3(args.start) if args.start is not None else None
    condition = args.condition or (cfg.devices.camera.sim.lighting if cfg.simulated else "robot")
    if "," in condition or not condition.strip():
        raise LinoLocError(f"--condition {condition!r}: a name without commas")

    stop_signals: list[int] = []

    def on_signal(signum: int, _frame: Any) -> None:
        stop_signals.append(signum)
        raise KeyboardInterrupt

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    ctx = zmq.Context()
    sim: SimProcess | None = None
    devices: SurveyDevices | None = None
    mover: Any = None
    poses: Any = None
    bar: Progress | None = None
    try:
        sim_control = args.sim_control
        if needs_sim(cfg):
            sim = SimProcess(cfg_path, world=cfg.devices.camera.sim.world, extra_args=["--no-drive"])
            info = sim.start()
            cfg = resolve_auto(cfg, info)
            sim_control = sim_control or info.raw.get("faults")
        drive = args.drive or ("sim" if sim_control else "prompt")
        if drive == "sim" and not sim_control:
            raise LinoLocError("survey --robot --drive sim: needs --sim-control ENDPOINT (the \"faults\" "
                               "endpoint `lino-loc sim` prints)")
        devices = SurveyDevices(default_device_factories(cfg, disparity=True)).start()
        if drive == "sim":
            mover = SimMover(sim_control, ctx, speed=args.drive_speed)
        elif drive == "control":
            mover = ControlMover(args.control, ctx)
            print(f"survey control on {mover.endpoint}: send {{\"cmd\": \"confirm\"}} when the robot is at "
                  "each stop ({\"cmd\": \"status\"} says which)", file=sys.stderr, flush=True)
        else:
            mover = PromptMover()
        if args.poses == "plan":
            poses = PlanPoses()
        elif args.poses == "stream":
            poses = StreamPoses(args.pose_stream, ctx)
        elif args.poses == "tum":
            poses = TumFilePoses(args.pose_tum)
        else:
            assert start is not None
            poses = OdometryPoses(start, devices.odometry)
            log.warning("survey: stop poses from odometry alone, from (%.2f, %.2f, %.2f): they drift with the "
                        "distance driven (wheel slip, track width); check the map (`lino-loc map check`) or use "
                        "marked positions (--poses plan) or an external pose source", *start)
        bar = Progress("survey --robot", force=args.progress)
        settings = CaptureSettings(condition=condition, settle_s=cfg.active_vision.settle_s,
                                   pan_timeout=args.pan_timeout)
        survey = RobotSurvey(
            args.out, stops, sweep, devices, mover, poses, settings,
            name=f"robot-{condition}",
            source=(f"lino-loc survey --robot ({reason}); poses {args.poses}; drive {drive}; "
                    f"heading step {args.heading_step:g} deg; {len(stops)} stops"),
            disparity_source="stereo-matcher" if cfg.devices.camera.kind == "sim" else "device",
            progress=lambda done, total: bar.update(done, total, label=f"survey --robot: {total - done} stops left",
                                                    base=survey.stops_resumed),
            overwrite=args.overwrite,
        )
        if isinstance(mover, ControlMover):  # status replies say how far the survey is
            mover.progress = lambda: {"stops": survey.report.stops, "stops_done": survey.report.stops_done,
                                      "stops_skipped": survey.report.stops_skipped,
                                      "images": survey.report.resumed_images + survey.report.images_this_run}
        if stop_signals:
            raise KeyboardInterrupt
        report = survey.run()
    except KeyboardInterrupt:
        print("lino-loc: survey interrupted before it started capturing", file=sys.stderr)
        return 130
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if bar is not None:
            bar.close()
        for thing in (poses, mover, devices):
            if thing is not None:
                try:
                    thing.close() if hasattr(thing, "close") else thing.stop()
                except Exception as exc:  # noqa: BLE001 - best effort at shutdown
                    log.warning("survey: closing %s: %s", type(thing).__name__, exc)
        if sim is not None:
            sim.stop()
        ctx.term()
    summary = report.as_dict()
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {report.dataset}: {report.images} images ({report.images_this_run} this run, "
              f"{report.images_per_minute:.0f}/min), {report.stops_done}/{report.stops} stops done, "
              f"{report.stops_skipped} skipped, {report.pans_missed} pans missed"
              + ("; interrupted: run the same command again to continue" if report.interrupted else ""),
              file=sys.stderr)
    return 130 if report.interrupted and stop_signals else 0


def add_robot_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("with the robot (--robot)")
    g.add_argument("--robot", action="store_true",
                   help="survey with the robot's camera, head and odometry (the simulated robot when none is "
                        "attached) instead of rendering")
    g.add_argument("--config", metavar="FILE", help="the daemon's configuration (devices, head range, settle time)")
    g.add_argument("--plan", metavar="PLAN.csv", help="stops: CSV with columns x,y[,theta] (m, m, rad; map frame)")
    g.add_argument("--grid", type=float, metavar="STEP", help="stops every STEP metres over --area")
    g.add_argument("--area", metavar="X0,Y0,X1,Y1", help="rectangle of --grid, metres (default: the simulated "
                   "world's mapped area)")
    g.add_argument("--poses", choices=POSE_MODES, default="plan",
                   help="where the stop pose comes from: plan (marked positions, default), stream (--pose-stream), "
                        "tum (--pose-tum), odometry (from --start; drifts)")
    g.add_argument("--pose-stream", metavar="ENDPOINT", help="ZeroMQ PUB endpoint of pose (or truth) messages")
    g.add_argument("--pose-tum", metavar="FILE", help="TUM trajectory of the base (stamp tx ty tz qx qy qz qw)")
    g.add_argument("--start", metavar="X,Y,THETA", help="the robot's pose now, for --poses odometry")
    g.add_argument("--drive", choices=DRIVE_MODES, default=None,
                   help="how the robot gets to each stop: sim (drives itself), prompt (operator at this terminal), "
                        "control (operator requests on --control); default sim when simulated, else prompt")
    g.add_argument("--control", metavar="ENDPOINT", help="REP endpoint of the operator control (loopback)")
    g.add_argument("--sim-control", metavar="ENDPOINT",
                   help="the control (\"faults\") endpoint of a `lino-loc sim` you started, for --drive sim")
    g.add_argument("--drive-speed", type=float, default=None, metavar="M/S", help="top speed of --drive sim")
    g.add_argument("--condition", help="condition name of the rows (default: the simulated lighting, or 'robot')")
    g.add_argument("--pan-timeout", type=float, default=10.0, metavar="S",
                   help="give up a pan after S seconds without a usable frame (default 10)")
    g.add_argument("--progress", action="store_true", help="draw the progress bar even when stderr is not a terminal")

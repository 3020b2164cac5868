"""`lino-loc sim`: run the simulated robot in this process until SIGINT/SIGTERM.

Starts :class:`drivers.sim.robot.SimRobot` (the simulated building, a wandering
differential-drive base, the Dynamixel bus and odometry board emulators on pseudo-terminals,
the rendered stereo camera on a ZeroMQ PUB socket) and publishes the true robot pose at 50 Hz
on a second PUB socket as ``[b"truth", TruthMessage JSON]`` (services.messages).

Its FIRST line on stdout is one JSON object naming the devices (a contract that `lino-loc run` and the tests read)::

    {"head": "/dev/pts/N", "odometry": "/tmp/lino-loc-sim-<pid>-XXXX/odometry",
     "camera": "tcp://127.0.0.1:PORT", "truth": "tcp://127.0.0.1:PORT2",
     "faults": "tcp://127.0.0.1:PORT3", "world": "office", "pid": 1234}

``odometry`` is a stable symlink to the board's current pseudo-terminal (it survives a
simulated unplug, like ``/dev/serial/by-id``); ``head`` is the bus's pseudo-terminal. Then
it logs to stderr, and on SIGINT/SIGTERM stops everything, removes what it created (ptys,
links, sockets) and exits 0. SIGUSR1 unplugs the odometry board for 2 s (fault injection),
SIGUSR2 switches the lights to ``--switch-lighting``. ``faults`` is the fault control, a REP
socket on loopback that injects every fault of the emulators and the camera for a while
(:mod:`drivers.sim.fault_control`; docs/protocols.md, section 6).

Settings: flags > ``--config FILE`` (``[devices.camera.sim]`` for the world, lighting,
scene changes, image size, fps and baseline; ``[devices.odometry]`` for the wheel radius,
ticks per revolution, track width and encoder signs, which must match the daemon's;
``[devices.head]`` for the servo ids; ports or the camera endpoint that are not ``"auto"``
become the symlinks / bind address) > the simulated robot's defaults (config/sim.toml).
Camera and truth bind to free ports on 127.0.0.1 unless given.
"""

from __future__ import annotations

import argparse
import copy
import ctypes
import json
import logging
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from typing import Any

from pydantic import ValidationError

from lino_loc.errors import LinoLocError

log = logging.getLogger("lino_loc.sim")

_PR_SET_PDEATHSIG = 1


def _start_pose(text: str) -> tuple[float, float, float]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected x,y,theta (metres, metres, radians), got {text!r}"
        ) from None
    if len(vals) != 3:
        raise argparse.ArgumentTypeError(f"expected x,y,theta (three numbers), got {text!r}")
    return vals  # type: ignore[return-value]


def _positive(kind: type) -> Any:
    def parse(text: str) -> Any:
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not v > 0:
            raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
        return v

    return parse


def _load_service_config(path: str | None) -> Any:
    from services.config import SIM_OVERRIDES, ConfigError, ServiceConfig, load_config

    if path is not None:
        return load_config(path)
    try:  # the simulated defaults (config/sim.toml), with LINO_LOC__* environment overrides
        return ServiceConfig(**copy.deepcopy(SIM_OVERRIDES))
    except ValidationError as exc:
        err = exc.errors(include_url=False)
        raise ConfigError(
            [f"(simulated defaults): {'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in err]
        ) from None


def robot_config(args: argparse.Namespace, tmpdir: str) -> tuple[Any, str]:
    """(SimRobotConfig, truth endpoint) from the flags, the configuration file and defaults."""
    from drivers.sim.robot import SimRobotConfig
    from services.config import AUTO

    cfg = _load_service_config(args.config)
    cam = cfg.devices.camera.sim
    head = cfg.devices.head
    odo = cfg.devices.odometry
    sim = cfg.simulated

    def pick(flag: Any, value: Any) -> Any:
        return value if flag is None else flag

    camera_endpoint = args.camera_endpoint or (
        cam.endpoint if sim and cam.endpoint != AUTO else "tcp://127.0.0.1:*"
    )
    scene_changes = (
        tuple(s for s in args.scene_changes.split(",") if s.strip())
        if args.scene_changes is not None
        else tuple(cam.scene_changes)
    )
    try:
        rc = SimRobotConfig(
            world=pick(args.world, cam.world),
            lighting=pick(args.lighting, cam.lighting),
            scene_changes=tuple(s.strip() for s in scene_changes),
            width=pick(args.width, cam.width),
            height=pick(args.height, cam.height),
            fps=pick(args.fps, cam.fps),
            baseline_m=cam.baseline_m,
            noise=not args.no_noise,
            seed=args.seed,
            drive=not args.no_drive,
            speed=args.speed,
            start=args.start,
            wheel_radius=odo.wheel_radius,
            ticks_per_rev=odo.ticks_per_rev,
            track_width=odo.track_width,
            left_sign=odo.left_sign,
            right_sign=odo.right_sign,
            odometry_rate_hz=odo.rate_hz,
            pan_id=head.pan_id,
            tilt_id=head.tilt_id,
            head_link=head.port if sim and head.port != AUTO else None,
            odometry_link=odo.port
            if sim and odo.port != AUTO
            else os.path.join(tmpdir, "odometry"),
            camera_endpoint=camera_endpoint,
        )
    except ValidationError as exc:
        e = exc.errors(include_url=False)[0]
        raise LinoLocError(f"sim: {'.'.join(str(p) for p in e['loc'])}: {e['msg']}") from None
    for link in (rc.head_link, rc.odometry_link):
        if link is not None and os.path.lexists(link) and not os.path.islink(link):
            raise LinoLocError(
                f"sim: {link} exists and is not a symlink: will not replace it with a pty link"
            )
    return rc, args.truth_endpoint or "tcp://127.0.0.1:*"


def _exit_with_parent() -> None:
    """Ask the kernel to send SIGTERM when the parent process dies (Linux)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError) as exc:
        log.warning("sim: --exit-with-parent unavailable: %s", exc)
        return
    if os.getppid() == 1:  # the parent died before prctl
        os.kill(os.getpid(), signal.SIGTERM)


class _SignalFlag:
    """A flag that signal handlers set. Not a ``threading.Event``: its ``set`` takes the Event's
    lock, and a handler that runs while the main thread holds that lock (inside ``wait``)
    deadlocks the process, which then ignores every further SIGTERM (seen after a ``kill -9``
    of the survey that started this simulator). Setting an attribute takes no lock."""

    def __init__(self) -> None:
        self._set = False

    def set(self) -> None:
        self._set = True

    def clear(self) -> None:
        self._set = False

    def is_set(self) -> bool:
        return self._set

    def wait(self, timeout: float) -> bool:
        """Sleep (in slices of 20 ms at most) until set or ``timeout`` s passed; whether set."""
        end = time.monotonic() + timeout
        while not self._set:
            left = end - time.monotonic()
            if left <= 0:
                break
            time.sleep(min(left, 0.02))
        return self._set


def run_sim(args: argparse.Namespace) -> int:
    import zmq

    from drivers.sim.fault_control import FaultController, FaultServer, OdometryUnplug
    from drivers.sim.robot import SimRobot, TruthSample, bind
    from services.messages import Pose2D, TruthMessage, encode

    done = _SignalFlag()
    unplug = _SignalFlag()
    switch = _SignalFlag()
    previous = {
        s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2)
    }
    signal.signal(signal.SIGINT, lambda *_: done.set())
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGUSR1, lambda *_: unplug.set())
    signal.signal(signal.SIGUSR2, lambda *_: switch.set())
    if args.exit_with_parent:
        _exit_with_parent()
    from services.sim_launcher import remove_stale_sim_folders, sim_folder_prefix

    for stale in remove_stale_sim_folders():
        log.info("sim: removed %s (its simulator is gone)", stale)
    tmpdir = tempfile.mkdtemp(prefix=sim_folder_prefix())
    ctx = zmq.Context()
    truth_sock = None
    robot = None
    faults = None
    control = None
    started = False
    truth_stats = {"sent": 0, "dropped": 0}
    try:
        rc, truth_endpoint = robot_config(args, tmpdir)
        truth_sock = ctx.socket(zmq.PUB)
        truth_sock.setsockopt(zmq.LINGER, 0)
        truth_sock.setsockopt(zmq.SNDHWM, 200)
        truth_endpoint = bind(truth_sock, truth_endpoint)
        sock = truth_sock

        def publish_truth(t: TruthSample) -> None:
            # runs in the robot's base thread, the only user of the truth socket
            msg = TruthMessage(
                stamp=t.stamp, seq=t.seq, pose=Pose2D(x=t.x, y=t.y, theta=t.theta), pan=t.pan
            )
            try:
                sock.send_multipart(encode("truth", msg), zmq.NOBLOCK)
                truth_stats["sent"] += 1
            except zmq.Again:
                truth_stats["dropped"] += 1

        robot = SimRobot(rc, on_truth=publish_truth, context=ctx)
        robot.world.check_lighting(args.switch_lighting)  # a bad name fails now, not at SIGUSR2
        sim_robot = robot

        def lights(name: str) -> None:  # bakes the lighting (seconds): off the caller's thread
            threading.Thread(target=sim_robot.switch_lighting, args=(name,), name="light-switch",
                             daemon=True).start()

        control = FaultController(robot, lights)
        faults = FaultServer(control, ctx, args.fault_endpoint)  # refuses a non-loopback endpoint
        robot.start()
        started = True
        fault_endpoint = faults.start()
        line = {
            "head": robot.head_port,
            "odometry": robot.odometry_port,
            "camera": robot.camera_endpoint,
            "truth": truth_endpoint,
            "faults": fault_endpoint,
            "world": robot.world.name,
            "pid": os.getpid(),
        }
        try:
            sys.stdout.write(json.dumps(line) + "\n")
            sys.stdout.flush()
        except BrokenPipeError:
            log.warning("sim: stdout is closed; running anyway")
        log.info("sim: running (%s); SIGINT/SIGTERM stops, SIGUSR1 unplugs the odometry board for 2 s, "
                 "SIGUSR2 switches the lights",
                 json.dumps(line))  # fmt: skip
        t_end = time.monotonic() + args.duration if args.duration else None
        next_report = time.monotonic() + args.stats_period
        while not done.is_set():
            timeout = 0.2 if t_end is None else max(0.0, min(0.2, t_end - time.monotonic()))
            done.wait(timeout)
            if t_end is not None and time.monotonic() >= t_end:
                break
            if unplug.is_set():
                unplug.clear()
                log.warning("sim: odometry board unplugged for 2 s (SIGUSR1)")
                try:
                    control.inject(OdometryUnplug(cmd="inject", fault="odometry_unplug", duration_s=2.0))
                except Exception:  # noqa: BLE001 - a fault that cannot be injected never stops the sim
                    log.exception("sim: SIGUSR1: the odometry board could not be unplugged")
            if switch.is_set():
                switch.clear()
                log.warning("sim: switching the lights to %s (SIGUSR2)", args.switch_lighting)
                lights(args.switch_lighting)
            if args.stats_period and time.monotonic() >= next_report:
                next_report += args.stats_period
                log.info("sim: %s, truth %s", json.dumps(robot.stats()), json.dumps(truth_stats))
        return 0
    finally:
        if faults is not None:
            faults.stop()
        if control is not None:
            control.clear()
        if robot is not None:
            stats = robot.stats()
            robot.stop()
            if started:
                log.info("sim: stopped; %s, truth %s", json.dumps(stats), json.dumps(truth_stats))
        if truth_sock is not None:
            truth_sock.close(0)
        ctx.term()
        shutil.rmtree(tmpdir, ignore_errors=True)
        for s, h in previous.items():
            signal.signal(s, h)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        metavar="FILE",
        help="service configuration (TOML); default: the simulated robot's",
    )
    p.add_argument(
        "--world", help="world name (config/worlds/<name>.json) or path (default office)"
    )
    p.add_argument("--lighting", help="lighting setup: tube, bulb, natural (default tube)")
    p.add_argument(
        "--switch-lighting",
        default="bulb",
        metavar="NAME",
        help="the lighting SIGUSR2 switches to while running (default bulb)",
    )
    p.add_argument(
        "--scene-changes",
        metavar="A,B",
        help="scene changes unknown to the map (boxes, people, ...)",
    )
    p.add_argument("--fps", type=_positive(float), help="camera frames per second (default 15)")
    p.add_argument("--width", type=_positive(int), help="image width, pixels (default 320)")
    p.add_argument("--height", type=_positive(int), help="image height, pixels (default 240)")
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the wander plan and the camera noise"
    )
    p.add_argument(
        "--speed", type=float, default=0.3, help="maximum linear speed, m/s (default 0.3)"
    )
    p.add_argument("--no-drive", action="store_true", help="the base stands still")
    p.add_argument(
        "--start",
        type=_start_pose,
        metavar="X,Y,THETA",
        help="initial pose (default: centre of the mapped area)",
    )
    p.add_argument("--no-noise", action="store_true", help="noiseless camera images")
    p.add_argument(
        "--camera-endpoint",
        help="PUB bind address of the camera (default tcp://127.0.0.1:*, a free port)",
    )
    p.add_argument(
        "--truth-endpoint", help="PUB bind address of the true pose (default tcp://127.0.0.1:*)"
    )
    p.add_argument(
        "--fault-endpoint",
        default="tcp://127.0.0.1:*",
        help="REP bind address of the fault control, loopback only (default tcp://127.0.0.1:*)",
    )
    p.add_argument(
        "--duration", type=_positive(float), metavar="S", help="stop after S seconds (benchmarks)"
    )
    p.add_argument(
        "--stats-period",
        type=float,
        default=30.0,
        metavar="S",
        help="log statistics every S s (0: never)",
    )
    p.add_argument(
        "--exit-with-parent", action="store_true", help="stop when the parent process dies (Linux)"
    )


_DESCRIPTION = """\
Run the simulated robot (building, wandering base, Dynamixel head and odometry board emulated
on pseudo-terminals, rendered stereo camera) until SIGINT/SIGTERM, then remove what it made.

The first line on stdout is one JSON object naming the devices:
  {"head": "/dev/pts/N", "odometry": "<symlink to the board's pty>",
   "camera": "tcp://127.0.0.1:PORT", "truth": "tcp://127.0.0.1:PORT2",
   "faults": "tcp://127.0.0.1:PORT3", "world": ..., "pid": ...}
camera: ZeroMQ PUB of [b"frame", header JSON, left, right] (drivers.sim.frame_transport);
truth: ZeroMQ PUB of [b"truth", TruthMessage JSON] at 50 Hz; faults: ZeroMQ REP of JSON
requests such as {"cmd": "inject", "fault": "odometry_crc", "duration_s": 3} or
{"cmd": "clear"} (docs/protocols.md, section 6). Logs go to stderr.
SIGUSR1 unplugs the odometry board for 2 s; SIGUSR2 switches the lights to --switch-lighting.
Negative numbers: --start=-1,2,0.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim",
        help="run the simulated robot (emulated head and odometry on ptys, camera and truth over ZeroMQ)",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_arguments(p)
    p.set_defaults(func=run_sim)

"""`lino-loc run [--config FILE] [--record FILE.mcap]`: the localization daemon (services.daemon).

``--record FILE.mcap`` records the session into that MCAP file (``[recording]`` turned on for
it; needs the ``viz`` extra, else one line naming it, exit 2). When recording and the filter
has no seed, one is drawn and logged, and stored in the file with the configuration
(:func:`recording_config`, :func:`recorder`; docs/recording.md).

Which robot:
- ``--config FILE``: that configuration (plus ``LINO_LOC__*`` environment overrides).
- no ``--config``: the real robot's defaults when its devices are attached (a
  ``/dev/ttyUSB*`` head adapter or an OAK-D); otherwise the SIMULATED robot
  (``config/sim.toml``, or :meth:`ServiceConfig.simulated_defaults`): ``lino-loc sim`` is
  started as a child process, its map is built once and cached (or reused), and the same
  daemon runs with the real head and odometry drivers over the simulator's emulators.

It refuses to start (one line, exit 2) when an endpoint can be reached from the network and
no CURVE keys are configured (``[endpoints.curve]``, services/curve_auth.py), or when the
configured key files cannot be read. It prints where the poses are published and how to watch them (stderr), then serves until
SIGTERM or SIGINT, which shut it down cleanly (threads stopped, pose saved, devices closed,
the child simulator stopped) with exit status 0. If the child simulator dies, the simulated
robot is gone (its emulated ports and camera with it): the daemon shuts down the same way and
exits with status 1, saying so in one line, so that whoever started it (a shell, systemd's
``Restart=``) starts both again.

BLAS threads: the filter's products are small; threaded OpenBLAS/OpenMP made them ~10x slower
on the 2-core robot computer. ``services.cli`` sets ``OPENBLAS_NUM_THREADS`` /
``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` to 1 before numpy loads (unless set); when
``run_daemon`` is entered some other way after numpy was loaded without them, it sets them and
re-executes itself once (same PID, as systemd's ``Type=notify`` expects).
"""

from __future__ import annotations

import argparse
import glob
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from drivers.sim.config_files import SIM_TOML
from lino_loc.errors import LinoLocError

log = logging.getLogger("lino_loc.service")

THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
_REEXEC_MARK = "LINO_LOC_RUN_REEXEC"



def _single_threaded_blas() -> None:
    """One BLAS/OpenMP thread unless the environment chose otherwise.

    ``services.cli`` already sets the variables before numpy loads; this covers other entry
    points (``run_daemon`` called after numpy was imported without them): it sets them and
    re-executes the process once (same PID)."""
    missing = [v for v in THREAD_VARS if v not in os.environ]
    if not missing:
        return
    for v in missing:
        os.environ[v] = "1"
    if os.environ.get(_REEXEC_MARK) or "numpy" not in sys.modules:
        return
    os.environ[_REEXEC_MARK] = "1"
    argv = list(getattr(sys, "orig_argv", []) or [sys.executable, *sys.argv])
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        os.execv(sys.executable, [sys.executable, *argv[1:]])
    except OSError as exc:  # keep going with threaded BLAS rather than not at all
        log.warning("could not re-exec with single-threaded BLAS: %s", exc)


def robot_devices_present() -> list[str]:
    """Names of the real robot's devices found on this machine (cheap checks first)."""
    found = sorted(glob.glob("/dev/ttyUSB*"))
    if found:
        return found
    try:
        import depthai as dai  # noqa: PLC0415 - slow import, only when needed

        devs = dai.Device.getAllAvailableDevices()
        return [f"OAK-D {d.getDeviceId() if hasattr(d, 'getDeviceId') else d}" for d in devs]
    except Exception:  # noqa: BLE001 - no depthai or no USB: no OAK-D
        return []


def choose_config(path: str | None) -> tuple[Any, Path | None, str]:
    """(ServiceConfig, the file it came from, a one-line reason)."""
    from services.config import ServiceConfig, load_config

    if path is not None:
        return load_config(path), Path(path), f"configuration {path}"
    devices = robot_devices_present()
    if devices:
        return load_config(None), None, f"robot devices found ({', '.join(devices)}): built-in robot defaults"
    if SIM_TOML.is_file():
        return load_config(SIM_TOML), SIM_TOML, f"no robot devices found: the simulated robot ({SIM_TOML})"
    return ServiceConfig.simulated_defaults(), None, "no robot devices found: the simulated robot (built-in)"


_WILDCARD_HOSTS = ("tcp://0.0.0.0:", "tcp://*:", "tcp://[::]:", "tcp://[*]:")


def echo_command(pub: str, curve: Any) -> str:
    """The `lino-loc echo` line that reads ``pub`` from this machine: a wildcard bind is
    reached on 127.0.0.1 (a wildcard is an address to bind, never one to connect to), and
    with CURVE the key options are shown (the server's public key next to its secret key,
    as `lino-loc keys generate` lays them out)."""
    endpoint = pub
    for prefix in _WILDCARD_HOSTS:
        if pub.startswith(prefix):
            endpoint = "tcp://127.0.0.1:" + pub[len(prefix):]
    cmd = "lino-loc echo --topic pose"
    if endpoint != "tcp://127.0.0.1:5556":
        cmd += f" --endpoint {endpoint}"
    if curve.enabled:
        secret = str(curve.server_secret_key)
        public = secret[: -len("_secret")] if secret.endswith(".key_secret") else "SERVER.key"
        cmd += f" --curve-server-key {public} --curve-client-key CLIENT.key_secret"
    return cmd


def banner(cfg: Any, reason: str, sim: Any, recording: Path | None = None, live: Any = None) -> str:
    ep = cfg.endpoints
    lines = [
        "",
        "lino-loc is running (" + reason + ")",
        f"  poses      {ep.pub}   topics: pose (every frame), status (1 Hz), particles"
        + (", truth" if sim is not None and cfg.publish.truth else ""),
        f"  control    {ep.rep}   JSON requests, e.g. {{\"cmd\": \"status\"}}",
        f"  map        {cfg.map.path}",
        f"  saved pose {cfg.persistence.state_file}",
    ]
    if sim is not None and sim.info is not None:
        i = sim.info
        lines.append(f"  simulator  pid {sim.proc.pid}: head {i.head}, odometry {i.odometry}, camera {i.camera}")
    if recording is not None:
        lines.append(f"  recording  {recording}   replay it: lino-loc replay {recording}")
    if live is not None:
        lines.append(f"  live view  {live.address} (Foxglove WebSocket; layout docs/foxglove-layout.json)"
                     if live.error is None else f"  live view  not served: {live.error}")
    if ep.curve.enabled:
        lines.append(f"  CURVE      on: only clients whose public key is in {ep.curve.authorized_clients}")
    lines += [
        "  watch it:  " + echo_command(ep.pub, ep.curve),
        "  stop it:   Ctrl-C (or SIGTERM)",
        "",
    ]
    return "\n".join(lines)


def run_daemon(args: argparse.Namespace) -> int:
    _single_threaded_blas()
    from services.curve_auth import load_server_keys
    from services.daemon import Daemon
    from services.sim_launcher import SimProcess, ensure_sim_map, needs_sim, resolve_auto

    cfg, cfg_path, reason = choose_config(args.config)
    cfg = recording_config(cfg, getattr(args, "record", None))
    logging.getLogger().setLevel(cfg.logging.level)
    if cfg.endpoints.curve.enabled:  # unreadable keys: one line now, before anything starts
        load_server_keys(cfg.endpoints.curve)
    stop_requested: list[int] = []

    def early_stop(signum: int, _frame: Any) -> None:
        stop_requested.append(signum)
        raise KeyboardInterrupt

    old = {s: signal.signal(s, early_stop) for s in (signal.SIGTERM, signal.SIGINT)}
    sim: SimProcess | None = None
    daemon: Daemon | None = None
    try:
        try:
            if cfg.simulated:
                amap, _ = ensure_sim_map(cfg, in_subprocess=True)
            else:
                from lino_loc.appearance_map import AppearanceMap

                amap = AppearanceMap.load(cfg.map.path, mmap=cfg.map.mmap)
            truth = None
            if needs_sim(cfg):
                sim = SimProcess(cfg_path, world=cfg.devices.camera.sim.world)
                info = sim.start()
                cfg = resolve_auto(cfg, info)
                truth = info.truth
            scene = map_scene(cfg, amap)
            daemon = Daemon(cfg, amap, truth_endpoint=truth, recorder=recorder(cfg, amap, scene),
                            live_view=live_view(cfg, scene))
            try:
                daemon.start()
            except OSError as exc:
                raise LinoLocError(str(exc)) from None
        except KeyboardInterrupt:
            log.info("interrupted while starting")
            return 0

        def on_signal(signum: int, _frame: Any) -> None:
            log.info("%s: shutting down", signal.Signals(signum).name)
            daemon.request_stop()

        for s in (signal.SIGTERM, signal.SIGINT):
            signal.signal(s, on_signal)
        if stop_requested:
            daemon.request_stop()
        sim_died = threading.Event()
        if sim is not None:
            threading.Thread(target=_watch_sim, args=(sim, daemon, sim_died), name="sim-watch", daemon=True).start()
        print(banner(cfg, reason, sim, daemon.recorder.path, daemon.live.info()), file=sys.stderr, flush=True)
        code = daemon.run()
        return 1 if sim_died.is_set() else code
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if sim is not None:
            code = sim.stop()
            log.info("simulator stopped (status %s)", code)


def recording_config(cfg: Any, record: str | None) -> Any:
    """``cfg`` with ``--record FILE`` applied (recording on, to FILE), the viz extra checked
    and, when recording, a seed drawn for the filter if it has none (so that the recording
    can be replayed with the service's seed; logged and stored in the file)."""
    if record is not None:
        path = Path(record).expanduser()
        if path.suffix != ".mcap":
            raise LinoLocError(f"--record {record}: the file name must end in .mcap")
        cfg = cfg.model_copy(update={"recording": cfg.recording.model_copy(
            update={"enabled": True, "path": path})})
    if not cfg.recording.enabled:
        return cfg
    from services.recording.channels import require_viz

    require_viz("recording (lino-loc run --record, [recording] enabled)")
    if cfg.localizer.filter.seed is None:
        seed = int.from_bytes(os.urandom(4), "little")
        log.info("recording: the filter's seed is %d (localizer.filter.seed)", seed)
        filt = cfg.localizer.filter.model_copy(update={"seed": seed})
        cfg = cfg.model_copy(update={"localizer": cfg.localizer.model_copy(update={"filter": filt})})
    return cfg


def map_scene(cfg: Any, amap: Any) -> Any:
    """What the map channels draw (survey poses, outline) when recording or live, else None."""
    if not (cfg.recording.enabled or cfg.live_view.enabled):
        return None
    from services.recording.live_view import MapScene

    return MapScene.of(amap, cfg)


def live_view(cfg: Any, scene: Any) -> Any:
    """The live view (``LiveView.off()`` unless ``[live_view] enabled``)."""
    from services.recording.live_view import LiveView

    return LiveView(cfg.live_view, scene) if cfg.live_view.enabled else LiveView.off()


def recorder(cfg: Any, amap: Any, scene: Any = None) -> Any:
    """The session's recorder (``Recorder.off()`` unless ``[recording] enabled``), with the
    metadata a replay needs: the configuration, the seed, the map's checksum; ``scene``: the
    map's survey poses and outline, written at the start of each part."""
    from services.recording.recorder import Recorder
    from services.status import map_info

    if not cfg.recording.enabled:
        return Recorder.off()
    info = map_info(amap, cfg.map.path)
    return Recorder(cfg.recording, {
        "config": cfg.model_dump_json(), "seed": str(cfg.localizer.filter.seed),
        "map_checksum": str(info.checksum), "map_path": info.path,
        "has_disparity": str("disparity" in getattr(amap, "channels", {})).lower(),
        "started": str(time.time()),
    }, scene=scene)


def _watch_sim(sim: Any, daemon: Any, died: threading.Event, period: float = 0.5) -> None:
    """Stop the daemon when the child simulator exits on its own (not at our shutdown)."""
    while not daemon.stopping:
        if not sim.alive:
            status = sim.proc.returncode if sim.proc is not None else None
            log.error("the simulated robot (lino-loc sim) exited with status %s: stopping", status)
            died.set()
            daemon.request_stop()
            return
        time.sleep(period)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run the localization daemon (the simulated robot when no robot is attached)",
        description=(
            "Localize at frame rate and publish poses over ZeroMQ. Without --config and "
            "without the robot's devices, runs on the simulated robot (`lino-loc sim`)."
        ),
    )
    p.add_argument("--config", metavar="FILE", help="TOML configuration (see config/lino.toml)")
    p.add_argument("--record", metavar="FILE.mcap",
                   help="record the session into this MCAP file (docs/recording.md; needs the viz extra)")
    p.set_defaults(func=run_daemon)

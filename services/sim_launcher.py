"""The simulated robot for ``lino-loc run``: start `lino-loc sim`, and build or reuse its map.

Two jobs, both for the simulated robot (``devices.camera.kind = "sim"``):

1. :class:`SimProcess` starts ``lino-loc sim --world W [--config FILE]`` as a child process,
   reads the JSON object it prints as its first stdout line (``{"head": "/dev/pts/N",
   "odometry": ..., "camera": "tcp://...", "truth": "tcp://...", "world": ..., "pid": n}``),
   and stops it (SIGTERM, then SIGKILL) when the daemon stops. The child gets
   ``PR_SET_PDEATHSIG`` = SIGTERM, so it does not outlive a daemon killed with ``kill -9``.
   :func:`resolve_auto` fills the ``"auto"`` ports and endpoint of the configuration with
   what the simulator printed.

2. :func:`ensure_sim_map` makes sure ``map.path`` holds the map described by ``[map.build]``:
   when the file is there, loads, and its side file ``<map>.build.json`` records the same
   build settings (the disparity channel's source among them), world and code, it is
   reused; otherwise the world is surveyed with the renderer
   (:func:`drivers.sim.survey.run_survey`) into a cache folder next to the map, the map is
   built once (:func:`lino_loc.appearance_map.build_map`, eq. 1), saved atomically, and the
   survey folder removed. A lock file serializes concurrent builders (two daemons, tests).

Usage::

    amap = ensure_sim_map(cfg)                     # AppearanceMap (built or cached)
    sim = SimProcess(config_path, world="office"); info = sim.start()
    cfg = resolve_auto(cfg, info); ...; sim.stop()
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import json
import logging
import math
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lino_loc.appearance_map import DEFAULT_SIZE, AppearanceMap, build_map
from lino_loc.atomic_file import pid_alive
from lino_loc.errors import LinoLocError
from services.config import AUTO, MapBuildConfig, ServiceConfig

log = logging.getLogger("lino_loc.service.sim")

SIDECAR_VERSION = 1

#: ``lino-loc sim``'s working folder in the temp dir: ``lino-loc-sim-<pid>-<random>``.
SIM_FOLDER_PREFIX = "lino-loc-sim-"
_SIM_FOLDER_RE = re.compile(r"^lino-loc-sim-(?P<pid>[0-9]+)-[A-Za-z0-9_]+$")


def sim_folder_prefix() -> str:
    """The ``mkdtemp`` prefix of this process's simulator folder (its pid in the name)."""
    return f"{SIM_FOLDER_PREFIX}{os.getpid()}-"


def remove_stale_sim_folders(tmp: str | Path | None = None) -> list[Path]:
    """Remove the simulator folders (``lino-loc-sim-<pid>-*`` in ``tmp``, default the temp
    dir) of this user whose process ``<pid>`` is gone (killed before it could clean up).
    A folder of a live process, of another user, or without a pid in its name is left
    alone. Returns the removed folders."""
    root = Path(tmp or tempfile.gettempdir())
    removed: list[Path] = []
    try:
        entries = list(root.iterdir())
    except OSError:
        return removed
    for entry in entries:
        m = _SIM_FOLDER_RE.match(entry.name)
        if m is None or pid_alive(int(m.group("pid"))):
            continue
        try:
            if entry.is_symlink() or not entry.is_dir() or entry.stat().st_uid != os.getuid():
                continue
        except OSError:
            continue
        shutil.rmtree(entry, ignore_errors=True)
        if not entry.exists():
            removed.append(entry)
    return removed
    return True

# --------------------------------------------------------------------------------------------
# the child process
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SimInfo:
    """What ``lino-loc sim`` printed on its first line."""

    head: str
    odometry: str
    camera: str
    truth: str | None
    world: str | None
    pid: int | None
    raw: dict[str, Any]

    @classmethod
    def parse(cls, line: str) -> SimInfo:
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as exc:
            raise LinoLocError(f"lino-loc sim: first line is not JSON ({exc.msg}): {line[:120]!r}") from None
        if not isinstance(obj, dict):
            raise LinoLocError(f"lino-loc sim: first line is not a JSON object: {line[:120]!r}")
        missing = [k for k in ("head", "odometry", "camera") if not isinstance(obj.get(k), str)]
        if missing:
            raise LinoLocError(f"lino-loc sim: first line lacks {', '.join(missing)}: {line[:200]!r}")
        pid = obj.get("pid")
        return cls(
            head=obj["head"],
            odometry=obj["odometry"],
            camera=obj["camera"],
            truth=obj.get("truth") if isinstance(obj.get("truth"), str) else None,
            world=obj.get("world") if isinstance(obj.get("world"), str) else None,
            pid=pid if isinstance(pid, int) else None,
            raw=obj,
        )


def _pdeathsig() -> None:  # runs in the child between fork and exec
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def _child_env() -> dict[str, str]:
    """Our environment, with this project's root first on PYTHONPATH (so that the child
    imports the same code even when the package is not installed)."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    parts = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    if root not in parts:
        env["PYTHONPATH"] = os.pathsep.join([root, *parts])
    return env


class SimProcess:
    """``lino-loc sim`` as a child process (see the module docstring)."""

    def __init__(
        self,
        config_path: str | Path | None = None,
        world: str = "office",
        extra_args: Sequence[str] = (),
        python: str | None = None,
    ) -> None:
        self.config_path = Path(config_path) if config_path is not None else None
        self.world = world
        self.extra_args = list(extra_args)
        self.python = python or sys.executable
        self.proc: subprocess.Popen[bytes] | None = None
        self.info: SimInfo | None = None
        self._pump: threading.Thread | None = None

    @property
    def argv(self) -> list[str]:
        argv = [self.python, "-m", "services.cli", "sim", "--world", self.world]
        if self.config_path is not None:
            argv += ["--config", str(self.config_path)]
        return argv + self.extra_args

    def start(self, timeout: float = 120.0) -> SimInfo:
        """Start the child and wait (up to ``timeout`` s) for its first line."""
        log.info("starting the simulated robot: %s", " ".join(self.argv[1:]))
        self.proc = subprocess.Popen(  # noqa: S603 - our own interpreter and module
            self.argv,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=None,  # the child's logs go to our stderr
            preexec_fn=_pdeathsig,  # noqa: PLW1509 - fork-safe: one prctl call
            close_fds=True,
            # its own session: a Ctrl-C on the terminal reaches the daemon only, which then
            # stops the simulator after closing its devices (not both at once)
            start_new_session=True,
            env=_child_env(),
        )
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        buf = b""
        deadline = time.monotonic() + timeout
        while b"\n" not in buf:
            left = deadline - time.monotonic()
            if left <= 0:
                self.stop()
                raise LinoLocError(f"lino-loc sim: no device line within {timeout:g} s")
            ready, _, _ = select.select([fd], [], [], min(left, 0.5))
            if not ready:
                if self.proc.poll() is not None:
                    raise LinoLocError(
                        f"lino-loc sim exited with status {self.proc.returncode} before printing its devices"
                    )
                continue
            chunk = os.read(fd, 65536)
            if not chunk:
                code = self.proc.wait(timeout=5)
                raise LinoLocError(f"lino-loc sim exited with status {code} before printing its devices")
            buf += chunk
        line, _, rest = buf.partition(b"\n")
        try:
            self.info = SimInfo.parse(line.decode("utf-8", errors="replace"))
        except LinoLocError:
            self.stop()
            raise
        # Keep reading its stdout so a chatty child never blocks on a full pipe.
        self._pump = threading.Thread(target=self._drain, args=(rest,), name="sim-stdout", daemon=True)
        self._pump.start()
        log.info("simulated robot running (pid %d): %s", self.proc.pid, json.dumps(self.info.raw))
        return self.info

    def _drain(self, first: bytes) -> None:
        proc = self.proc
        if proc is None or proc.stdout is None:
            return
        if first.strip():
            log.debug("sim: %s", first.decode(errors="replace").rstrip())
        try:
            for line in proc.stdout:
                log.debug("sim: %s", line.decode(errors="replace").rstrip())
        except (OSError, ValueError):
            pass

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout: float = 5.0) -> int | None:
        """SIGTERM, wait up to ``timeout`` s, then SIGKILL. Returns the exit status."""
        proc = self.proc
        if proc is None:
            return None
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                log.warning("lino-loc sim did not stop within %g s; killing it", timeout)
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                proc.wait(5)
        if proc.stdout is not None:
            with contextlib.suppress(OSError):
                proc.stdout.close()
        return proc.returncode


def needs_sim(cfg: ServiceConfig) -> bool:
    """True when some device of the configuration is "the simulator started for this daemon"."""
    d = cfg.devices
    return cfg.simulated and (
        d.camera.sim.endpoint == AUTO
        or (d.head.kind == "dynamixel" and d.head.port == AUTO)
        or (d.odometry.kind == "serial" and d.odometry.port == AUTO)
    )


def resolve_auto(cfg: ServiceConfig, info: SimInfo) -> ServiceConfig:
    """``cfg`` with its "auto" ports and camera endpoint replaced by the simulator's."""
    d = cfg.devices
    cam_sim = d.camera.sim
    if cam_sim.endpoint == AUTO:
        cam_sim = cam_sim.model_copy(update={"endpoint": info.camera})
    head = d.head.model_copy(update={"port": info.head}) if d.head.port == AUTO else d.head
    odo = d.odometry.model_copy(update={"port": info.odometry}) if d.odometry.port == AUTO else d.odometry
    devices = d.model_copy(
        update={"camera": d.camera.model_copy(update={"sim": cam_sim}), "head": head, "odometry": odo}
    )
    return cfg.model_copy(update={"devices": devices})


# --------------------------------------------------------------------------------------------
# the simulated map: build once, then reuse
# --------------------------------------------------------------------------------------------


def _world_fingerprint(name: str) -> str:
    from drivers.sim.world import load_world

    return load_world(name).fingerprint


def _build_main(config_json: str) -> int:
    """Entry of the map-building child process (see :func:`ensure_sim_map`)."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        ensure_sim_map(ServiceConfig.model_validate_json(config_json))
    except LinoLocError as exc:
        print(f"lino-loc: error: {exc}", file=sys.stderr)
        return 2
    return 0


def sidecar_path(map_path: Path) -> Path:
    return map_path.with_name(map_path.name + ".build.json")


def _code_fingerprint() -> str:
    """The code that renders the survey and builds the map (a cached map from other code is
    rebuilt): :func:`drivers.sim.code_fingerprint.code_fingerprint`."""
    from drivers.sim.code_fingerprint import code_fingerprint

    return code_fingerprint()


def _translated(world: Any, dataset: Any, out: Path, build: MapBuildConfig) -> Any:
    """The survey seen from the lattice every ``build.step / build.translations`` inside its cells
    (:func:`lino_loc.translated_dataset.translate_dataset`), lattice positions kept where the
    world's floor is free inside the mapped area (the floor plan a simulated building has), warped
    on every CPU."""
    from lino_loc.dataset import Dataset
    from lino_loc.translated_dataset import translate_dataset

    report = translate_dataset(dataset, out, build.translations, step=build.step,
                               keep=lambda xy: world.is_mapped_free(xy[:, 0], xy[:, 1]), overwrite=True,
                               workers=os.cpu_count() or 1)
    log.info("virtual translations: %d survey images -> %d map images (%d fell back to the survey view)",
             report.rows_in, report.rows_out, report.fallbacks)
    return Dataset.open(out)


def _build_record(build: MapBuildConfig, world_fingerprint: str) -> dict[str, Any]:
    return {
        "version": SIDECAR_VERSION,
        "build": build.model_dump(mode="json", exclude_none=True),  # unset optional keys: old caches stay valid
        "world_fingerprint": world_fingerprint,
        "code_fingerprint": _code_fingerprint(),
    }


@contextlib.contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+b") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _cached(map_path: Path, record: dict[str, Any], mmap: bool = False) -> AppearanceMap | None:
    """The cached map if it is there, loads (memory-mapped with ``mmap``), and was built with
    ``record``; else None."""
    if not map_path.is_file():
        return None
    side = sidecar_path(map_path)
    try:
        saved = json.loads(side.read_text())
    except (OSError, json.JSONDecodeError):
        log.info("%s: no build record (%s); rebuilding", map_path, side.name)
        return None
    if {k: saved.get(k) for k in record} != record:
        log.info("%s: built with other settings or another world version; rebuilding", map_path)
        return None
    try:
        amap = AppearanceMap.load(map_path, mmap=mmap)
    except LinoLocError as exc:
        log.warning("cached map unusable (%s); rebuilding", exc)
        return None
    if saved.get("sha256") not in (None, amap.meta.sha256):
        log.info("%s: checksum differs from its build record; rebuilding", map_path)
        return None
    return amap


def ensure_sim_map(
    cfg: ServiceConfig, *, seed: int = 0, in_subprocess: bool = False
) -> tuple[AppearanceMap, bool]:
    """(the simulated world's map, whether it was built now). Without ``[map.build]`` the
    file at ``map.path`` is just loaded.

    ``in_subprocess``: build in a child Python process (the daemon does this, so that the
    survey's images and the PCA's work arrays never inflate its own resident memory)."""
    if in_subprocess and cfg.map.build is not None:
        world_fp = _world_fingerprint(cfg.map.build.world)
        amap = _cached(Path(cfg.map.path), _build_record(cfg.map.build, world_fp), cfg.map.mmap)
        if amap is not None:
            log.info("using the cached simulated map %s (%d map entries)", cfg.map.path, len(amap))
            return amap, False
        code = subprocess.run(  # noqa: S603 - our own interpreter and module
            [sys.executable, "-c", "import sys; from services.sim_launcher import _build_main; "
             "sys.exit(_build_main(sys.stdin.read()))"],
            input=cfg.model_dump_json().encode(), env=_child_env(), check=False,
        ).returncode
        if code != 0:
            raise LinoLocError(f"building the simulated map {cfg.map.path} failed (status {code})")
        return AppearanceMap.load(cfg.map.path, mmap=cfg.map.mmap), True
    from drivers.sim.renderer import CameraModel
    from drivers.sim.survey import run_survey
    from drivers.sim.world import load_world
    from lino_loc.dataset import Dataset
    from lino_loc.virtual_views import offsets

    map_path = Path(cfg.map.path)
    build = cfg.map.build
    if build is None:
        return AppearanceMap.load(map_path, mmap=cfg.map.mmap), False
    world = load_world(build.world)
    record = _build_record(build, world.fingerprint)
    amap = _cached(map_path, record)
    if amap is not None:
        log.info("using the cached simulated map %s (%d map entries)", map_path, len(amap))
        return amap, False
    with _file_lock(map_path.with_name(map_path.name + ".lock")):
        amap = _cached(map_path, record)  # another process may have built it meanwhile
        if amap is not None:
            return amap, False
        survey_dir = map_path.with_name(f".{map_path.stem}.survey")
        translated_dir = survey_dir.with_name(f"{survey_dir.name}.t{build.translations}")
        t0 = time.monotonic()
        log.info(
            "building the simulated map once: survey of %s under %s light, every %g m and %g deg, "
            "%dx%d images (cached at %s)",
            world.name, build.lighting, build.step, build.heading_step_deg, build.width,
            build.height, map_path,
        )
        camera = CameraModel(width=build.width, height=build.height)
        try:
            result = run_survey(
                world, survey_dir, step=build.step,
                heading_step_rad=math.radians(build.heading_step_deg), lighting=build.lighting,
                camera=camera, seed=seed, stereo=build.disparity, overwrite=True,
                dense_depth=build.disparity and build.disparity_source == "dense-depth",
            )
            size = (min(DEFAULT_SIZE[0], build.width), min(DEFAULT_SIZE[1], build.height))
            channels = ("intensity", "disparity") if build.disparity else ("intensity",)
            dataset = Dataset.open(survey_dir)
            if build.translations > 1:
                dataset = _translated(world, dataset, translated_dir, build)
            amap = build_map(
                dataset, n_features=build.features, preprocess=build.preprocess,
                size=size, channels=channels, seed=seed, disparity_features=build.disparity_features,
                virtual_offsets=None if build.virtual_headings == 1 else offsets(
                    math.radians(build.virtual_step_deg), build.virtual_headings),
            )
            amap.save(map_path)
            side = sidecar_path(map_path)
            tmp = side.with_name(side.name + ".tmp")
            tmp.write_text(json.dumps({**record, "sha256": amap.meta.sha256, "rows": result.rows}))
            os.replace(tmp, side)
        finally:
            shutil.rmtree(survey_dir, ignore_errors=True)
            shutil.rmtree(translated_dir, ignore_errors=True)
        log.info("simulated map built: %d map entries in %.1f s -> %s", len(amap), time.monotonic() - t0, map_path)
        return amap, True

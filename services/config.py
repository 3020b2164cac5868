"""The service's configuration: one pydantic model tree, loaded from TOML plus environment.

``ServiceConfig`` has one section per concern::

    [devices.camera]   kind = "oakd" | "sim"; [devices.camera.oakd] (drivers.oakd.OakdConfig)
                       or [devices.camera.sim] (the simulated camera)
    [devices.head]     kind = "dynamixel" | "sim"; drivers.dynamixel_head.HeadConfig fields
    [devices.odometry] kind = "serial" | "sim"; drivers.serial_odometry.OdometryConfig fields
    [map]              path of the appearance map; [map.build] to build it once (simulation)
    [localizer]        lino_loc.localizer.LocalizerConfig: motion, sensor, filter, fusion
    [active_vision]    services.active_head.ActiveVisionSettings: the head's range, settle
                       time, interval, home (the method's settings are its defaults)
    [endpoints]        ZeroMQ PUB and REP addresses, high-water mark; [endpoints.curve] the
                       CURVE keys (services.curve_auth.CurveConfig), required off loopback
    [publish]          services.publisher.PublishConfig: particle throttling, truth (simulation)
    [persistence]      services.persistence.PersistenceConfig: state file (last pose), save period
    [recording]        services.recording.recorder.RecordingConfig: the session's MCAP file
    [live_view]        services.recording.live_view.LiveViewConfig: a Foxglove WebSocket server
    [map_refresh]      services.map_refresh.MapRefreshConfig: confident views written into a
                       dataset for `lino-loc map extend` (off by default)
    [logging]          level

Sources, highest priority first: environment variables ``LINO_LOC__SECTION__FIELD``
(nested with ``__``, e.g. ``LINO_LOC__DEVICES__HEAD__PORT=/dev/ttyUSB1``; lists and tables as
JSON), then the TOML file, then the defaults below (the real robot's). Unknown keys are
errors everywhere (also misspelt ``LINO_LOC__...`` variables), so typos never pass silently.
A key that was a setting once (:data:`RETIRED_KEYS`) fails with one line naming its new key
or saying that it is no longer a setting.

Relative paths are relative to the working directory; ``~`` is expanded.

Usage::

    from services.config import load_config, check_config
    cfg = load_config("config/lino.toml")         # raises ConfigError (a LinoLocError)
    problems = check_config("config/lino.toml")   # ["FILE: section.field: message", ...]
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from drivers.dynamixel_head import HeadConfig
from drivers.oakd_config import OakdConfig
from drivers.serial_odometry import OdometryConfig
from lino_loc.errors import LinoLocError
from lino_loc.localizer import LocalizerConfig
from lino_loc.particle_filter import FilterConfig, old_key_problems
from lino_loc.preprocessing import Preprocess
from services.active_head import METHOD_SETTINGS, ActiveVisionSettings
from services.curve_auth import CurveConfig, curve_problem
from services.map_refresh import MapRefreshConfig
from services.persistence import PersistenceConfig
from services.publisher import PublishConfig
from services.recording.live_view import LiveViewConfig
from services.recording.recorder import RecordingConfig
from services.relay_publisher import RelayConfig

ENV_PREFIX = "LINO_LOC__"
ENV_DELIMITER = "__"

#: The string that stands for "the simulator's device" in port/endpoint fields.
AUTO = "auto"

_ENDPOINT_RE = re.compile(r"^(tcp://[^\s]+:(\d+|\*)|ipc://[^\s]+|inproc://[^\s]+)$")


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _check_port(v: str) -> str:
    if v == AUTO or v.startswith("/"):
        return v
    raise ValueError(
        f'{v!r} is not a device path: use an absolute path (e.g. /dev/serial/by-id/...) or "auto"'
    )


# --------------------------------------------------------------------------------------------
# devices
# --------------------------------------------------------------------------------------------


class SimCameraConfig(_Section):
    """The simulated robot's camera (rendered in the simulated building)."""

    endpoint: str = Field(
        AUTO,
        description='how to reach the simulated camera: "auto" = the simulator started for '
        "this daemon, or the address that `lino-loc sim` prints",
    )
    world: str = Field("office", description="world name (config/worlds/<name>.json) or path")
    lighting: str = Field("tube", description="lighting setup: tube, bulb, natural")
    scene_changes: list[str] = Field(
        default_factory=list, description="scene-change sets unknown to the map (boxes, people, ...)"
    )
    width: int = Field(320, ge=16, le=4096, description="pixels")
    height: int = Field(240, ge=16, le=4096, description="pixels")
    fps: float = Field(15.0, gt=0.0, le=120.0, description="frames per second")
    baseline_m: float = Field(0.075, gt=0.0, description="stereo baseline, metres")


class CameraConfig(_Section):
    """The stereo camera: ``kind`` selects which of the two sub-tables is used."""

    kind: Literal["oakd", "sim"] = "oakd"
    oakd: OakdConfig = Field(default_factory=OakdConfig)
    sim: SimCameraConfig = Field(default_factory=SimCameraConfig)


class HeadDeviceConfig(HeadConfig):
    """The pan-tilt head: ``kind`` plus :class:`drivers.dynamixel_head.HeadConfig`.

    ``dynamixel``: the real driver on ``port`` (on the simulated robot ``"auto"``, the
    Dynamixel emulator's pseudo-terminal). ``sim``: an in-process simulated head.
    """

    kind: Literal["dynamixel", "sim"] = "dynamixel"

    @field_validator("port")
    @classmethod
    def _port(cls, v: str) -> str:
        return _check_port(v)

    def driver_config(self) -> HeadConfig:
        """The plain driver configuration (``port`` must already be resolved)."""
        return HeadConfig.model_validate(self.model_dump(exclude={"kind"}))


class OdometryDeviceConfig(OdometryConfig):
    """Wheel odometry: ``kind`` plus :class:`drivers.serial_odometry.OdometryConfig`.

    ``serial``: the real driver on ``port`` (``"auto"`` on the simulated robot: the odometry
    board emulator's pseudo-terminal). ``sim``: in-process simulated odometry.
    """

    kind: Literal["serial", "sim"] = "serial"

    @field_validator("port")
    @classmethod
    def _port(cls, v: str) -> str:
        return _check_port(v)

    def driver_config(self) -> OdometryConfig:
        return OdometryConfig.model_validate(self.model_dump(exclude={"kind"}))


class DevicesConfig(_Section):
    camera: CameraConfig = Field(default_factory=CameraConfig)
    head: HeadDeviceConfig = Field(default_factory=HeadDeviceConfig)
    odometry: OdometryDeviceConfig = Field(default_factory=OdometryDeviceConfig)


# --------------------------------------------------------------------------------------------
# map, localizer, active vision
# --------------------------------------------------------------------------------------------


class MapBuildConfig(_Section):
    """How to build the map of a simulated world when ``map.path`` does not exist yet.

    Same meaning as ``lino-loc survey`` + ``lino-loc map build``; the result is cached at
    ``map.path`` and reused while these settings are unchanged.
    """

    world: str = Field("office", description="world name or path")
    lighting: str = Field("tube", description="lighting of the survey (the paper maps under tubes)")
    step: float = Field(0.75, gt=0.0, description="survey grid step, metres")
    heading_step_deg: float = Field(15.0, gt=0.0, le=180.0, description="survey heading step, degrees")
    width: int = Field(320, ge=16, description="survey image width, pixels")
    height: int = Field(240, ge=16, description="survey image height, pixels")
    features: int = Field(5, ge=1, le=200, description="PCA features per image (eq. 1)")
    preprocess: Preprocess = "none"
    disparity: bool = Field(False, description="also build the disparity channel (EM-PCA)")
    disparity_features: int | None = Field(
        None, ge=1, le=200, description="the disparity channel's features (default: features); its EM's "
        "cost grows with the square of it"
    )
    disparity_source: Literal["stereo-matcher", "dense-depth"] = Field(
        "stereo-matcher",
        description="the disparity channel's data: the survey's stereo pairs through the product's block "
        "matcher (sparse, as on the robot) or the renderer's exact dense depth (no camera gives it)",
    )
    virtual_headings: int = Field(
        1, ge=1, le=31, description="map entries per image: the image turned by this many headings "
        "virtual_step_deg apart (lino_loc.virtual_views); 1 = the images alone"
    )
    virtual_step_deg: float = Field(3.0, gt=0.0, le=30.0, description="degrees between virtual headings")
    translations: int = Field(
        1, ge=1, le=9, description="odd m: every survey image is also seen from the lattice every step / m inside "
        "its cell, synthesized from its stereo disparity (lino_loc.translated_dataset; needs disparity = true); "
        "1 = the survey positions alone"
    )

    @model_validator(mode="after")
    def _translations_need_disparity(self) -> MapBuildConfig:
        if self.translations % 2 == 0:
            raise ValueError(f"translations must be odd (got {self.translations})")
        if self.translations > 1 and not (self.disparity and self.disparity_source == "stereo-matcher"):
            raise ValueError("translations need the survey's stereo disparity: set disparity = true "
                             "(disparity_source = \"stereo-matcher\")")
        return self


class MapConfig(_Section):
    path: Path = Field(Path("/var/lib/lino-loc/map.npz"), description="appearance map file")
    build: MapBuildConfig | None = Field(
        None, description="build the map here if the file is missing (simulation only)"
    )
    mmap: bool = Field(
        False, description="memory-map the map file's arrays instead of reading them into memory "
        "(the same checks; shared, reclaimable pages; for maps of 100k entries and more: docs/scale.md)"
    )

    @field_validator("path")
    @classmethod
    def _expand(cls, v: Path) -> Path:
        return v.expanduser()


# --------------------------------------------------------------------------------------------
# service plumbing
# --------------------------------------------------------------------------------------------


class EndpointsConfig(_Section):
    """ZeroMQ addresses (docs/zeromq.md) and their CURVE keys (services/curve_auth.py).

    An address other machines can reach (anything but loopback, ``ipc://``, ``inproc://``)
    is refused unless ``curve`` names the keys; with keys, both sockets use CURVE on any
    address."""

    pub: str = Field("tcp://127.0.0.1:5556", description="PUB socket: pose, status, particles, truth")
    rep: str = Field("tcp://127.0.0.1:5557", description="REP socket: control requests")
    sndhwm: int = Field(
        100, ge=1, description="PUB high-water mark: messages queued per slow subscriber, then dropped"
    )
    curve: CurveConfig = Field(default_factory=CurveConfig)
    relay: RelayConfig = Field(default_factory=RelayConfig)

    @field_validator("pub", "rep")
    @classmethod
    def _endpoint(cls, v: str) -> str:
        if not _ENDPOINT_RE.match(v):
            raise ValueError(f"{v!r} is not a ZeroMQ endpoint (tcp://HOST:PORT, ipc://PATH)")
        return v

    @model_validator(mode="after")
    def _distinct(self) -> EndpointsConfig:
        if self.pub == self.rep:
            raise ValueError(f"pub and rep must differ (both {self.pub})")
        problem = curve_problem({"pub": self.pub, "rep": self.rep}, self.curve)
        if problem is not None:
            raise ValueError(problem)
        return self


class LoggingConfig(_Section):
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"] = "INFO"

    @field_validator("level", mode="before")
    @classmethod
    def _upper(cls, v: Any) -> Any:
        return v.upper() if isinstance(v, str) else v


# --------------------------------------------------------------------------------------------
# the whole configuration
# --------------------------------------------------------------------------------------------


class ServiceConfig(BaseSettings):
    """Everything ``lino-loc run`` needs. Defaults describe the real robot."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter=ENV_DELIMITER,
        case_sensitive=False,
        extra="forbid",
    )

    devices: DevicesConfig = Field(default_factory=DevicesConfig)
    map: MapConfig = Field(default_factory=MapConfig)
    localizer: LocalizerConfig = Field(default_factory=LocalizerConfig)
    active_vision: ActiveVisionSettings = Field(default_factory=ActiveVisionSettings)
    endpoints: EndpointsConfig = Field(default_factory=EndpointsConfig)
    publish: PublishConfig = Field(default_factory=PublishConfig)
    persistence: PersistenceConfig = Field(default_factory=PersistenceConfig)
    recording: RecordingConfig = Field(default_factory=RecordingConfig)
    live_view: LiveViewConfig = Field(default_factory=LiveViewConfig)
    map_refresh: MapRefreshConfig = Field(default_factory=MapRefreshConfig)
    logging: LoggingConfig = Field(default_factory=LoggingConfig)

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # The file's content arrives as init kwargs: environment > file > defaults.
        return (env_settings, init_settings)

    @property
    def simulated(self) -> bool:
        """True on the simulated robot (the camera is simulated)."""
        return self.devices.camera.kind == "sim"

    @model_validator(mode="after")
    def _consistent(self) -> ServiceConfig:
        head = self.devices.head
        av = self.active_vision
        if av.pan_min < head.pan_min - 1e-9 or av.pan_max > head.pan_max + 1e-9:
            raise ValueError(
                f"active_vision pan range [{av.pan_min}, {av.pan_max}] exceeds the head's limits "
                f"[{head.pan_min}, {head.pan_max}] (devices.head.pan_min/pan_max)"
            )
        if not self.simulated:
            for name in ("head", "odometry"):
                if getattr(self.devices, name).port == AUTO:
                    raise ValueError(
                        f'devices.{name}.port = "auto" names the simulator\'s emulator port and '
                        'needs devices.camera.kind = "sim"; give the device path'
                    )
            if self.map.build is not None:
                raise ValueError('map.build is for the simulated robot (devices.camera.kind = "sim")')
        elif self.map.build is not None and self.map.build.world != self.devices.camera.sim.world:
            raise ValueError(
                f"map.build.world ({self.map.build.world!r}) differs from "
                f"devices.camera.sim.world ({self.devices.camera.sim.world!r})"
            )
        return self

    @classmethod
    def simulated_defaults(cls) -> ServiceConfig:
        """The simulated robot's configuration (what ``config/sim.toml`` holds), no env."""
        return cls.model_validate(SIM_OVERRIDES)


#: What config/sim.toml changes from the defaults (a test keeps the two in step).
SIM_OVERRIDES: dict[str, Any] = {
    "devices": {
        "camera": {"kind": "sim",
                   "sim": {"endpoint": AUTO, "world": "office", "lighting": "tube",
                           "width": 320, "height": 240, "fps": 15.0}},
        "head": {"kind": "dynamixel", "port": AUTO},
        "odometry": {"kind": "serial", "port": AUTO},
    },
    "map": {
        "path": "~/.cache/lino-loc/maps/office-tube-75cm-15deg-20f-d5-disparity-t3.npz",
        "build": {"world": "office", "lighting": "tube", "step": 0.75, "heading_step_deg": 15.0,
                  "features": 20, "disparity_features": 5, "preprocess": "none", "virtual_headings": 5,
                  "disparity": True, "translations": 3},
    },
    "localizer": {"filter": {"n_particles": 1000}},
    "persistence": {"state_file": "~/.local/state/lino-loc/sim-state.json"},
    "live_view": {"enabled": True},
}  # fmt: skip


# --------------------------------------------------------------------------------------------
# loading and checking
# --------------------------------------------------------------------------------------------


#: Keys that were settings once: dotted key -> what became of it ("renamed to NEW" or "no
#: longer a setting: ..."). A file or variable using one fails with that line.
RETIRED_KEYS: dict[str, str] = {
    **{
        f"active_vision.{k}": "no longer a setting: the active-vision method's own default "
        f"(lino_loc.active_vision.ActiveVisionConfig.{k})"
        for k in METHOD_SETTINGS
    },
    "publish.status_period_s": "no longer a setting: one status message a second "
    "(services.status.STATUS_PERIOD_S)",
}


def _retired_message(key: str) -> str:
    what = RETIRED_KEYS[key]
    return what if what.startswith("no longer") else f"renamed to {what}"


def _retired_in(data: Mapping[str, Any], prefix: str = "") -> list[str]:
    """The retired keys present in a nested mapping (dotted, in file order)."""
    found = []
    for k, v in data.items():
        key = f"{prefix}{k}"
        if key in RETIRED_KEYS:
            found.append(key)
        elif isinstance(v, Mapping):
            found.extend(_retired_in(v, key + "."))
    return found


def _retired_env(environ: Mapping[str, str]) -> dict[str, str]:
    """Retired key -> the LINO_LOC__ variable that sets it."""
    out = {}
    for name in sorted(environ):
        if name.upper().startswith(ENV_PREFIX):
            key = ".".join(name[len(ENV_PREFIX) :].lower().split(ENV_DELIMITER))
            if key in RETIRED_KEYS:
                out[key] = name
    return out


class ConfigError(LinoLocError):
    """A configuration that does not validate. ``problems`` holds every error line."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        first = problems[0] if problems else "invalid configuration"
        more = f" (and {len(problems) - 1} more; see `lino-loc config check`)" if len(problems) > 1 else ""
        super().__init__(first + more)


def _format_loc(loc: tuple[Any, ...]) -> str:
    return ".".join(str(p) for p in loc) if loc else "(top level)"


def _format_msg(err: Mapping[str, Any]) -> str:
    etype = err.get("type", "")
    msg = str(err.get("msg", "invalid"))
    if etype == "extra_forbidden":
        return "unknown key (misspelt? see `lino-loc config show` for the valid ones)"
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    if etype != "missing" and "input" in err and not isinstance(err["input"], dict | list):
        got = repr(err["input"])
        if got not in msg and str(err["input"]) not in msg:
            msg = f"{msg} (got {got})"
    return " ".join(msg.split())


def _env_name(loc: tuple[Any, ...]) -> str:
    return ENV_PREFIX + ENV_DELIMITER.join(str(p).upper() for p in loc)


def _env_for(loc: tuple[Any, ...], environ: Mapping[str, str]) -> str | None:
    """The LINO_LOC__ variable that set ``loc`` (or one of its parents), if any."""
    upper = {k.upper(): k for k in environ}
    for n in range(len(loc), 0, -1):
        name = _env_name(loc[:n])
        if name in upper:
            return upper[name]
    return None


def _model_of(annotation: Any) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()) or ():
        m = _model_of(arg)
        if m is not None:
            return m
    return None


def _unknown_env(environ: Mapping[str, str]) -> list[str]:
    """LINO_LOC__ variables that name no field."""
    problems = []
    for key in sorted(environ):
        if not key.upper().startswith(ENV_PREFIX):
            continue
        parts = key[len(ENV_PREFIX) :].lower().split(ENV_DELIMITER)
        model: type[BaseModel] | None = ServiceConfig
        for i, part in enumerate(parts):
            fields = model.model_fields if model is not None else {}
            if part not in fields:
                if model is FilterConfig and old_key_problems({part: None}):
                    break  # a retired filter key: FilterConfig's validator names its new key
                where = ".".join(parts[: i + 1])
                problems.append(f"{where}: unknown key (from environment {key})")
                break
            model = _model_of(fields[part].annotation)
            if model is None and i < len(parts) - 1:
                where = ".".join(parts[: i + 2])
                problems.append(f"{where}: unknown key (from environment {key})")
                break
    return problems


def read_toml(path: str | Path) -> dict[str, Any]:
    """The parsed TOML file; raises ConfigError naming the file (and the line on a syntax error)."""
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ConfigError([f"{p}: file not found"]) from None
    except IsADirectoryError:
        raise ConfigError([f"{p}: is a directory, not a TOML file"]) from None
    except UnicodeDecodeError as exc:
        raise ConfigError([f"{p}: not UTF-8 text (byte {exc.start})"]) from None
    except OSError as exc:
        raise ConfigError([f"{p}: cannot read: {exc.strerror or exc}"]) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([f"{p}: TOML syntax error: {exc}"]) from None


def _validate(data: dict[str, Any], label: str, environ: Mapping[str, str]) -> ServiceConfig:
    problems: list[str] = []
    retired_env = _retired_env(environ)
    seen: set[str] = set(retired_env)
    for key in _retired_in(data):
        problems.append(f"{label}: {key}: {_retired_message(key)}")
        seen.add(key)
    for key, name in retired_env.items():
        problems.append(f"{label}: {key}: {_retired_message(key)} (from environment {name})")
    for p in _unknown_env({k: v for k, v in environ.items() if k not in retired_env.values()}):
        problems.append(f"{label}: {p}")
        seen.add(p.split(":", 1)[0])
    try:
        cfg = ServiceConfig(**data)
    except ValidationError as exc:
        for err in exc.errors(include_url=False):
            loc = tuple(err.get("loc", ()))
            where = _format_loc(loc)
            if where in seen and err.get("type") == "extra_forbidden" and where in RETIRED_KEYS:
                continue  # already reported as a retired key
            env = _env_for(loc, environ)
            if env is not None and where in seen:
                continue  # already reported as an unknown environment variable
            line = f"{label}: {where}: {_format_msg(err)}"
            if env is not None:
                line += f" (from environment {env})"
            problems.append(line)
    else:
        if not problems:
            return cfg
    raise ConfigError(problems)


def load_config(path: str | Path | None = None) -> ServiceConfig:
    """The effective configuration: ``LINO_LOC__*`` environment > ``path`` (TOML) > defaults.

    Raises :class:`ConfigError` (a LinoLocError: one line, exit status 2) listing every
    problem in ``.problems``.
    """
    data = read_toml(path) if path is not None else {}
    label = str(path) if path is not None else "(defaults)"
    return _validate(data, label, os.environ)


def check_config(path: str | Path) -> list[str]:
    """Every problem of the configuration file (plus environment), one line each; [] if valid.

    A valid configuration is then checked against the file system (:func:`file_problems`):
    the files it names must exist. ``lino-loc run`` (:func:`load_config`) does not do this
    (the daemon reports a missing map itself, and the simulated robot builds its map).
    """
    try:
        cfg = load_config(path)
    except ConfigError as exc:
        return exc.problems
    return file_problems(cfg, str(path))


def _path_problem(path: Path, kind: Literal["file", "parent"]) -> str | None:
    """Why ``path`` cannot serve: for ``"file"``, it must be a readable file; for
    ``"parent"``, its folder must exist or be creatable (its nearest existing ancestor a
    writable folder). None if fine. A path this user may not look at is a problem too (the
    check cannot vouch for it)."""
    target = path if kind == "file" else path.parent
    try:
        st = target.stat()
    except FileNotFoundError:
        if kind == "file":
            return f"{path}: no such file"
        anc = next((a for a in target.parents if a.exists()), None)
        if anc is None or not anc.is_dir() or not os.access(anc, os.W_OK | os.X_OK):
            return f"folder {target} does not exist and cannot be created ({anc} is not a writable folder)"
        return None
    except PermissionError:
        return f"{target}: cannot be checked by this user (permission denied); run the check as the service's user"
    except OSError as exc:
        return f"{target}: {exc.strerror or exc}"
    if kind == "file":
        if stat.S_ISDIR(st.st_mode):
            return f"{path}: is a folder, not a file"
        if not os.access(path, os.R_OK):
            return f"{path}: not readable by this user"
    elif not stat.S_ISDIR(st.st_mode):
        return f"{target}: not a folder (the folder of {path.name})"
    return None


def file_problems(cfg: ServiceConfig, label: str) -> list[str]:
    """The files ``cfg`` names that cannot serve, one line each as ``LABEL: key: path: why``:
    ``map.path`` must be a readable file unless ``map.build`` is set (the simulated robot
    builds a missing map); ``persistence.state_file``'s folder must exist or be creatable.
    Paths relative to the working directory, as the service reads them."""
    named: list[tuple[str, Path, Literal["file", "parent"]]] = []
    if cfg.map.build is None:
        named.append(("map.path", cfg.map.path, "file"))
    named.append(("persistence.state_file", cfg.persistence.state_file, "parent"))
    problems = []
    for key, path, kind in named:
        msg = _path_problem(Path(path), kind)
        if msg is not None:
            problems.append(f"{label}: {key}: {msg}")
    return problems


# --------------------------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------------------------


def _toml_key(k: str) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _toml_value(k)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def to_toml(data: Mapping[str, Any], _prefix: str = "") -> str:
    """A TOML document of nested dicts (None values become comments: TOML has no null)."""
    lines: list[str] = []
    tables: list[tuple[str, Mapping[str, Any]]] = []
    for k, v in data.items():
        if isinstance(v, Mapping):
            tables.append((f"{_prefix}.{_toml_key(k)}" if _prefix else _toml_key(k), v))
        elif v is None:
            lines.append(f"# {_toml_key(k)} = (unset)")
        else:
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    blocks = []
    if lines:
        blocks.append("\n".join(([f"[{_prefix}]"] if _prefix else []) + lines))
    blocks.extend(to_toml(v, name) for name, v in tables)
    return "\n\n".join(b for b in blocks if b)


def _kind_first(d: Any) -> Any:
    if not isinstance(d, dict):
        return d
    keys = sorted(d, key=lambda k: k != "kind")  # stable: only moves "kind" to the front
    return {k: _kind_first(d[k]) for k in keys}


def config_as_dict(cfg: ServiceConfig) -> dict[str, Any]:
    """JSON-compatible dict of the effective configuration (``kind`` first in each section)."""
    return _kind_first(cfg.model_dump(mode="json"))

"""Everything on the ZeroMQ wire, as pydantic models (a **contract**, docs/zeromq.md).

Two sockets (addresses from ``[endpoints]`` of the configuration):

- **PUB** (``tcp://127.0.0.1:5556``): every message is two frames ``[topic, json]``.
  ``pose`` (:class:`PoseMessage`, every filter update), ``status`` (:class:`StatusMessage`,
  once a second), ``particles`` (:class:`ParticlesMessage`, throttled,
  possibly subsampled) and, in simulation, ``truth`` (:class:`TruthMessage`).
- **REP** (``tcp://127.0.0.1:5557``): one JSON object in (a :data:`Request`, discriminated
  by ``"cmd"``), one JSON object out (``{"ok": true, "cmd": ..., ...}`` or
  ``{"ok": false, "error": "..."}``). :func:`parse_request` turns any bytes into a
  request or an :class:`ErrorReply` and never raises.

Units and frames: REP-103/REP-105. Metres, radians (counter-clockwise), frame ``map``,
timestamps in seconds since the Unix epoch. ``theta`` is wrapped to [-pi, pi). A
covariance is 9 numbers, the 3 x 3 matrix over (x, y, theta) in row-major order.

Versioning: every message carries ``"v"`` (:data:`PROTOCOL_VERSION`), and each exported
JSON Schema has ``$id`` ``urn:lino-loc:schema:<name>:v<version>``. Adding an optional
field to a published message is *not* a version change: clients must ignore fields they do
not know (the published models use ``extra="ignore"``, and their schemas allow additional
properties). Removing or renaming a field, or changing its meaning or unit, bumps the
version. Requests are strict (``extra="forbid"``): a misspelt field is an error rather
than silently ignored; a request may send ``"v"``, and one with another version is
refused with an error naming it.

Usage::

    from services.messages import PoseMessage, Pose2D, parse_request, encode, decode
    frames = encode("pose", PoseMessage(stamp=t, pose=Pose2D(x=1, y=2, theta=0.1),
                                        covariance=cov, state="tracking"))
    req = parse_request(b'{"cmd": "ping"}')      # PingRequest, or ErrorReply
"""

from __future__ import annotations

import json
import math
import time
from typing import Annotated, Any, Literal, Protocol, Union

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from lino_loc.pose_estimate import Estimate
from lino_loc.poses import wrap_angle
from services.topics import TOPIC_NAMES

#: Version of the wire protocol (the "v" field, and the schema $id).
PROTOCOL_VERSION = 1

#: Requests larger than this are refused without being parsed.
MAX_REQUEST_BYTES = 64 * 1024

#: Covariance used by ``set_pose`` when the client sends none: AMCL's defaults
#: (sigma 0.5 m in x and y, pi/12 rad in theta), row-major 3 x 3.
DEFAULT_SET_POSE_COVARIANCE: tuple[float, ...] = (
    0.25, 0.0, 0.0,
    0.0, 0.25, 0.0,
    0.0, 0.0, (math.pi / 12.0) ** 2,
)  # fmt: skip

#: Limits of a belief given to the daemon (``set_pose``; :func:`belief_problem` for saved
#: states too). A pose may lie at most POSE_MARGIN_M outside the map's bounds (which already
#: hold ``localizer.sensor.map_margin`` around the surveyed poses): the robot can stand a
#: little beyond where the survey camera stood, not metres away.
POSE_MARGIN_M = 2.0
#: Largest heading standard deviation, rad: beyond pi a Gaussian heading says no more than
#: "any heading" (``global_localization`` says that).
MAX_STD_THETA = math.pi
#: Largest position standard deviation (m) and |x|, |y| (m) a request may carry whatever the
#: map (the daemon then checks the map's own limits: a position standard deviation no larger
#: than the map's extent, the pose within its bounds plus POSE_MARGIN_M).
MAX_STD_XY_M = 1000.0
MAX_ABS_POSITION_M = 1.0e6

LocalizationState = Literal["global", "tracking", "lost"]
"""``global``: the belief is spread (global localization or after a kidnapping);
``tracking``: the belief is concentrated and followed; ``lost``: the observations no longer
agree with the belief (recovery under way)."""

HealthStateName = Literal["ok", "degraded", "failed"]

# --------------------------------------------------------------------------------------------
# Shared pieces
# --------------------------------------------------------------------------------------------


def _finite(v: float) -> float:
    if not math.isfinite(v):
        raise ValueError(f"must be a finite number, got {v}")
    return v


Finite = Annotated[float, AfterValidator(_finite)]
"""A float that is neither NaN nor infinite."""

NonNegative = Annotated[float, Field(ge=0.0), AfterValidator(_finite)]
"""A finite float >= 0."""


def _check_covariance(values: list[float]) -> list[float]:
    """9 finite numbers forming a symmetric, positive semi-definite 3 x 3 matrix."""
    c = np.asarray(values, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(c)):
        raise ValueError("covariance entries must be finite numbers")
    scale = float(np.max(np.abs(c))) if c.size else 0.0
    tol = 1e-9 + 1e-6 * scale
    if np.any(np.abs(c - c.T) > tol):
        raise ValueError("covariance must be symmetric (row-major 3 x 3 over x, y, theta)")
    if np.any(np.diag(c) < 0.0):
        raise ValueError("covariance diagonal (variances) must be >= 0")
    sym = 0.5 * (c + c.T)
    if float(np.min(np.linalg.eigvalsh(sym))) < -tol:
        raise ValueError("covariance must be positive semi-definite")
    return [float(v) for v in sym.reshape(-1)]


class BoundsLike(Protocol):
    """An axis-aligned box of the map, metres (``lino_loc.sensor_model.Bounds``)."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float


def covariance_problem(cov: Any, max_std_xy: float, max_std_theta: float = MAX_STD_THETA) -> str | None:
    """Why a 3 x 3 covariance over (x, y, theta) is not a sane belief, in one line, or None.

    It must be finite, symmetric and positive semi-definite (:func:`_check_covariance`), its
    position standard deviation, the square root of the largest eigenvalue of the 2 x 2
    position block, sqrt((a + d) / 2 + hypot((a - d) / 2, b)), at most ``max_std_xy`` (m) and
    its heading standard deviation sqrt(c_33) at most ``max_std_theta`` (rad)."""
    try:
        c = np.asarray(_check_covariance(list(np.asarray(cov, dtype=np.float64).reshape(-1))))
        c = c.reshape(3, 3)
    except ValueError as exc:
        return str(exc)
    a, b, d = float(c[0, 0]), float(c[0, 1]), float(c[1, 1])
    std_xy = math.sqrt(max(0.5 * (a + d) + math.hypot(0.5 * (a - d), b), 0.0))
    std_th = math.sqrt(max(float(c[2, 2]), 0.0))
    problems = []
    if std_xy > max_std_xy:
        problems.append(f"position standard deviation {std_xy:.4g} m exceeds {max_std_xy:.4g} m")
    if std_th > max_std_theta:
        problems.append(f"heading standard deviation {std_th:.4g} rad exceeds {max_std_theta:.4g} rad")
    return f"covariance: {'; '.join(problems)}" if problems else None


def belief_problem(
    mean: Any, cov: Any, bounds: BoundsLike, margin: float = POSE_MARGIN_M
) -> str | None:
    """Why a Gaussian belief (mean (x, y, theta), 3 x 3 covariance) does not fit the map, in
    one line naming the value, or None when it does: the pose finite and within ``bounds``
    grown by ``margin`` m on each side, the covariance sane (:func:`covariance_problem`) with
    a position standard deviation no larger than the map's extent, max(x_max - x_min,
    y_max - y_min), and a heading standard deviation at most :data:`MAX_STD_THETA`. For
    ``set_pose`` and for any saved state the daemon would start from."""
    m = np.asarray(mean, dtype=np.float64).reshape(-1)
    if m.shape[0] != 3 or not np.all(np.isfinite(m)):
        return f"pose {m.tolist()}: must be 3 finite numbers (x, y, theta)"
    x, y = float(m[0]), float(m[1])
    if not (bounds.x_min - margin <= x <= bounds.x_max + margin
            and bounds.y_min - margin <= y <= bounds.y_max + margin):
        return (
            f"pose ({x:.6g}, {y:.6g}) lies outside the map: x in [{bounds.x_min:.3f}, "
            f"{bounds.x_max:.3f}], y in [{bounds.y_min:.3f}, {bounds.y_max:.3f}] m, plus {margin:g} m"
        )
    extent = max(bounds.x_max - bounds.x_min, bounds.y_max - bounds.y_min)
    return covariance_problem(cov, extent)


Covariance = Annotated[
    list[float],
    Field(
        min_length=9,
        max_length=9,
        description="3 x 3 covariance over (x, y, theta), row-major; m^2, m*rad, rad^2",
    ),
    AfterValidator(_check_covariance),
]


class Pose2D(BaseModel):
    """A planar pose in the ``map`` frame: metres, radians (CCW). ``theta`` is wrapped."""

    model_config = ConfigDict(extra="forbid")

    x: Finite = Field(description="metres")
    y: Finite = Field(description="metres")
    theta: Finite = Field(description="radians, counter-clockwise, wrapped to [-pi, pi)")

    @field_validator("theta")
    @classmethod
    def _wrap(cls, v: float) -> float:
        return float(wrap_angle(v))

    def as_tuple(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.theta)


class _Published(BaseModel):
    """Base of published messages: tolerant reader (unknown fields ignored)."""

    model_config = ConfigDict(extra="ignore", json_schema_serialization_defaults_required=True)

    v: Literal[1] = Field(PROTOCOL_VERSION, description="protocol version")


# --------------------------------------------------------------------------------------------
# Published messages (PUB socket)
# --------------------------------------------------------------------------------------------


class PoseMessage(_Published):
    """Topic ``pose``: the estimated robot pose after each filter update."""

    stamp: Finite = Field(ge=0.0, description="capture time of the frame, s since the Unix epoch")
    frame_id: Literal["map"] = "map"
    seq: int = Field(0, ge=0, description="update counter since the daemon started")
    pose: Pose2D = Field(description="robot (base) pose; the camera looks along theta + pan")
    covariance: Covariance
    state: LocalizationState
    pan: Finite | None = Field(None, description="head pan angle at the frame's time, radians")
    ess: NonNegative | None = Field(None, description="effective sample size of the particles")
    n_particles: Annotated[int, Field(ge=0)] | None = Field(None, description="particles in the filter")
    dead_reckoning: bool = Field(
        False,
        description="true while no camera observation is used (camera failed): the pose is "
        "predicted from odometry alone and its covariance grows",
    )
    latency_ms: NonNegative | None = Field(
        None, description="from the frame's capture to publication, milliseconds"
    )
    quality: Annotated[float, Field(ge=0.0, le=1.0)] | None = Field(
        None, description="how far to trust the pose, 0 (not at all) to 1; higher means a "
        "smaller error (lino_loc.quality: the views' support of the belief, the mode's weight "
        "and spread, the lost test's doubt; the error by quality band is in docs/results.md)",
    )

    @classmethod
    def from_estimate(
        cls,
        est: Estimate,
        *,
        stamp: float,
        seq: int,
        pan: float | None,
        dead_reckoning: bool = False,
        now: float | None = None,
    ) -> PoseMessage:
        """The message of one filter estimate: the covariance symmetrized, (C + C^T) / 2, and
        flattened row-major; the latency from ``stamp`` to ``now`` (default: the clock).
        Raises ``ValueError`` (pydantic's) when the estimate holds a non-finite value."""
        cov = np.asarray(est.covariance, dtype=np.float64)
        cov = 0.5 * (cov + cov.T)
        now = time.time() if now is None else now
        return cls(
            stamp=stamp,
            seq=seq,
            pose=Pose2D(x=float(est.pose[0]), y=float(est.pose[1]), theta=float(est.pose[2])),
            covariance=[float(v) for v in cov.reshape(-1)],
            state=est.state,
            pan=pan,
            ess=float(est.ess) if math.isfinite(est.ess) else None,
            n_particles=int(est.n_particles),
            dead_reckoning=dead_reckoning,
            latency_ms=max(0.0, (now - stamp) * 1000.0),
            quality=min(max(float(est.quality), 0.0), 1.0) if math.isfinite(est.quality) else None,
        )


class TruthMessage(_Published):
    """Topic ``truth`` (simulation only): the simulator's true robot pose."""

    stamp: Finite = Field(ge=0.0, description="s since the Unix epoch")
    frame_id: Literal["map"] = "map"
    seq: int = Field(0, ge=0)
    pose: Pose2D
    pan: Finite | None = Field(None, description="true head pan angle, radians")


class DeviceHealthModel(BaseModel):
    """Health of one device (mirrors ``drivers.interfaces.DeviceHealth``)."""

    model_config = ConfigDict(extra="ignore", json_schema_serialization_defaults_required=True)

    state: HealthStateName
    error: str | None = Field(None, description="the most recent error message (kept after recovery)")
    error_stamp: Finite | None = Field(None, description="time of that error, s since the epoch")
    counters: dict[str, int] = Field(
        default_factory=dict, description="monotonic event counts (timeouts, crc_errors, ...)"
    )

    @classmethod
    def from_health(cls, health: Any) -> DeviceHealthModel:
        """From a ``drivers.interfaces.DeviceHealth`` (duck-typed: state, last_error, ...)."""
        state = getattr(health.state, "value", health.state)
        return cls(
            state=state,
            error=health.last_error,
            error_stamp=health.last_error_stamp,
            counters=dict(health.counters),
        )


class LatencyStats(BaseModel):
    """Frame-to-publish latency over the last status period, milliseconds."""

    model_config = ConfigDict(extra="ignore", json_schema_serialization_defaults_required=True)

    p50: NonNegative | None = None
    p99: NonNegative | None = None


class MapInfo(BaseModel):
    """The appearance map in use."""

    model_config = ConfigDict(extra="ignore", json_schema_serialization_defaults_required=True)

    path: str
    n_images: int = Field(ge=0)
    channels: list[str] = Field(default_factory=list, description='e.g. ["intensity", "disparity"]')
    checksum: str | None = None


class PersistenceInfo(BaseModel):
    """The saved pose: how the daemon started, and the saves since."""

    model_config = ConfigDict(extra="ignore", json_schema_serialization_defaults_required=True)

    initial_belief: str | None = Field(
        None, description="how the belief started: the saved pose reused (unconfirmed until "
        "the views confirm it), or global localization and why (no saved pose, or the reason "
        "the saved one was refused)"
    )
    saves: int = Field(0, ge=0, description="poses saved since start")
    save_error: str | None = Field(
        None, description="why the last save failed (None after a successful one)"
    )


class PosePortInfo(BaseModel):
    """The pose port's subscribers as the daemon sees them (services/subscription_guard.py)."""

    model_config = ConfigDict(extra="ignore", json_schema_serialization_defaults_required=True)

    subscribers: int = Field(0, ge=0, description="subscriber connections open")
    subscriptions: int = Field(
        0, ge=0, description="distinct subscription prefixes held by the subscribers (libzmq's table)"
    )
    subscription_bytes: int = Field(0, ge=0, description="their summed length, bytes")
    ignored_subscriptions: int = Field(
        0, ge=0, description="subscriptions since start that match no topic (they get nothing)"
    )
    evicted_subscribers: int = Field(
        0, ge=0, description="subscriber connections ended since start because the table "
        "passed its cap (the one that sent the most each time)"
    )
    dropped_sends: int = Field(0, ge=0, description="messages ZeroMQ refused to queue since start")
    refused_handshakes: int = Field(
        0, ge=0, description="connections refused at the handshake since start (no CURVE keys, "
        "a key not authorized, not ZeroMQ)"
    )
    relay_running: bool | None = Field(
        None, description="whether the pose relay process runs now (None: no relay, the daemon "
        "binds the pose port itself)"
    )
    relay_restarts: int = Field(
        0, ge=0, description="times the pose relay was started again since start (it exited: "
        "its memory limit, a crash, a kill)"
    )
    relay_resident_bytes: int | None = Field(
        None, ge=0, description="the pose relay's resident memory at its last report, bytes"
    )


class ActiveVisionInfo(BaseModel):
    """Active-vision switches as the daemon sees them."""

    model_config = ConfigDict(extra="ignore", json_schema_serialization_defaults_required=True)

    enabled: bool
    paused: bool = False
    head_paused: bool = False
    head_commands: int = Field(0, ge=0, description="pan commands sent by active vision since start")
    last_decision: str | None = Field(
        None,
        description="the policy's last answer: move, home, converged, no gain, stay, settling, "
        "interval, head moving, no new frame; or confirm (a look for new views of a converged "
        "belief not yet confirmed)",
    )
    last_command_rad: Finite | None = Field(None, description="the last pan command (radians)")
    frames_head_moving: int = Field(
        0, ge=0, description="frames used for prediction only: taken while the head turned or settled"
    )


class RecordingInfo(BaseModel):
    """The session's recording (``lino-loc run --record``, ``[recording]``)."""

    model_config = ConfigDict(extra="ignore", json_schema_serialization_defaults_required=True)

    file: str | None = Field(None, description="the MCAP file being written (the latest part)")
    files: int = Field(0, ge=0, description="parts written so far (size-based rotation)")
    megabytes: float = Field(0.0, ge=0.0, description="MB written (flushed) so far, all parts")
    messages: int = Field(0, ge=0, description="messages written")
    dropped: int = Field(
        0, ge=0, description="events not recorded because the writer fell behind (its queue was "
        "full) or had failed; the loop never waits for the recorder"
    )
    error: str | None = Field(None, description="why recording stopped (None while it works)")


class LiveViewInfo(BaseModel):
    """The live view (``[live_view]``: a Foxglove WebSocket server in the daemon)."""

    model_config = ConfigDict(extra="ignore", json_schema_serialization_defaults_required=True)

    address: str = Field(description="ws://HOST:PORT (the port bound, or the one configured)")
    serving: bool = Field(False, description="the server runs (false: see error)")
    clients: int = Field(0, ge=0, description="clients subscribed to at least one topic")
    topics: list[str] = Field(default_factory=list, description="the topics subscribed to")
    messages: int = Field(0, ge=0, description="messages sent to the server since start")
    dropped: int = Field(
        0, ge=0, description="events not sent because the sender fell behind (its queue was full); "
        "the loop never waits for the live view"
    )
    error: str | None = Field(None, description="why the server is not serving (None while it is)")


class StatusMessage(_Published):
    """Topic ``status`` (once a second) and the ``status`` reply."""

    stamp: Finite = Field(ge=0.0, description="s since the Unix epoch")
    state: Literal["starting", "global", "tracking", "lost"]
    pose_rate_hz: Finite = Field(ge=0.0, description="pose updates per second (last period)")
    frame_rate_hz: Finite = Field(ge=0.0, description="camera frames received per second")
    frames: int = Field(0, ge=0, description="frames received since start")
    dropped_frames: int = Field(0, ge=0, description="frames dropped since start (loop busy)")
    out_of_order_frames: int = Field(
        0, ge=0, description="frames skipped because they were older than the last one used"
    )
    appearance_changes: int = Field(
        0, ge=0, description="changes of the scene's appearance (lights switched) the filter "
        "found and relearnt after, since start"
    )
    update_errors: int = Field(
        0, ge=0, description="frame updates that raised since start (logged; the frame was "
        "skipped and the daemon went on)"
    )
    standing_matches: int = Field(
        0, ge=0, description="updates whose standing match moved the belief to where the views "
        "taken while standing jointly match the map's (localizer.standing_match), since start"
    )
    standing_relocations: int = Field(
        0, ge=0, description="of standing_matches, those that moved an unconfirmed belief to a place "
        "far from the estimate whose views fit better (localizer.standing_match.relocate), since start"
    )
    latency_ms: LatencyStats = Field(default_factory=LatencyStats)
    devices: dict[str, DeviceHealthModel] = Field(
        default_factory=dict, description="keys: camera, head, odometry"
    )
    uptime_s: Finite = Field(ge=0.0)
    map: MapInfo | None = None
    active_vision: ActiveVisionInfo | None = None
    persistence: PersistenceInfo | None = None
    pose_port: PosePortInfo | None = None
    recording: RecordingInfo | None = None
    live_view: LiveViewInfo | None = None
    control_refused_handshakes: int = Field(
        0, ge=0, description="control connections refused at the handshake since start (no "
        "CURVE keys, a key not authorized, not ZeroMQ)"
    )
    simulated: bool = False
    version: str | None = Field(None, description="software version of the daemon")


class ParticlesMessage(_Published):
    """Topic ``particles`` (throttled, for viewers): the particle set, maybe subsampled."""

    stamp: Finite = Field(ge=0.0, description="s since the Unix epoch")
    frame_id: Literal["map"] = "map"
    seq: int = Field(0, ge=0, description="seq of the pose message of the same update")
    poses: list[tuple[Finite, Finite, Finite]] = Field(description="[[x, y, theta], ...]")
    weights: list[NonNegative] = Field(
        description="normalised weights, same length as poses"
    )
    n_total: int = Field(ge=0, description="particles in the filter before subsampling")

    @model_validator(mode="after")
    def _same_length(self) -> ParticlesMessage:
        if len(self.poses) != len(self.weights):
            raise ValueError(
                f"poses and weights differ in length ({len(self.poses)} != {len(self.weights)})"
            )
        if len(self.poses) > self.n_total:
            raise ValueError(f"more poses ({len(self.poses)}) than n_total ({self.n_total})")
        return self

    @property
    def subsampled(self) -> bool:
        return len(self.poses) < self.n_total


#: Topic name -> payload model.
TOPICS: dict[str, type[_Published]] = {
    "pose": PoseMessage,
    "status": StatusMessage,
    "particles": ParticlesMessage,
    "truth": TruthMessage,
}
assert tuple(TOPICS) == TOPIC_NAMES, "services/topics.py names the same topics"

# --------------------------------------------------------------------------------------------
# Control requests (REP socket)
# --------------------------------------------------------------------------------------------


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid")

    v: Literal[1] = Field(PROTOCOL_VERSION, description="protocol version (optional)")


class SetPoseRequest(_Request):
    """Reinitialise the filter around ``pose`` (like RViz's "2D Pose Estimate")."""

    cmd: Literal["set_pose"]
    pose: Pose2D
    covariance: Covariance = Field(
        default_factory=lambda: list(DEFAULT_SET_POSE_COVARIANCE),
        description="default: diag(0.25 m^2, 0.25 m^2, (pi/12)^2 rad^2); position standard "
        "deviation at most 1000 m (and the map's extent), heading standard deviation at most pi",
    )
    frame_id: Literal["map"] = "map"

    @model_validator(mode="after")
    def _sane(self) -> SetPoseRequest:
        """Absolute limits, whatever the map: |x|, |y| <= MAX_ABS_POSITION_M, the covariance
        within MAX_STD_XY_M and MAX_STD_THETA (the daemon checks the map's own limits)."""
        for name, v in (("x", self.pose.x), ("y", self.pose.y)):
            if abs(v) > MAX_ABS_POSITION_M:
                raise ValueError(f"pose.{name} = {v:.6g} m is beyond +-{MAX_ABS_POSITION_M:g} m")
        problem = covariance_problem(self.covariance, MAX_STD_XY_M)
        if problem is not None:
            raise ValueError(problem)
        return self


class GlobalLocalizationRequest(_Request):
    """Forget the belief and localize from scratch (particles seeded from the sensor model)."""

    cmd: Literal["global_localization"]


class StatusRequest(_Request):
    """The current :class:`StatusMessage`."""

    cmd: Literal["status"]


class GetPoseRequest(_Request):
    """The latest :class:`PoseMessage` (null before the first update)."""

    cmd: Literal["get_pose"]


PauseTarget = Literal["active_vision", "head"]


class PauseRequest(_Request):
    """Pause active vision (head stays where it is) or the head entirely (no commands sent)."""

    cmd: Literal["pause"]
    target: PauseTarget = "active_vision"


class ResumeRequest(_Request):
    """Undo :class:`PauseRequest`."""

    cmd: Literal["resume"]
    target: PauseTarget = "active_vision"


class SetActiveVisionRequest(_Request):
    """Switch active vision on or off (persists until the daemon restarts)."""

    cmd: Literal["set_active_vision"]
    enabled: bool


class PingRequest(_Request):
    """Liveness check."""

    cmd: Literal["ping"]


class SaveStateRequest(_Request):
    """Write the persistence file (last pose) now."""

    cmd: Literal["save_state"]


Request = Annotated[
    Union[  # noqa: UP007 (a discriminated union needs the Union form for the schema title)
        SetPoseRequest,
        GlobalLocalizationRequest,
        StatusRequest,
        GetPoseRequest,
        PauseRequest,
        ResumeRequest,
        SetActiveVisionRequest,
        PingRequest,
        SaveStateRequest,
    ],
    Field(discriminator="cmd"),
]
"""Any control request, discriminated by ``"cmd"``."""

REQUEST_ADAPTER: TypeAdapter[Any] = TypeAdapter(Request)

#: cmd -> request model.
COMMANDS: dict[str, type[_Request]] = {
    m.model_fields["cmd"].annotation.__args__[0]: m  # type: ignore[union-attr]
    for m in (
        SetPoseRequest,
        GlobalLocalizationRequest,
        StatusRequest,
        GetPoseRequest,
        PauseRequest,
        ResumeRequest,
        SetActiveVisionRequest,
        PingRequest,
        SaveStateRequest,
    )
}

# --------------------------------------------------------------------------------------------
# Replies
# --------------------------------------------------------------------------------------------


class _Reply(BaseModel):
    model_config = ConfigDict(extra="ignore", json_schema_serialization_defaults_required=True)

    v: Literal[1] = Field(PROTOCOL_VERSION, description="protocol version")


class ErrorReply(_Reply):
    """The request was refused or failed. ``error`` is one line naming the field or value."""

    ok: Literal[False] = False
    error: str
    cmd: str | None = Field(None, description="the request's cmd when it could be read")


class AckReply(_Reply):
    """Done: ``set_pose``, ``global_localization``."""

    ok: Literal[True] = True
    cmd: Literal["set_pose", "global_localization"]
    message: str | None = None


class ControlStateReply(_Reply):
    """Reply to ``pause``, ``resume`` and ``set_active_vision``: the switches afterwards."""

    ok: Literal[True] = True
    cmd: Literal["pause", "resume", "set_active_vision"]
    active_vision: ActiveVisionInfo


class StatusReply(_Reply):
    ok: Literal[True] = True
    cmd: Literal["status"] = "status"
    status: StatusMessage


class GetPoseReply(_Reply):
    ok: Literal[True] = True
    cmd: Literal["get_pose"] = "get_pose"
    pose: PoseMessage | None = Field(description="null before the first update")


class PingReply(_Reply):
    ok: Literal[True] = True
    cmd: Literal["ping"] = "ping"
    stamp: Finite = Field(description="daemon clock, s since the Unix epoch")
    version: str | None = Field(None, description="software version of the daemon")


class SaveStateReply(_Reply):
    ok: Literal[True] = True
    cmd: Literal["save_state"] = "save_state"
    path: str
    stamp: Finite = Field(description="time the state was written, s since the Unix epoch")


Reply = Union[  # noqa: UP007
    AckReply, ControlStateReply, StatusReply, GetPoseReply, PingReply, SaveStateReply, ErrorReply
]
"""Any control reply: ``ok`` false -> :class:`ErrorReply`; else by ``cmd``."""

REPLY_ADAPTER: TypeAdapter[Any] = TypeAdapter(Reply)

# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name} is not allowed")


def _json_type(obj: object) -> str:
    if obj is None:
        return "null"
    if isinstance(obj, bool):
        return "boolean"
    if isinstance(obj, int | float):
        return "number"
    return {str: "string", list: "array", dict: "object"}.get(type(obj), type(obj).__name__)


def _loc(loc: tuple[Any, ...]) -> str:
    parts = [str(p) for p in loc]
    return ".".join(parts) if parts else "(request)"


def format_validation_error(exc: ValidationError, *, skip_tag: bool = False) -> str:
    """One line: ``field.path: message; other.field: message``.

    ``skip_tag`` drops the first location element (the tag pydantic adds when a
    discriminated union such as :data:`REQUEST_ADAPTER` was validated).
    """
    msgs = []
    for err in exc.errors(include_url=False):
        loc = tuple(err.get("loc", ()))
        if skip_tag and loc:
            loc = loc[1:]
        msg = err.get("msg", "invalid")
        if err.get("type") == "extra_forbidden":
            msg = "unknown field"
        elif msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        msgs.append(f"{_loc(loc)}: {msg}")
    return "; ".join(msgs)


def error_reply(message: str, cmd: str | None = None) -> ErrorReply:
    """An :class:`ErrorReply` with ``message`` made one line."""
    return ErrorReply(error=" ".join(str(message).split()) or "error", cmd=cmd)


def parse_request(raw: bytes | bytearray | memoryview | str) -> Any:
    """A :data:`Request` model, or an :class:`ErrorReply` explaining why not. Never raises.

    Checks in order: size (:data:`MAX_REQUEST_BYTES`), UTF-8, JSON syntax (no NaN or
    Infinity), a JSON object, a known ``"cmd"``, a supported ``"v"``, then the fields of that
    command (every problem named by its field path).
    """
    try:
        if isinstance(raw, str):
            raw = raw.encode("utf-8", errors="surrogatepass")
        data = bytes(raw)
        if len(data) > MAX_REQUEST_BYTES:
            return error_reply(f"request too large: {len(data)} bytes (limit {MAX_REQUEST_BYTES})")
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            return error_reply(f"request is not UTF-8 text (byte {exc.start})")
        if not text.strip():
            return error_reply('empty request: expected a JSON object such as {"cmd": "ping"}')
        try:
            obj = json.loads(text, parse_constant=_reject_constant)
        except json.JSONDecodeError as exc:
            return error_reply(
                f"malformed JSON at line {exc.lineno} column {exc.colno}: {exc.msg}"
            )
        except ValueError as exc:
            return error_reply(f"malformed JSON: {exc}")
        except RecursionError:
            return error_reply("malformed JSON: nested too deeply")
        if not isinstance(obj, dict):
            return error_reply(f"request must be a JSON object, got {_json_type(obj)}")
        if "cmd" not in obj:
            return error_reply(f"cmd: missing (one of {', '.join(COMMANDS)})")
        cmd = obj["cmd"]
        if not isinstance(cmd, str):
            return error_reply(f"cmd: must be a string (one of {', '.join(COMMANDS)})")
        if cmd not in COMMANDS:
            shown = cmd if len(cmd) <= 40 else cmd[:40] + "..."
            return error_reply(f"cmd: unknown command {shown!r} (one of {', '.join(COMMANDS)})")
        if "v" in obj and obj["v"] != PROTOCOL_VERSION:
            return error_reply(
                f"v: unsupported protocol version {obj['v']!r} (this daemon speaks {PROTOCOL_VERSION})",
                cmd=cmd,
            )
        try:
            # Strict: no "1" for a number or "yes" for a boolean from a control client.
            return COMMANDS[cmd].model_validate_json(text, strict=True)
        except ValidationError as exc:
            return error_reply(f"{cmd}: {format_validation_error(exc)}", cmd=cmd)
    except Exception as exc:  # noqa: BLE001 - the control socket must never die on input
        return error_reply(f"could not parse request: {type(exc).__name__}: {exc}")


def dump_json(model: BaseModel) -> bytes:
    """Compact UTF-8 JSON of a model (None fields kept, as null)."""
    return model.model_dump_json().encode("utf-8")


def encode(topic: str, message: BaseModel) -> list[bytes]:
    """The two PUB frames ``[topic, json]`` of a published message."""
    if topic not in TOPICS:
        raise ValueError(f"unknown topic {topic!r} (one of {', '.join(TOPICS)})")
    if not isinstance(message, TOPICS[topic]):
        raise TypeError(f"topic {topic!r} carries {TOPICS[topic].__name__}, not {type(message).__name__}")
    return [topic.encode("ascii"), dump_json(message)]


def decode(frames: list[bytes]) -> tuple[str, BaseModel]:
    """``(topic, model)`` of two received PUB frames; raises ValueError on a bad message."""
    if len(frames) != 2:
        raise ValueError(f"expected 2 frames [topic, json], got {len(frames)}")
    topic = bytes(frames[0]).decode("ascii", errors="replace")
    model = TOPICS.get(topic)
    if model is None:
        raise ValueError(f"unknown topic {topic!r}")
    try:
        return topic, model.model_validate_json(bytes(frames[1]))
    except ValidationError as exc:
        raise ValueError(f"{topic}: {format_validation_error(exc)}") from None


def encode_reply(reply: BaseModel) -> bytes:
    """JSON bytes of a reply model (what the REP socket sends)."""
    return dump_json(reply)


def parse_reply(raw: bytes | str) -> Any:
    """A reply model from the REP socket's answer (for clients; raises ValueError)."""
    try:
        return REPLY_ADAPTER.validate_json(raw)
    except ValidationError as exc:
        raise ValueError(f"reply: {format_validation_error(exc)}") from None

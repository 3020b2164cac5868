"""The channel layer: every topic of a recording, its schema and its message encoding.

One table, :data:`TOPICS`, is the contract of the file format (docs/recording.md shows it):
the recorder, the replay's output and a live Foxglove view use the same topics with the same
schemas, so a recording and a live session open with the same layout.

Two kinds of channel:

- ``protobuf`` channels carry foxglove-sdk's own schemas (``foxglove.messages``; the schema
  is ``Message.get_schema()``, a protobuf FileDescriptorSet, and the bytes are
  ``message.encode()``), for what Foxglove draws;
- ``json`` channels carry a JSON object per message with a JSON Schema (``jsonschema``) made
  from a pydantic model: the raw odometry and head readings, the Localizer's inputs, the
  estimate with its covariance, the status, the truth.

Raw inputs (enough to run the Localizer again, stamps included)::

    /camera/image      foxglove.CompressedImage  PNG (lossless) of the left image, stamp = capture
    /camera/disparity  foxglove.RawImage         16UC1, disparity x DISPARITY_SCALE (0 = none),
                                                 or 32FC1 (NaN = none) when 16 bits would lose a value
    /odometry          lino_loc.OdometryIncrement  every increment as the board's driver gave it
    /head/state        lino_loc.HeadState          every present reading of the head
    /localizer/input   lino_loc.LocalizerInput     every call the loop made on the Localizer, in
                                                   order (``seq``): update (the composed action
                                                   u_t, the pan, image used or not), predict,
                                                   set_pose, start_global

Outputs::

    /pose              foxglove.PoseInFrame      the robot's pose in ``map``
    /pose/estimate     lino_loc.Pose             the pose message: covariance, state, quality, ESS
    /pose/ellipse      foxglove.SceneUpdate      the 95 % position ellipse (and heading wedge)
    /particles         foxglove.PosesInFrame     the particle set, throttled
    /tf                foxglove.FrameTransform   map -> base_link (the estimate), base_link ->
                                                 camera (the head's pan)
    /status            lino_loc.Status           the status message, 1 Hz
    /truth             lino_loc.Truth            simulation: the true pose (JSON)
    /truth/pose        foxglove.PoseInFrame      simulation: the true pose, drawable

The map (once, at the start of a recording; on subscription in a live view)::

    /map/survey        foxglove.SceneUpdate      the map's survey poses (entity ``survey``)
    /map/outline       foxglove.SceneUpdate      the building's outline (entity ``outline``): the
                                                 world's walls in simulation, else the survey's
                                                 extent

Frames (REP-103/105): ``map``, ``base_link`` (the robot), ``camera`` (the head, turned by the
pan about the vertical axis).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from lino_loc.errors import LinoLocError

#: The optional extra that holds mcap and foxglove-sdk.
EXTRA = "viz"
INSTALL_HINT = f"pip install 'lino-loc[{EXTRA}]'"

#: The MCAP profile and the name of the metadata record that holds the session's settings.
PROFILE = "lino-loc"
METADATA_NAME = "lino-loc"
#: Version of the file layout (the topics and their meaning); a reader refuses newer ones.
FORMAT_VERSION = 1

MAP_FRAME = "map"
BASE_FRAME = "base_link"
CAMERA_FRAME = "camera"


def require_viz(what: str) -> None:
    """Raise a one-line LinoLocError naming the extra when mcap or foxglove-sdk is missing."""
    missing = []
    for module in ("mcap", "foxglove", "mcap_protobuf"):
        try:
            __import__(module)
        except ImportError:
            missing.append(module)
    if missing:
        raise LinoLocError(
            f"{what} needs the {EXTRA!r} extra ({', '.join(missing)} not installed): {INSTALL_HINT}"
        )


# --------------------------------------------------------------------------------------------
# JSON records (the raw inputs the foxglove schemas do not cover)
# --------------------------------------------------------------------------------------------


class _Record(BaseModel):
    model_config = ConfigDict(extra="forbid")


class OdometryRecord(_Record):
    """One wheel-odometry increment (``drivers.interfaces.OdometryIncrement``)."""

    stamp: float = Field(description="host time of the second sample, s since the epoch")
    dt: float = Field(description="time between the samples by the board's clock, s (0: unknown)")
    dx: float = Field(description="m, base frame at the first sample")
    dy: float = Field(description="m")
    dtheta: float = Field(description="rad, counter-clockwise")
    sequence: int = 0


class HeadRecord(_Record):
    """One present reading of the head (``drivers.interfaces.HeadState``, stale ones left out)."""

    stamp: float = Field(description="host time of the read, s since the epoch")
    pan: float = Field(description="rad, counter-clockwise about the robot's vertical axis")
    tilt: float = Field(description="rad, up positive")
    moving: bool


class InputRecord(_Record):
    """One call of the loop on the Localizer, in order (``seq`` counts from 0 per session).

    ``update``: ``Localizer.update(delta, pan, image, disparity, stamp)`` with the frame of
    ``stamp`` on /camera/image (``image``: it was used, the head at rest; else prediction
    only) and /camera/disparity (``disparity``: it was passed). ``predict``:
    ``predict_only(delta, stamp)`` (dead reckoning). ``set_pose``: ``set_pose(mean, cov,
    confirmed)``. ``start_global``. ``cause``: why a belief changed (``start``, ``control``,
    ``failures``: the loop's reset after failed updates)."""

    seq: int
    kind: Literal["update", "predict", "set_pose", "start_global"]
    stamp: float
    delta: list[float] | None = Field(None, description="the composed action u_t (dx, dy, dtheta)")
    pan: float | None = None
    moving: bool | None = Field(None, description="the head moved around the frame's stamp")
    image: bool = False
    disparity: bool = False
    mean: list[float] | None = None
    cov: list[float] | None = Field(None, description="3 x 3, row-major")
    confirmed: bool | None = None
    cause: str | None = None


# --------------------------------------------------------------------------------------------
# the table
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Topic:
    """One channel: its topic, schema name, and where the schema comes from (a foxglove
    message class name for ``protobuf``, a pydantic model for ``json``)."""

    topic: str
    schema_name: str
    encoding: Literal["protobuf", "json"]
    source: str
    role: Literal["input", "output"]
    what: str

    @property
    def schema_encoding(self) -> str:
        return "protobuf" if self.encoding == "protobuf" else "jsonschema"


TOPICS: dict[str, Topic] = {t.topic: t for t in (
    Topic("/camera/image", "foxglove.CompressedImage", "protobuf", "CompressedImage", "input",
          "left image, PNG"),
    Topic("/camera/disparity", "foxglove.RawImage", "protobuf", "RawImage", "input",
          "disparity, 16UC1 x DISPARITY_SCALE (0 = none) or 32FC1"),
    Topic("/odometry", "lino_loc.OdometryIncrement", "json", "OdometryRecord", "input",
          "wheel-odometry increments"),
    Topic("/head/state", "lino_loc.HeadState", "json", "HeadRecord", "input",
          "the head's present angles"),
    Topic("/localizer/input", "lino_loc.LocalizerInput", "json", "InputRecord", "input",
          "the loop's calls on the Localizer"),
    Topic("/pose", "foxglove.PoseInFrame", "protobuf", "PoseInFrame", "output",
          "the robot's pose in map"),
    Topic("/pose/estimate", "lino_loc.Pose", "json", "PoseMessage", "output",
          "pose, covariance, state, quality"),
    Topic("/pose/ellipse", "foxglove.SceneUpdate", "protobuf", "SceneUpdate", "output",
          "95 % position ellipse"),
    Topic("/particles", "foxglove.PosesInFrame", "protobuf", "PosesInFrame", "output",
          "particles, throttled"),
    Topic("/tf", "foxglove.FrameTransform", "protobuf", "FrameTransform", "output",
          "map->base_link, base_link->camera"),
    Topic("/status", "lino_loc.Status", "json", "StatusMessage", "output", "status, 1 Hz"),
    Topic("/truth", "lino_loc.Truth", "json", "TruthMessage", "output",
          "simulation: the true pose"),
    Topic("/truth/pose", "foxglove.PoseInFrame", "protobuf", "PoseInFrame", "output",
          "simulation: the true pose"),
    Topic("/map/survey", "foxglove.SceneUpdate", "protobuf", "SceneUpdate", "output",
          "the map's survey poses, once"),
    Topic("/map/outline", "foxglove.SceneUpdate", "protobuf", "SceneUpdate", "output",
          "the building's outline, once"),
)}  # fmt: skip

#: The topics a recording must have to be replayed.
REPLAY_TOPICS = ("/camera/image", "/localizer/input")


def _json_model(name: str) -> type[BaseModel]:
    from services import messages

    local = {"OdometryRecord": OdometryRecord, "HeadRecord": HeadRecord, "InputRecord": InputRecord}
    return local[name] if name in local else getattr(messages, name)


@cache
def schema_bytes(topic: str) -> bytes:
    """The schema data of a topic: foxglove's FileDescriptorSet, or the model's JSON Schema."""
    t = TOPICS[topic]
    if t.encoding == "protobuf":
        import foxglove.messages as fm

        return bytes(getattr(fm, t.source).get_schema().data)
    return json.dumps(_json_model(t.source).model_json_schema(), sort_keys=True).encode()


def json_bytes(obj: dict[str, Any]) -> bytes:
    """A JSON message (floats as Python's shortest round-trip repr: exact float64)."""
    return json.dumps(obj, allow_nan=False, separators=(",", ":")).encode()


def stamp_ns(stamp: float) -> int:
    """Nanoseconds since the epoch of a stamp in seconds (an MCAP log time; the key that ties
    a /localizer/input record to its frame's images)."""
    return int(round(float(stamp) * 1e9))


def sdk_channel_args(topic: str) -> dict[str, Any]:
    """``foxglove.Channel(**sdk_channel_args(topic))``: the same topic, encoding and schema on
    a foxglove-sdk channel (a live view, ``foxglove.start_server``), so that a live session and
    a recording look alike to Foxglove; messages are then the bytes of
    :mod:`services.recording.topic_messages` (``channel.log(data, log_time=ns)``)."""
    import foxglove

    t = TOPICS[topic]
    schema = foxglove.Schema(name=t.schema_name, encoding=t.schema_encoding, data=schema_bytes(topic))
    return {"topic": topic, "message_encoding": t.encoding, "schema": schema}

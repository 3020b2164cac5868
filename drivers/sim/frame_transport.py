"""Stereo frames of the simulated camera on the wire (ZeroMQ multipart messages).

The simulated robot (:mod:`drivers.sim.robot`) publishes every rendered pair on a ZeroMQ PUB
socket; :class:`drivers.sim.camera.SimStereoCamera` subscribes to it. One frame is one
multipart message of four parts::

    [b"frame", header_json, left_bytes, right_bytes]

``header_json`` is a UTF-8 JSON object (:class:`FrameHeader`)::

    {"v": 1, "seq": int, "stamp": float, "width": int, "height": int,
     "fx": float, "fy": float, "cx": float, "cy": float, "baseline_m": float,
     "encoding": "mono8"}

``stamp`` is the time the image was taken (seconds since the Unix epoch), ``seq`` counts the
frames of one publisher from 0, ``fx .. cy`` are the pinhole intrinsics of the rectified left
image in pixels, and ``left``/``right`` are ``width * height`` bytes each, uint8 row-major
(``mono8``). Unknown header keys are ignored (forward compatibility); anything else that
does not match raises :class:`FrameError` in :func:`decode_frame`, so that a reader can
count and skip a malformed message instead of crashing.

Usage::

    from drivers.sim.frame_transport import encode_frame, decode_frame, FrameError
    parts = encode_frame(seq, stamp, left, right, intrinsics, baseline_m)
    frame = decode_frame(sock.recv_multipart())     # -> StereoFrame, or FrameError
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from drivers.interfaces import CameraIntrinsics, StereoFrame

#: First part of every frame message (also the SUB subscription prefix).
FRAME_TOPIC = b"frame"
#: Version of the header (the "v" field).
FRAME_VERSION = 1
#: The only pixel encoding: 8-bit grey, row-major.
ENCODING = "mono8"
#: Largest image side accepted by the decoder (guards against absurd allocations).
MAX_SIDE = 8192


class FrameError(ValueError):
    """A message that is not a valid frame (the reason in a few words)."""


class FrameHeader(BaseModel):
    """The JSON header of one frame (see the module docstring)."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    v: int = Field(FRAME_VERSION, description="header version")
    seq: int = Field(ge=0, description="frame counter of the publisher, from 0")
    stamp: float = Field(ge=0.0, description="capture time, s since the Unix epoch")
    width: int = Field(gt=0, le=MAX_SIDE)
    height: int = Field(gt=0, le=MAX_SIDE)
    fx: float = Field(gt=0.0)
    fy: float = Field(gt=0.0)
    cx: float
    cy: float
    baseline_m: float = Field(ge=0.0)
    encoding: str = ENCODING

    @field_validator("stamp", "fx", "fy", "cx", "cy", "baseline_m")
    @classmethod
    def _finite(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError(f"must be finite, got {v}")
        return v

    @field_validator("v")
    @classmethod
    def _version(cls, v: int) -> int:
        if v != FRAME_VERSION:
            raise ValueError(f"unsupported frame version {v} (this reader: {FRAME_VERSION})")
        return v

    @field_validator("encoding")
    @classmethod
    def _encoding(cls, v: str) -> str:
        if v != ENCODING:
            raise ValueError(f"unsupported encoding {v!r} (only {ENCODING!r})")
        return v

    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height)


def _as_mono8(img: NDArray[np.uint8], name: str) -> NDArray[np.uint8]:
    a = np.asarray(img)
    if a.ndim != 2 or a.dtype != np.uint8:
        raise ValueError(f"{name} must be a 2-D uint8 image, got {a.dtype} {a.shape}")
    return np.ascontiguousarray(a)


def encode_frame(
    seq: int,
    stamp: float,
    left: NDArray[np.uint8],
    right: NDArray[np.uint8],
    intrinsics: CameraIntrinsics,
    baseline_m: float,
) -> list[bytes]:
    """The four message parts of one stereo pair (raises ValueError on a programming mistake:
    wrong dtype, shapes that differ or do not match the intrinsics)."""
    lu = _as_mono8(left, "left")
    ru = _as_mono8(right, "right")
    h, w = lu.shape
    if ru.shape != lu.shape:
        raise ValueError(f"left {lu.shape} and right {ru.shape} differ in size")
    if (w, h) != (intrinsics.width, intrinsics.height):
        raise ValueError(
            f"image {w}x{h} does not match intrinsics {intrinsics.width}x{intrinsics.height}"
        )
    header = {
        "v": FRAME_VERSION,
        "seq": int(seq),
        "stamp": float(stamp),
        "width": int(w),
        "height": int(h),
        "fx": float(intrinsics.fx),
        "fy": float(intrinsics.fy),
        "cx": float(intrinsics.cx),
        "cy": float(intrinsics.cy),
        "baseline_m": float(baseline_m),
        "encoding": ENCODING,
    }
    return [FRAME_TOPIC, json.dumps(header).encode("utf-8"), lu.tobytes(), ru.tobytes()]


def decode_header(raw: bytes) -> FrameHeader:
    """The validated header of a frame (raises :class:`FrameError`)."""
    try:
        data = json.loads(bytes(raw).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FrameError(f"header is not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise FrameError("header is not a JSON object")
    try:
        return FrameHeader.model_validate(data)
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        where = ".".join(str(p) for p in err.get("loc", ())) or "header"
        raise FrameError(f"header {where}: {err.get('msg', 'invalid')}") from None


def decode_frame(parts: Sequence[bytes | memoryview]) -> StereoFrame:
    """A :class:`StereoFrame` (``disparity`` None) from the four parts of a frame message.

    Raises :class:`FrameError` on anything malformed: wrong number of parts, wrong topic, a
    header that is not valid, or image sizes that do not match the header."""
    if len(parts) != 4:
        raise FrameError(f"expected 4 parts [frame, header, left, right], got {len(parts)}")
    if bytes(parts[0]) != FRAME_TOPIC:
        raise FrameError(f"unexpected topic {bytes(parts[0])[:32]!r}")
    header = decode_header(parts[1])
    n = header.width * header.height
    images = []
    for name, buf in (("left", parts[2]), ("right", parts[3])):
        size = len(buf)
        if size != n:
            raise FrameError(
                f"{name} image has {size} bytes, header says {header.width}x{header.height}"
            )
        # a copy: the frame outlives the message buffer and must be writable by consumers
        images.append(
            np.frombuffer(buf, dtype=np.uint8).reshape(header.height, header.width).copy()
        )
    return StereoFrame(
        stamp=header.stamp,
        left=images[0],
        right=images[1],
        disparity=None,
        intrinsics=header.intrinsics(),
        baseline_m=header.baseline_m,
        sequence=header.seq,
    )

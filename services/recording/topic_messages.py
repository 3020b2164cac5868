"""The messages of one recorded event on their topics: ``(topic, log time ns, bytes)``.

The recorder's writer thread and the replay's output both call these, so that a recording and
a replay's output hold the same messages for the same event (:mod:`services.recording.channels`
says what each topic carries). Log times are the data's own stamps (a frame's capture time,
an increment's or a reading's host time, the pose's frame stamp); the status message's own
stamp for ``/status``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from services.recording import foxglove_messages as fx
from services.recording.channels import json_bytes, stamp_ns

Messages = list[tuple[str, int, bytes]]


def frame_messages(stamp: float, left: np.ndarray | None, disparity: np.ndarray | None) -> Messages:
    """/camera/image (PNG) and /camera/disparity of a frame."""
    t = stamp_ns(stamp)
    out: Messages = []
    if left is not None:
        out.append(("/camera/image", t, fx.compressed_image(left, stamp).encode()))
    if disparity is not None:
        out.append(("/camera/disparity", t, fx.raw_disparity(disparity, stamp).encode()))
    return out


def input_messages(record: Mapping[str, Any]) -> Messages:
    return [("/localizer/input", stamp_ns(record["stamp"]), json_bytes(dict(record)))]


def pose_messages(pose_json: bytes, pose: Mapping[str, Any]) -> Messages:
    """/pose, /pose/estimate, /pose/ellipse, /tf of one pose message (``pose``: its fields,
    ``pose_json``: its JSON as published)."""
    stamp = float(pose["stamp"])
    p = pose["pose"]
    xyt = (p["x"], p["y"], p["theta"])
    t = stamp_ns(stamp)
    out: Messages = [
        ("/pose", t, fx.pose_in_frame(xyt, stamp).encode()),
        ("/pose/estimate", t, pose_json),
        ("/pose/ellipse", t, fx.ellipse_update(xyt, pose["covariance"], stamp, pose["state"]).encode()),
    ]
    out += [("/tf", t, m.encode()) for m in fx.transforms(stamp, xyt, pose.get("pan"))]
    return out


def particles_messages(stamp: float, poses: np.ndarray) -> Messages:
    return [("/particles", stamp_ns(stamp), fx.poses_in_frame(poses, stamp).encode())]


def odometry_messages(records: Sequence[Mapping[str, Any]]) -> Messages:
    return [("/odometry", stamp_ns(r["stamp"]), json_bytes(dict(r))) for r in records]


def head_messages(record: Mapping[str, Any]) -> Messages:
    return [("/head/state", stamp_ns(record["stamp"]), json_bytes(dict(record)))]


def status_messages(status_json: bytes, stamp: float) -> Messages:
    return [("/status", stamp_ns(stamp), status_json)]


def truth_messages(truth_json: bytes) -> Messages:
    """/truth as received, and /truth/pose drawable (nothing for a message without a pose)."""
    try:
        msg = json.loads(truth_json)
        stamp = float(msg["stamp"])
        p = msg["pose"]
        xyt = (float(p["x"]), float(p["y"]), float(p["theta"]))
    except (ValueError, KeyError, TypeError):
        return []
    t = stamp_ns(stamp)
    return [("/truth", t, bytes(truth_json)), ("/truth/pose", t, fx.pose_in_frame(xyt, stamp).encode())]


def map_messages(survey_poses: np.ndarray, outline: np.ndarray, stamp: float,
                 outline_what: str = "walls") -> Messages:
    """/map/survey (the map's poses) and /map/outline ((M, 2, 2) segments) at ``stamp``."""
    t = stamp_ns(stamp)
    return [("/map/survey", t, fx.survey_update(survey_poses, stamp).encode()),
            ("/map/outline", t, fx.outline_update(outline, stamp, outline_what).encode())]

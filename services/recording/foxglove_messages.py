"""Foxglove messages (``foxglove.messages``, foxglove-sdk's protobuf schemas) of the filter's
outputs and the camera's frames: what a recording and a live view draw.

- :func:`pose_in_frame`: a planar pose ``(x, y, theta)`` as a PoseInFrame in ``frame_id``,
  z = 0, the heading as the quaternion ``(0, 0, sin(theta/2), cos(theta/2))`` (REP-103);
- :func:`ellipse_update`: the position covariance's ellipse of :data:`ELLIPSE_PROBABILITY`
  as a flat SpherePrimitive (a sphere scaled to the ellipse's axes) on a SceneUpdate entity
  ``pose_ellipse``: semi-axes ``sqrt(chi2_2(p) * lambda_i)`` along the eigenvectors of the
  2 x 2 position block (PoseInFrame has no covariance), with the heading as an arrow;
- :func:`poses_in_frame`: particles as a PosesInFrame;
- :func:`transforms`: ``map -> base_link`` (the estimate) and ``base_link -> camera`` (the
  head's pan about z) as FrameTransforms;
- :func:`compressed_image`, :func:`raw_disparity`: the frame's images
  (:mod:`services.recording.image_codec`).

Stamps are seconds since the epoch as float; :func:`timestamp` splits them into whole seconds
and nanoseconds.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from services.recording.channels import BASE_FRAME, CAMERA_FRAME, MAP_FRAME, stamp_ns
from services.recording.image_codec import encode_disparity, encode_png

#: Probability inside the drawn covariance ellipse; chi-square quantile of 2 degrees of
#: freedom: -2 ln(1 - p) (5.991 for 95 %).
ELLIPSE_PROBABILITY = 0.95
_CHI2 = -2.0 * math.log(1.0 - ELLIPSE_PROBABILITY)
#: Thickness of the drawn ellipse, m.
ELLIPSE_THICKNESS_M = 0.02


def _m() -> Any:
    import foxglove.messages as fm

    return fm


def timestamp(stamp: float) -> Any:
    """foxglove Timestamp of seconds since the epoch (nanoseconds rounded)."""
    ns = stamp_ns(stamp)
    return _m().Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _parts(x: float, y: float, theta: float) -> tuple[Any, Any]:
    """(Vector3 (x, y, 0), Quaternion of a turn by theta about z)."""
    m = _m()
    half = 0.5 * float(theta)
    return (m.Vector3(x=float(x), y=float(y), z=0.0),
            m.Quaternion(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)))


def _pose(x: float, y: float, theta: float) -> Any:
    position, orientation = _parts(x, y, theta)
    return _m().Pose(position=position, orientation=orientation)


def pose_in_frame(pose: ArrayLike, stamp: float, frame_id: str = MAP_FRAME) -> Any:
    x, y, theta = (float(v) for v in np.asarray(pose, dtype=np.float64)[:3])
    return _m().PoseInFrame(timestamp=timestamp(stamp), frame_id=frame_id, pose=_pose(x, y, theta))


def ellipse_axes(cov: ArrayLike) -> tuple[float, float, float]:
    """(semi-axis a, semi-axis b, angle of a) of the position block's ellipse (module
    docstring); a degenerate or non-finite covariance gives zero axes."""
    c = np.asarray(cov, dtype=np.float64).reshape(3, 3)[:2, :2]
    c = 0.5 * (c + c.T)
    if not np.all(np.isfinite(c)):
        return 0.0, 0.0, 0.0
    vals, vecs = np.linalg.eigh(c)
    vals = np.maximum(vals, 0.0)
    a, b = math.sqrt(_CHI2 * vals[1]), math.sqrt(_CHI2 * vals[0])
    return a, b, math.atan2(float(vecs[1, 1]), float(vecs[0, 1]))


def ellipse_update(pose: ArrayLike, cov: ArrayLike, stamp: float, state: str = "") -> Any:
    """SceneUpdate with the entity ``pose_ellipse`` (module docstring); colour by state:
    tracking green, global amber, lost red."""
    m = _m()
    x, y, theta = (float(v) for v in np.asarray(pose, dtype=np.float64)[:3])
    a, b, angle = ellipse_axes(cov)
    rgb = {"tracking": (0.1, 0.7, 0.2), "lost": (0.9, 0.1, 0.1)}.get(state, (1.0, 0.7, 0.0))
    color = m.Color(r=rgb[0], g=rgb[1], b=rgb[2], a=0.35)
    sphere = m.SpherePrimitive(pose=_pose(x, y, angle), color=color,
                               size=m.Vector3(x=2 * a, y=2 * b, z=ELLIPSE_THICKNESS_M))
    arrow = m.ArrowPrimitive(pose=_pose(x, y, theta), shaft_length=0.3, shaft_diameter=0.03,
                             head_length=0.1, head_diameter=0.08,
                             color=m.Color(r=rgb[0], g=rgb[1], b=rgb[2], a=1.0))
    entity = m.SceneEntity(timestamp=timestamp(stamp), frame_id=MAP_FRAME, id="pose_ellipse",
                           spheres=[sphere], arrows=[arrow],
                           metadata=[m.KeyValuePair(key="state", value=state)])
    return m.SceneUpdate(entities=[entity])


def poses_in_frame(poses: ArrayLike, stamp: float) -> Any:
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    return _m().PosesInFrame(timestamp=timestamp(stamp), frame_id=MAP_FRAME,
                             poses=[_pose(*row) for row in p.tolist()])


def transforms(stamp: float, pose: ArrayLike | None, pan: float | None) -> list[Any]:
    """``map -> base_link`` when ``pose`` is given, ``base_link -> camera`` when ``pan`` is."""
    m = _m()
    ts = timestamp(stamp)
    out = []
    for parent, child, p in ((MAP_FRAME, BASE_FRAME, pose),
                             (BASE_FRAME, CAMERA_FRAME, None if pan is None else (0.0, 0.0, pan))):
        if p is None:
            continue
        translation, rotation = _parts(*(float(v) for v in np.asarray(p, dtype=np.float64)[:3]))
        out.append(m.FrameTransform(timestamp=ts, parent_frame_id=parent, child_frame_id=child,
                                    translation=translation, rotation=rotation))
    return out


def compressed_image(left: np.ndarray, stamp: float) -> Any:
    return _m().CompressedImage(timestamp=timestamp(stamp), frame_id=CAMERA_FRAME,
                                data=encode_png(left), format="png")


def raw_disparity(disp: np.ndarray, stamp: float) -> Any:
    encoding, step, data = encode_disparity(disp)
    h, w = np.asarray(disp).shape
    return _m().RawImage(timestamp=timestamp(stamp), frame_id=CAMERA_FRAME, width=int(w),
                         height=int(h), encoding=encoding, step=step, data=data)

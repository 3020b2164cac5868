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
  (:mod:`services.recording.image_codec`);
- :func:`survey_update`: the map's survey poses as a SceneUpdate entity ``survey`` in ``map``:
  a small sphere per surveyed position and a tick of :data:`SURVEY_TICK_M` along each pose's
  heading (one LINE_LIST; every k-th pose beyond :data:`MAX_SURVEY_POSES`);
- :func:`outline_update`: line segments (the building's walls) as a SceneUpdate entity
  ``outline`` in ``map`` (one LINE_LIST).

The map's two entities have no lifetime (they stay until replaced): a viewer draws them from
one message.

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
#: Length of a survey pose's heading tick, m; diameter of a surveyed position's sphere, m.
SURVEY_TICK_M = 0.15
SURVEY_DOT_M = 0.06
#: Survey poses drawn at most (a map with virtual headings holds thousands; every k-th).
MAX_SURVEY_POSES = 1500
#: Width of the outline's lines, m.
OUTLINE_WIDTH_M = 0.03


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


def survey_update(poses: ArrayLike, stamp: float) -> Any:
    """SceneUpdate with the entity ``survey`` (module docstring) of (N, 3) poses; positions
    closer than 1 cm are drawn once."""
    m = _m()
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] > MAX_SURVEY_POSES:
        p = p[:: -(-p.shape[0] // MAX_SURVEY_POSES)]
    xy = np.unique(np.round(p[:, :2], 2), axis=0)
    dot = m.Vector3(x=SURVEY_DOT_M, y=SURVEY_DOT_M, z=SURVEY_DOT_M)
    blue = m.Color(r=0.2, g=0.45, b=1.0, a=0.8)
    spheres = [m.SpherePrimitive(pose=_pose(x, y, 0.0), size=dot, color=blue) for x, y in xy.tolist()]
    points = []
    for x, y, theta in p.tolist():
        points += [m.Point3(x=x, y=y, z=0.0),
                   m.Point3(x=x + SURVEY_TICK_M * math.cos(theta), y=y + SURVEY_TICK_M * math.sin(theta), z=0.0)]
    ticks = m.LinePrimitive(type=m.LinePrimitiveLineType.LineList, pose=_pose(0.0, 0.0, 0.0),
                            thickness=0.01, points=points, color=m.Color(r=0.2, g=0.45, b=1.0, a=0.5))
    entity = m.SceneEntity(timestamp=timestamp(stamp), frame_id=MAP_FRAME, id="survey",
                           spheres=spheres, lines=[ticks] if points else [])
    return m.SceneUpdate(entities=[entity])


def outline_update(segments: ArrayLike, stamp: float, what: str = "walls") -> Any:
    """SceneUpdate with the entity ``outline``: (M, 2, 2) segments ``[[x0, y0], [x1, y1]]``
    in ``map`` as one LINE_LIST; ``what`` goes into its metadata (``walls``, ``survey extent``)."""
    m = _m()
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2)
    points = [m.Point3(x=x, y=y, z=0.0) for x, y in seg.reshape(-1, 2).tolist()]
    line = m.LinePrimitive(type=m.LinePrimitiveLineType.LineList, pose=_pose(0.0, 0.0, 0.0),
                           thickness=OUTLINE_WIDTH_M, points=points,
                           color=m.Color(r=0.85, g=0.85, b=0.85, a=1.0))
    entity = m.SceneEntity(timestamp=timestamp(stamp), frame_id=MAP_FRAME, id="outline",
                           lines=[line] if points else [],
                           metadata=[m.KeyValuePair(key="what", value=what)])
    return m.SceneUpdate(entities=[entity])

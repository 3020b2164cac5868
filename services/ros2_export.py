"""A recording (or a replay's output) as a rosbag2 with ROS 2 message types, without ROS.

:func:`export_ros2` reads a recording's parts in order (:mod:`services.recording.recording_reader`)
and writes a rosbag2 folder (``metadata.yaml`` and one ``.mcap``, MCAP storage, CDR messages)
with ``rosbags``' writer and its ROS 2 Jazzy type store. Topics, as nav2's AMCL and a ROS 2
base driver publish them:

- ``/amcl_pose`` geometry_msgs/msg/PoseWithCovarianceStamped, frame ``map``, one per pose
  (``/pose/estimate``). The 6 x 6 covariance is row-major over (x, y, z, rot x, rot y, rot z)
  (the message definition; REP-103): the recording's 3 x 3 over (x, y, theta) goes to the
  rows/columns 0, 1 and 5 (:func:`covariance_6x6`), every cross term kept. z, roll and pitch
  are 0 with variance 0, as nav2's AMCL publishes them: the pose is planar by construction,
  those coordinates are not estimated but fixed.
- ``/particle_cloud`` geometry_msgs/msg/PoseArray, frame ``map`` (the throttled ``/particles``).
- ``/tf`` tf2_msgs/msg/TFMessage (REP-105): ``odom -> base_link`` at every odometry
  increment; at every pose ``map -> odom`` = (map -> base_link) (+) inverse(odom -> base_link)
  and ``odom -> base_link`` at the pose's stamp, and ``base_link -> camera`` (the head's pan)
  when the pose has one, in one message. The odom frame's pose of base_link is the composition
  of the recorded ``/odometry`` increments from the first one (the origin of ``odom``); at a
  stamp inside an increment the increment is split in proportion to time along its arc, by the
  daemon's own rule (:class:`services.device_threads.OdometryBuffer`), so the odom pose at a
  frame's stamp is the one whose increments made the filter's actions. A recording without
  odometry keeps base_link at the odom origin: map -> odom is then the pose itself.
- ``/odom`` nav_msgs/msg/Odometry, frame ``odom``, child ``base_link``, per increment: the
  integrated pose, and the twist (dx, dy, dtheta) / dt in base_link (dt the board's, else the
  time since the previous increment; 0 when unknown). Covariances 0: the recording has none.
- ``/camera/image_raw/compressed`` sensor_msgs/msg/CompressedImage, frame ``camera``: the
  recorded PNG bytes as they are (lossless, no decoding; the image_transport "compressed"
  topic of ``/camera/image_raw``, format ``mono8; png compressed mono8`` or ``rgb8; ...``).
- ``/truth`` geometry_msgs/msg/PoseStamped, frame ``map`` (simulation: the true pose).

Stamps: every header stamp and every bag time is the recorded message's own stamp (the MCAP
log time, nanoseconds since the epoch) split into ``sec`` and ``nanosec``.

Errors (one line, :class:`lino_loc.errors.LinoLocError`): a missing file, a file that is not
MCAP, a recording without ``/pose/estimate`` or without a pose, an existing output, rosbags not
installed (the ``ros2`` extra).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lino_loc.errors import LinoLocError
from lino_loc.poses import between, compose
from services.recording.channels import BASE_FRAME, CAMERA_FRAME, MAP_FRAME, stamp_ns
from services.recording.recording_reader import Message, Recording, protobuf_decoder, read_recording

#: The optional extra that holds rosbags.
EXTRA = "ros2"
INSTALL_HINT = f"pip install 'lino-loc[{EXTRA}]'"
ODOM_FRAME = "odom"
#: The ROS 2 distribution whose message definitions the bag carries.
ROS_DISTRO = "ROS2_JAZZY"

#: bag topic -> ROS 2 message type.
BAG_TOPICS: dict[str, str] = {
    "/amcl_pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "/particle_cloud": "geometry_msgs/msg/PoseArray",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/odom": "nav_msgs/msg/Odometry",
    "/camera/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
    "/truth": "geometry_msgs/msg/PoseStamped",
}
#: The recording's channel that a bag needs.
POSE_TOPIC = "/pose/estimate"
#: Index in the 6 x 6 covariance of each of (x, y, theta).
COV_INDEX = (0, 1, 5)


def require_rosbags(what: str) -> None:
    """Raise a one-line LinoLocError naming the extra when rosbags is missing."""
    try:
        import rosbags.rosbag2  # noqa: F401
    except ImportError:
        raise LinoLocError(f"{what} needs the {EXTRA!r} extra (rosbags not installed): "
                           f"{INSTALL_HINT}") from None


def covariance_6x6(cov3: Any) -> list[float]:
    """The 36 row-major entries over (x, y, z, rot x, rot y, rot z) of a 3 x 3 covariance over
    (x, y, theta): entry (i, j) goes to (COV_INDEX[i], COV_INDEX[j]); z, roll, pitch rows and
    columns are 0 (module docstring)."""
    c = np.asarray(cov3, dtype=np.float64).reshape(3, 3)
    out = np.zeros((6, 6))
    out[np.ix_(COV_INDEX, COV_INDEX)] = c
    return [float(v) for v in out.ravel()]


def inverse(p: Any) -> np.ndarray:
    """The inverse of a planar transform: q with p (+) q = identity."""
    return between(p, np.zeros(3))


def map_to_odom(map_base: Any, odom_base: Any) -> np.ndarray:
    """REP-105: map -> odom = (map -> base_link) (+) inverse(odom -> base_link)."""
    return compose(map_base, inverse(odom_base))


@dataclass
class ExportResult:
    """What an export wrote: messages per bag topic, the bag's bytes, the time it took."""

    bag: Path
    messages: dict[str, int] = field(default_factory=dict)
    bytes: int = 0
    span_s: float = 0.0
    wall_s: float = 0.0
    truth_tum: Path | None = None
    truncated: str | None = None


def odometry_poses(increments: list[dict[str, Any]], queries: list[float]) -> dict[int, np.ndarray]:
    """odom -> base_link at each of ``queries`` (s) and at each increment's stamp, keyed by
    nanoseconds: the increments composed from the origin, split at a query inside one
    (:class:`services.device_threads.OdometryBuffer`)."""
    from drivers.interfaces import OdometryIncrement
    from services.device_threads import OdometryBuffer

    buf = OdometryBuffer(max_spans=max(2000, len(increments) + 1))
    buf.add([OdometryIncrement(stamp=r["stamp"], dx=r["dx"], dy=r["dy"], dtheta=r["dtheta"],
                               dt=r.get("dt", 0.0), sequence=r.get("sequence", 0)) for r in increments])
    pose = np.zeros(3)
    out: dict[int, np.ndarray] = {}
    for t in sorted({float(r["stamp"]) for r in increments} | set(queries)):
        delta, _ = buf.take_until(t)
        pose = compose(pose, delta)
        out[stamp_ns(t)] = pose
    return out


def _first_pass(paths: list[Path]) -> tuple[Recording, list[dict[str, Any]], list[float]]:
    """The recording's odometry increments and pose stamps (the odom frame needs them all)."""
    rec = Recording(paths)
    odometry: list[dict[str, Any]] = []
    stamps: list[float] = []
    for m in read_recording(paths, rec):
        if m.topic == "/odometry":
            odometry.append(json.loads(m.data))
        elif m.topic == POSE_TOPIC:
            stamps.append(float(json.loads(m.data)["stamp"]))
    if POSE_TOPIC not in rec.topics:
        have = ", ".join(sorted(rec.topics)) or "none"
        raise LinoLocError(f"{paths[0]}: no {POSE_TOPIC} channel: not a lino-loc recording or "
                           f"replay (channels: {have})")
    if not stamps:
        raise LinoLocError(f"{paths[0]}: no pose on {POSE_TOPIC}: nothing to export")
    return rec, odometry, stamps


def export_ros2(paths: list[Path] | list[str], bag: Path | str) -> ExportResult:
    """Write the bag ``bag`` (a folder that must not exist) from the recording ``paths`` (its
    parts, in order), as the module docstring says; a truth TUM beside it
    (:func:`truth_tum_path`) when the recording has ``/truth``."""
    require_rosbags("lino-loc export ros2")
    files = [Path(p) for p in paths]
    bag = Path(bag)
    if bag.exists():
        raise LinoLocError(f"--out {bag}: exists (a rosbag2 is a new folder): remove it or choose another")
    started = time.perf_counter()
    rec, odometry, stamps = _first_pass(files)
    odom = odometry_poses(odometry, stamps)
    writer = _BagWriter(bag, rec, odom)
    try:
        for m in read_recording(files, Recording(files)):
            writer.on_message(m)
    finally:
        writer.close()
    result = writer.result
    result.wall_s = time.perf_counter() - started
    result.truncated = rec.truncated
    result.bytes = sum(f.stat().st_size for f in bag.rglob("*") if f.is_file())
    if writer.truth:
        result.truth_tum = truth_tum_path(bag)
        from services.replay import write_tum

        write_tum(result.truth_tum, writer.truth)
    return result


def truth_tum_path(bag: Path) -> Path:
    """``BAG-truth.tum`` beside the bag folder."""
    return bag.with_name(bag.name + "-truth.tum")


class _BagWriter:
    """The rosbags writer and the messages of one recorded message (see :func:`export_ros2`)."""

    def __init__(self, bag: Path, rec: Recording, odom: dict[int, np.ndarray]) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        self.ts = get_typestore(getattr(Stores, ROS_DISTRO))
        self.t = self.ts.types
        self.odom = odom
        self.rec = rec
        try:
            bag.parent.mkdir(parents=True, exist_ok=True)
            self.writer = Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP)
            self.writer.open()
        except Exception as exc:  # noqa: BLE001 - rosbags' WriterError, OSError: one line
            raise LinoLocError(f"--out {bag}: cannot write the bag ({exc})") from None
        self.conns = {topic: self.writer.add_connection(topic, msgtype, typestore=self.ts)
                      for topic, msgtype in BAG_TOPICS.items()}
        self.result = ExportResult(bag=bag, messages=dict.fromkeys(BAG_TOPICS, 0))
        self.truth: list[tuple[float, float, float, float]] = []
        self.last_odom: tuple[float, np.ndarray] | None = None
        self._decoders: dict[str, Any] = {}
        self._first: int | None = None

    def close(self) -> None:
        self.writer.close()

    def _write(self, topic: str, ns: int, msg: Any) -> None:
        self.writer.write(self.conns[topic], ns, self.ts.serialize_cdr(msg, BAG_TOPICS[topic]))
        self.result.messages[topic] += 1
        self._first = ns if self._first is None else min(self._first, ns)
        self.result.span_s = max(self.result.span_s, (ns - self._first) / 1e9)

    def _decode(self, m: Message) -> Any:
        if m.schema_name not in self._decoders:
            self._decoders[m.schema_name] = protobuf_decoder(self.rec, m.schema_name)
        return self._decoders[m.schema_name](m.data)

    # ------------------------------------------------------------------ message parts
    def header(self, ns: int, frame: str) -> Any:
        stamp = self.t["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return self.t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def pose(self, p: Any) -> Any:
        x, y, th = (float(v) for v in p)
        g = self.t
        return g["geometry_msgs/msg/Pose"](
            position=g["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
            orientation=g["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2)))

    def transform(self, ns: int, parent: str, child: str, p: Any) -> Any:
        x, y, th = (float(v) for v in p)
        g = self.t
        tf = g["geometry_msgs/msg/Transform"](
            translation=g["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
            rotation=g["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2)))
        return g["geometry_msgs/msg/TransformStamped"](header=self.header(ns, parent), child_frame_id=child,
                                                        transform=tf)

    # ------------------------------------------------------------------ recorded messages
    def on_message(self, m: Message) -> None:
        if m.topic == POSE_TOPIC:
            self.on_pose(json.loads(m.data), m.log_ns)
        elif m.topic == "/odometry":
            self.on_odometry(json.loads(m.data), m.log_ns)
        elif m.topic == "/particles":
            msg = self._decode(m)
            poses = [self.pose((p.position.x, p.position.y, 2 * math.atan2(p.orientation.z, p.orientation.w)))
                     for p in msg.poses]
            self._write("/particle_cloud", m.log_ns, self.t["geometry_msgs/msg/PoseArray"](
                header=self.header(m.log_ns, MAP_FRAME), poses=poses))
        elif m.topic == "/camera/image":
            self.on_image(self._decode(m), m.log_ns)
        elif m.topic == "/truth":
            self.on_truth(json.loads(m.data), m.log_ns)

    def on_pose(self, p: dict[str, Any], ns: int) -> None:
        g = self.t
        xyt = np.array([p["pose"]["x"], p["pose"]["y"], p["pose"]["theta"]], dtype=np.float64)
        pwc = g["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(xyt),
                                                        covariance=np.array(covariance_6x6(p["covariance"])))
        self._write("/amcl_pose", ns, g["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=self.header(ns, MAP_FRAME), pose=pwc))
        odom_base = self.odom.get(stamp_ns(p["stamp"]), np.zeros(3))
        tfs = [self.transform(ns, MAP_FRAME, ODOM_FRAME, map_to_odom(xyt, odom_base)),
               self.transform(ns, ODOM_FRAME, BASE_FRAME, odom_base)]
        if p.get("pan") is not None:
            tfs.append(self.transform(ns, BASE_FRAME, CAMERA_FRAME, (0.0, 0.0, p["pan"])))
        self._write("/tf", ns, g["tf2_msgs/msg/TFMessage"](transforms=tfs))

    def on_odometry(self, r: dict[str, Any], ns: int) -> None:
        g = self.t
        pose = self.odom.get(stamp_ns(r["stamp"]))
        if pose is None:
            return
        dt = float(r.get("dt") or 0.0)
        if dt <= 0 and self.last_odom is not None:
            dt = float(r["stamp"]) - self.last_odom[0]
        self.last_odom = (float(r["stamp"]), pose)
        v = [r["dx"] / dt, r["dy"] / dt, r["dtheta"] / dt] if dt > 0 else [0.0, 0.0, 0.0]
        vec = g["geometry_msgs/msg/Vector3"]
        twist = g["geometry_msgs/msg/Twist"](linear=vec(x=v[0], y=v[1], z=0.0), angular=vec(x=0.0, y=0.0, z=v[2]))
        zeros = np.zeros(36)
        msg = g["nav_msgs/msg/Odometry"](
            header=self.header(ns, ODOM_FRAME), child_frame_id=BASE_FRAME,
            pose=g["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(pose), covariance=zeros),
            twist=g["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=zeros))
        self._write("/odom", ns, msg)
        self._write("/tf", ns, g["tf2_msgs/msg/TFMessage"](
            transforms=[self.transform(ns, ODOM_FRAME, BASE_FRAME, pose)]))

    def on_image(self, img: Any, ns: int) -> None:
        data = bytes(img.data)
        fmt = str(img.format)
        if fmt == "png":  # image_transport's form: ORIGINAL; png compressed DECODED
            enc = _png_encoding(data)
            fmt = f"{enc}; png compressed {enc}" if enc else "png"
        self._write("/camera/image_raw/compressed", ns, self.t["sensor_msgs/msg/CompressedImage"](
            header=self.header(ns, img.frame_id or CAMERA_FRAME), format=fmt,
            data=np.frombuffer(data, dtype=np.uint8)))

    def on_truth(self, t: dict[str, Any], ns: int) -> None:
        try:
            xyt = (float(t["pose"]["x"]), float(t["pose"]["y"]), float(t["pose"]["theta"]))
        except (KeyError, TypeError, ValueError):
            return
        self.truth.append((float(t.get("stamp", ns / 1e9)), *xyt))
        self._write("/truth", ns, self.t["geometry_msgs/msg/PoseStamped"](
            header=self.header(ns, MAP_FRAME), pose=self.pose(xyt)))


def _png_encoding(data: bytes) -> str | None:
    """ROS image encoding of an 8-bit PNG from its IHDR (bit depth, colour type), else None."""
    if len(data) < 26 or data[:8] != b"\x89PNG\r\n\x1a\n" or data[24] != 8:
        return None
    return {0: "mono8", 2: "rgb8", 6: "rgba8"}.get(data[25])


def iter_bag(bag: Path, topics: list[str] | None = None) -> Iterator[tuple[str, int, Any]]:
    """(topic, bag time ns, deserialized message) of a bag, in time order (rosbags' AnyReader)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([Path(bag)], default_typestore=get_typestore(getattr(Stores, ROS_DISTRO))) as reader:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        for conn, t, raw in reader.messages(connections=conns):
            yield conn.topic, t, reader.deserialize(raw, conn.msgtype)

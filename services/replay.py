"""Replay: the Localizer run again on a recording's inputs, as fast as it can.

The recording's ``/localizer/input`` holds every call the service's loop made on the
Localizer, in order: each frame's ``update`` with the action u_t it composed, the pan it
interpolated and whether the head was at rest (the image used), dead reckoning's
``predict_only``, and every belief change (the start, the control socket). :func:`replay`
makes the same calls in the same order, with the frame's own image (``/camera/image``, PNG,
lossless) and disparity (``/camera/disparity``, lossless), on a Localizer built from the
recorded configuration (or ``--config``) with the recorded seed (or ``--seed``). The filter
draws its random numbers only in these calls (active vision and the publisher use none of
the filter's), so with the service's configuration and seed the poses are the service's bit
for bit, and two replays with one seed are identical. A reset after failed updates is not
taken from the file: the replay applies the loop's own rule
(:data:`services.daemon.RESET_AFTER_FAILED_UPDATES`), so another configuration fails, and
resets, on its own.

``recompose``: the action and the pan are not taken from ``/localizer/input`` but composed
again from the raw ``/odometry`` and ``/head/state`` streams with the daemon's own buffers
(:class:`services.device_threads.OdometryBuffer`, ``HeadHistory``) and the configured
head-settle rule, in the order the recorder received them. What differs from the service:
the order of an odometry increment and a frame as the threads interleaved them (an increment
that reached the buffer after the loop took the frame goes into the next action in the
service; the recorder receives it from the odometry thread, with the same race: a split
increment's two parts round differently from the whole) and a changed
``active_vision.settle_s``. docs/recording.md says what was measured.

Output: ``out`` (MCAP, the channel layer of :mod:`services.recording.channels`: the inputs
copied, the replay's poses, ellipses, particles and transforms) and the TUM trajectory
``out`` with the suffix ``.tum`` (``timestamp x y z qx qy qz qw``, one line per pose, for evo).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lino_loc.errors import LinoLocError
from services.recording import topic_messages as tm
from services.recording.channels import REPLAY_TOPICS, TOPICS, stamp_ns
from services.recording.image_codec import decode_disparity, decode_png
from services.recording.recording_reader import Message, Recording, protobuf_decoder, read_recording

log = logging.getLogger("lino_loc.replay")

#: Frames kept waiting for their /localizer/input record (the recorder writes a frame's
#: images just before it).
IMAGE_CACHE = 64
#: Sections of the recorded configuration a replay leaves at their defaults: the sockets (and
#: CURVE key files of the robot), the saved pose, the log level.
REPLAY_IGNORES = ("endpoints", "persistence", "logging")
#: Topics a replay's output copies from the recording unchanged.
COPIED = ("/camera/image", "/camera/disparity", "/odometry", "/head/state", "/localizer/input",
          "/truth", "/truth/pose")


@dataclass
class ReplayResult:
    """What a replay did. ``poses``: (stamp, x, y, theta) per pose, in order."""

    poses: list[tuple[float, float, float, float]] = field(default_factory=list)
    updates: int = 0
    predicts: int = 0
    belief_changes: int = 0
    errors: int = 0
    missing_frames: int = 0
    missing_inputs: int = 0
    service: dict[str, int | float | bool | None] | None = None
    span_s: float = 0.0
    wall_s: float = 0.0
    truncated: str | None = None
    seed: int | None = None

    @property
    def speed(self) -> float:
        """Recording time per replay time (x real time)."""
        return self.span_s / self.wall_s if self.wall_s > 0 else math.inf


def tum_line(stamp: float, x: float, y: float, theta: float) -> str:
    """One TUM line: ``timestamp x y z qx qy qz qw`` (z = 0, rotation about z)."""
    h = 0.5 * theta
    return f"{stamp:.9f} {x!r} {y!r} 0.0 0.0 0.0 {math.sin(h)!r} {math.cos(h)!r}"


def replay_config(rec_meta: dict[str, Any], config: Any | None, seed: int | None, path: Path) -> Any:
    """The ServiceConfig to replay with: ``config`` or the recorded one, ``seed`` over it."""
    from services.config import ServiceConfig

    if config is None:
        if "config" not in rec_meta:
            raise LinoLocError(f"{path}: no recorded configuration: give --config")
        recorded = rec_meta["config"]
        data = dict(json.loads(recorded) if isinstance(recorded, str) else recorded)
        for section in REPLAY_IGNORES:  # the robot's sockets and key files are not the replay's
            data.pop(section, None)
        try:
            config = ServiceConfig.model_validate(data)
        except ValueError as exc:
            first = str(exc).splitlines()[1:3]
            raise LinoLocError(f"{path}: the recorded configuration does not validate here "
                               f"({' '.join(x.strip() for x in first)}): give --config") from None
    if seed is None:
        seed = config.localizer.filter.seed
    if seed is None:
        seed = 0
        log.warning("no seed recorded or given: replaying with seed 0 (the service's poses differ)")
    filt = config.localizer.filter.model_copy(update={"seed": int(seed)})
    return config.model_copy(update={"localizer": config.localizer.model_copy(update={"filter": filt})})


def load_map(cfg: Any, expected_checksum: str | None) -> Any:
    """The configuration's map (built once in simulation, as ``lino-loc run`` does)."""
    from services.sim_launcher import ensure_sim_map
    from services.status import map_info

    if cfg.simulated:
        amap, _ = ensure_sim_map(cfg)
    else:
        from lino_loc.appearance_map import AppearanceMap

        amap = AppearanceMap.load(cfg.map.path)
    got = map_info(amap, cfg.map.path).checksum
    if expected_checksum not in (None, "None") and got != expected_checksum:
        log.warning("the map %s is not the recording's (checksum %s, recorded %s): poses differ",
                    cfg.map.path, got, expected_checksum)
    return amap


class _Session:
    """The replay's Localizer and what it keeps between messages (see :func:`replay`)."""

    def __init__(self, rec: Recording, cfg: Any, amap: Any, out: Any, recompose: bool) -> None:
        from lino_loc.active_vision import HeadSettle
        from lino_loc.localizer import Localizer
        from services.device_threads import HeadHistory, OdometryBuffer

        self.rec, self.cfg, self.out, self.recompose = rec, cfg, out, recompose
        self.localizer = Localizer(amap, cfg.localizer)
        self.has_disparity = "disparity" in getattr(amap, "channels", {})
        self.images: OrderedDict[int, Message] = OrderedDict()
        self.disparities: OrderedDict[int, Message] = OrderedDict()
        self.odometry, self.heads = OdometryBuffer(), HeadHistory()
        self.settle = HeadSettle(cfg.active_vision.settle_s)
        self.result = ReplayResult(seed=cfg.localizer.filter.seed)
        self.service: dict[int, tuple[float, float, float]] = {}
        self.mine: dict[int, tuple[float, float, float]] = {}
        self.failed_in_a_row = 0
        self.next_seq = 0
        self.next_particles: float | None = None
        self._image_decoder = protobuf_decoder(rec, TOPICS["/camera/image"].schema_name)
        self._disp_decoder = (protobuf_decoder(rec, TOPICS["/camera/disparity"].schema_name)
                              if TOPICS["/camera/disparity"].schema_name in rec.schemas else None)

    # ------------------------------------------------------------------ messages
    def on_message(self, m: Message) -> None:
        if self.out is not None and m.topic in COPIED:
            self.out.write(m.topic, m.log_ns, m.publish_ns, m.data, m.sequence)
        if m.topic == "/camera/image":
            _keep(self.images, m)
        elif m.topic == "/camera/disparity":
            _keep(self.disparities, m)
        elif m.topic == "/localizer/input":
            self.on_input(json.loads(m.data))
        elif m.topic == "/pose/estimate":
            p = json.loads(m.data)
            self.service[stamp_ns(p["stamp"])] = (p["pose"]["x"], p["pose"]["y"], p["pose"]["theta"])
        elif self.recompose and m.topic == "/odometry":
            self._add_odometry(json.loads(m.data))
        elif self.recompose and m.topic == "/head/state":
            from drivers.interfaces import HeadState

            h = json.loads(m.data)
            self.heads.add(HeadState(stamp=h["stamp"], pan=h["pan"], tilt=h["tilt"], moving=h["moving"]))

    def _add_odometry(self, r: dict[str, Any]) -> None:
        from drivers.interfaces import OdometryIncrement

        self.odometry.add([OdometryIncrement(stamp=r["stamp"], dx=r["dx"], dy=r["dy"],
                                             dtheta=r["dtheta"], dt=r["dt"], sequence=r["sequence"])])

    def on_input(self, r: dict[str, Any]) -> None:
        seq = int(r["seq"])
        if seq != self.next_seq:
            self.result.missing_inputs += max(0, seq - self.next_seq)
        self.next_seq = seq + 1
        kind = r["kind"]
        if kind == "update":
            self._update(r)
        elif kind == "predict":
            delta = self.odometry.take_until(r["stamp"])[0] if self.recompose else np.asarray(r["delta"])
            self._survive(lambda: self.localizer.predict_only(delta, stamp=r["stamp"]), r["stamp"], None, True)
            self.result.predicts += 1
        elif r.get("cause") != "failures":
            self.result.belief_changes += 1
            if kind == "set_pose":
                self.localizer.set_pose(np.asarray(r["mean"]), np.asarray(r["cov"]).reshape(3, 3),
                                        confirmed=bool(r["confirmed"]))
            else:
                self.localizer.start_global()

    def _inputs(self, r: dict[str, Any]) -> tuple[np.ndarray, float, bool]:
        """(action, pan, at rest) of an update: recorded, or composed again (``recompose``)."""
        stamp = float(r["stamp"])
        if not self.recompose:
            return np.asarray(r["delta"], dtype=np.float64), float(r["pan"]), bool(r["image"])
        delta, _ = self.odometry.take_until(stamp)
        pan, moving = self.heads.pan_at(stamp)
        return delta, pan, self.settle.at_rest(stamp, moving, self.heads.last_motion)

    def _update(self, r: dict[str, Any]) -> None:
        stamp = float(r["stamp"])
        key = stamp_ns(stamp)
        delta, pan, at_rest = self._inputs(r)
        img_msg, disp_msg = self.images.pop(key, None), self.disparities.pop(key, None)
        image = disparity = None
        if at_rest and img_msg is None:
            self.result.missing_frames += 1
        elif at_rest:
            assert img_msg is not None
            image = decode_png(self._image_decoder(img_msg.data).data)
            if disp_msg is not None and self.has_disparity and self._disp_decoder is not None:
                d = self._disp_decoder(disp_msg.data)
                disparity = decode_disparity(d.encoding, d.width, d.height, d.data)
        self._survive(lambda: self.localizer.update(delta, pan, image, disparity, stamp=stamp), stamp, pan)
        self.result.updates += 1

    def _survive(self, call: Any, stamp: float, pan: float | None, dead_reckoning: bool = False) -> None:
        """One call, its pose kept and written; failures as the daemon's loop counts them."""
        from services.daemon import RESET_AFTER_FAILED_UPDATES
        from services.messages import PoseMessage

        try:
            est = call()
            msg = PoseMessage.from_estimate(est, stamp=stamp, seq=len(self.result.poses), pan=pan,
                                            dead_reckoning=dead_reckoning, now=stamp)
        except Exception as exc:  # noqa: BLE001 - as the daemon: count, go on, reset after several
            self.result.errors += 1
            self.failed_in_a_row += 1
            log.debug("replay: a call failed at %.3f: %s", stamp, exc)
            if self.failed_in_a_row % RESET_AFTER_FAILED_UPDATES == 0:
                self.localizer.start_global()
            return
        self.failed_in_a_row = 0
        x, y, th = msg.pose.x, msg.pose.y, msg.pose.theta  # theta wrapped, as published
        self.result.poses.append((stamp, x, y, th))
        self.mine[stamp_ns(stamp)] = (x, y, th)
        self._write_pose(msg, stamp)

    def _write_pose(self, msg: Any, stamp: float) -> None:
        if self.out is None:
            return
        for topic, t, data in tm.pose_messages(msg.model_dump_json().encode(), msg.model_dump()):
            self.out.write(topic, t, t, data)
        rate = self.cfg.recording.particles_rate_hz
        if rate > 0 and (self.next_particles is None or stamp >= self.next_particles):
            from services.recording.recorder import subsample

            self.next_particles = stamp + 1.0 / rate
            poses = subsample(self.localizer.particles()[0], self.cfg.recording.particles_max_count)
            for topic, t, data in tm.particles_messages(stamp, poses):
                self.out.write(topic, t, t, data)

    def compare(self) -> dict[str, int | float | bool | None] | None:
        """Position differences to the service's poses at the same stamps (None: none recorded)."""
        common = sorted(set(self.service) & set(self.mine))
        if not self.service:
            return None
        d = np.array([math.hypot(self.mine[k][0] - self.service[k][0], self.mine[k][1] - self.service[k][1])
                      for k in common])
        same = sum(self.mine[k] == tuple(self.service[k]) for k in common)
        return {"matched": len(common), "service_poses": len(self.service), "identical": same,
                "bit_identical": same == len(common) == len(self.service),
                "median_m": float(np.median(d)) if d.size else None,
                "max_m": float(d.max()) if d.size else None}


def _keep(cache: OrderedDict[int, Message], m: Message) -> None:
    cache[m.log_ns] = m
    while len(cache) > IMAGE_CACHE:
        cache.popitem(last=False)


def _check_topics(rec: Recording, path: Path) -> None:
    missing = [t for t in REPLAY_TOPICS if t not in rec.topics]
    if missing:
        have = ", ".join(sorted(rec.topics)) or "none"
        raise LinoLocError(f"{path}: no {' or '.join(missing)} channel: not a lino-loc recording "
                           f"(channels: {have})")


def _open_session(rec: Recording, paths: list[Path], opts: dict[str, Any]) -> tuple[_Session, Any]:
    from services.recording.session_file import SessionFile

    _check_topics(rec, paths[0])
    cfg = replay_config(rec.metadata, opts["config"], opts["seed"], paths[0])
    amap = load_map(cfg, rec.metadata.get("map_checksum"))
    writer = None
    if opts["out"] is not None:
        meta = {**{k: v for k, v in rec.metadata.items() if k not in ("part", "format_version")},
                "config": cfg.model_dump_json(), "seed": str(cfg.localizer.filter.seed),
                "replay_of": json.dumps([str(p) for p in paths]),
                "recompose": str(bool(opts["recompose"])).lower()}
        writer = SessionFile(Path(opts["out"]), meta, 0.0)
    return _Session(rec, cfg, amap, writer, bool(opts["recompose"])), writer


def replay(paths: list[Path] | list[str], *, config: Any | None = None, seed: int | None = None,
           out: Path | None = None, recompose: bool = False) -> ReplayResult:
    """Replay the recording ``paths`` (its parts, in order) as the module docstring says;
    ``out``: write the MCAP there and the TUM file next to it. Raises LinoLocError (one line)
    for a missing file, a file that is not MCAP, a recording without the camera or the
    Localizer's input channel."""
    files = [Path(p) for p in paths]
    rec = Recording(files)
    session: _Session | None = None
    writer = None
    first = last = None
    started = time.perf_counter()
    try:
        for m in read_recording(files, rec):
            if session is None:
                session, writer = _open_session(rec, files, {"config": config, "seed": seed, "out": out,
                                                             "recompose": recompose})
                started = time.perf_counter()
            if m.topic == "/localizer/input":
                first = m.log_ns if first is None else first
                last = m.log_ns
            session.on_message(m)
        if session is None:
            _check_topics(rec, files[0])
            raise LinoLocError(f"{files[0]}: no messages")
    finally:
        if writer is not None:
            writer.close()
    result = session.result
    result.wall_s = time.perf_counter() - started
    result.span_s = (last - first) / 1e9 if first is not None and last is not None else 0.0
    result.truncated = rec.truncated
    result.service = session.compare()
    if out is not None:
        write_tum(Path(out).with_suffix(".tum"), result.poses)
    return result


def write_tum(path: Path, poses: list[tuple[float, float, float, float]]) -> None:
    """The TUM trajectory (:func:`tum_line` per pose)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(tum_line(*p) + "\n" for p in poses))

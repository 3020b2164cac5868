"""Luxonis OAK-D stereo camera through ``depthai`` v3: rectified pair + subpixel disparity.

Implements :class:`drivers.interfaces.StereoCamera`. The device pipeline is two ``Camera``
nodes on CAM_B / CAM_C (the mono pair) feeding a ``StereoDepth`` node (rectification,
left-right check, subpixel, confidence threshold, disparity aligned to the rectified left
image); its ``rectifiedLeft``, ``rectifiedRight`` and ``disparity`` outputs go to host output
queues. A supervisor thread owns the pipeline: it starts it, assembles frames, and when the
device disappears (queue closed, pipeline stopped, any depthai error) stops it in ``finally``
and starts a new one, without ending the process; meanwhile the health says DEGRADED (FAILED
if it never started). The waits before restarts double from ``reconnect_backoff_min`` up to
``reconnect_backoff_max`` and fall back to the minimum once a pipeline has started
(:class:`drivers.backoff.Backoff`).

The host-side parts are separate and testable without a device:
- :func:`stereo_config` maps :class:`OakdConfig` to a ``dai.StereoDepthConfig``;
- :func:`gray_from_imgframe`, :func:`disparity_from_imgframe`, :func:`host_stamp` and
  :class:`FrameAssembler` turn ``ImgFrame`` messages into :class:`StereoFrame` (disparity in
  pixels = raw / 2^fractional bits, raw 0 = no value -> NaN);
- :func:`host_pipeline_factory` builds a host-only ``Pipeline(False)`` whose
  ``ThreadedHostNode`` sends host-built ``ImgFrame``s into the same kind of output queues, so
  the same supervisor and conversion run on the simulated robot and in tests.

Timestamps: depthai stamps frames on its host clock ``dai.Clock`` (steady clock = Python's
``time.monotonic``); :func:`host_stamp` maps that to seconds since the epoch.

Usage::

    cam = OakdCamera(OakdConfig()); cam.open()
    frame = cam.read(timeout=0.5); cam.close()
"""

from __future__ import annotations

import collections
import datetime
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.backoff import Backoff
from drivers.interfaces import (
    CameraIntrinsics,
    DeviceHealth,
    HealthState,
    HealthTracker,
    StereoFrame,
)

os.environ.setdefault("DEPTHAI_LEVEL", "error")  # silence "USB protocol not available"
import depthai as dai  # noqa: E402

from drivers.oakd_config import OakdConfig  # noqa: E402

log = logging.getLogger("lino_loc.drivers.oakd")

# --------------------------------------------------------------------------------------------
# host-side mapping and conversion
# --------------------------------------------------------------------------------------------

_MEDIAN = {
    "off": "MEDIAN_OFF",
    "3x3": "KERNEL_3x3",
    "5x5": "KERNEL_5x5",
    "7x7": "KERNEL_7x7",
}


def fractional_bits(config: OakdConfig) -> int:
    """Fractional bits of the raw disparity (0 without subpixel)."""
    return config.subpixel_fractional_bits if config.subpixel else 0


def stereo_config(config: OakdConfig) -> dai.StereoDepthConfig:
    """The on-device stereo settings as a host-built ``StereoDepthConfig``."""
    c = dai.StereoDepthConfig()
    c.setConfidenceThreshold(config.confidence_threshold)
    c.setLeftRightCheck(config.left_right_check)
    c.setLeftRightCheckThreshold(config.left_right_check_threshold)
    c.setSubpixel(config.subpixel)
    if config.subpixel:
        c.setSubpixelFractionalBits(config.subpixel_fractional_bits)
    c.setExtendedDisparity(config.extended_disparity)
    c.setMedianFilter(getattr(dai.MedianFilter, _MEDIAN[config.median_filter]))
    c.setDepthAlign(dai.StereoDepthConfig.AlgorithmControl.DepthAlign.RECTIFIED_LEFT)
    return c


def host_stamp(msg: Any) -> float:
    """Seconds since the epoch of a message stamped on ``dai.Clock`` (= time.monotonic)."""
    return msg.getTimestamp().total_seconds() + (time.time() - time.monotonic())


def gray_from_imgframe(msg: Any) -> NDArray[np.uint8]:
    """(H, W) uint8 grey image of an ``ImgFrame`` (GRAY8/RAW8 as is; YUV: the Y plane)."""
    t = msg.getType()
    h, w = msg.getHeight(), msg.getWidth()
    if t in (dai.ImgFrame.Type.GRAY8, dai.ImgFrame.Type.RAW8, dai.ImgFrame.Type.YUV400p):
        arr = np.asarray(msg.getData(), dtype=np.uint8)[: h * w].reshape(h, w)
    elif t in (dai.ImgFrame.Type.NV12, dai.ImgFrame.Type.NV21, dai.ImgFrame.Type.YUV420p):
        arr = np.asarray(msg.getData(), dtype=np.uint8)[: h * w].reshape(h, w)
    else:
        import cv2

        bgr = msg.getCvFrame()
        arr = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if bgr.ndim == 3 else bgr
    return np.ascontiguousarray(arr, dtype=np.uint8)


def disparity_to_pixels(raw: NDArray[Any], frac_bits: int) -> NDArray[np.float32]:
    """Raw disparity -> float32 pixels: raw / 2^frac_bits; 0 (no value) -> NaN."""
    out = raw.astype(np.float32) * np.float32(1.0 / (1 << frac_bits))
    out[raw == 0] = np.nan
    return out


def disparity_from_imgframe(msg: Any, frac_bits: int) -> NDArray[np.float32]:
    """Disparity ``ImgFrame`` (RAW16 subpixel or RAW8 integer) -> float32 pixels, NaN = none."""
    h, w = msg.getHeight(), msg.getWidth()
    data = np.asarray(msg.getData(), dtype=np.uint8)
    if msg.getType() == dai.ImgFrame.Type.RAW8:
        raw: NDArray[Any] = data[: h * w].reshape(h, w)
        frac_bits = 0
    else:
        raw = data[: 2 * h * w].view(np.uint16).reshape(h, w)
    return disparity_to_pixels(raw, frac_bits)


def make_imgframe(array: NDArray[Any], kind: str, sequence: int, stamp_monotonic: float) -> Any:
    """A host-built ``ImgFrame``: ``kind`` 'gray' (uint8) or 'disparity' (uint16 raw)."""
    f = dai.ImgFrame()
    h, w = array.shape
    if kind == "gray":
        f.setType(dai.ImgFrame.Type.GRAY8)
        data = np.ascontiguousarray(array, dtype=np.uint8)
    else:
        f.setType(dai.ImgFrame.Type.RAW16)
        data = np.ascontiguousarray(array, dtype=np.uint16)
    f.setWidth(w)  # host-built frames need their size set explicitly
    f.setHeight(h)
    f.setStride(w * data.itemsize)
    f.setData(data.view(np.uint8).ravel())
    f.setSequenceNum(sequence)
    f.setTimestamp(datetime.timedelta(seconds=stamp_monotonic))
    return f


class FrameAssembler:
    """Pairs left / right / disparity messages by sequence number into :class:`StereoFrame`s."""

    def __init__(
        self,
        streams: tuple[str, ...],
        intrinsics: CameraIntrinsics,
        baseline_m: float,
        frac_bits: int,
        keep: int = 8,
    ) -> None:
        self.streams = streams
        self.intrinsics = intrinsics
        self.baseline_m = baseline_m
        self.frac_bits = frac_bits
        self.keep = keep
        self._partial: dict[int, dict[str, Any]] = {}
        self.incomplete = 0  # sequences given up on

    def add(self, stream: str, msg: Any) -> StereoFrame | None:
        seq = int(msg.getSequenceNum())
        parts = self._partial.setdefault(seq, {})
        parts[stream] = msg
        if len(parts) == len(self.streams):
            del self._partial[seq]
            for old in [s for s in self._partial if s < seq]:  # older ones will never complete
                del self._partial[old]
                self.incomplete += 1
            return self._convert(seq, parts)
        while len(self._partial) > self.keep:
            del self._partial[min(self._partial)]
            self.incomplete += 1
        return None

    def missing(self, seq: int) -> list[str]:
        parts = self._partial.get(seq, {})
        return [s for s in self.streams if s not in parts]

    def _convert(self, seq: int, parts: dict[str, Any]) -> StereoFrame:
        left = gray_from_imgframe(parts["left"])
        right = gray_from_imgframe(parts["right"]) if "right" in parts else None
        disp = (
            disparity_from_imgframe(parts["disparity"], self.frac_bits)
            if "disparity" in parts
            else None
        )
        return StereoFrame(
            stamp=host_stamp(parts["left"]),
            left=left,
            right=right,
            disparity=disp,
            intrinsics=self.intrinsics,
            baseline_m=self.baseline_m,
            sequence=seq,
        )


def default_intrinsics(config: OakdConfig) -> CameraIntrinsics:
    """Pinhole intrinsics from the horizontal field of view (no calibration available)."""
    fx = config.width / (2.0 * math.tan(math.radians(config.hfov_deg) / 2.0))
    return CameraIntrinsics(fx, fx, config.width / 2.0, config.height / 2.0,
                            config.width, config.height)  # fmt: skip


# --------------------------------------------------------------------------------------------
# pipelines
# --------------------------------------------------------------------------------------------


@dataclass
class PipelineSession:
    """A started pipeline and its output queues (``queues`` keyed by stream name; 'left'
    first). ``device`` is closed after the pipeline is stopped, if given."""

    pipeline: Any
    queues: dict[str, Any]
    intrinsics: CameraIntrinsics
    baseline_m: float
    frac_bits: int
    device: Any = None
    keepalive: list[Any] = field(default_factory=list)

    def stop(self) -> None:
        # Host nodes first: Pipeline.stop() joins their threads while holding the GIL, so a
        # Python run() loop still going would never see isRunning() turn False (deadlock).
        for node in self.keepalive:
            halt = getattr(node, "halt", None)
            if halt is not None:
                halt()
        try:
            self.pipeline.stop()
        finally:
            if self.device is not None:
                try:
                    self.device.close()
                except RuntimeError:
                    pass


PipelineFactory = Callable[[OakdConfig], PipelineSession]


def device_pipeline_factory(config: OakdConfig) -> PipelineSession:
    """Build and start the device pipeline (raises if no device is reachable)."""
    device = dai.Device(dai.DeviceInfo(config.device)) if config.device else dai.Device()
    pipeline = dai.Pipeline(device)
    started = False
    try:
        size = (config.width, config.height)
        cam_l = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
        cam_r = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
        out_l = cam_l.requestOutput(size, fps=config.fps)
        out_r = cam_r.requestOutput(size, fps=config.fps)
        stereo = pipeline.create(dai.node.StereoDepth).build(
            out_l, out_r, getattr(dai.node.StereoDepth.PresetMode, config.preset)
        )
        stereo.setRectification(True)
        stereo.setLeftRightCheck(config.left_right_check)
        stereo.setSubpixel(config.subpixel)
        if config.subpixel:
            stereo.setSubpixelFractionalBits(config.subpixel_fractional_bits)
        stereo.setExtendedDisparity(config.extended_disparity)
        stereo.setDepthAlign(dai.StereoDepthConfig.AlgorithmControl.DepthAlign.RECTIFIED_LEFT)
        ic = stereo.initialConfig
        ic.setConfidenceThreshold(config.confidence_threshold)
        ic.setLeftRightCheckThreshold(config.left_right_check_threshold)
        ic.setMedianFilter(getattr(dai.MedianFilter, _MEDIAN[config.median_filter]))
        queues = {"left": stereo.rectifiedLeft.createOutputQueue(config.queue_size, False)}
        if config.output_right:
            queues["right"] = stereo.rectifiedRight.createOutputQueue(config.queue_size, False)
        if config.output_disparity:
            queues["disparity"] = stereo.disparity.createOutputQueue(config.queue_size, False)
        intrinsics, baseline = default_intrinsics(config), config.baseline_m
        try:
            calib = device.readCalibration()
            # depthai rectifies both images onto the right camera's intrinsic matrix
            m = calib.getCameraIntrinsics(dai.CameraBoardSocket.CAM_C, config.width, config.height)
            intrinsics = CameraIntrinsics(m[0][0], m[1][1], m[0][2], m[1][2],
                                          config.width, config.height)  # fmt: skip
            baseline = (
                calib.getBaselineDistance(
                    dai.CameraBoardSocket.CAM_C, dai.CameraBoardSocket.CAM_B, False
                )
                / 100.0
            )
        except RuntimeError as exc:
            log.warning("oakd: no calibration (%s); using configured intrinsics/baseline", exc)
        pipeline.start()
        started = True
        return PipelineSession(pipeline, queues, intrinsics, abs(baseline),
                               fractional_bits(config), device)  # fmt: skip
    finally:
        if not started:
            try:
                pipeline.stop()
            finally:
                device.close()


StereoSource = Callable[[], "tuple[NDArray[np.uint8], NDArray[np.uint8] | None, NDArray[np.float32] | None] | None"]  # fmt: skip


class HostStereoSource(dai.node.ThreadedHostNode):
    """Host node that sends (left, right, disparity) from a Python callable as ``ImgFrame``s.

    ``source()`` returns grey uint8 images and a disparity in pixels (NaN = none), or None to
    end the stream (the node then stops the pipeline, like an unplugged device). Disparity is
    sent as RAW16 with ``frac_bits`` fractional bits, as the device does.
    """

    def __init__(self) -> None:
        super().__init__()
        self.left = self.createOutput()
        self.right = self.createOutput()
        self.disparity = self.createOutput()
        self.source: StereoSource | None = None
        self.fps = 30.0
        self.frac_bits = 3
        self.sequence = 0
        self._halt = threading.Event()
        self._done = threading.Event()

    def halt(self, timeout: float = 2.0) -> None:
        """Make run() return (call before Pipeline.stop(), from another thread)."""
        self._halt.set()
        self._done.wait(timeout)

    def run(self) -> None:
        try:
            self._loop()
        finally:
            self._done.set()

    def _loop(self) -> None:
        period = 1.0 / self.fps
        next_t = time.monotonic()
        while self.isRunning() and not self._halt.is_set():
            now = time.monotonic()
            if now < next_t:
                self._halt.wait(next_t - now)
                continue
            next_t += period
            assert self.source is not None
            item = self.source()
            if item is None:
                self.stopPipeline()
                return
            left, right, disp = item
            stamp = time.monotonic()
            seq = self.sequence
            self.sequence += 1
            self.left.send(make_imgframe(left, "gray", seq, stamp))
            if right is not None:
                self.right.send(make_imgframe(right, "gray", seq, stamp))
            if disp is not None:
                raw = np.nan_to_num(disp, nan=0.0) * (1 << self.frac_bits)
                raw = np.clip(np.rint(raw), 0, 65535).astype(np.uint16)
                self.disparity.send(make_imgframe(raw, "disparity", seq, stamp))


def host_pipeline_factory(
    source_factory: Callable[[], StereoSource],
    intrinsics: CameraIntrinsics | None = None,
) -> PipelineFactory:
    """A factory of host-only pipelines (``Pipeline(False)``) fed by ``source_factory()``.

    Each (re)start calls ``source_factory`` for a fresh source. Used by the simulated robot and
    by the tests; the supervisor and the conversions are the same as on the device.
    """

    def factory(config: OakdConfig) -> PipelineSession:
        pipeline = dai.Pipeline(False)
        started = False
        try:
            node = pipeline.create(HostStereoSource)
            node.source = source_factory()
            node.fps = config.fps
            node.frac_bits = fractional_bits(config) or 0
            queues = {"left": node.left.createOutputQueue(config.queue_size, False)}
            if config.output_right:
                queues["right"] = node.right.createOutputQueue(config.queue_size, False)
            if config.output_disparity:
                queues["disparity"] = node.disparity.createOutputQueue(config.queue_size, False)
            pipeline.start()
            started = True
            return PipelineSession(
                pipeline,
                queues,
                intrinsics or default_intrinsics(config),
                config.baseline_m,
                node.frac_bits,
                keepalive=[node],
            )
        finally:
            if not started:
                pipeline.stop()

    return factory


# --------------------------------------------------------------------------------------------
# the adapter
# --------------------------------------------------------------------------------------------


class OakdCamera:
    """:class:`~drivers.interfaces.StereoCamera` on an OAK-D, with a reconnecting supervisor."""

    def __init__(
        self, config: OakdConfig | None = None, pipeline_factory: PipelineFactory | None = None
    ) -> None:
        self.config = config or OakdConfig()
        self._factory = pipeline_factory or device_pipeline_factory
        self._health = HealthTracker(
            ("frames", "frames_dropped", "incomplete", "reconnects", "start_failures")
        )
        self._frames: collections.deque[StereoFrame] = collections.deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ever_started = False
        self._last_frame = time.monotonic()

    def open(self) -> None:
        """Start the supervisor thread (it keeps (re)starting the pipeline). Never raises."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._last_frame = time.monotonic()
        self._thread = threading.Thread(target=self._supervise, name="oakd", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None

    def __enter__(self) -> OakdCamera:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def health(self) -> DeviceHealth:
        if (
            self._health.state is HealthState.OK
            and time.monotonic() - self._last_frame > self.config.stale_after
        ):
            self._health.error(f"oakd: no frame for more than {self.config.stale_after} s")
        return self._health.snapshot()

    def read(self, timeout: float | None = None) -> StereoFrame | None:
        """The oldest buffered frame (at most ``buffer`` are kept), or None after ``timeout``."""
        with self._cond:
            if not self._frames and timeout:
                self._cond.wait_for(lambda: bool(self._frames), timeout)
            return self._frames.popleft() if self._frames else None

    # ---------------------------------------------------------------------------------------
    def _supervise(self) -> None:
        """Run pipeline sessions until ``close``, waiting the backoff after each one.

        A session that started resets the backoff, so the wait after losing a running device
        is ``reconnect_backoff_min``; each start failure in a row doubles it (capped)."""
        c = self.config
        backoff = Backoff(c.reconnect_backoff_min, c.reconnect_backoff_max)
        while not self._stop.is_set():
            if not self._session(backoff) or backoff.wait(self._stop):
                break

    def _session(self, backoff: Backoff) -> bool:
        """Start one pipeline and stream from it until it stops; False if ``close`` ended it."""
        session: PipelineSession | None = None
        try:
            session = self._factory(self.config)
            if self._ever_started:
                self._health.count("reconnects")
            self._ever_started = True
            self._health.set_state(HealthState.OK)
            log.info("oakd: pipeline running")
            backoff.reset()
            self._stream(session)
            if not self._stop.is_set():
                self._health.error("oakd: device lost (pipeline stopped); restarting")
                log.warning("oakd: pipeline stopped; restarting")
        except Exception as exc:  # noqa: BLE001 - depthai raises RuntimeError and others
            if self._stop.is_set():
                return False
            state = HealthState.DEGRADED if self._ever_started else HealthState.FAILED
            if session is None:
                self._health.count("start_failures")
                what = "cannot start"
            else:
                what = "device lost"
            self._health.error(f"oakd: {what} ({type(exc).__name__}: {exc})", state)
            log.warning("oakd: %s: %s (retry in %.1f s)", what, exc, backoff.delay)
        finally:
            if session is not None:
                try:
                    session.stop()
                except Exception as exc:  # noqa: BLE001
                    log.debug("oakd: stop failed: %s", exc)
        return True

    def _stream(self, s: PipelineSession) -> None:
        """Assemble frames until the pipeline stops or ``close``."""
        names = tuple(s.queues)
        asm = FrameAssembler(names, s.intrinsics, s.baseline_m, s.frac_bits)
        primary = s.queues["left"]
        others = [(n, q) for n, q in s.queues.items() if n != "left"]
        poll = datetime.timedelta(seconds=0.2)
        wait = datetime.timedelta(seconds=2.0 / self.config.fps)
        while not self._stop.is_set():
            msg = primary.get(poll)
            if msg is None:
                if not s.pipeline.isRunning():
                    return
                continue
            seq = int(msg.getSequenceNum())
            frame = asm.add("left", msg)
            for name, q in others:
                while frame is None and name in asm.missing(seq):
                    m = q.get(wait)
                    if m is None:
                        break
                    frame = asm.add(name, m) or frame
            self._health.count("incomplete", asm.incomplete)
            asm.incomplete = 0
            if frame is not None:
                self._publish(frame)

    def _publish(self, frame: StereoFrame) -> None:
        self._health.count("frames")
        self._last_frame = time.monotonic()
        with self._cond:
            self._frames.append(frame)
            while len(self._frames) > self.config.buffer:
                self._frames.popleft()
                self._health.count("frames_dropped")
            self._cond.notify_all()
        if self._health.state is not HealthState.OK:
            self._health.set_state(HealthState.OK)

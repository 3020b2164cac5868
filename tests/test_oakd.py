"""OAK-D adapter: host-side parts (configuration mapping, ImgFrame conversion, frame
assembly) and the supervisor on host-only depthai pipelines; one hardware test."""

from __future__ import annotations

import os

os.environ.setdefault("DEPTHAI_SEARCH_TIMEOUT", "300")  # ms; before depthai is imported
os.environ.setdefault("DEPTHAI_LEVEL", "error")

import math  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

import depthai as dai  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from drivers.interfaces import CameraIntrinsics, HealthState, StereoCamera  # noqa: E402
from drivers.oakd import (  # noqa: E402
    FrameAssembler,
    OakdCamera,
    OakdConfig,
    PipelineSession,
    default_intrinsics,
    disparity_from_imgframe,
    disparity_to_pixels,
    gray_from_imgframe,
    host_pipeline_factory,
    host_stamp,
    make_imgframe,
    stereo_config,
)

H, W = 40, 64
INTR = CameraIntrinsics(50.0, 50.0, 32.0, 20.0, W, H)


def test_stereo_config_mapping() -> None:
    cfg = OakdConfig(confidence_threshold=180, left_right_check=True,
                     left_right_check_threshold=7, subpixel=True,
                     subpixel_fractional_bits=4, median_filter="off")  # fmt: skip
    c = stereo_config(cfg)
    assert c.getConfidenceThreshold() == 180
    assert c.getLeftRightCheck() is True
    assert c.getLeftRightCheckThreshold() == 7
    assert c.getSubpixel() is True
    assert c.getSubpixelFractionalBits() == 4
    assert c.getMedianFilter() == dai.MedianFilter.MEDIAN_OFF
    assert c.getMaxDisparity() == 95 * 2**4
    assert c.algorithmControl.depthAlign == (
        dai.StereoDepthConfig.AlgorithmControl.DepthAlign.RECTIFIED_LEFT
    )
    c2 = stereo_config(OakdConfig(subpixel=False, left_right_check=False, median_filter="5x5"))
    assert c2.getSubpixel() is False and c2.getLeftRightCheck() is False
    assert c2.getMedianFilter() == dai.MedianFilter.KERNEL_5x5
    assert c2.getMaxDisparity() == 95


def test_default_intrinsics_from_fov() -> None:
    k = default_intrinsics(OakdConfig(width=640, height=400, hfov_deg=90.0))
    assert k.fx == pytest.approx(320.0) and (k.cx, k.cy) == (320.0, 200.0)


@pytest.mark.parametrize("bits", [3, 4, 5])
def test_disparity_conversion(bits: int) -> None:
    raw = np.array([[0, 1, 8 << bits], [(95 << bits) - 1, 3 << bits, 0]], dtype=np.uint16)
    d = disparity_to_pixels(raw, bits)
    assert d.dtype == np.float32
    assert np.isnan(d[0, 0]) and np.isnan(d[1, 2])
    assert d[0, 1] == 1.0 / 2**bits and d[0, 2] == 8.0 and d[1, 1] == 3.0
    assert d[1, 0] == pytest.approx(95 - 1 / 2**bits)
    f = make_imgframe(raw, "disparity", 7, time.monotonic())
    assert (f.getWidth(), f.getHeight(), f.getSequenceNum()) == (3, 2, 7)
    np.testing.assert_array_equal(disparity_from_imgframe(f, bits), d)


def test_gray_and_stamp_conversion() -> None:
    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, (H, W), dtype=np.uint8)
    t = time.monotonic()
    f = make_imgframe(img, "gray", 3, t)
    np.testing.assert_array_equal(gray_from_imgframe(f), img)
    assert host_stamp(f) == pytest.approx(time.time() - (time.monotonic() - t), abs=2e-3)


def test_frame_assembler_pairs_by_sequence() -> None:
    rng = np.random.default_rng(2)
    t = time.monotonic()
    asm = FrameAssembler(("left", "right", "disparity"), INTR, 0.075, 3)
    msgs = {}
    for seq in range(3):
        msgs[seq] = {
            "left": make_imgframe(rng.integers(0, 256, (H, W), dtype=np.uint8), "gray", seq, t),
            "right": make_imgframe(rng.integers(0, 256, (H, W), dtype=np.uint8), "gray", seq, t),
            "disparity": make_imgframe(np.full((H, W), 8 * seq, np.uint16), "disparity", seq, t),
        }
    assert asm.add("left", msgs[0]["left"]) is None
    assert asm.add("left", msgs[1]["left"]) is None
    assert asm.add("disparity", msgs[1]["disparity"]) is None
    assert asm.missing(1) == ["right"]
    frame = asm.add("right", msgs[1]["right"])
    assert frame is not None and frame.sequence == 1
    assert asm.incomplete == 1  # seq 0 can no longer complete
    assert np.all(frame.disparity == 1.0)
    np.testing.assert_array_equal(frame.right, gray_from_imgframe(msgs[1]["right"]))
    assert frame.intrinsics == INTR and frame.baseline_m == 0.075


class Scene:
    """A synthetic source: random texture, disparity 12.375 px left half, none right half."""

    def __init__(self, frames_per_session: int | None = None) -> None:
        self.rng = np.random.default_rng(9)
        self.frames_per_session = frames_per_session
        self.sessions = 0
        self.lock = threading.Lock()

    def factory(self):  # noqa: ANN201 - returns a StereoSource
        with self.lock:
            self.sessions += 1
        count = [0]

        def source():  # noqa: ANN202
            if self.frames_per_session is not None and count[0] >= self.frames_per_session:
                return None  # "unplugged"
            count[0] += 1
            left = self.rng.integers(0, 256, (H, W), dtype=np.uint8)
            right = np.roll(left, -12, axis=1)
            disp = np.full((H, W), np.nan, np.float32)
            disp[:, : W // 2] = 12.375
            return left, right, disp

        return source


def fast_config(**kw: object) -> OakdConfig:
    base: dict[str, object] = dict(width=W, height=H, fps=100.0, reconnect_backoff_min=0.05,
                                   reconnect_backoff_max=0.1, buffer=4)  # fmt: skip
    base.update(kw)
    return OakdConfig(**base)  # type: ignore[arg-type]


def test_host_pipeline_frames_through_the_adapter() -> None:
    scene = Scene()
    cam = OakdCamera(fast_config(), host_pipeline_factory(scene.factory, INTR))
    assert isinstance(cam, StereoCamera)
    cam.open()
    try:
        frames = []
        deadline = time.monotonic() + 5
        while len(frames) < 5 and time.monotonic() < deadline:
            f = cam.read(timeout=0.5)
            if f is not None:
                frames.append(f)
        assert len(frames) == 5
        for f in frames:
            assert f.left.shape == (H, W) and f.left.dtype == np.uint8
            assert f.right is not None and np.array_equal(f.right, np.roll(f.left, -12, axis=1))
            assert f.disparity is not None and f.disparity.dtype == np.float32
            assert np.all(f.disparity[:, : W // 2] == 12.375)  # exact with 3 fractional bits
            assert np.all(np.isnan(f.disparity[:, W // 2 :]))
            assert f.intrinsics == INTR and f.baseline_m == 0.075
            assert abs(f.stamp - time.time()) < 2.0
        seqs = [f.sequence for f in frames]
        assert seqs == sorted(seqs)
        assert [f.stamp for f in frames] == sorted(f.stamp for f in frames)
        assert cam.health().state is HealthState.OK
        assert cam.health().counters["frames"] >= 5
    finally:
        cam.close()


def test_reconnects_after_the_device_goes_away() -> None:
    scene = Scene(frames_per_session=5)
    cam = OakdCamera(fast_config(), host_pipeline_factory(scene.factory, INTR))
    cam.open()
    try:
        got = 0
        deadline = time.monotonic() + 10
        while scene.sessions < 3 and time.monotonic() < deadline:
            if cam.read(timeout=0.2) is not None:
                got += 1
        assert scene.sessions >= 3
        h = cam.health()
        assert h.counters["reconnects"] >= 2
        # host-only pipelines end like an unplugged device: the output queues close
        assert "device lost" in (h.last_error or "")
        assert got >= 8
    finally:
        cam.close()
    assert not cam._thread  # closed cleanly


def test_start_failures_are_retried_without_raising() -> None:
    scene = Scene()
    inner = host_pipeline_factory(scene.factory, INTR)
    calls = [0]

    def flaky(config: OakdConfig) -> PipelineSession:
        calls[0] += 1
        if calls[0] <= 2:
            raise RuntimeError("No available devices")
        return inner(config)

    cam = OakdCamera(fast_config(), flaky)
    cam.open()
    try:
        time.sleep(0.02)
        assert cam.health().state is HealthState.FAILED
        assert cam.read(timeout=3.0) is not None
        h = cam.health()
        assert h.state is HealthState.OK and h.counters["start_failures"] == 2
        assert "No available devices" in (h.last_error or "")
    finally:
        cam.close()


def _devices() -> list:
    return list(dai.Device.getAllAvailableDevices())


def test_real_factory_without_device_reports_failed() -> None:
    if _devices():
        pytest.skip("a device is attached")
    cam = OakdCamera(fast_config(reconnect_backoff_min=5.0))
    cam.open()
    try:
        deadline = time.monotonic() + 8
        while cam.health().counters["start_failures"] == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        h = cam.health()
        assert h.state is HealthState.FAILED and h.counters["start_failures"] >= 1
        assert cam.read(timeout=0.05) is None
    finally:
        t0 = time.monotonic()
        cam.close()
        assert time.monotonic() - t0 < 5


@pytest.mark.hardware
def test_real_oakd_pipeline() -> None:
    if not _devices():
        pytest.skip("no OAK device attached")
    cfg = OakdConfig()
    cam = OakdCamera(cfg)
    cam.open()
    try:
        frame = None
        deadline = time.monotonic() + 20
        while frame is None and time.monotonic() < deadline:
            frame = cam.read(timeout=1.0)
        assert frame is not None, cam.health()
        assert frame.left.shape == (cfg.height, cfg.width) and frame.left.dtype == np.uint8
        assert frame.disparity is not None and frame.disparity.shape == frame.left.shape
        valid = frame.disparity[np.isfinite(frame.disparity)]
        assert valid.size == 0 or (
            valid.min() > 0 and valid.max() <= 95 * (2 if cfg.extended_disparity else 1)
        )
        assert 0.03 < frame.baseline_m < 0.2
        assert math.isfinite(frame.intrinsics.fx) and frame.intrinsics.fx > 100
        assert abs(frame.stamp - time.time()) < 1.0
    finally:
        cam.close()

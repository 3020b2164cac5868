"""The simulated camera's wire format and its client adapter, against a real ZeroMQ PUB socket."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import zmq

import drivers.sim.camera as sim_camera
from drivers.interfaces import CameraIntrinsics, HealthState, StereoCamera
from drivers.sim.camera import SimStereoCamera
from drivers.sim.frame_transport import FRAME_TOPIC, FrameError, decode_frame, encode_frame
from lino_loc.disparity import StereoConfig

INTR = CameraIntrinsics(fx=100.0, fy=100.0, cx=79.5, cy=59.5, width=160, height=120)


def _pair(seed: int, shift: int = 0, w: int = 160, h: int = 120) -> tuple[np.ndarray, np.ndarray]:
    """A random texture (left) and the same texture seen ``shift`` pixels further left (right):
    right[:, x] = left[:, x + shift], so the disparity x_left - x_right is ``shift``."""
    rng = np.random.default_rng(seed)
    big = rng.integers(0, 256, size=(h, w + shift), dtype=np.uint8)
    return big[:, :w].copy(), big[:, shift : shift + w].copy()


def _parts(seq: int, seed: int = 0, shift: int = 0) -> list[bytes]:
    left, right = _pair(seed, shift)
    return encode_frame(seq, 1.7e9 + seq, left, right, INTR, 0.075)


# -- wire format ----------------------------------------------------------------------------------


def test_encode_decode_round_trip() -> None:
    left, right = _pair(1, 3)
    parts = encode_frame(7, 1.7e9 + 0.25, left, right, INTR, 0.075)
    assert parts[0] == FRAME_TOPIC and len(parts) == 4
    header = json.loads(parts[1])
    assert header == {"v": 1, "seq": 7, "stamp": 1.7e9 + 0.25, "width": 160, "height": 120, "fx": 100.0,
                      "fy": 100.0, "cx": 79.5, "cy": 59.5, "baseline_m": 0.075, "encoding": "mono8"}  # fmt: skip
    f = decode_frame(parts)
    assert f.sequence == 7 and f.stamp == 1.7e9 + 0.25 and f.baseline_m == 0.075
    assert f.intrinsics == INTR and f.disparity is None
    np.testing.assert_array_equal(f.left, left)
    np.testing.assert_array_equal(f.right, right)
    f.left[0, 0] = 1  # writable, owned by the frame


def test_decode_ignores_unknown_header_keys() -> None:
    parts = _parts(3)
    header = json.loads(parts[1])
    header["future_field"] = [1, 2]
    parts[1] = json.dumps(header).encode()
    assert decode_frame(parts).sequence == 3


@pytest.mark.parametrize(
    "mutate, reason",
    [
        (lambda p: p[:3], "expected 4 parts"),
        (lambda p: [b"frome", *p[1:]], "unexpected topic"),
        (lambda p: [p[0], b"{not json", *p[2:]], "not JSON"),
        (lambda p: [p[0], b"[1, 2]", *p[2:]], "not a JSON object"),
        (lambda p: [p[0], p[1].replace(b'"v": 1', b'"v": 2'), *p[2:]], "version"),
        (lambda p: [p[0], p[1].replace(b'"mono8"', b'"rgb8"'), *p[2:]], "encoding"),
        (lambda p: [p[0], p[1].replace(b'"seq": 5', b'"seq": -1'), *p[2:]], "seq"),
        (lambda p: [p[0], p[1].replace(b'"fx": 100.0', b'"fx": NaN'), *p[2:]], "fx"),
        (lambda p: [p[0], p[1].replace(b'"width": 160', b'"width": "wide"'), *p[2:]], "width"),
        (lambda p: [*p[:2], p[2][:-1], p[3]], "left image has"),
        (lambda p: [*p[:3], p[3] + b"x"], "right image has"),
    ],
)
def test_decode_rejects_malformed(mutate, reason: str) -> None:
    with pytest.raises(FrameError, match=reason):
        decode_frame(mutate(_parts(5)))


def test_encode_rejects_programming_mistakes() -> None:
    left, right = _pair(0)
    with pytest.raises(ValueError, match="differ"):
        encode_frame(0, 1.0, left, right[:, :-1], INTR, 0.075)
    with pytest.raises(ValueError, match="uint8"):
        encode_frame(0, 1.0, left.astype(np.float32), right, INTR, 0.075)
    with pytest.raises(ValueError, match="intrinsics"):
        encode_frame(0, 1.0, left[:, :80], right[:, :80], INTR, 0.075)


# -- the adapter against a PUB socket -----------------------------------------------------------


@pytest.fixture()
def pub():
    ctx = zmq.Context()
    sock = ctx.socket(zmq.PUB)
    sock.setsockopt(zmq.LINGER, 0)
    port = sock.bind_to_random_port("tcp://127.0.0.1")
    yield sock, f"tcp://127.0.0.1:{port}"
    sock.close(0)
    ctx.term()


def _until_connected(sock: zmq.Socket, cam: SimStereoCamera, seq0: int = 1000) -> int:
    """Publish frames until the SUB receives one (ZeroMQ's slow joiner); returns next seq."""
    seq = seq0
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        sock.send_multipart(_parts(seq))
        seq += 1
        if cam.read(timeout=0.05) is not None:
            time.sleep(0.05)
            while cam.read() is not None:  # empty the queue
                pass
            return seq
    raise AssertionError("the SUB socket never received a frame")


def test_newest_frame_dropped_lost_and_health(pub) -> None:
    sock, endpoint = pub
    cam = SimStereoCamera(endpoint, compute_disparity=False, stale_after=0.3)
    assert isinstance(cam, StereoCamera)
    assert cam.health().state is HealthState.FAILED  # not opened
    assert cam.open() is True
    h = cam.health()
    assert h.state is HealthState.DEGRADED and "waiting" in (h.last_error or "")
    assert cam.read(timeout=0.05) is None
    seq = _until_connected(sock, cam)
    assert cam.health().state is HealthState.OK
    before = cam.health().counters
    for s in (seq, seq + 1, seq + 2):
        sock.send_multipart(_parts(s))
    time.sleep(0.2)  # all three queued on the SUB side
    f = cam.read(timeout=1.0)
    assert f is not None and f.sequence == seq + 2  # the newest
    after = cam.health().counters
    assert after["dropped"] - before["dropped"] == 2
    assert after["frames"] - before["frames"] == 1
    # a sequence gap means frames never reached us: counted as lost
    sock.send_multipart(_parts(seq + 10))
    f = cam.read(timeout=1.0)
    assert f is not None and f.sequence == seq + 10
    assert cam.health().counters["lost"] - after["lost"] == 7
    # no frame for longer than stale_after: degraded, then ok again with frames
    time.sleep(0.4)
    h = cam.health()
    assert h.state is HealthState.DEGRADED and "no frame" in (h.last_error or "")
    sock.send_multipart(_parts(seq + 11))
    assert cam.read(timeout=1.0) is not None
    assert cam.health().state is HealthState.OK
    cam.close()
    assert cam.health().state is HealthState.FAILED


def test_malformed_frames_are_counted_and_skipped(pub) -> None:
    sock, endpoint = pub
    with SimStereoCamera(endpoint, compute_disparity=False) as cam:
        seq = _until_connected(sock, cam)
        good = _parts(seq)
        sock.send_multipart([FRAME_TOPIC, b"{broken json", good[2], good[3]])
        sock.send_multipart([FRAME_TOPIC, good[1]])  # missing images
        sock.send_multipart([FRAME_TOPIC, good[1], good[2][:10], good[3]])  # truncated
        sock.send_multipart(good)
        time.sleep(0.2)
        f = cam.read(timeout=1.0)
        assert f is not None and f.sequence == seq
        c = cam.health().counters
        assert c["malformed"] == 3 and c["dropped"] == 0
        # only malformed frames: read times out with None and does not raise
        sock.send_multipart([FRAME_TOPIC, b"\xff\xfe"])
        assert cam.read(timeout=0.3) is None
        assert cam.health().counters["malformed"] == 4


def test_a_malformed_message_shows_in_the_health_for_the_hold_time(pub, monkeypatch) -> None:
    monkeypatch.setattr(sim_camera, "MALFORMED_HOLD_S", 0.4)
    sock, endpoint = pub
    with SimStereoCamera(endpoint, compute_disparity=False) as cam:
        seq = _until_connected(sock, cam)
        assert cam.health().state is HealthState.OK
        sock.send_multipart([FRAME_TOPIC, b"{broken json"])
        t0 = time.monotonic()
        states = []
        while time.monotonic() - t0 < 0.25:  # good frames, but within the hold
            sock.send_multipart(_parts(seq))
            seq += 1
            f = cam.read(timeout=0.5)
            assert f is not None
            h = cam.health()
            states.append(h.state)
            assert "malformed" in (h.last_error or "")
            time.sleep(0.02)
        assert states and set(states) == {HealthState.DEGRADED}
        time.sleep(0.2)
        sock.send_multipart(_parts(seq))
        assert cam.read(timeout=0.5) is not None
        assert cam.health().state is HealthState.OK and cam.health().counters["malformed"] == 1


def test_disparity_of_a_known_shift(pub) -> None:
    sock, endpoint = pub
    shift = 6
    stereo = StereoConfig(num_disparities=16, block_size=9)
    with SimStereoCamera(endpoint, stereo) as cam:
        seq = _until_connected(sock, cam)
        sock.send_multipart(_parts(seq, seed=4, shift=shift))
        f = cam.read(timeout=1.0)
    assert f is not None and f.disparity is not None
    assert f.disparity.shape == (120, 160) and f.disparity.dtype == np.float32
    valid = np.isfinite(f.disparity)
    assert valid.mean() > 0.5
    assert abs(float(np.median(f.disparity[valid])) - shift) < 0.25
    assert np.mean(np.abs(f.disparity[valid] - shift) < 1.0) > 0.95


def test_disparity_error_is_reported_not_raised(pub) -> None:
    sock, endpoint = pub
    with SimStereoCamera(
        endpoint, StereoConfig(num_disparities=160)
    ) as cam:  # wider than the image
        seq = _until_connected(sock, cam)
        sock.send_multipart(_parts(seq))
        f = cam.read(timeout=1.0)
        assert f is not None and f.disparity is None
        assert cam.health().counters["disparity_errors"] >= 1


def test_publisher_restart_is_survived() -> None:
    ctx = zmq.Context()
    try:
        sock = ctx.socket(zmq.PUB)
        sock.setsockopt(zmq.LINGER, 0)
        port = sock.bind_to_random_port("tcp://127.0.0.1")
        endpoint = f"tcp://127.0.0.1:{port}"
        with SimStereoCamera(endpoint, compute_disparity=False, stale_after=0.2) as cam:
            _until_connected(sock, cam, seq0=500)
            sock.close(0)  # the simulator goes away ...
            time.sleep(0.3)
            assert cam.read(timeout=0.1) is None
            assert cam.health().state is HealthState.DEGRADED
            sock = ctx.socket(zmq.PUB)  # ... and comes back on the same port, counting from 0
            sock.setsockopt(zmq.LINGER, 0)
            sock.bind(endpoint)
            _until_connected(sock, cam, seq0=0)
            assert cam.health().state is HealthState.OK
            assert cam.health().counters["publisher_restarts"] >= 1
        sock.close(0)
    finally:
        ctx.term()


def test_bad_endpoint_fails_without_raising() -> None:
    cam = SimStereoCamera("not-an-endpoint")
    assert cam.open() is False
    h = cam.health()
    assert h.state is HealthState.FAILED and "cannot connect" in (h.last_error or "")
    assert cam.read(timeout=0.01) is None
    cam.close()

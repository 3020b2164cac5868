"""Pose sources of a robot survey: interpolation at a frame's stamp, TUM files, a ZeroMQ
pose stream, odometry from a known start."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import zmq

from drivers.interfaces import OdometryIncrement
from lino_loc.errors import LinoLocError
from lino_loc.poses import wrap_angle
from services.device_threads import OdometryBuffer
from services.messages import Pose2D, PoseMessage, encode
from services.survey_poses import (
    OdometryPoses,
    PoseTrack,
    StreamPoses,
    TumFilePoses,
    parse_tum_lines,
    read_tum_track,
)


def test_track_interpolates_position_and_heading_across_the_wrap():
    tr = PoseTrack(max_gap=1.0)
    tr.add(10.0, (0.0, 0.0, math.pi - 0.1))
    tr.add(11.0, (1.0, 2.0, -math.pi + 0.1))  # +0.2 rad through +-pi
    x, y, th = tr.at(10.25)
    assert (x, y) == pytest.approx((0.25, 0.5))
    assert th == pytest.approx(math.pi - 0.05)
    assert tr.at(11.0) == (1.0, 2.0, pytest.approx(-math.pi + 0.1))
    assert tr.at(9.99) is None and tr.at(11.01) is None  # never extrapolated


def test_track_refuses_a_gap_and_out_of_order_samples():
    tr = PoseTrack(max_gap=0.5)
    tr.add(0.0, (0.0, 0.0, 0.0))
    tr.add(2.0, (1.0, 0.0, 0.0))
    assert tr.at(1.0) is None  # 2 s between the samples around it
    tr.add(1.5, (9.0, 9.0, 0.0))
    assert tr.out_of_order == 1 and len(tr) == 2


def test_track_waits_for_a_sample_past_the_stamp():
    tr = PoseTrack()
    tr.add(0.0, (0.0, 0.0, 0.0))
    assert tr.pose_at(0.1, timeout=0.05) is None
    tr.add(0.2, (2.0, 0.0, 0.0))
    assert tr.pose_at(0.1, timeout=0.05)[0] == pytest.approx(1.0)


def _quat_z(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def test_tum_yaw_and_errors(tmp_path):
    q = _quat_z(2.5)
    rows = parse_tum_lines(["# t x y z qx qy qz qw", f"1.0 3 4 0.2 {q[0]} {q[1]} {q[2]} {q[3]}"], "t.txt")
    assert rows[0][0] == 1.0 and rows[0][1] == pytest.approx((3.0, 4.0, 2.5))
    with pytest.raises(LinoLocError, match=r"t.txt: line 2: expected 8 numbers"):
        parse_tum_lines(["", "1 2 3"], "t.txt")
    with pytest.raises(LinoLocError, match="line 1: not a number"):
        parse_tum_lines(["1 2 3 4 a 0 0 1"], "t.txt")
    with pytest.raises(LinoLocError, match="norm"):
        parse_tum_lines(["1 2 3 4 0 0 0 0"], "t.txt")
    with pytest.raises(LinoLocError, match="not found"):
        read_tum_track(tmp_path / "none.txt")


def test_tum_file_is_read_again_while_it_grows(tmp_path):
    path = tmp_path / "slam.txt"
    q = _quat_z(0.0)
    path.write_text(f"100.0 0 0 0 {q[0]} {q[1]} {q[2]} {q[3]}\n100.1 0.1 0 0 {q[0]}")  # a line being written
    src = TumFilePoses(path)
    assert len(src.track) == 1 and src.pose_at(100.05) is None
    with open(path, "a") as fh:
        fh.write(f" {q[1]} {q[2]} {q[3]}\n")
    assert src.pose_at(100.05, timeout=1.0)[0] == pytest.approx(0.05)


def test_stream_of_pose_messages_is_interpolated():
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    src = StreamPoses(f"tcp://127.0.0.1:{port}", ctx)
    try:
        t0 = 1000.0
        deadline = time.monotonic() + 10
        k = 0
        while len(src.track) < 5:  # until the subscription is up and a few samples are in
            assert time.monotonic() < deadline, "no pose message arrived"
            msg = PoseMessage(stamp=t0 + 0.1 * k, pose=Pose2D(x=0.1 * k, y=1.0, theta=0.0),
                              covariance=[0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.01], state="tracking")
            pub.send_multipart(encode("pose", msg))
            pub.send_multipart([b"pose", b"{not json"])
            k += 1
            time.sleep(0.02)
        stamp = src.track.last_stamp - 0.15
        assert src.pose_at(stamp)[0] == pytest.approx(stamp - t0, abs=1e-9)
        assert src.bad >= 1  # the malformed messages were counted, not fatal
    finally:
        src.close()
        pub.close(0)
        ctx.term()


def test_odometry_poses_compose_from_the_start():
    buf = OdometryBuffer()
    # 1 m forward in 10 increments, then a quarter turn on the spot
    incs = [OdometryIncrement(stamp=1.0 + 0.1 * i, dx=0.1, dy=0.0, dtheta=0.0, dt=0.1) for i in range(1, 11)]
    incs += [OdometryIncrement(stamp=2.0 + 0.1 * i, dx=0.0, dy=0.0, dtheta=math.pi / 20, dt=0.1)
             for i in range(1, 11)]
    buf.add(incs)
    src = OdometryPoses((1.0, 2.0, math.pi / 2), buf)
    assert src.pose_at(1.5) == pytest.approx((1.0, 2.5, math.pi / 2))
    x, y, th = src.pose_at(3.0)
    assert (x, y) == pytest.approx((1.0, 3.0))
    assert abs(float(wrap_angle(th - math.pi))) < 1e-9
    assert src.distance == pytest.approx(1.0) and src.turned == pytest.approx(math.pi / 2)
    assert np.isfinite(src.pose).all()

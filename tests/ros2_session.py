"""A tiny synthetic session written with the recording's own writer (no service): frames at
10 Hz with poses, odometry increments at 50 Hz, particles, the head's pan and the truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lino_loc.poses import compose
from services.recording import topic_messages as tm
from services.recording.session_file import SessionFile

T0 = 1_700_000_000.25
#: the covariance of every pose (x, y, theta), with cross terms
COV = [0.04, 0.01, 0.002, 0.01, 0.09, -0.003, 0.002, -0.003, 0.01]


def write_session(path: Path, frames: int = 12, truth: bool = True, rotate_mb: float = 0.0) -> SessionFile:
    """The session: the robot drives an arc (0.2 m/s, 0.3 rad/s); odometry increments of 20 ms,
    the filter's pose = truth + a fixed offset; returns the (closed) SessionFile."""
    from services.messages import Pose2D, PoseMessage, TruthMessage

    f = SessionFile(path, {"seed": "3", "map_path": "none"}, rotate_mb=rotate_mb)
    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, (24, 32), dtype=np.uint8)
    true = np.array([1.0, 2.0, 0.3])
    seq = 0
    for k in range(frames):
        stamp = T0 + k / 10
        for j in range(5):  # the increments up to the frame, written as the odometry thread would
            inc = {"stamp": stamp - 0.08 + j * 0.02, "dt": 0.02, "dx": 0.004, "dy": 0.0, "dtheta": 0.006,
                   "sequence": seq}
            seq += 1
            for topic, t, data in tm.odometry_messages([inc]):
                f.write(topic, t, t, data)
            true = compose(true, [0.004, 0.0, 0.006])
        est = true + np.array([0.05, -0.02, 0.01])
        pose = PoseMessage(stamp=stamp, seq=k, pose=Pose2D(x=est[0], y=est[1], theta=est[2]),
                           covariance=COV, state="tracking", pan=0.1 * k, quality=0.5 + 0.03 * k)
        msgs = tm.frame_messages(stamp, left, None) + tm.pose_messages(pose.model_dump_json().encode(),
                                                                      pose.model_dump())
        if k % 3 == 0:
            msgs += tm.particles_messages(stamp, est + rng.normal(0, 0.1, (20, 3)))
        if truth:
            tr = TruthMessage(stamp=stamp, seq=k, pose=Pose2D(x=true[0], y=true[1], theta=true[2]))
            msgs += tm.truth_messages(tr.model_dump_json().encode())
        for topic, t, data in msgs:
            f.write(topic, t, t, data)
        f.flush()
    f.close()
    return f

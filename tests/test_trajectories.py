"""TUM trajectory files: round trip, quaternion convention, angle wrap-around, user errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lino_loc.errors import LinoLocError
from lino_loc.poses import wrap_angle
from services.evaluation.trajectories import read_tum, trajectory_names, write_tum


def test_round_trip_keeps_stamps_and_planar_poses(tmp_path) -> None:
    rng = np.random.default_rng(0)
    stamps = np.cumsum(rng.uniform(0.1, 0.3, 50)) + 1.3e9
    poses = np.column_stack([rng.uniform(-5, 5, 50), rng.uniform(-5, 5, 50), rng.uniform(-np.pi, np.pi, 50)])
    path = write_tum(tmp_path / "t.tum", stamps, poses, comment="test\nsecond line")
    s, p = read_tum(path)
    np.testing.assert_allclose(s, stamps, atol=1e-6)
    np.testing.assert_allclose(p[:, :2], poses[:, :2], atol=1e-6)
    np.testing.assert_allclose(wrap_angle(p[:, 2] - poses[:, 2]), 0.0, atol=1e-8)


def test_lines_are_tum_with_unit_yaw_quaternion(tmp_path) -> None:
    path = write_tum(tmp_path / "t.tum", [0.0, 1.0], [[1.0, 2.0, math.pi / 2], [0.0, 0.0, -math.pi]])
    rows = [ln.split() for ln in path.read_text().splitlines() if not ln.startswith("#")]
    assert [len(r) for r in rows] == [8, 8]
    q = np.array([[float(v) for v in r[4:]] for r in rows])
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-9)
    # rotation about z only; yaw pi/2 -> (0, 0, sin(pi/4), cos(pi/4))
    np.testing.assert_allclose(q[0], [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-9)
    assert float(rows[0][3]) == 0.0  # tz


def test_heading_near_pi_survives_the_wrap(tmp_path) -> None:
    th = np.array([math.pi - 1e-7, -math.pi + 1e-7, -math.pi])
    poses = np.column_stack([np.zeros(3), np.zeros(3), th])
    _, p = read_tum(write_tum(tmp_path / "w.tum", np.arange(3.0), poses))
    np.testing.assert_allclose(np.abs(wrap_angle(p[:, 2] - th)), 0.0, atol=1e-6)


def test_reads_a_general_3d_tum_file_as_yaw(tmp_path) -> None:
    yaw = 0.7
    # a rotation about z by yaw written with a negative-w quaternion (same rotation)
    (tmp_path / "g.tum").write_text(f"# c\n5.0 1 2 3 0 0 {-math.sin(yaw / 2)} {-math.cos(yaw / 2)}\n")
    s, p = read_tum(tmp_path / "g.tum")
    assert s[0] == 5.0
    np.testing.assert_allclose(p[0], [1.0, 2.0, yaw], atol=1e-12)


def test_user_errors_are_one_line(tmp_path) -> None:
    with pytest.raises(LinoLocError, match="stamps but"):
        write_tum(tmp_path / "a.tum", [0.0], np.zeros((2, 3)))
    with pytest.raises(LinoLocError, match="NaN"):
        write_tum(tmp_path / "a.tum", [0.0], [[np.nan, 0, 0]])
    (tmp_path / "bad.tum").write_text("1 2 3\n")
    with pytest.raises(LinoLocError, match="line 1"):
        read_tum(tmp_path / "bad.tum")
    with pytest.raises(LinoLocError, match="cannot read"):
        read_tum(tmp_path / "missing.tum")


def test_trajectory_names_are_file_safe() -> None:
    est, truth = trajectory_names("bulb+boxes/people")
    assert "/" not in est and est.endswith(".estimate.tum") and truth.endswith(".truth.tum")

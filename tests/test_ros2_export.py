"""`lino-loc export ros2`: a recording as a rosbag2, read back by rosbags (and by evo).

The recording is a tiny synthetic session written with the recording's own writer
(tests/ros2_session.py): a known covariance with cross terms, odometry increments, particles,
the head's pan and the truth.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("rosbags")

sys.path.insert(0, str(Path(__file__).parent))
from ros2_session import COV, T0, write_session  # noqa: E402

from lino_loc.errors import LinoLocError  # noqa: E402
from lino_loc.poses import compose  # noqa: E402
from services.recording.channels import stamp_ns  # noqa: E402
from services.ros2_export import (  # noqa: E402
    BAG_TOPICS,
    covariance_6x6,
    export_ros2,
    iter_bag,
    require_rosbags,
    truth_tum_path,
)


def _cli(argv: list[str]) -> int:
    from services.cli import main

    return main(argv)


def _xyt(pose) -> tuple[float, float, float]:
    return (pose.position.x, pose.position.y, 2 * math.atan2(pose.orientation.z, pose.orientation.w))


def _tf_xyt(tf) -> tuple[float, float, float]:
    t, r = tf.transform.translation, tf.transform.rotation
    return (t.x, t.y, 2 * math.atan2(r.z, r.w))


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("ros2")
    write_session(d / "s.mcap")
    assert _cli(["export", "ros2", str(d / "s.mcap"), "--out", str(d / "bag")]) == 0
    return d / "bag"


def test_the_bag_has_the_ros2_types_frames_and_stamps(bag: Path) -> None:
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == BAG_TOPICS
    msgs: dict[str, list] = {}
    for topic, t, m in iter_bag(bag):
        msgs.setdefault(topic, []).append((t, m))
    assert len(msgs["/amcl_pose"]) == 12 and len(msgs["/odom"]) == 60 and len(msgs["/truth"]) == 12
    assert len(msgs["/particle_cloud"]) == 4 and len(msgs["/camera/image_raw/compressed"]) == 12
    for k, (t, m) in enumerate(msgs["/amcl_pose"]):
        ns = stamp_ns(T0 + k / 10)  # the recording's stamp, split into sec and nanosec
        assert t == ns and m.header.stamp.sec == ns // 10**9 and m.header.stamp.nanosec == ns % 10**9
        assert m.header.frame_id == "map"
    assert {m.header.frame_id for _, m in msgs["/particle_cloud"]} == {"map"}
    assert len(msgs["/particle_cloud"][0][1].poses) == 20
    odom = msgs["/odom"][0][1]
    assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_link")
    assert odom.twist.twist.linear.x == pytest.approx(0.004 / 0.02)
    assert odom.twist.twist.angular.z == pytest.approx(0.006 / 0.02)
    img = msgs["/camera/image_raw/compressed"][0][1]
    assert img.header.frame_id == "camera" and img.format == "mono8; png compressed mono8"
    import cv2

    assert cv2.imdecode(np.asarray(img.data), cv2.IMREAD_UNCHANGED).shape == (24, 32)
    pairs = {(tf.header.frame_id, tf.child_frame_id) for _, m in msgs["/tf"] for tf in m.transforms}
    assert pairs == {("map", "odom"), ("odom", "base_link"), ("base_link", "camera")}


def test_the_covariance_is_6x6_row_major_over_x_y_z_roll_pitch_yaw(bag: Path) -> None:
    c = np.asarray(next(m for _, _, m in iter_bag(bag, ["/amcl_pose"])).pose.covariance).reshape(6, 6)
    c3 = np.asarray(COV).reshape(3, 3)
    idx = [0, 1, 5]  # x, y, rot z
    assert np.array_equal(c[np.ix_(idx, idx)], c3)
    assert c[0, 5] == COV[2] and c[5, 1] == COV[7] and c[1, 0] == COV[3]  # the cross terms
    assert not c[2:5, :].any() and not c[:, 2:5].any()  # z, roll, pitch: fixed, not estimated
    assert covariance_6x6(np.eye(3))[35] == 1.0 and covariance_6x6(np.eye(3))[14] == 0.0


def test_map_to_odom_composed_with_odometry_gives_the_pose(bag: Path) -> None:
    """REP-105: (map -> odom) (+) (odom -> base_link) at a pose's stamp = the pose; odom ->
    base_link is the odometry integrated from the first increment."""
    poses = {t: _xyt(m.pose.pose) for _, t, m in iter_bag(bag, ["/amcl_pose"])}
    checked = 0
    for _, t, m in iter_bag(bag, ["/tf"]):
        tfs = {(tf.header.frame_id, tf.child_frame_id): _tf_xyt(tf) for tf in m.transforms}
        if ("map", "odom") not in tfs:
            continue
        got = compose(tfs[("map", "odom")], tfs[("odom", "base_link")])
        assert np.allclose(got, poses[t], atol=1e-9, rtol=0)
        checked += 1
    assert checked == len(poses) == 12
    # the odom frame: the k-th frame's stamp closes 5 (k + 1) increments of (0.004, 0, 0.006)
    last_odom = [m for _, _, m in iter_bag(bag, ["/odom"])][-1]
    expect = np.zeros(3)
    for _ in range(60):
        expect = compose(expect, [0.004, 0.0, 0.006])
    assert np.allclose(_xyt(last_odom.pose.pose), expect, atol=1e-12)


def test_the_truth_goes_to_a_tum_file_beside_the_bag(bag: Path) -> None:
    lines = truth_tum_path(bag).read_text().splitlines()
    assert len(lines) == 12 and len(lines[0].split()) == 8
    assert float(lines[0].split()[0]) == pytest.approx(T0)


def test_a_rotated_recording_exports_its_parts_in_order(tmp_path: Path) -> None:
    f = write_session(tmp_path / "r.mcap", frames=9, truth=False, rotate_mb=0.00001)
    assert len(f.files) > 2
    r = export_ros2(f.files, tmp_path / "bag")
    assert r.messages["/amcl_pose"] == 9 and r.messages["/truth"] == 0 and r.truth_tum is None
    stamps = [t for _, t, _ in iter_bag(tmp_path / "bag", ["/amcl_pose"])]
    assert stamps == sorted(stamps) and len(set(stamps)) == 9


def test_a_replay_output_exports_too(tmp_path: Path) -> None:
    """A replay's OUT.mcap has the recording's layout: its /pose/estimate, /odometry, /truth."""
    write_session(tmp_path / "s.mcap", frames=4)
    from services.recording.recording_reader import Recording, read_recording
    from services.recording.session_file import SessionFile

    out = SessionFile(tmp_path / "s-replay.mcap", {"replay_of": "[\"s.mcap\"]"})
    for m in read_recording([tmp_path / "s.mcap"], Recording([tmp_path / "s.mcap"])):
        out.write(m.topic, m.log_ns, m.publish_ns, m.data, m.sequence)
    out.close()
    r = export_ros2([tmp_path / "s-replay.mcap"], tmp_path / "bag")
    assert r.messages["/amcl_pose"] == 4 and r.messages["/odom"] == 20


def _one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str], *needles: str) -> None:
    assert _cli(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("lino-loc: error: "), err
    for n in needles:
        assert n in err[0], err


def test_bad_input_gives_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = str(tmp_path / "bag")
    _one_line_exit_2(["export", "ros2", str(tmp_path / "none.mcap"), "--out", out], capsys,
                     "none.mcap", "no such file")
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n" * 10)
    _one_line_exit_2(["export", "ros2", str(text), "--out", out], capsys, "notes.mcap", "not an MCAP file")
    other = tmp_path / "other.mcap"
    from mcap.writer import Writer

    with other.open("wb") as fh:
        w = Writer(fh)
        w.start()
        cid = w.register_channel("/chatter", "json", w.register_schema("x", "jsonschema", b"{}"))
        w.add_message(cid, 1, b"{}", 1)
        w.finish()
    _one_line_exit_2(["export", "ros2", str(other), "--out", out], capsys, "/pose/estimate", "/chatter")
    assert not (tmp_path / "bag").exists()
    write_session(tmp_path / "s.mcap", frames=2)
    (tmp_path / "bag").mkdir()
    _one_line_exit_2(["export", "ros2", str(tmp_path / "s.mcap"), "--out", out], capsys, "exists")
    _one_line_exit_2(["export", "ros2", str(tmp_path / "s.mcap"), "--out", str(text / "bag")], capsys,
                     "cannot write")


def test_without_rosbags_the_command_names_the_extra(monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "rosbags.rosbag2", None)  # as if not installed
    with pytest.raises(LinoLocError, match=r"pip install 'lino-loc\[ros2\]'"):
        require_rosbags("x")
    _one_line_exit_2(["export", "ros2", "x.mcap", "--out", "b"], capsys, "lino-loc[ros2]")


@pytest.mark.skipif(shutil.which("evo_traj", path=os.path.dirname(sys.executable)) is None,
                    reason="evo (the test extra) is not installed")
def test_evo_reads_the_bag(bag: Path, tmp_path: Path) -> None:
    """evo's own command lines, as docs/ros2.md gives them (HOME: evo writes its settings there)."""
    env = {**os.environ, "HOME": str(tmp_path), "MPLBACKEND": "Agg"}
    bindir = Path(sys.executable).parent
    traj = subprocess.run([str(bindir / "evo_traj"), "bag2", str(bag), "/amcl_pose"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert traj.returncode == 0, traj.stderr
    assert "12 poses" in traj.stdout
    ape = subprocess.run([str(bindir / "evo_ape"), "bag2", str(bag), "/truth", "/amcl_pose",
                          "--save_results", str(tmp_path / "ape.zip")], env=env,
                         capture_output=True, text=True, timeout=120)
    assert ape.returncode == 0, ape.stderr
    import zipfile

    with zipfile.ZipFile(tmp_path / "ape.zip") as z:
        stats = json.loads(z.read("stats.json"))
    # the session's estimate is the truth moved by (0.05, -0.02) in map
    assert stats["max"] == pytest.approx(math.hypot(0.05, -0.02), abs=1e-6)


def test_the_bridge_example_maps_the_documented_pose_as_the_export_does() -> None:
    """examples/ros2_pose_bridge.py (it needs ROS 2 to run; its conversion does not): the pose
    example of docs/zeromq.md gives the export's covariance layout, stamp and quaternion."""
    import importlib.util
    import re

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("ros2_pose_bridge", root / "examples" / "ros2_pose_bridge.py")
    bridge = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bridge)
    doc = (root / "docs" / "zeromq.md").read_text(encoding="utf-8")
    example = json.loads(re.search(r"<!-- example: pose -->\n```json\n(.*?)```", doc, re.S).group(1))
    f = bridge.pose_fields(example)
    assert f["covariance"] == covariance_6x6(example["covariance"])
    ns = stamp_ns(example["stamp"])
    assert (f["sec"], f["nanosec"]) == (ns // 10**9, ns % 10**9) and f["frame_id"] == "map"
    assert 2 * math.atan2(f["qz"], f["qw"]) == pytest.approx(example["pose"]["theta"])


def test_the_odom_frame_is_the_odometry_integrated_and_split_at_a_stamp(bag: Path) -> None:
    from services.ros2_export import odometry_poses

    odom = {t: _xyt(m.pose.pose) for _, t, m in iter_bag(bag, ["/odom"])}
    for _, t, m in iter_bag(bag, ["/tf"]):  # at a pose's stamp (the end of an increment here)
        tfs = {(tf.header.frame_id, tf.child_frame_id): _tf_xyt(tf) for tf in m.transforms}
        if ("map", "odom") in tfs:
            assert np.allclose(tfs[("odom", "base_link")], odom[t], atol=1e-12)
    incs = [{"stamp": 10.0 + 0.1 * k, "dt": 0.1, "dx": 0.1, "dy": 0.0, "dtheta": 0.0} for k in range(1, 4)]
    poses = odometry_poses(incs, [10.15])  # half-way through the second increment
    assert np.allclose(poses[stamp_ns(10.15)], [0.15, 0.0, 0.0])
    assert np.allclose(poses[stamp_ns(10.3)], [0.3, 0.0, 0.0])


def test_a_cut_recording_exports_up_to_its_last_whole_chunk(tmp_path: Path) -> None:
    write_session(tmp_path / "s.mcap", frames=12)
    data = (tmp_path / "s.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    r = export_ros2([tmp_path / "cut.mcap"], tmp_path / "bag")
    assert r.truncated is not None and "cut short" in r.truncated
    assert 0 < r.messages["/amcl_pose"] < 12

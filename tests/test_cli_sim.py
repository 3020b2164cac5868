"""`lino-loc sim` as a real process: the device line, truth over ZeroMQ, camera frames, SIGTERM."""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zmq

from drivers.dynamixel_head import DynamixelHead, HeadConfig
from drivers.interfaces import HealthState
from drivers.serial_odometry import OdometryConfig, SerialOdometry
from drivers.sim.camera import SimStereoCamera
from lino_loc.errors import LinoLocError
from services import cli
from services.messages import TruthMessage, decode

ROOT = Path(__file__).resolve().parents[1]


def _start(*args: str) -> tuple[subprocess.Popen, dict]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "sim", *args],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    if not sel.select(timeout=60.0):
        proc.kill()
        raise AssertionError(f"no device line within 60 s; stderr: {proc.stderr.read()}")
    line = proc.stdout.readline()
    assert line.endswith("\n"), (line, proc.poll())
    return proc, json.loads(line)


def _stop(proc: subprocess.Popen, sig: int = signal.SIGTERM) -> tuple[int, str, str]:
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=20)
    return proc.returncode, out, err


@pytest.fixture(scope="module")
def sim():
    proc, devices = _start("--width", "80", "--height", "60", "--fps", "5", "--seed", "1",
                           "--stats-period", "0")  # fmt: skip
    try:
        yield proc, devices
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_device_line(sim) -> None:
    proc, d = sim
    assert set(d) == {"head", "odometry", "camera", "truth", "faults", "world", "pid"}
    assert d["pid"] == proc.pid and d["world"] == "office"
    assert d["head"].startswith("/dev/pts/") and os.path.exists(d["head"])
    assert os.path.islink(d["odometry"]) and os.readlink(d["odometry"]).startswith("/dev/pts/")
    for key in ("camera", "truth", "faults"):
        assert d[key].startswith("tcp://127.0.0.1:") and int(d[key].rsplit(":", 1)[1]) > 0
    assert len({d["camera"], d["truth"], d["faults"]}) == 3


def test_truth_stream_is_valid_and_50_hz(sim) -> None:
    _, d = sim
    ctx = zmq.Context()
    sock = ctx.socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.SUBSCRIBE, b"truth")
    sock.connect(d["truth"])
    try:
        msgs = []
        deadline = time.monotonic() + 10.0
        while len(msgs) < 60 and time.monotonic() < deadline:
            if sock.poll(1000):
                topic, msg = decode(sock.recv_multipart())
                assert topic == "truth" and isinstance(msg, TruthMessage)
                msgs.append(msg)
    finally:
        sock.close(0)
        ctx.term()
    assert len(msgs) == 60
    stamps = [m.stamp for m in msgs]
    span = stamps[-1] - stamps[0]
    assert abs(span - 59 * 0.02) < 1e-3 and abs(stamps[-1] - time.time()) < 1.0
    assert [m.seq for m in msgs] == list(range(msgs[0].seq, msgs[0].seq + 60))
    assert all(m.pan == 0.0 and m.frame_id == "map" for m in msgs)


def test_camera_frames_and_head(sim) -> None:
    _, d = sim
    with SimStereoCamera(d["camera"]) as cam:
        frame = None
        deadline = time.monotonic() + 10.0
        while frame is None and time.monotonic() < deadline:
            frame = cam.read(timeout=0.5)
        assert frame is not None
        assert frame.left.shape == frame.right.shape == (60, 80)
        assert frame.intrinsics.width == 80 and frame.baseline_m == 0.075
        assert frame.disparity is not None and frame.disparity.shape == (60, 80)
        assert abs(frame.stamp - time.time()) < 1.0
        assert cam.health().state is HealthState.OK
    head = DynamixelHead(HeadConfig(port=d["head"]))
    try:
        assert head.open()
        state = head.read()
        assert not state.stale and abs(state.pan) < 0.01
    finally:
        head.close()


def test_sigusr1_unplugs_the_odometry_board_and_it_comes_back(sim) -> None:
    proc, d = sim
    odo = SerialOdometry(OdometryConfig(port=d["odometry"], stale_after=0.3))
    odo.open()
    try:
        assert odo.read(timeout=3.0), "no odometry"
        proc.send_signal(signal.SIGUSR1)
        deadline = time.monotonic() + 3.0
        while os.path.lexists(d["odometry"]) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not os.path.lexists(d["odometry"])  # unplugged: the by-id style link is gone
        time.sleep(0.5)
        odo.read()
        assert odo.health().state is not HealthState.OK
        assert odo.health().counters["reconnects"] >= 1  # the adapter saw the port vanish
        deadline = time.monotonic() + 8.0  # back after 2 s; the adapter retries with backoff
        incs = []
        while not incs and time.monotonic() < deadline:
            incs = odo.read(timeout=0.2)
        assert incs, "no odometry after the board came back"
        assert os.path.islink(d["odometry"])
        assert odo.health().state is HealthState.OK
    finally:
        odo.close()


def _fault_request(endpoint: str, payload: dict | bytes) -> dict:
    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.REQ)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(endpoint)
    try:
        s.send(payload if isinstance(payload, bytes) else json.dumps(payload).encode())
        assert s.poll(5000), f"no reply to {payload!r}"
        return json.loads(s.recv())
    finally:
        s.close(0)


def test_fault_control_reaches_the_head_and_odometry_drivers(sim) -> None:
    """CRC errors injected through the fault socket are counted by the real adapters' health;
    when the fault's time is up, the devices answer cleanly again."""
    proc, d = sim
    assert _fault_request(d["faults"], b"{nope")["ok"] is False
    assert "fraction" in _fault_request(d["faults"], {"cmd": "inject", "fault": "head_crc", "fraction": 7})["error"]
    head = DynamixelHead(HeadConfig(port=d["head"]))
    odo = SerialOdometry(OdometryConfig(port=d["odometry"]))
    odo.open()
    try:
        assert head.open() and not head.read().stale
        assert odo.read(timeout=3.0), "no odometry"
        for fault in ("head_crc", "odometry_crc"):
            r = _fault_request(d["faults"], {"cmd": "inject", "fault": fault, "duration_s": 1.0})
            assert r["ok"] is True and fault in r["active"], r
        t_end = time.monotonic() + 0.8
        while time.monotonic() < t_end:
            head.read()
            odo.read(timeout=0.1)
        assert head.health().counters["crc_errors"] >= 3
        assert odo.health().counters["corrupt_lines"] >= 10
        time.sleep(0.5)  # the faults end on time
        assert _fault_request(d["faults"], {"cmd": "status"})["active"] == {}
        odo.read()
        corrupt = odo.health().counters["corrupt_lines"]
        assert not head.read().stale and odo.read(timeout=1.0)
        assert odo.health().counters["corrupt_lines"] <= corrupt + 1  # a line cut at the end at most
    finally:
        head.close()
        odo.close()
    assert proc.poll() is None


def test_sigterm_exits_zero_and_cleans_up(sim) -> None:
    proc, d = sim
    link_dir = os.path.dirname(d["odometry"])
    pty = os.readlink(d["odometry"])
    t_stop = time.time()
    code, out, err = _stop(proc)
    assert code == 0, err
    assert out == ""  # the device line was the only stdout output
    assert "stopped" in err and "Traceback" not in err
    assert not os.path.lexists(d["odometry"]) and not os.path.exists(link_dir)
    for path in (d["head"], pty):
        # gone; or re-created since for someone else (ptys are numbered from the lowest free one)
        assert not os.path.exists(path) or os.stat(path).st_ctime >= t_stop, path
    ctx = zmq.Context()  # the ports are free again
    try:
        for key in ("camera", "truth", "faults"):
            s = ctx.socket(zmq.PUB)
            s.setsockopt(zmq.LINGER, 0)
            s.bind(d[key])
            s.close(0)
    finally:
        ctx.term()


@pytest.mark.parametrize(
    "args, reason",
    [
        (["--world", "nowhere"], "not found"),
        (["--start=-5,0,0"], "not free"),
        (["--lighting", "disco"], "unknown lighting"),
        (["--scene-changes", "boxes,aliens"], "unknown scene change"),
        (["--fault-endpoint", "tcp://0.0.0.0:5999"], "not a loopback endpoint"),
    ],
)
def test_bad_input_exits_2_with_one_line(args: list[str], reason: str, capsys) -> None:
    # in-process (the CLI's own main): a process per case costs seconds of imports
    code = cli.main(["sim", *args])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    lines = [ln for ln in err.splitlines() if "error" in ln]
    assert len(lines) == 1 and reason in lines[0], err
    assert "Traceback" not in err


def test_bad_flag_value_exits_2(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(["sim", "--fps", "0"])
    assert exc.value.code == 2
    assert "must be > 0" in capsys.readouterr().err


def test_configuration_file_and_flags(tmp_path) -> None:
    from services.commands.sim import robot_config

    cfg = tmp_path / "sim.toml"
    cfg.write_text(
        f"""
[devices.camera]
kind = "sim"
[devices.camera.sim]
world = "office"
lighting = "bulb"
scene_changes = ["boxes"]
width = 64
height = 48
fps = 7.0
baseline_m = 0.1
endpoint = "tcp://127.0.0.1:5999"
[devices.head]
kind = "dynamixel"
port = "{tmp_path}/head"
pan_id = 3
tilt_id = 4
[devices.odometry]
kind = "serial"
port = "auto"
wheel_radius = 0.07
ticks_per_rev = 1024
track_width = 0.42
left_sign = -1
rate_hz = 40.0
"""
    )
    args = cli.build_parser().parse_args(["sim", "--config", str(cfg), "--fps", "3", "--no-drive"])
    rc, truth = robot_config(args, str(tmp_path / "run"))
    assert (rc.world, rc.lighting, rc.scene_changes) == ("office", "bulb", ("boxes",))
    assert (rc.width, rc.height, rc.fps, rc.baseline_m) == (64, 48, 3.0, 0.1)  # flag beats file
    assert (rc.wheel_radius, rc.ticks_per_rev, rc.track_width) == (0.07, 1024.0, 0.42)
    assert (rc.left_sign, rc.right_sign, rc.odometry_rate_hz) == (-1, 1, 40.0)
    assert (rc.pan_id, rc.tilt_id, rc.head_link) == (3, 4, f"{tmp_path}/head")
    assert rc.odometry_link == str(tmp_path / "run" / "odometry")
    assert rc.camera_endpoint == "tcp://127.0.0.1:5999" and truth == "tcp://127.0.0.1:*"
    assert rc.drive is False
    (tmp_path / "head").write_text("a real file")
    with pytest.raises(LinoLocError, match="not a symlink"):
        robot_config(args, str(tmp_path / "run"))

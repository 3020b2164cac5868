"""End to end: `lino-loc survey --robot` against the simulated robot, real processes and sockets.

The simulator runs 80 x 60 images at 15 fps; the head sweeps every 30 deg (12 captures a
stop: the emulated head's +-2.6 rad range covers 9 of them, the base turns once for the other
3). Three rigs:

- the product path: `survey --robot` starts its own `lino-loc sim` (no robot attached, the
  configuration's "auto" devices) and drives a plan of 4 stops by the simulator's ``goto``; it
  is killed with SIGKILL in the middle and run again: the dataset then holds every capture
  once, every image written before the kill unchanged; `lino-loc dataset check` accepts it,
  each image shows the simulated building at its row's pose, and `lino-loc map build` makes a
  map that localizes a view the survey never took;
- the operator mode: a `lino-loc sim` started by the test, the survey waiting on its control
  socket at each stop; the test drives the simulated robot there (``goto``) and confirms;
- the external-pose mode: the same simulator; the test relays the simulator's true pose,
  shifted by 10 cm, as the project's ``pose`` messages; the survey's robot poses are those.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq

ROOT = Path(__file__).resolve().parents[1]
HEADING_STEP_DEG = 30.0
CAPTURES_PER_STOP = 12
PLAN4 = [(3.5, 1.0), (4.0, 1.0), (4.0, 1.5), (3.5, 1.5)]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]])
    for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env[v] = "1"
    for k in [k for k in env if k.upper().startswith("LINO_LOC__")]:
        del env[k]
    return env


def _config(path: Path, camera: str = "auto", head: str = "auto", odometry: str = "auto") -> Path:
    path.write_text(f"""
[devices.camera]
kind = "sim"
[devices.camera.sim]
endpoint = "{camera}"
world = "office"
width = 80
height = 60
fps = 15.0
[devices.head]
kind = "dynamixel"
port = "{head}"
[devices.odometry]
kind = "serial"
port = "{odometry}"
[map]
path = "{path.parent / 'unused.npz'}"
[logging]
level = "INFO"
""")
    return path


def _plan(path: Path, stops: list[tuple[float, float]]) -> Path:
    path.write_text("x,y\n" + "".join(f"{x},{y}\n" for x, y in stops))
    return path


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "services.cli", *args]


def _survey_argv(cfg: Path, plan: Path, out: Path, *extra: str) -> list[str]:
    return _cli("survey", "--robot", "--config", str(cfg), "--plan", str(plan), "--out", str(out),
                "--heading-step", str(HEADING_STEP_DEG), "--drive-speed", "0.6", "--json", *extra)


def _journal_rows(out: Path) -> list[dict[str, Any]]:
    path = out / "poses.journal.jsonl"
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            obj = json.loads(line)
        except json.JSONDecodeError:
            continue
        if "row" in obj:
            rows.append(obj)
    return rows


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped, does not)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _summary(proc: subprocess.CompletedProcess[str]) -> dict[str, Any]:
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------------
# the product path: its own simulator, killed and resumed
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def resumed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("robot-survey")
    cfg = _config(tmp / "sim.toml")
    plan = _plan(tmp / "plan.csv", PLAN4)
    out = tmp / "survey"
    argv = _survey_argv(cfg, plan, out)
    log = open(tmp / "first.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=log, env=_env(), cwd=ROOT)
    deadline = time.monotonic() + 150
    while len(_journal_rows(out)) < 16:  # past the first stop, into the second
        assert proc.poll() is None, (tmp / "first.log").read_text()[-3000:]
        assert time.monotonic() < deadline, "the survey captured too little in 150 s"
        time.sleep(0.1)
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    log.close()
    before = _journal_rows(out)
    hashes = {r["row"]["image"]: _sha(out / r["row"]["image"]) for r in before}
    # the killed survey's simulator gets SIGTERM on its parent's death, and stops
    found = re.search(r"simulated robot running \(pid ([0-9]+)\)", (tmp / "first.log").read_text())
    assert found, "the survey did not say which simulator it started"
    sim_pid = int(found.group(1))
    deadline = time.monotonic() + 15
    while _alive(sim_pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    sim_stopped = not _alive(sim_pid)
    if not sim_stopped:
        os.kill(sim_pid, signal.SIGKILL)
    second = subprocess.run(argv, capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=240)
    yield {"tmp": tmp, "out": out, "before": before, "hashes": hashes, "summary": _summary(second),
           "stderr": second.stderr, "sim_stopped": sim_stopped}


def test_kill9_loses_no_image_and_the_rerun_completes_the_plan(resumed):
    out, before, s = resumed["out"], resumed["before"], resumed["summary"]
    assert s["resumed_images"] == len(before) >= 16
    assert s["images"] == len(PLAN4) * CAPTURES_PER_STOP and s["pans_missed"] == 0
    assert s["images_this_run"] == s["images"] - len(before)
    for rel, digest in resumed["hashes"].items():  # every image captured before the kill, unchanged
        assert _sha(out / rel) == digest
    rows = _journal_rows(out)
    keys = [(r["extra"]["stop"], r["extra"]["turn_index"], r["extra"]["pan_index"]) for r in rows]
    assert len(set(keys)) == len(keys) == s["images"]
    assert "continuing" in resumed["stderr"]
    assert resumed["sim_stopped"], "the killed survey's simulator kept running"


def test_dataset_is_accepted_and_shows_the_building_at_its_poses(resumed):
    from drivers.sim.renderer import CameraModel, Renderer
    from lino_loc.dataset import Dataset

    out = resumed["out"]
    check = subprocess.run(_cli("dataset", "check", str(out), "--json"), capture_output=True, text=True,
                           env=_env(), cwd=ROOT, timeout=120)
    assert check.returncode == 0, check.stdout + check.stderr
    assert json.loads(check.stdout)["problems"] == []
    ds = Dataset.open(out)
    assert ds.has_disparity and ds.has_right and ds.meta.disparity_source == "stereo-matcher"
    # the positions are the plan's, the headings every 30 deg at each
    for (x, y) in PLAN4:
        at = np.flatnonzero(np.hypot(ds.poses[:, 0] - x, ds.poses[:, 1] - y) < 1e-9)
        deg = sorted(round(math.degrees(t) / HEADING_STEP_DEG) % CAPTURES_PER_STOP for t in ds.poses[at, 2])
        assert deg == list(range(CAPTURES_PER_STOP))
        # the reported pan is the head's (its encoder's steps), within 0.5 deg of the sweep's
        err = [abs(math.remainder(math.degrees(t), HEADING_STEP_DEG)) for t in ds.poses[at, 2]]
        assert max(err) < 0.5
    # each image is the view at its pose: it matches a rendering there better than one 30 deg off
    cam = ds.meta.camera
    r = Renderer("office", camera=CameraModel(width=cam.width, height=cam.height))
    rng = np.random.default_rng(0)
    for i in rng.choice(len(ds), 8, replace=False):
        x, y, th = ds.poses[i]
        img = ds.image(int(i)).astype(float)

        def corr(theta: float, img: np.ndarray = img, x: float = x, y: float = y) -> float:
            ref = r.render(float(x), float(y), theta, stereo=False, noise=False).grey.astype(float)
            return float(np.corrcoef(img.ravel(), ref.ravel())[0, 1])

        here = corr(float(th))
        assert here > 0.9
        assert here > max(corr(float(th) + math.radians(30)), corr(float(th) - math.radians(30)))


def test_map_of_the_robot_survey_localizes(resumed):
    from drivers.sim.renderer import CameraModel, Renderer
    from lino_loc.appearance_map import AppearanceMap
    from lino_loc.localizer import Localizer, LocalizerConfig

    tmp, out = resumed["tmp"], resumed["out"]
    map_path = tmp / "robot.npz"
    build = subprocess.run(_cli("map", "build", str(out), "--out", str(map_path), "--features", "5", "--json"),
                           capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=180)
    assert build.returncode == 0, build.stderr[-2000:]
    amap = AppearanceMap.load(map_path)
    assert len(amap) >= len(PLAN4) * CAPTURES_PER_STOP
    r = Renderer("office", camera=CameraModel(width=80, height=60))
    truth = np.array([3.75, 1.25, 0.4])  # between the stops and between the headings
    loc = Localizer(amap, LocalizerConfig(), rng=np.random.default_rng(1))
    rng = np.random.default_rng(2)
    for _ in range(15):
        view = r.render(*truth, stereo=True, rng=rng)
        est = loc.update((0.0, 0.0, 0.0), pan=0.0, image=view.grey)
    assert math.hypot(*(est.pose[:2] - truth[:2])) < 0.35
    # the map holds a view every 30 deg: the estimate is at most one of those steps off
    assert abs(math.remainder(float(est.pose[2] - truth[2]), 2 * math.pi)) < math.radians(HEADING_STEP_DEG)


# --------------------------------------------------------------------------------------------
# a simulator started by the test: the operator mode and the external-pose mode
# --------------------------------------------------------------------------------------------


def _request(endpoint: str, req: dict[str, Any], timeout: float = 10.0) -> dict[str, Any]:
    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.REQ)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(endpoint)
    try:
        s.send(json.dumps(req).encode())
        assert s.poll(int(timeout * 1000)), f"{endpoint} did not answer {req}"
        return json.loads(s.recv())
    finally:
        s.close(0)


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("robot-survey-sim")
    cfg = _config(tmp / "simulator.toml")
    log = open(tmp / "sim.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen(_cli("sim", "--config", str(cfg), "--no-drive", "--stats-period", "0"),
                            stdout=subprocess.PIPE, stderr=log, env=_env(), cwd=ROOT)
    line = proc.stdout.readline().decode()
    assert line, (tmp / "sim.log").read_text()[-2000:]
    info = json.loads(line)
    info["tmp"] = tmp
    info["survey_config"] = _config(tmp / "survey.toml", camera=info["camera"], head=info["head"],
                                    odometry=info["odometry"])
    yield info
    proc.send_signal(signal.SIGTERM)
    proc.wait(10)
    log.close()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_operator_mode_confirms_each_stop_through_its_control(sim):
    tmp = sim["tmp"]
    out = tmp / "operator"
    control = f"tcp://127.0.0.1:{_free_port()}"
    plan = _plan(tmp / "one.csv", [(4.5, 1.25)])
    proc = subprocess.Popen(_survey_argv(sim["survey_config"], plan, out, "--drive", "control", "--control", control),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT)
    confirmed = []
    deadline = time.monotonic() + 120
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            try:
                st = _request(control, {"cmd": "status"}, timeout=1.0)
            except AssertionError:
                continue  # not bound yet
            if not st.get("waiting"):
                time.sleep(0.1)
                continue
            # the "operator" drives the robot to the marked pose, then confirms
            x, y, th = st["pose"]
            assert _request(sim["faults"], {"cmd": "goto", "x": x, "y": y, "theta": th, "speed": 0.6})["ok"]
            while _request(sim["faults"], {"cmd": "where"})["state"] == "driving":
                time.sleep(0.1)
            assert _request(control, {"cmd": "confirm"})["ok"]
            confirmed.append(st["pose"])
            assert st["stops"] == 1 and st["stops_done"] == 0
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr[-3000:]
    s = json.loads(stdout.strip().splitlines()[-1])
    assert s["images"] == CAPTURES_PER_STOP and s["stops_done"] == 1
    assert len(confirmed) == 2  # the stop, and the stop with the base turned
    assert confirmed[0] == [4.5, 1.25, 0.0] and confirmed[1][:2] == [4.5, 1.25] and confirmed[1][2] != 0.0
    rows = _journal_rows(out)
    assert all(r["extra"]["robot"][:2] == [4.5, 1.25] for r in rows)  # the marked position


def test_external_pose_mode_takes_the_stream_interpolated_at_each_frame(sim):
    from services.messages import Pose2D, PoseMessage, TruthMessage, decode, encode

    tmp = sim["tmp"]
    out = tmp / "external"
    port = _free_port()
    stop = threading.Event()
    offset = 0.10  # the "other localization system" is 10 cm off in y: the rows must say so

    def relay() -> None:
        ctx = zmq.Context.instance()
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.SUBSCRIBE, b"truth")
        sub.connect(sim["truth"])
        pub = ctx.socket(zmq.PUB)
        pub.bind(f"tcp://127.0.0.1:{port}")
        try:
            while not stop.is_set():
                if not sub.poll(100):
                    continue
                _, t = decode(sub.recv_multipart())
                assert isinstance(t, TruthMessage)
                msg = PoseMessage(stamp=t.stamp, pose=Pose2D(x=t.pose.x, y=t.pose.y + offset, theta=t.pose.theta),
                                  covariance=[1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-4], state="tracking")
                pub.send_multipart(encode("pose", msg))
        finally:
            sub.close(0)
            pub.close(0)

    th = threading.Thread(target=relay, daemon=True)
    th.start()
    try:
        plan = _plan(tmp / "two.csv", [(4.0, 1.0)])
        proc = subprocess.run(
            _survey_argv(sim["survey_config"], plan, out, "--drive", "sim", "--sim-control", sim["faults"],
                         "--poses", "stream", "--pose-stream", f"tcp://127.0.0.1:{port}"),
            capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=180)
    finally:
        stop.set()
        th.join(5)
    s = _summary(proc)
    assert s["images"] == CAPTURES_PER_STOP
    rows = _journal_rows(out)
    for r in rows:
        rx, ry, rth = r["extra"]["robot"]
        assert math.hypot(rx - 4.0, ry - (1.0 + offset)) < 0.02  # the stream's pose, not the plan's
        cam_theta = float(r["row"]["theta"])
        assert abs(math.remainder(cam_theta - (rth + r["extra"]["pan"]), 2 * math.pi)) < 1e-9


def test_bad_input_is_one_line_and_status_2(tmp_path):
    cfg = _config(tmp_path / "c.toml")
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y\n1,oops\n")
    for extra, needle in (
        (["--plan", str(bad)], "line 2, field 'y': not a number"),
        (["--plan", str(bad), "--grid", "0.5"], "exactly one of --plan"),
        (["--grid", "0.5", "--poses", "odometry"], "needs --start"),
        (["--plan", str(tmp_path / "none.csv")], "plan file not found"),
    ):
        p = subprocess.run(_cli("survey", "--robot", "--config", str(cfg), "--out", str(tmp_path / "o"), *extra),
                           capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=60)
        assert p.returncode == 2, p.stderr
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0] and "Traceback" not in p.stderr


def test_odometry_mode_dead_reckons_from_the_start_and_warns(sim):
    tmp = sim["tmp"]
    out = tmp / "odometry"
    here = _request(sim["faults"], {"cmd": "where"})["pose"]  # where the earlier tests left the robot
    plan = _plan(tmp / "odo.csv", [(3.25, 1.25)])
    proc = subprocess.run(
        _survey_argv(sim["survey_config"], plan, out, "--drive", "sim", "--sim-control", sim["faults"],
                     "--poses", "odometry", "--start", ",".join(f"{v:.6f}" for v in here)),
        capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=180)
    s = _summary(proc)
    assert "they drift" in proc.stderr
    assert s["images"] == CAPTURES_PER_STOP and s["odometry_distance_m"] > 0.5
    truth = _request(sim["faults"], {"cmd": "where"})["pose"]
    for r in _journal_rows(out):
        rx, ry, _ = r["extra"]["robot"]
        assert math.hypot(rx - 3.25, ry - 1.25) < 0.05  # dead reckoning over about a metre
    assert math.hypot(truth[0] - 3.25, truth[1] - 1.25) < 0.02

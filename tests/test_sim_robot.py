"""The simulated robot in-process: the real head and odometry adapters against its emulators,
the camera frames over ZeroMQ, the truth stream, free space and the drive planner."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from drivers.dynamixel_head import DynamixelHead, HeadConfig
from drivers.interfaces import HealthState
from drivers.serial_odometry import OdometryConfig, SerialOdometry
from drivers.sim.camera import SimStereoCamera
from drivers.sim.drive import DrivePlanner, PlannerConfig
from drivers.sim.free_space import FreeSpace
from drivers.sim.robot import SimRobot, SimRobotConfig, TruthSample, base_step, integrate
from drivers.sim.wheel_noise import WheelOdometryNoise
from drivers.sim.world import load_world
from lino_loc.errors import LinoLocError
from lino_loc.poses import between, compose, wrap_angle

RADIUS = 0.25


@pytest.fixture(scope="module")
def world():
    return load_world("office")


@pytest.fixture(scope="module")
def free(world):
    return FreeSpace(world, RADIUS + 0.01)


class _Recorder:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.items: list = []

    def __call__(self, item) -> None:
        with self.lock:
            self.items.append(item)

    def snapshot(self) -> list:
        with self.lock:
            return list(self.items)


@pytest.fixture(scope="module")
def still(world):
    """A robot that stands still, noiseless camera: frames are reproducible renders."""
    frames = _Recorder()
    cfg = SimRobotConfig(
        width=80, height=60, fps=10, drive=False, noise=False, start=(2.0, 1.0, 0.3)
    )
    robot = SimRobot(cfg, world=world, on_frame=frames)
    robot.frames = frames  # type: ignore[attr-defined]
    with robot:
        yield robot


@pytest.fixture(scope="module")
def driving(world):
    truths = _Recorder()
    # seed 3's first goal lies behind the centre of the office: start facing it (saves a turn)
    cfg = SimRobotConfig(
        width=80,
        height=60,
        fps=5,
        drive=True,
        seed=3,
        speed=0.4,
        start=(4.0, 1.25, -2.9),
        wheel_radius=0.06,
        ticks_per_rev=2000,
        track_width=0.36,
        left_sign=-1,  # a non-default base
        odometry_noise=WheelOdometryNoise.exact(),  # this checks the adapter's integration, not slip
    )
    robot = SimRobot(cfg, world=world, on_truth=truths)
    robot.truths = truths  # type: ignore[attr-defined]
    with robot:
        yield robot


# -- head: the real adapter moves the emulated servos, the camera looks where the head points ---


def test_head_adapter_pans_the_rendered_camera(still) -> None:
    head = DynamixelHead(HeadConfig(port=still.head_port, profile_velocity=3.0))
    cam = SimStereoCamera(still.camera_endpoint, compute_disparity=False)
    assert head.open()
    cam.open()
    try:
        views = {}
        for goal in (0.0, 1.0):
            head.command(goal, 0.0)
            state = head.wait_until_still(3.0)
            assert not state.moving and abs(state.pan - goal) < 0.002
            t_still = time.time()
            deadline = time.monotonic() + 3.0
            frame = None
            while time.monotonic() < deadline:
                f = cam.read(timeout=0.5)
                if f is not None and f.stamp > t_still + 0.01:
                    frame = f
                    break
            assert frame is not None, "no frame after the head stopped"
            assert frame.left.shape == (60, 80) and frame.intrinsics == still.intrinsics
            # the published image is the render from the true pose and the head's present pan
            expect = still.renderer.render(2.0, 1.0, 0.3, state.pan, 0.0, noise=False).left
            np.testing.assert_array_equal(frame.left, expect)
            views[goal] = frame.left.astype(np.float32)
            assert abs(still.truth.pan - goal) < 0.002
        assert np.mean(np.abs(views[0.0] - views[1.0])) > 5.0  # it really looks elsewhere
        # the robot records a frame's info after sending it: wait for that of the frame read
        deadline = time.monotonic() + 2.0
        info = [f for f in still.frames.snapshot() if f.stamp > t_still + 0.01]
        while not info and time.monotonic() < deadline:
            time.sleep(0.01)
            info = [f for f in still.frames.snapshot() if f.stamp > t_still + 0.01]
        assert info and all(abs(f.pan - 1.0) < 0.002 for f in info)
        assert all(f.pose == pytest.approx((2.0, 1.0, 0.3)) for f in info)
    finally:
        head.command(0.0, 0.0)
        head.close()
        cam.close()


def test_frame_rate_and_stamps(still) -> None:
    frames = still.frames.snapshot()[-10:]
    assert len(frames) >= 5
    gaps = np.diff([f.stamp for f in frames])
    assert np.all(gaps > 0.05) and abs(float(np.median(gaps)) - 0.1) < 0.03
    s = still.stats()
    assert 8.0 < s["fps"] < 11.0 and s["frames_unsent"] == 0 and s["callback_errors"] == 0


# -- base: truth stream, odometry, free space --------------------------------------------------------


def _truth_at(truths: list[TruthSample], t: float) -> np.ndarray:
    stamps = np.array([s.stamp for s in truths])
    k = int(np.searchsorted(stamps, t, side="right")) - 1
    assert 0 <= k < len(truths) - 1, "time outside the recorded truth"
    s = truths[k]
    return np.array(integrate(s.pose, s.v, s.omega, t - s.stamp))


def _wait_moving(robot: SimRobot, timeout: float = 10.0) -> None:
    """The plan starts by turning towards its first goal: wait until the base drives."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if robot.truth is not None and robot.truth.v > 0.2:
            return
        time.sleep(0.05)
    raise AssertionError("the simulated robot does not drive")


def test_truth_at_50_hz_and_in_free_space(driving, world) -> None:
    _wait_moving(driving)
    t0 = time.monotonic()
    n0 = len(driving.truths.snapshot())
    time.sleep(2.0)
    truths = driving.truths.snapshot()
    rate = (len(truths) - n0) / (time.monotonic() - t0)
    assert 45.0 < rate < 55.0
    stamps = np.array([s.stamp for s in truths])
    np.testing.assert_allclose(np.diff(stamps), 0.02, atol=1e-6)  # nominal tick times
    assert np.all(np.diff([s.seq for s in truths]) == 1)
    assert abs(stamps[-1] - time.time()) < 0.2
    xy = np.array([s.pose[:2] for s in truths])
    assert np.all(world.is_free(xy[:, 0], xy[:, 1], RADIUS))
    assert np.sum(np.hypot(*np.diff(xy, axis=0).T)) > 0.3  # it drives


def test_odometry_adapter_integrates_to_the_true_motion(driving) -> None:
    c = driving.config
    _wait_moving(driving)
    odo = SerialOdometry(OdometryConfig(port=driving.odometry_port, wheel_radius=c.wheel_radius,
                                        ticks_per_rev=c.ticks_per_rev, track_width=c.track_width,
                                        left_sign=c.left_sign))  # fmt: skip
    odo.open()
    try:
        first = odo.read(timeout=2.0)
        assert first, "no odometry from the emulator"
        incs = []
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end:
            incs.extend(odo.read(timeout=0.1))
        health = odo.health()
    finally:
        odo.close()
    assert health.state is HealthState.OK and health.counters["corrupt_lines"] == 0
    assert len(incs) > 120
    est = np.zeros(3)
    for inc in incs:
        est = compose(est, (inc.dx, inc.dy, inc.dtheta))
    time.sleep(0.1)
    truths = driving.truths.snapshot()
    a = _truth_at(truths, incs[0].stamp - incs[0].dt)
    b = _truth_at(truths, incs[-1].stamp)
    true_rel = between(a, b)
    travelled = float(np.hypot(*true_rel[:2]))
    path = sum(math.hypot(i.dx, i.dy) for i in incs)
    assert path > 0.3, "the robot did not drive during the test"
    err = float(np.hypot(*(est[:2] - true_rel[:2])))
    assert err < 0.02 + 0.02 * path, (est, true_rel, travelled, path)
    assert abs(float(wrap_angle(est[2] - true_rel[2]))) < 0.03


def test_base_never_leaves_free_space_even_when_pushed_into_a_wall(world, free) -> None:
    class Ram:  # a plan that drives straight ahead whatever happens
        blocked_calls = 0

        def command(self, pose, dt):
            return 0.5, 0.0

        def blocked(self):
            self.blocked_calls += 1

    plan = Ram()
    pose = (4.0, 1.25, 0.4)
    xy = np.empty((2000, 2))
    for k in range(2000):
        v, omega, pose, _ = base_step(pose, plan, free, 0.02)
        xy[k] = pose[:2]
    assert np.all(world.is_free(xy[:, 0], xy[:, 1], RADIUS))
    assert plan.blocked_calls > 1000  # it reached the wall and stayed in front of it


def _simulate(world, free, seed: int, steps: int = 1500) -> np.ndarray:
    cfg = SimRobotConfig(speed=0.4, robot_radius=RADIUS).planner_config()
    plan = DrivePlanner(world, cfg, np.random.default_rng(seed))
    pose = (4.0, 1.25, 0.0)
    out = np.empty((steps, 3))
    for k in range(steps):
        _, _, pose, _ = base_step(pose, plan, free, 0.02)
        out[k] = pose
    return out


def test_drive_planner_is_deterministic_smooth_and_free(world, free) -> None:
    a = _simulate(world, free, seed=1)
    b = _simulate(world, free, seed=1)
    c = _simulate(world, free, seed=2)
    np.testing.assert_array_equal(a, b)
    assert np.max(np.hypot(*(a[:, :2] - c[:, :2]).T)) > 0.5
    assert np.all(world.is_free(a[:, 0], a[:, 1], RADIUS))
    xmin, xmax, ymin, ymax = world.mapped_area
    assert np.all((a[:, 0] >= xmin) & (a[:, 0] <= xmax) & (a[:, 1] >= ymin) & (a[:, 1] <= ymax))
    step = np.hypot(*np.diff(a[:, :2], axis=0).T)
    assert step.sum() > 5.0 and step.max() <= 0.4 * 0.02 + 1e-9  # moves, never faster than speed
    speed = step / 0.02
    assert np.max(np.abs(np.diff(speed))) <= 0.5 * 0.02 + 1e-6  # bounded acceleration
    turn = np.abs(wrap_angle(np.diff(a[:, 2]))) / 0.02
    assert turn.max() <= 0.8 + 1e-6


def test_free_space_raster_is_conservative(world, free) -> None:
    rng = np.random.default_rng(0)
    xmin, xmax, ymin, ymax = world.room
    x = rng.uniform(xmin, xmax, 20000)
    y = rng.uniform(ymin, ymax, 20000)
    fast = free.is_free(x, y)
    exact = world.is_free(x, y, RADIUS + 0.01)
    assert not np.any(fast & ~exact)  # never calls an occupied point free
    assert fast.sum() > 0.9 * exact.sum()  # and loses little


def test_start_in_an_obstacle_is_a_user_error(world) -> None:
    with pytest.raises(LinoLocError, match="not free"):
        SimRobot(SimRobotConfig(start=(-5.0, 0.0, 0.0)), world=world)


def test_sim_robot_drives_with_the_shared_planner_and_wheel_noise_model() -> None:
    c = SimRobotConfig(speed=0.2, turn_rate=0.5, robot_radius=0.3)
    p = c.planner_config()
    assert isinstance(p, PlannerConfig)
    assert (p.speed, p.turn_rate) == (0.2, 0.5) and p.clearance == pytest.approx(0.41)
    assert p.accel is not None and p.angular_accel is not None  # the simulated base accelerates smoothly
    model = WheelOdometryNoise()
    assert c.odometry_noise.slip_k == model.slip_k and c.odometry_noise.scale_bias_std == model.scale_bias_std
    assert c.odometry_noise.wheel_base_error == 0.0  # the emulated board's track width is the daemon's

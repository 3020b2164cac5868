"""Wire models of services.messages: validation, round trips, and a parse_request that never raises."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pydantic import ValidationError

from drivers.interfaces import HealthTracker
from services import messages as m
from services.schemas import EXAMPLES

COV = [0.04, 0.01, 0.0, 0.01, 0.09, 0.0, 0.0, 0.0, 0.01]


def _pose_msg(**kw):
    base = dict(stamp=1763767825.5, pose=m.Pose2D(x=1.0, y=2.0, theta=0.5), covariance=COV, state="tracking")
    base.update(kw)
    return m.PoseMessage(**base)


# ------------------------------------------------------------------ published messages


def test_pose_message_round_trip_through_frames():
    msg = _pose_msg(seq=7, pan=-0.3, ess=412.0, n_particles=1000)
    frames = m.encode("pose", msg)
    assert frames[0] == b"pose"
    data = json.loads(frames[1])
    assert data["frame_id"] == "map" and data["v"] == m.PROTOCOL_VERSION
    assert data["pose"] == {"x": 1.0, "y": 2.0, "theta": 0.5}
    assert len(data["covariance"]) == 9
    topic, back = m.decode(frames)
    assert topic == "pose" and back == msg


def test_theta_is_wrapped_to_minus_pi_pi():
    for theta, expect in [(7.0, 7.0 - 2 * math.pi), (-4.0, -4.0 + 2 * math.pi), (math.pi, -math.pi), (0.25, 0.25)]:
        p = m.Pose2D(x=0, y=0, theta=theta)
        assert p.theta == pytest.approx(expect)
        assert -math.pi <= p.theta < math.pi


@pytest.mark.parametrize(
    "cov, why",
    [
        ([1, 0, 0, 0, 1, 0, 0, 0], "8 entries"),
        ([1, 0.5, 0, 0, 1, 0, 0, 0, 1], "not symmetric"),
        ([1, 2, 0, 2, 1, 0, 0, 0, 1], "indefinite (eigenvalue -1)"),
        ([-1, 0, 0, 0, 1, 0, 0, 0, 1], "negative variance"),
        ([float("nan"), 0, 0, 0, 1, 0, 0, 0, 1], "NaN"),
        ([float("inf"), 0, 0, 0, 1, 0, 0, 0, 1], "infinite"),
    ],
)
def test_bad_covariances_are_refused(cov, why):
    with pytest.raises(ValidationError, match="covariance"):
        _pose_msg(covariance=cov)


def test_psd_covariance_accepted_and_symmetrised_within_tolerance():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(3, 3))
    c = a @ a.T  # PSD
    noisy = c + 1e-12 * rng.normal(size=(3, 3))
    msg = _pose_msg(covariance=noisy.reshape(-1).tolist())
    got = np.array(msg.covariance).reshape(3, 3)
    np.testing.assert_array_equal(got, got.T)
    np.testing.assert_allclose(got, c, atol=1e-9)
    # singular (rank 1) is PSD too: a pose known exactly along one direction
    v = np.array([1.0, 2.0, 0.5])
    assert _pose_msg(covariance=np.outer(v, v).reshape(-1).tolist())


def test_non_finite_pose_and_bad_state_refused():
    with pytest.raises(ValidationError):
        m.Pose2D(x=float("nan"), y=0, theta=0)
    with pytest.raises(ValidationError):
        _pose_msg(state="confused")
    with pytest.raises(ValidationError):
        _pose_msg(stamp=-1.0)


def test_published_messages_ignore_unknown_fields_for_forward_compatibility():
    data = {**EXAMPLES["pose"][0], "some_future_field": 1}
    msg = m.PoseMessage.model_validate(data)
    assert "some_future_field" not in msg.model_dump()


def test_particles_lengths_must_agree():
    ok = m.ParticlesMessage(stamp=1.0, poses=[(0, 0, 0), (1, 1, 1)], weights=[0.5, 0.5], n_total=10)
    assert ok.subsampled
    with pytest.raises(ValidationError, match="differ in length"):
        m.ParticlesMessage(stamp=1.0, poses=[(0, 0, 0)], weights=[0.5, 0.5], n_total=10)
    with pytest.raises(ValidationError, match="n_total"):
        m.ParticlesMessage(stamp=1.0, poses=[(0, 0, 0), (1, 1, 1)], weights=[0.5, 0.5], n_total=1)


def test_device_health_from_driver_health():
    t = HealthTracker(("timeouts",))
    t.count("timeouts", 3)
    t.error("servo 2: no status packet")
    h = m.DeviceHealthModel.from_health(t.snapshot())
    assert h.state == "degraded" and h.error == "servo 2: no status packet"
    assert h.counters == {"timeouts": 3} and h.error_stamp is not None


def test_encode_refuses_wrong_topic_or_model():
    with pytest.raises(ValueError):
        m.encode("poses", _pose_msg())
    with pytest.raises(TypeError):
        m.encode("truth", _pose_msg())
    with pytest.raises(ValueError, match="2 frames"):
        m.decode([b"pose"])
    with pytest.raises(ValueError, match="pose"):
        m.decode([b"pose", b'{"stamp": 1}'])


# ------------------------------------------------------------------ requests


def test_every_example_request_parses_to_its_model():
    for req in EXAMPLES["request"]:
        got = m.parse_request(json.dumps(req).encode())
        assert not isinstance(got, m.ErrorReply), got
        assert isinstance(got, m.COMMANDS[req["cmd"]])


def test_set_pose_defaults_and_wrapping():
    got = m.parse_request(b'{"cmd": "set_pose", "pose": {"x": 1, "y": -2, "theta": 10}}')
    assert isinstance(got, m.SetPoseRequest)
    assert got.covariance == list(m.DEFAULT_SET_POSE_COVARIANCE)
    assert got.pose.theta == pytest.approx(10 - 4 * math.pi)


@pytest.mark.parametrize(
    "raw, expect",
    [
        (b"", "empty request"),
        (b"{", "malformed JSON at line 1 column 2"),
        (b'{"cmd": "ping",}', "malformed JSON"),
        (b"\xff\xfe{}", "not UTF-8"),
        (b"[1, 2]", "must be a JSON object, got array"),
        (b"42", "got number"),
        (b"{}", "cmd: missing"),
        (b'{"cmd": 3}', "cmd: must be a string"),
        (b'{"cmd": "fly"}', "unknown command 'fly'"),
        (b'{"cmd": "ping", "v": 2}', "v: unsupported protocol version 2"),
        (b'{"cmd": "ping", "verbose": true}', "verbose: unknown field"),
        (b'{"cmd": "set_pose"}', "pose: Field required"),
        (b'{"cmd": "set_pose", "pose": {"x": "1", "y": 0, "theta": 0}}', "pose.x:"),
        (b'{"cmd": "set_pose", "pose": {"x": 1e999, "y": 0, "theta": 0}}', "pose.x: must be a finite number"),
        (b'{"cmd": "set_pose", "pose": {"x": NaN, "y": 0, "theta": 0}}', "non-finite number NaN"),
        (b'{"cmd": "set_pose", "pose": {"x": 0, "y": 0, "theta": 0}, "covariance": [1]}', "covariance:"),
        (b'{"cmd": "set_pose", "pose": {"x": 0, "y": 0, "theta": 0}, "covariance": [1,2,0,2,1,0,0,0,1]}',
         "covariance: covariance must be positive semi-definite"),
        (b'{"cmd": "set_active_vision", "enabled": "yes"}', "enabled:"),
        (b'{"cmd": "set_active_vision"}', "enabled: Field required"),
        (b'{"cmd": "pause", "target": "wheels"}', "target:"),
        (b"[" * 50000, "nested too deeply"),
        (b" " * (m.MAX_REQUEST_BYTES + 1), "request too large"),
    ],
)
def test_malformed_requests_get_one_line_errors_naming_the_problem(raw, expect):
    got = m.parse_request(raw)
    assert isinstance(got, m.ErrorReply), got
    assert expect in got.error
    assert "\n" not in got.error and got.ok is False
    reply = json.loads(m.encode_reply(got))
    assert reply["ok"] is False and reply["error"] == got.error


def test_parse_request_never_raises_on_random_input():
    rng = np.random.default_rng(20261121)
    seeds = [json.dumps(r) for r in EXAMPLES["request"]]
    junk = [b"null", b"true", b'"cmd"', b"{}", b'{"cmd": null}', b'{"cmd": ["ping"]}', b'{"cmd": {"a": 1}}']
    n_requests = n_errors = 0
    for i in range(1500):
        kind = i % 3
        if kind == 0:  # random bytes
            raw = rng.integers(0, 256, size=int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
        elif kind == 1:  # an example with random bytes overwritten
            b = bytearray(seeds[int(rng.integers(len(seeds)))].encode())
            for _ in range(int(rng.integers(1, 4))):
                b[int(rng.integers(len(b)))] = int(rng.integers(0, 256))
            raw = bytes(b)
        else:  # an example with a field replaced by a random JSON value
            obj = json.loads(seeds[int(rng.integers(len(seeds)))])
            key = list(obj)[int(rng.integers(len(obj)))]
            choices = [None, True, -1, 1e308, "x", [], {}, [1.0] * 9, {"x": 1}]
            obj[key] = choices[int(rng.integers(len(choices)))]
            raw = json.dumps(obj).encode()
        got = m.parse_request(raw)  # must not raise
        if isinstance(got, m.ErrorReply):
            n_errors += 1
            assert got.error and "\n" not in got.error
        else:
            n_requests += 1
            assert got.cmd in m.COMMANDS
    for raw in junk:
        assert isinstance(m.parse_request(raw), m.ErrorReply)
    assert n_errors > 500 and n_requests >= 5  # both paths exercised


def test_parse_request_accepts_str_and_memoryview():
    assert isinstance(m.parse_request('{"cmd": "ping"}'), m.PingRequest)
    assert isinstance(m.parse_request(memoryview(b'{"cmd": "status"}')), m.StatusRequest)


# ------------------------------------------------------------------ replies


def test_reply_examples_parse_and_discriminate():
    for data in EXAMPLES["reply"]:
        got = m.parse_reply(json.dumps(data))
        assert got.ok is data["ok"]
        if data["ok"]:
            assert got.cmd == data["cmd"]
        else:
            assert isinstance(got, m.ErrorReply)


def test_status_reply_embeds_a_status_message():
    status = m.StatusMessage.model_validate(EXAMPLES["status"][0])
    raw = m.encode_reply(m.StatusReply(status=status))
    back = m.parse_reply(raw)
    assert isinstance(back, m.StatusReply) and back.status == status
    assert back.status.devices["head"].state == "degraded"
    with pytest.raises(ValueError, match="reply"):
        m.parse_reply(b'{"ok": true, "cmd": "teleport"}')


def test_error_reply_is_one_line():
    e = m.error_reply("bad\nthing   here", cmd="ping")
    assert e.error == "bad thing here" and e.cmd == "ping"


def test_pose_message_from_estimate_symmetrizes_and_times():
    from lino_loc.pose_estimate import Estimate

    cov = np.array([[0.04, 0.011, 0.0], [0.009, 0.09, 0.0], [0.0, 0.0, 0.01]])
    est = Estimate(pose=np.array([1.0, 2.0, 0.5]), covariance=cov, ess=412.0, n_particles=1000,
                   state="tracking", cluster_weight=1.0, log_likelihood=-3.0)
    msg = m.PoseMessage.from_estimate(est, stamp=100.0, seq=3, pan=0.2, now=100.25)
    assert msg.covariance[1] == msg.covariance[3] == pytest.approx(0.01)
    assert (msg.pose.x, msg.pose.y, msg.pose.theta) == (1.0, 2.0, 0.5)
    assert msg.latency_ms == pytest.approx(250.0) and msg.seq == 3 and msg.pan == 0.2
    bad = Estimate(pose=np.array([math.nan, 2.0, 0.5]), covariance=cov, ess=1.0, n_particles=1,
                   state="tracking", cluster_weight=1.0, log_likelihood=-3.0)
    with pytest.raises(ValueError):
        m.PoseMessage.from_estimate(bad, stamp=100.0, seq=4, pan=None)

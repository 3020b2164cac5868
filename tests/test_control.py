"""The control socket: every message gets exactly one reply, errors for anything malformed,
and commands that change the filter run in the loop's thread through the CommandQueue."""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import pytest
import zmq

from services.control import CommandQueue, ControlServer, handle_raw
from services.messages import AckReply, PingReply, error_reply, parse_reply


def _handler(req: Any) -> Any:
    if req.cmd == "ping":
        return PingReply(stamp=123.0)
    if req.cmd == "status":
        raise RuntimeError("broken on purpose")
    if req.cmd == "get_pose":
        raise TimeoutError("the localization loop did not answer within 2 s")
    return AckReply(cmd="set_pose")


@pytest.mark.parametrize(
    ("frames", "needle"),
    [
        ([b"not json"], "malformed JSON"),
        ([b"[1, 2]"], "JSON object"),
        ([b'{"cmd": "fly"}'], "unknown command"),
        ([b'{"cmd": "set_pose", "pose": {"x": "a", "y": 0, "theta": 0}}'], "pose.x"),
        ([b'{"cmd": "ping", "v": 7}'], "protocol version"),
        ([b"\xff\xfe"], "UTF-8"),
        ([b""], "empty request"),
        ([b'{"cmd": "ping"}', b"extra"], "2 frames"),
        ([b'{"cmd": "status"}'], "RuntimeError: broken on purpose"),
        ([b'{"cmd": "get_pose"}'], "did not answer"),
    ],
)
def test_errors_are_replies(frames: list[bytes], needle: str) -> None:
    reply = json.loads(handle_raw(frames, _handler))
    assert reply["ok"] is False and needle in reply["error"]
    assert "\n" not in reply["error"]


def test_valid_request_reaches_the_handler() -> None:
    reply = parse_reply(handle_raw([b'{"cmd": "ping"}'], _handler))
    assert isinstance(reply, PingReply) and reply.stamp == 123.0


def test_command_queue_runs_in_the_loop_thread() -> None:
    q = CommandQueue()
    seen: list[str] = []
    stop = threading.Event()

    def loop() -> None:
        while not stop.is_set():
            q.run_pending()
            time.sleep(0.005)

    t = threading.Thread(target=loop, name="the-loop")
    t.start()
    try:
        assert q.call(lambda: seen.append(threading.current_thread().name) or 42) == 42
        assert seen == ["the-loop"]
        with pytest.raises(ZeroDivisionError):
            q.call(lambda: 1 / 0)
    finally:
        stop.set()
        t.join()
    # nobody runs the queue: a bounded wait, then an error; the stale call never runs later
    ran: list[int] = []
    with pytest.raises(TimeoutError):
        q.call(lambda: ran.append(1), timeout=0.05)
    assert q.run_pending() == 1 and ran == []


def test_command_queue_is_bounded() -> None:
    q = CommandQueue(maxsize=2)
    q.submit(lambda: None)
    q.submit(lambda: None)
    with pytest.raises(RuntimeError, match="too many"):
        q.submit(lambda: None).result(0)


def test_server_answers_garbage_and_keeps_serving() -> None:
    ctx = zmq.Context()
    calls: list[str] = []

    def handler(req: Any) -> Any:
        calls.append(req.cmd)
        return PingReply(stamp=1.0) if req.cmd == "ping" else error_reply("no", cmd=req.cmd)

    server = ControlServer(ctx, "tcp://127.0.0.1:*", handler)
    endpoint = server._sock.getsockopt(zmq.LAST_ENDPOINT).decode()
    server.start()
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.setsockopt(zmq.RCVTIMEO, 5000)
    req.connect(endpoint)
    try:
        for raw in (b"{", b"\x00" * 100_000, b'{"cmd": 3}', b'{"cmd": "ping"}', b"null"):
            req.send(raw)
            reply = json.loads(req.recv())
            assert reply["ok"] is (raw == b'{"cmd": "ping"}')
        req.send_multipart([b'{"cmd": "ping"}', b"second"])
        assert json.loads(req.recv())["ok"] is False
        req.send(b'{"cmd": "ping"}')
        assert json.loads(req.recv())["cmd"] == "ping"
        assert calls == ["ping", "ping"]  # only valid requests reached the handler
        assert server.requests == 7 and server.errors == 5
    finally:
        req.close(0)
        server.stop()
        ctx.term()
    assert not server.is_alive()

"""The operator's control of a robot survey: requests on a real REP socket."""

from __future__ import annotations

import json
import threading

import pytest
import zmq

from lino_loc.errors import LinoLocError
from services.survey_moves import ControlMover, PromptMover, check_local


def _ask(ctx: zmq.Context, endpoint: str, raw: bytes) -> dict:
    s = ctx.socket(zmq.REQ)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(endpoint)
    try:
        s.send(raw)
        assert s.poll(5000), "the survey control did not answer"
        return json.loads(s.recv())
    finally:
        s.close(0)


def test_control_confirms_skips_and_quits_only_a_waiting_stop():
    ctx = zmq.Context()
    mover = ControlMover("tcp://127.0.0.1:*", ctx, progress=lambda: {"stops_left": 3})
    try:
        ep = mover.endpoint
        assert _ask(ctx, ep, b'{"cmd": "status"}') == {"ok": True, "cmd": "status", "waiting": False, "stops_left": 3}
        assert _ask(ctx, ep, b'{"cmd": "confirm"}')["ok"] is False  # nothing waits
        for raw, needle in ((b"not json", "not UTF-8 JSON"), (b"[1]", "JSON object"),
                            (b'{"cmd": "fly"}', "must be one of")):
            reply = _ask(ctx, ep, raw)
            assert reply["ok"] is False and needle in reply["error"]
        answers: list[str] = []
        for cmd, expected in (("confirm", "ok"), ("skip", "skip"), ("quit", "quit")):
            t = threading.Thread(target=lambda: answers.append(mover.reach(4, (1.0, 2.0, 0.5), "stop 5/9")))
            t.start()
            for _ in range(100):
                st = _ask(ctx, ep, b'{"cmd": "status"}')
                if st["waiting"]:
                    break
            assert st["stop"] == 4 and st["pose"] == [1.0, 2.0, 0.5] and st["label"] == "stop 5/9"
            assert _ask(ctx, ep, json.dumps({"cmd": cmd}).encode())["ok"] is True
            t.join(5)
            assert answers[-1] == expected
        assert _ask(ctx, ep, b'{"cmd": "status"}')["waiting"] is False
    finally:
        mover.close()
        ctx.term()


def test_a_stop_answered_is_not_waiting_before_the_survey_takes_the_answer():
    # between the answer and the survey's thread taking it, status must not offer the stop again
    # (an operator polling status would confirm it twice and be refused)
    ctx = zmq.Context()
    mover = ControlMover("tcp://127.0.0.1:*", ctx)
    try:
        with mover._cond:  # what reach() does first; no thread takes the answer here
            mover._waiting = {"stop": 2, "pose": [1.0, 2.0, 0.5], "label": "stop 3/4"}
        assert _ask(ctx, mover.endpoint, b'{"cmd": "status"}')["waiting"] is True
        assert _ask(ctx, mover.endpoint, b'{"cmd": "confirm"}')["ok"] is True
        st = _ask(ctx, mover.endpoint, b'{"cmd": "status"}')
        assert st["waiting"] is False and "stop" not in st
        assert _ask(ctx, mover.endpoint, b'{"cmd": "confirm"}')["ok"] is False
    finally:
        mover.close()
        ctx.term()


def test_control_refuses_a_network_endpoint():
    with pytest.raises(LinoLocError, match="not a loopback endpoint"):
        check_local("tcp://0.0.0.0:5570")
    assert check_local("ipc:///tmp/x") == "ipc:///tmp/x"


def test_prompt_reads_the_operators_answers(tmp_path):
    import io

    out = io.StringIO()
    mover = PromptMover(io.StringIO("huh\n\ns\nq\n"), out)
    assert [mover.reach(0, (1.0, 2.0, 0.0), "stop 1/2") for _ in range(3)] == ["ok", "skip", "quit"]
    assert "not understood" in out.getvalue() and "x=1.000 m" in out.getvalue()
    assert mover.reach(1, (0, 0, 0), "stop 2/2") == "quit"  # end of input: nobody to confirm

"""`lino-loc echo` against a real PUB socket on 127.0.0.1 (random free port)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zmq

from services import cli
from services import messages as m
from services.commands import echo
from services.schemas import EXAMPLES

ROOT = Path(__file__).resolve().parents[1]


class Publisher:
    """Publishes pose, status and a foreign 'poses' topic every few ms until stopped.

    Publishing continuously sidesteps the slow-joiner effect: whatever the subscriber misses
    before its subscription arrives, later messages reach it.
    """

    def __init__(self, publish: bool = True) -> None:
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.PUB)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.bind("tcp://127.0.0.1:*")
        self.endpoint = self.sock.getsockopt(zmq.LAST_ENDPOINT).decode()
        self.stop = threading.Event()
        self.sent = 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        if publish:
            self.thread.start()

    def _run(self) -> None:
        status = m.StatusMessage.model_validate(EXAMPLES["status"][0])
        seq = 0
        while not self.stop.is_set():
            pose = m.PoseMessage.model_validate({**EXAMPLES["pose"][0], "seq": seq, "stamp": time.time()})
            self.sock.send_multipart(m.encode("pose", pose))
            self.sock.send_multipart(m.encode("status", status))
            self.sock.send_multipart([b"poses", b"{}"])  # shares the prefix of "pose"
            self.sock.send_multipart([b"pose"])  # malformed: one frame
            seq += 1
            self.sent = seq
            time.sleep(0.005)

    def close(self) -> None:
        self.stop.set()
        if self.thread.is_alive():
            self.thread.join(2.0)
        self.sock.close(linger=0)
        self.ctx.term()


@pytest.fixture
def publisher():
    p = Publisher()
    yield p
    p.close()


def _run(argv: list[str]) -> int:
    import argparse

    parser = argparse.ArgumentParser()
    echo.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["echo", *argv])
    return args.func(args)


def test_registered_in_cli():
    assert "services.commands.echo" in cli.COMMAND_MODULES
    assert "services.commands.config_cmd" in cli.COMMAND_MODULES


def test_prints_count_pose_lines_only(publisher, capsys):
    t0 = time.monotonic()
    assert _run(["--endpoint", publisher.endpoint, "--count", "5", "--timeout", "5", "--validate"]) == 0
    assert time.monotonic() - t0 < 5
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert len(lines) == 5
    seqs = []
    for line in lines:
        topic, payload = line.split(" ", 1)
        assert topic == "pose"  # not "status", not "poses"
        msg = m.PoseMessage.model_validate_json(payload)
        seqs.append(msg.seq)
    assert seqs == sorted(seqs) and len(set(seqs)) == 5
    assert "invalid message" not in captured.err
    assert "skipping a 1-frame message" in captured.err  # said once, not per message
    assert captured.err.count("skipping") == 1


def test_several_topics_and_json_output(publisher, capsys):
    assert _run(["--endpoint", publisher.endpoint, "--topic", "status", "--topic", "pose",
                 "--count", "6", "--timeout", "5", "--json"]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1
    obj = json.loads(out)
    assert obj["count"] == 6 and obj["endpoint"] == publisher.endpoint
    assert obj["topics"] == ["status", "pose"]
    topics = {msg["topic"] for msg in obj["messages"]}
    assert topics == {"pose", "status"}
    for msg in obj["messages"]:
        m.TOPICS[msg["topic"]].model_validate(msg["payload"])


def test_timeout_exits_1_with_a_message(capsys):
    quiet = Publisher(publish=False)
    try:
        t0 = time.monotonic()
        assert _run(["--endpoint", quiet.endpoint, "--timeout", "0.3"]) == 1
        elapsed = time.monotonic() - t0
    finally:
        quiet.close()
    assert 0.25 < elapsed < 3.0
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "no pose message on" in captured.err and quiet.endpoint in captured.err


def test_bad_endpoint_is_a_usage_error(capsys):
    assert _run(["--endpoint", "nonsense", "--timeout", "0.1"]) == 2
    assert "cannot connect" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["--count", "0"], ["--timeout", "-1"], ["--topic", "poses"]])
def test_argument_validation(argv):
    with pytest.raises(SystemExit) as info:
        _run(argv)
    assert info.value.code == 2


def _default_sigint() -> None:
    """Ctrl-C as at a terminal. A test run started in the background by a non-interactive
    shell (`./scripts/test.sh &`) inherits SIGINT ignored, its children too, and Python then
    (rightly) installs no KeyboardInterrupt handler: echo would ignore the SIGINT."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_is_quiet(publisher):
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONFAULTHANDLER": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.commands.echo", "--endpoint", publisher.endpoint],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
        preexec_fn=_default_sigint,  # noqa: PLW1509 - one signal() call between fork and exec
    )
    try:
        first = proc.stdout.readline()  # blocks until the stream flows
        assert first.startswith(b"pose {"), first
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            running = proc.poll() is None
            proc.send_signal(signal.SIGABRT)  # faulthandler: every thread's stack on stderr
            _, err = proc.communicate(timeout=10)
            pytest.fail(f"echo did not stop 10 s after SIGINT (still running: {running}); stderr:\n"
                        + err.decode(errors="replace")[-4000:])
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0
    assert b"Traceback" not in err and b"KeyboardInterrupt" not in err
    assert all(line.startswith(b"pose {") for line in out.splitlines()[:-1])


def test_closed_pipe_is_quiet(publisher):
    """`lino-loc echo | head -2`: the reader leaves; echo stops without a traceback."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.commands.echo", "--endpoint", publisher.endpoint, "--timeout", "5"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    try:
        proc.stdout.readline()
        proc.stdout.close()  # the reader goes away
        _, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert b"Traceback" not in err

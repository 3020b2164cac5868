"""How the robot of a survey gets to each stop, and who says it is there.

A mover's ``reach(stop_index, pose, label) -> "ok" | "skip" | "quit"`` returns once the robot
stands at ``pose`` (x, y, theta: the stop's position, facing the stop's heading plus the base
turn of the captures to come), ``"skip"`` when this stop is to be left out, ``"quit"`` when
the survey is to end now (what was captured is kept; a new run continues).

- :class:`SimMover`: the simulated robot drives there itself: a ``goto`` request on the
  control socket of `lino-loc sim` (:mod:`drivers.sim.fault_control`), then ``where`` every
  0.1 s until the state is ``arrived`` (ok), ``blocked`` or the goal is refused (skip, with a
  warning), or ``timeout`` s pass (skip).
- :class:`PromptMover`: the operator drives the robot and confirms at the terminal: one line
  naming the stop and the pose, then Enter (ok), ``s`` (skip) or ``q`` (quit).
- :class:`ControlMover`: the operator (or a program) confirms by a request on a ZeroMQ REP
  socket, one JSON object per request and per reply::

      {"cmd": "status"}    -> {"ok": true, "waiting": true, "stop": 3, "pose": [x, y, theta], "stops_done": 3, ...}
      {"cmd": "confirm"}   -> the robot is at the pose: capture (ok)
      {"cmd": "skip"}      -> leave this stop out
      {"cmd": "quit"}      -> end the survey now
      anything else        -> {"ok": false, "error": "<one line>"}, nothing changes

  ``confirm``, ``skip`` and ``quit`` while no stop is waiting get ``{"ok": false, ...}``; a
  stop is waiting from the moment it is offered until it is answered (not until the survey
  has captured it), so a client polling ``status`` never answers one stop twice.
  The socket binds to a loopback endpoint unless told otherwise (it has no authentication).
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from typing import Any, Protocol, TextIO

from lino_loc.errors import LinoLocError
from services.curve_auth import is_loopback

log = logging.getLogger("lino_loc.survey")

Pose = tuple[float, float, float]


class Mover(Protocol):
    def reach(self, stop_index: int, pose: Pose, label: str) -> str: ...

    def close(self) -> None: ...


class SimMover:
    """Drive the simulated robot with ``goto`` / ``where`` (see the module docstring)."""

    def __init__(self, endpoint: str, context: Any, speed: float | None = None, timeout: float = 120.0) -> None:
        self.endpoint = endpoint
        self.speed = speed
        self.timeout = timeout
        self._ctx = context
        self._sock: Any = None
        self.driven_s = 0.0

    def _request(self, req: dict[str, Any], timeout: float = 5.0) -> dict[str, Any]:
        import zmq

        if self._sock is None:
            self._sock = self._ctx.socket(zmq.REQ)
            self._sock.setsockopt(zmq.LINGER, 0)
            self._sock.connect(self.endpoint)
        self._sock.send(json.dumps(req).encode())
        if not self._sock.poll(int(timeout * 1000)):
            self._sock.close(0)
            self._sock = None
            raise LinoLocError(f"the simulator's control {self.endpoint} did not answer {req['cmd']!r} "
                               f"within {timeout:g} s")
        return json.loads(self._sock.recv())

    def where(self) -> dict[str, Any]:
        return self._request({"cmd": "where"})

    def reach(self, stop_index: int, pose: Pose, label: str) -> str:
        t0 = time.monotonic()
        req: dict[str, Any] = {"cmd": "goto", "x": pose[0], "y": pose[1], "theta": pose[2]}
        if self.speed is not None:
            req["speed"] = self.speed
        reply = self._request(req)
        if not reply.get("ok"):
            log.warning("%s: the simulated robot cannot go to (%.2f, %.2f): %s; stop skipped",
                        label, pose[0], pose[1], reply.get("error"))
            return "skip"
        while time.monotonic() - t0 < self.timeout:
            time.sleep(0.1)
            state = self.where().get("state")
            if state == "arrived":
                self.driven_s += time.monotonic() - t0
                return "ok"
            if state != "driving":
                log.warning("%s: the simulated robot stopped on its way (%s); stop skipped", label, state)
                return "skip"
        log.warning("%s: the simulated robot did not arrive within %g s; stop skipped", label, self.timeout)
        return "skip"

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close(0)
            self._sock = None


class PromptMover:
    """Ask the operator at the terminal (see the module docstring)."""

    def __init__(self, stdin: TextIO | None = None, stdout: TextIO | None = None) -> None:
        self.stdin = stdin or sys.stdin
        self.stdout = stdout or sys.stderr

    def reach(self, stop_index: int, pose: Pose, label: str) -> str:
        import math

        while True:
            self.stdout.write(
                f"\n{label}: put the robot at x={pose[0]:.3f} m, y={pose[1]:.3f} m, facing "
                f"{math.degrees(pose[2]):.1f} deg; then Enter (s = skip this stop, q = quit): "
            )
            self.stdout.flush()
            line = self.stdin.readline()
            if not line:  # end of input: nobody to confirm
                return "quit"
            answer = line.strip().lower()
            if answer in ("", "y", "yes", "ok"):
                return "ok"
            if answer in ("s", "skip"):
                return "skip"
            if answer in ("q", "quit"):
                return "quit"
            self.stdout.write(f"  not understood: {answer!r}\n")

    def close(self) -> None:
        pass


def check_local(endpoint: str) -> str:
    """``endpoint`` if it is loopback / ipc / inproc (the control has no authentication)."""
    if is_loopback(endpoint):
        return endpoint
    raise LinoLocError(f"--control {endpoint!r}: not a loopback endpoint (tcp://127.0.0.1:PORT or ipc://PATH): "
                       "the survey's control has no authentication")


class ControlMover:
    """Confirmations by requests on a REP socket served by a thread (module docstring)."""

    ANSWERS = ("confirm", "skip", "quit")

    def __init__(self, endpoint: str, context: Any, progress: Any = None) -> None:
        import zmq

        from drivers.sim.robot import bind

        sock = context.socket(zmq.REP)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.MAXMSGSIZE, 65536)
        self.endpoint = bind(sock, check_local(endpoint))
        self._sock = sock
        self._cond = threading.Condition()
        self._waiting: dict[str, Any] | None = None
        self._answer: str | None = None
        self._stop = threading.Event()
        self.progress = progress  # () -> dict: done/left, for status replies
        self._thread = threading.Thread(target=self._serve, name="survey-control", daemon=True)
        self._thread.start()

    def _reply(self, raw: bytes) -> dict[str, Any]:
        try:
            req = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            return {"ok": False, "error": "request is not UTF-8 JSON"}
        if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
            return {"ok": False, "error": "request must be a JSON object with a string 'cmd'"}
        cmd = req["cmd"]
        with self._cond:
            if cmd == "status":
                # a stop already answered is not waiting, even before the survey has taken the answer
                waiting = self._waiting is not None and self._answer is None
                out: dict[str, Any] = {"ok": True, "cmd": "status", "waiting": waiting}
                if waiting:
                    out.update(self._waiting)
                if self.progress is not None:
                    out.update(self.progress())
                return out
            if cmd in self.ANSWERS:
                if self._waiting is None or self._answer is not None:
                    return {"ok": False, "error": f"{cmd}: no stop is waiting for a confirmation"}
                self._answer = cmd
                self._cond.notify_all()
                return {"ok": True, "cmd": cmd, "stop": self._waiting["stop"]}
        return {"ok": False, "error": f"cmd: must be one of status, {', '.join(self.ANSWERS)}, got {cmd[:40]!r}"}

    def _serve(self) -> None:
        import zmq

        while not self._stop.is_set():
            try:
                if not self._sock.poll(100):
                    continue
                frames = self._sock.recv_multipart()
                reply = self._reply(frames[0]) if len(frames) == 1 else {
                    "ok": False, "error": f"request must be one frame, got {len(frames)}"}
                self._sock.send(json.dumps(reply).encode())
            except zmq.ZMQError as exc:
                if self._stop.is_set():
                    return
                log.warning("survey control: %s", exc)
            except Exception:  # noqa: BLE001 - the control never dies on a request
                log.exception("survey control: request failed")

    def reach(self, stop_index: int, pose: Pose, label: str) -> str:
        with self._cond:
            self._waiting = {"stop": stop_index, "pose": list(pose), "label": label}
            self._answer = None
        log.info("%s: waiting for a confirmation on %s ({\"cmd\": \"confirm\"}) with the robot at "
                 "(%.3f, %.3f, %.3f)", label, self.endpoint, *pose)
        with self._cond:
            while self._answer is None and not self._stop.is_set():
                self._cond.wait(0.2)
            answer, self._waiting, self._answer = self._answer, None, None
        return {"confirm": "ok", "skip": "skip", None: "quit"}.get(answer, answer or "quit")

    def close(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._thread.join(timeout=2.0)
        self._sock.close(0)

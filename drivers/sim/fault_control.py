"""Fault control of the simulated robot: inject the emulators' faults from outside, for a while.

``lino-loc sim`` serves it on a ZeroMQ REP socket bound to a loopback endpoint (the ``faults``
key of its first output line; the control has no authentication, so :func:`check_loopback`
refuses any other address). One request is one JSON object, one reply is one JSON object;
a request that is not valid gets ``{"ok": false, "error": "<one line>"}`` and changes nothing,
and nothing a client sends stops the simulator.

Requests (:func:`parse_request`; every field other than ``cmd`` and ``fault`` is optional)::

    {"cmd": "inject", "fault": NAME, "duration_s": 2.0, ...}   the fault for duration_s seconds
    {"cmd": "clear"}                    end every active fault now ("fault": NAME: that one)
    {"cmd": "status"}                   the active faults and the seconds left of each
    {"cmd": "lights", "lighting": "bulb"}   switch the building's lights (as SIGUSR2)
    {"cmd": "goto", "x": 1.0, "y": 0.5, "theta": 0.0}   drive the base there (path through free
                                        space; ``speed`` m/s optional), then stand still
    {"cmd": "where"}                    the true pose now, and the goto's goal and state
                                        (``idle``, ``wandering``, ``driving``, ``arrived``, ``blocked``)
    {"cmd": "ping"}

Faults (``duration_s`` in (0, 600] s, default 2; ``fraction`` in (0, 1], default 1: the share
of packets, lines or frames the fault hits while it is active):

| ``fault`` | what the device does | parameters |
|---|---|---|
| ``head_no_reply`` | the servos stay silent: the adapter times out | ``servo``: pan, tilt, both |
| ``head_crc`` | status packets with a wrong CRC | ``fraction`` |
| ``head_hardware_error`` | Hardware Error Status bits and torque off until the servo is rebooted; with ``persistent``, raised again after every reboot until the fault ends | ``servo``: pan, tilt; ``bits`` (default 0x20, overload); ``persistent`` (default false) |
| ``head_unplug`` | the bus adapter vanishes, then comes back on a new pty behind the same link (needs ``devices.head.port`` set in the simulator's configuration) | |
| ``odometry_crc`` | lines with a digit changed after their checksum | ``fraction`` |
| ``odometry_garbage`` | random bytes before lines | ``fraction``, ``bytes`` (1-120, default 16) |
| ``odometry_drop`` | lines not sent (sequence numbers still advance) | ``fraction`` |
| ``odometry_split`` | lines written in two pieces | ``fraction`` |
| ``odometry_unplug`` | the board vanishes, then comes back behind the same link | |
| ``camera_stall`` | no frames (the socket stays bound) | |
| ``camera_unplug`` | the frame socket closed, bound again at the end (sequence from 0) | |
| ``camera_malformed`` | messages that are not valid frames instead of frames | ``fraction`` |

Injecting a fault that is active replaces it (new parameters, new end; a port that is out
stays out). Replies: ``{"ok": true, "cmd": ..., "active": {NAME: seconds_left}}`` plus
``"fault"`` and ``"until"`` (s since the epoch) for ``inject``, ``"cleared"`` for ``clear``.

Usage::

    control = FaultController(robot)
    server = FaultServer(control, zmq_context, "tcp://127.0.0.1:*"); endpoint = server.start()
    ...; server.stop(); control.clear()
"""

from __future__ import annotations

import ipaddress
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import zmq
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from drivers.sim.robot import bind
from lino_loc.errors import LinoLocError

log = logging.getLogger("lino_loc.drivers.sim_faults")

#: Longest fault a request may ask for, s.
MAX_DURATION_S = 600.0
#: Largest request accepted, bytes (ZMQ_MAXMSGSIZE of the socket: a client cannot make the
#: simulator allocate more than this for one message).
MAX_REQUEST_BYTES = 65536
#: Default Hardware Error Status bits of ``head_hardware_error``: bit 5, overload.
OVERLOAD_BIT = 0x20


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class _Inject(_Request):
    cmd: Literal["inject"]
    duration_s: float = Field(2.0, gt=0.0, le=MAX_DURATION_S, allow_inf_nan=False)


class _Fraction(_Inject):
    fraction: float = Field(1.0, gt=0.0, le=1.0, allow_inf_nan=False)


class HeadNoReply(_Inject):
    fault: Literal["head_no_reply"]
    servo: Literal["pan", "tilt", "both"] = "both"


class HeadCrc(_Fraction):
    fault: Literal["head_crc"]


class HeadHardwareError(_Inject):
    fault: Literal["head_hardware_error"]
    servo: Literal["pan", "tilt"] = "pan"
    bits: int = Field(OVERLOAD_BIT, ge=1, le=255)
    persistent: bool = Field(False, description="raised again after every reboot until the fault ends")


class HeadUnplug(_Inject):
    fault: Literal["head_unplug"]


class OdometryCrc(_Fraction):
    fault: Literal["odometry_crc"]


class OdometryGarbage(_Fraction):
    fault: Literal["odometry_garbage"]
    bytes: int = Field(16, ge=1, le=120)


class OdometryDrop(_Fraction):
    fault: Literal["odometry_drop"]


class OdometrySplit(_Fraction):
    fault: Literal["odometry_split"]


class OdometryUnplug(_Inject):
    fault: Literal["odometry_unplug"]


class CameraStall(_Inject):
    fault: Literal["camera_stall"]


class CameraUnplug(_Inject):
    fault: Literal["camera_unplug"]


class CameraMalformed(_Fraction):
    fault: Literal["camera_malformed"]


FAULT_MODELS: dict[str, type[_Inject]] = {
    m.model_fields["fault"].annotation.__args__[0]: m  # type: ignore[union-attr]
    for m in (HeadNoReply, HeadCrc, HeadHardwareError, HeadUnplug, OdometryCrc, OdometryGarbage,
              OdometryDrop, OdometrySplit, OdometryUnplug, CameraStall, CameraUnplug, CameraMalformed)
}
FAULTS = tuple(FAULT_MODELS)
FaultName = Literal[
    "head_no_reply", "head_crc", "head_hardware_error", "head_unplug", "odometry_crc",
    "odometry_garbage", "odometry_drop", "odometry_split", "odometry_unplug", "camera_stall",
    "camera_unplug", "camera_malformed",
]


class Clear(_Request):
    cmd: Literal["clear"]
    fault: FaultName | None = None


class Status(_Request):
    cmd: Literal["status"]


class Ping(_Request):
    cmd: Literal["ping"]


class Lights(_Request):
    cmd: Literal["lights"]
    lighting: str = Field(min_length=1, max_length=64)


class Goto(_Request):
    cmd: Literal["goto"]
    x: float = Field(allow_inf_nan=False, description="m, map frame")
    y: float = Field(allow_inf_nan=False, description="m, map frame")
    theta: float = Field(0.0, allow_inf_nan=False, description="rad")
    speed: float | None = Field(None, gt=0.0, le=2.0, allow_inf_nan=False, description="top speed, m/s")


class Where(_Request):
    cmd: Literal["where"]


_COMMANDS: dict[str, type[_Request]] = {"clear": Clear, "status": Status, "ping": Ping, "lights": Lights,
                                        "goto": Goto, "where": Where}
Request = _Inject | Clear | Status | Ping | Lights | Goto | Where


#: The odometry faults that are line faults of the board emulator, and their kind there.
_ODOMETRY_KINDS = {"odometry_crc": "corrupt", "odometry_garbage": "garbage", "odometry_drop": "drop",
                   "odometry_split": "split"}


class RequestError(ValueError):
    """A request that is not valid; the message is one line naming the field or value."""


def parse_request(raw: bytes) -> Request:
    """The validated request in ``raw`` (UTF-8 JSON). Raises :class:`RequestError`."""
    try:
        obj = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise RequestError("request is not UTF-8") from None
    except (json.JSONDecodeError, RecursionError) as exc:
        raise RequestError(f"request is not JSON: {getattr(exc, 'msg', exc)}") from None
    if not isinstance(obj, dict):
        raise RequestError("request must be a JSON object")
    cmd = obj.get("cmd")
    names = ", ".join(["inject", *_COMMANDS])
    if not isinstance(cmd, str) or (cmd != "inject" and cmd not in _COMMANDS):
        raise RequestError(f"cmd: must be one of {names}, got {_short(cmd)}")
    if cmd == "inject":
        fault = obj.get("fault")
        if not isinstance(fault, str) or fault not in FAULT_MODELS:
            raise RequestError(f"fault: must be one of {', '.join(FAULTS)}, got {_short(fault)}")
        model: type[_Request] = FAULT_MODELS[fault]
    else:
        model = _COMMANDS[cmd]
    try:
        return model.model_validate(obj)  # type: ignore[return-value]
    except ValidationError as exc:
        e = exc.errors(include_url=False)[0]
        where = ".".join(str(p) for p in e["loc"]) or "request"
        raise RequestError(f"{cmd}: {where}: {e['msg']}") from None


def _short(v: object) -> str:
    text = json.dumps(v) if isinstance(v, (str, int, float, bool, type(None))) else type(v).__name__
    return text if len(text) <= 40 else text[:37] + "..."


def check_loopback(endpoint: str) -> str:
    """``endpoint`` if it is local to this machine (``tcp://`` on a loopback address or
    ``localhost``, ``ipc://``, ``inproc://``); else LinoLocError: the control is unauthenticated."""
    if endpoint.startswith(("ipc://", "inproc://")):
        return endpoint
    if endpoint.startswith("tcp://"):
        host = endpoint[len("tcp://"):].rsplit(":", 1)[0].strip("[]")
        try:
            if host == "localhost" or ipaddress.ip_address(host).is_loopback:
                return endpoint
        except ValueError:
            pass
    raise LinoLocError(
        f"fault control: {endpoint!r} is not a loopback endpoint (tcp://127.0.0.1:PORT or ipc://PATH): "
        "it has no authentication"
    )


@dataclass
class _Active:
    until_mono: float
    until_stamp: float
    undo: Callable[[], None]


class FaultController:
    """Applies the faults to a :class:`drivers.sim.robot.SimRobot` and ends them on time.

    Thread-safe. :meth:`expire` must be called often (the server does, every 50 ms at most);
    ``lights`` switches the building's lights (None: ``lights`` requests are refused)."""

    def __init__(self, robot: Any, lights: Callable[[str], None] | None = None) -> None:
        self.robot = robot
        self.lights = lights
        self._lock = threading.RLock()
        self._active: dict[str, _Active] = {}
        self.injected: dict[str, int] = {}

    def handle(self, req: Request) -> dict[str, Any]:
        """Carry out a validated request; its reply. Raises RequestError when the robot cannot
        (a head without a stable link, an unknown lighting)."""
        if isinstance(req, _Inject):
            return self.inject(req)
        if isinstance(req, Clear):
            cleared = self.clear(req.fault)
            return {"ok": True, "cmd": "clear", "cleared": cleared, "active": self.active()}
        if isinstance(req, Lights):
            if self.lights is None:
                raise RequestError("lights: this simulator cannot switch its lights")
            try:
                self.robot.world.check_lighting(req.lighting)
            except LinoLocError as exc:
                raise RequestError(f"lights: lighting: {exc}") from None
            self.lights(req.lighting)
            return {"ok": True, "cmd": "lights", "lighting": req.lighting}
        if isinstance(req, Goto):
            goto = getattr(self.robot, "goto", None)
            if goto is None:
                raise RequestError("goto: this simulator cannot drive its base to a pose")
            try:
                plan = goto(req.x, req.y, req.theta, req.speed)
            except LinoLocError as exc:
                raise RequestError(str(exc)) from None
            return {"ok": True, "cmd": "goto", "goal": list(plan.goal), "waypoints": len(plan.waypoints)}
        if isinstance(req, Where):
            where = getattr(self.robot, "where", None)
            if where is None:
                raise RequestError("where: this simulator does not report its pose")
            return {"ok": True, "cmd": "where", **where()}
        return {"ok": True, "cmd": req.cmd, "active": self.active()}  # type: ignore[union-attr]

    def inject(self, req: _Inject) -> dict[str, Any]:
        name: str = req.fault  # type: ignore[attr-defined]
        if name == "head_unplug" and not getattr(self.robot.config, "head_link", None):
            raise RequestError("inject: head_unplug needs a stable head link (devices.head.port in the "
                               "simulator's configuration): without one the adapter cannot find the bus again")
        with self._lock:
            old = self._active.pop(name, None)
            keep_out = old is not None and name.endswith("_unplug")
            if old is not None and not keep_out:
                old.undo()
            undo = self._undo_of(req) if keep_out else self._apply(req)
            until = time.monotonic() + req.duration_s
            stamp = time.time() + req.duration_s
            self._active[name] = _Active(until, stamp, undo)
            self.injected[name] = self.injected.get(name, 0) + 1
        log.warning("sim: fault %s for %g s (%s)", name, req.duration_s, req.model_dump_json(exclude={"cmd", "fault"}))
        return {"ok": True, "cmd": "inject", "fault": name, "until": round(stamp, 3), "active": self.active()}

    def _servo_ids(self, servo: str) -> list[int]:
        c = self.robot.config
        return {"pan": [c.pan_id], "tilt": [c.tilt_id], "both": [c.pan_id, c.tilt_id]}[servo]

    def _undo_of(self, req: _Inject) -> Callable[[], None]:
        """What ends the fault of ``req`` (without applying it)."""
        robot, head, odo = self.robot, self.robot.head, self.robot.odometry
        name: str = req.fault  # type: ignore[attr-defined]

        def undo() -> None:
            if isinstance(req, HeadNoReply):
                for i in self._servo_ids(req.servo):
                    head.set_no_reply(i, False)
            elif isinstance(req, HeadHardwareError):
                head.clear_hardware_error(self._servo_ids(req.servo)[0])
            elif name == "head_crc":
                head.set_corruption_rate(0.0)
            elif name == "head_unplug":
                head.reconnect()
            elif name in _ODOMETRY_KINDS:
                odo.set_fault_rate(_ODOMETRY_KINDS[name], 0.0)
            elif name == "odometry_unplug":
                odo.reconnect()
            else:
                robot.set_camera_fault(name.removeprefix("camera_"), False)

        return undo

    def _apply(self, req: _Inject) -> Callable[[], None]:
        """Start the fault of ``req``; returns what ends it."""
        head, odo = self.robot.head, self.robot.odometry
        if isinstance(req, HeadNoReply):
            for i in self._servo_ids(req.servo):
                head.set_no_reply(i, True)
        elif isinstance(req, HeadCrc):
            head.set_corruption_rate(req.fraction)
        elif isinstance(req, HeadHardwareError):
            head.set_hardware_error(self._servo_ids(req.servo)[0], req.bits, persistent=req.persistent)
        elif isinstance(req, HeadUnplug):
            head.disconnect()
        elif isinstance(req, OdometryGarbage):
            odo.set_fault_rate("garbage", req.fraction, req.bytes)
        elif isinstance(req, (OdometryCrc, OdometryDrop, OdometrySplit)):
            odo.set_fault_rate(_ODOMETRY_KINDS[req.fault], req.fraction)
        elif isinstance(req, OdometryUnplug):
            odo.disconnect()
        else:
            fraction = req.fraction if isinstance(req, CameraMalformed) else 1.0
            self.robot.set_camera_fault(req.fault.removeprefix("camera_"), True, fraction)  # type: ignore[attr-defined]
        return self._undo_of(req)

    def clear(self, name: str | None = None) -> list[str]:
        """End the fault ``name`` (None: all) now; the names ended."""
        with self._lock:
            names = [n for n in self._active if name is None or n == name]
            for n in names:
                self._end(n)
        return names

    def expire(self, now: float | None = None) -> None:
        """End the faults whose time is up."""
        now = time.monotonic() if now is None else now
        with self._lock:
            for n in [n for n, a in self._active.items() if a.until_mono <= now]:
                self._end(n)

    def _end(self, name: str) -> None:
        a = self._active.pop(name)
        try:
            a.undo()
        except Exception:  # noqa: BLE001 - ending a fault must never stop the simulator
            log.exception("sim: ending fault %s failed", name)
        log.warning("sim: fault %s ended", name)

    def next_deadline(self) -> float | None:
        """Monotonic time of the next fault end (None: no fault active)."""
        with self._lock:
            return min((a.until_mono for a in self._active.values()), default=None)

    def active(self) -> dict[str, float]:
        """Active faults and the seconds left of each."""
        now = time.monotonic()
        with self._lock:
            return {n: round(max(0.0, a.until_mono - now), 3) for n, a in self._active.items()}


def respond(controller: FaultController, frames: list[bytes]) -> dict[str, Any]:
    """The reply to one received message (never raises)."""
    try:
        if len(frames) != 1:
            raise RequestError(f"request must be one frame, got {len(frames)}")
        return controller.handle(parse_request(frames[0]))
    except RequestError as exc:
        return {"ok": False, "error": str(exc)}
    except Exception as exc:  # noqa: BLE001 - a bug here must not stop the simulator
        log.exception("sim: fault request failed")
        return {"ok": False, "error": f"internal error: {type(exc).__name__}: {exc}".splitlines()[0]}


class FaultServer:
    """The REP socket of the fault control, served by a thread; ends faults on time."""

    def __init__(self, controller: FaultController, context: zmq.Context, endpoint: str) -> None:
        self.controller = controller
        self._ctx = context
        self.endpoint = check_loopback(endpoint)
        self._sock: zmq.Socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> str:
        """Bind (raises LinoLocError naming the endpoint) and serve; returns the bound endpoint."""
        sock = self._ctx.socket(zmq.REP)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_REQUEST_BYTES)
        try:
            self.endpoint = bind(sock, self.endpoint)
        except LinoLocError:
            sock.close(0)
            raise
        self._sock = sock
        self._thread = threading.Thread(target=self._serve, name="sim-faults", daemon=True)
        self._thread.start()
        return self.endpoint

    def _serve(self) -> None:
        sock = self._sock
        assert sock is not None
        while not self._stop.is_set():
            self.controller.expire()
            nxt = self.controller.next_deadline()
            wait = 50 if nxt is None else max(1, min(50, int((nxt - time.monotonic()) * 1000) + 1))
            try:
                if not sock.poll(wait):
                    continue
                frames = sock.recv_multipart()
                reply = respond(self.controller, frames)
                sock.send(json.dumps(reply).encode())
            except zmq.ZMQError as exc:
                if self._stop.is_set():
                    return
                log.warning("sim: fault control socket: %s", exc)

    def stop(self) -> None:
        """Stop serving and close the socket (active faults stay: clear them with the controller)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._sock is not None:
            self._sock.close(0)
            self._sock = None

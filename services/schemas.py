"""JSON Schemas of everything on the ZeroMQ wire, exported to ``schemas/<name>.json``.

``python -m services.schemas [DIR]`` regenerates the files (default: ``schemas/`` of the
project); ``tests/test_schemas.py`` fails when the committed files differ from the models
in :mod:`services.messages`, and validates :data:`EXAMPLES` against both.

Published messages and replies are described as the daemon *sends* them (serialization
mode: every field present); requests as the daemon *accepts* them (validation mode:
optional fields may be left out). Each schema has ``$id``
``urn:lino-loc:schema:<name>:v<PROTOCOL_VERSION>``; see :mod:`services.messages` for the
versioning rules.

Usage::

    from services.schemas import schema_for, export, SCHEMAS
    schema_for("pose")["$id"]        # 'urn:lino-loc:schema:pose:v1'
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, TypeAdapter

from services import messages as m

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

#: The project's schemas/ folder (where the committed files live).
SCHEMA_DIR = Path(__file__).resolve().parents[1] / "schemas"

#: name -> (model or type, mode, description)
SCHEMAS: dict[str, tuple[Any, Literal["validation", "serialization"], str]] = {
    "pose": (m.PoseMessage, "serialization", "PUB topic `pose`: the estimated pose after each update"),
    "truth": (m.TruthMessage, "serialization", "PUB topic `truth` (simulation): the true pose"),
    "status": (m.StatusMessage, "serialization", "PUB topic `status` (1 Hz) and the status reply"),
    "particles": (m.ParticlesMessage, "serialization", "PUB topic `particles` (throttled)"),
    "request": (m.Request, "validation", "REP socket: a control request, discriminated by `cmd`"),
    "reply": (m.Reply, "serialization", "REP socket: the reply to a control request"),
}


def schema_id(name: str) -> str:
    return f"urn:lino-loc:schema:{name}:v{m.PROTOCOL_VERSION}"


def schema_for(name: str) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of one wire message."""
    obj, mode, description = SCHEMAS[name]
    if isinstance(obj, type) and issubclass(obj, BaseModel):
        body = obj.model_json_schema(mode=mode)
    else:
        body = TypeAdapter(obj).json_schema(mode=mode)
    head = {
        "$schema": JSON_SCHEMA_DIALECT,
        "$id": schema_id(name),
        "title": body.pop("title", name),
        "description": description,
        "x-protocol-version": m.PROTOCOL_VERSION,
    }
    if "description" in body:
        head["x-model-description"] = " ".join(body.pop("description").split())
    return {**head, **body}


def render(name: str) -> str:
    """The file content of ``schemas/<name>.json``."""
    return json.dumps(schema_for(name), indent=2, ensure_ascii=False) + "\n"


def export(directory: str | Path = SCHEMA_DIR) -> list[Path]:
    """Write every schema to ``directory/<name>.json``; returns the paths written."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    written = []
    for name in SCHEMAS:
        path = d / f"{name}.json"
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(render(name), encoding="utf-8")
        tmp.replace(path)
        written.append(path)
    return written


# --------------------------------------------------------------------------------------------
# Examples (docs/zeromq.md shows them; tests validate them against models and schemas)
# --------------------------------------------------------------------------------------------

_COV = [0.0121, 0.0008, 0.0, 0.0008, 0.0144, 0.0, 0.0, 0.0, 0.0036]

EXAMPLES: dict[str, list[dict[str, Any]]] = {
    "pose": [
        {
            "v": 1, "stamp": 1763767825.412, "frame_id": "map", "seq": 1832,
            "pose": {"x": 3.412, "y": 1.105, "theta": 1.571},
            "covariance": _COV, "state": "tracking", "pan": -0.524, "ess": 612.4,
            "n_particles": 1000, "dead_reckoning": False, "latency_ms": 21.7, "quality": 0.87,
        },
    ],
    "truth": [
        {"v": 1, "stamp": 1763767825.412, "frame_id": "map", "seq": 1832,
         "pose": {"x": 3.38, "y": 1.12, "theta": 1.56}, "pan": -0.52},
    ],
    "status": [
        {
            "v": 1, "stamp": 1763767826.0, "state": "tracking", "pose_rate_hz": 14.9,
            "frame_rate_hz": 15.0, "frames": 27510, "dropped_frames": 12, "out_of_order_frames": 0,
            "appearance_changes": 0, "update_errors": 0, "standing_matches": 4, "standing_relocations": 1,
            "latency_ms": {"p50": 21.3, "p99": 48.0},
            "devices": {
                "camera": {"state": "ok", "error": None, "error_stamp": None, "counters": {"frames": 27510}},
                "head": {"state": "degraded", "error": "servo 2: no status packet (timeout)",
                         "error_stamp": 1763767811.2, "counters": {"timeouts": 3, "reboots": 0}},
                "odometry": {"state": "ok", "error": None, "error_stamp": None,
                             "counters": {"lines": 91650, "corrupt_lines": 2}},
            },
            "uptime_s": 1834.5,
            "map": {"path": "/var/lib/lino-loc/map.npz", "n_images": 408,
                    "channels": ["intensity"], "checksum": "sha256:9f2c41"},
            "active_vision": {"enabled": True, "paused": False, "head_paused": False, "head_commands": 3,
                              "last_decision": "converged", "last_command_rad": 0.0,
                              "frames_head_moving": 12},
            "persistence": {"initial_belief": "the saved pose (2.41, 1.07, 1.57), 3 s old, to be "
                            "confirmed by the views", "saves": 366, "save_error": None},
            "pose_port": {"subscribers": 3, "subscriptions": 2, "subscription_bytes": 10,
                          "ignored_subscriptions": 0, "evicted_subscribers": 0, "dropped_sends": 0,
                          "refused_handshakes": 0, "relay_running": True, "relay_restarts": 0,
                          "relay_resident_bytes": 40353792},
            "recording": {"file": "/var/lib/lino-loc/recordings/lino-20261202-065300.mcap",
                          "files": 1, "megabytes": 41.2, "messages": 48211, "dropped": 0,
                          "error": None},
            "live_view": {"address": "ws://127.0.0.1:8765", "serving": True, "clients": 1,
                          "topics": ["/camera/image", "/particles", "/pose"], "messages": 5120,
                          "dropped": 0, "error": None},
            "control_refused_handshakes": 0,
            "simulated": False, "version": "0.1.0",
        },
    ],
    "particles": [
        {"v": 1, "stamp": 1763767825.412, "frame_id": "map", "seq": 1832,
         "poses": [[3.40, 1.10, 1.57], [3.45, 1.08, 1.60], [3.37, 1.15, 1.55]],
         "weights": [0.5, 0.3, 0.2], "n_total": 1000},
    ],
    "request": [
        {"cmd": "ping"},
        {"cmd": "get_pose"},
        {"cmd": "status"},
        {"cmd": "set_pose", "pose": {"x": 2.0, "y": 1.0, "theta": 3.1416},
         "covariance": [0.25, 0, 0, 0, 0.25, 0, 0, 0, 0.0685]},
        {"cmd": "set_pose", "pose": {"x": 2.0, "y": 1.0, "theta": -1.0}},
        {"cmd": "global_localization"},
        {"cmd": "pause", "target": "active_vision"},
        {"cmd": "resume", "target": "head"},
        {"cmd": "set_active_vision", "enabled": False},
        {"cmd": "save_state", "v": 1},
    ],
    "reply": [
        {"v": 1, "ok": True, "cmd": "ping", "stamp": 1763767826.1, "version": "0.1.0"},
        {"v": 1, "ok": True, "cmd": "set_pose", "message": "filter reinitialised around (2, 1, 3.14)"},
        {"v": 1, "ok": True, "cmd": "global_localization", "message": None},
        {"v": 1, "ok": True, "cmd": "set_active_vision",
         "active_vision": {"enabled": False, "paused": False, "head_paused": False, "head_commands": 0,
                           "last_decision": None, "last_command_rad": None, "frames_head_moving": 0}},
        {"v": 1, "ok": True, "cmd": "save_state", "path": "/var/lib/lino-loc/state.json",
         "stamp": 1763767826.3},
        {"v": 1, "ok": True, "cmd": "get_pose", "pose": None},
        {"v": 1, "ok": False, "error": "cmd: unknown command 'fly' (one of set_pose, ...)", "cmd": None},
    ],
}  # fmt: skip

#: Payloads every schema and model must refuse (name -> list of (payload, why)).
COUNTER_EXAMPLES: dict[str, list[tuple[dict[str, Any], str]]] = {
    "pose": [
        ({**EXAMPLES["pose"][0], "state": "confused"}, "unknown state"),
        ({**EXAMPLES["pose"][0], "covariance": _COV[:8]}, "8 covariance entries"),
        ({k: v for k, v in EXAMPLES["pose"][0].items() if k != "pose"}, "no pose"),
        ({**EXAMPLES["pose"][0], "frame_id": "odom"}, "wrong frame"),
    ],
    "request": [
        ({"cmd": "fly"}, "unknown cmd"),
        ({"cmd": "set_pose"}, "no pose"),
        ({"cmd": "set_active_vision", "enabled": "yes"}, "string for a boolean"),
        ({"cmd": "ping", "verbose": True}, "unknown field"),
        ({"cmd": "pause", "target": "wheels"}, "unknown target"),
    ],
    "particles": [
        ({**EXAMPLES["particles"][0], "poses": [[1.0, 2.0]]}, "pose with 2 numbers"),
    ],
}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    directory = Path(args[0]) if args else SCHEMA_DIR
    for path in export(directory):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())

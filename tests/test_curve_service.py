"""The running daemon with CURVE: a real `lino-loc run` (its own simulated robot), real sockets.

The daemon binds 127.0.0.1 with CURVE keys configured (CURVE is used whenever keys are
configured; it is required off loopback, which `lino-loc run` enforces before binding
anything: the last test). A client without the keys, or with a key pair the daemon does not
know, gets no pose and no reply; the authorized client gets both. No traffic leaves loopback.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import zmq

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_curve_auth import _client, _gets_pose, _gets_reply  # noqa: E402
from test_daemon_integration import MAP_CACHE, ROOT, _env, _free_port, config_text, stop  # noqa: E402

from services.cli import main as cli_main  # noqa: E402


def _run(cfg: Path, log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", "run", "--config", str(cfg)],
        stdout=subprocess.DEVNULL, stderr=open(log, "ab"), env=_env(), cwd=ROOT,
    )


def test_a_curve_daemon_serves_only_its_authorized_client(tmp_path: Path) -> None:
    keys = tmp_path / "keys"
    assert cli_main(["keys", "generate", str(keys), "--json"]) == 0
    assert cli_main(["keys", "generate", str(keys), "--client", "stranger", "--json"]) == 0
    (keys / "clients" / "stranger.key").unlink()  # a valid key pair, not authorized
    pub, rep = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    cfg = tmp_path / "daemon.toml"
    MAP_CACHE.parent.mkdir(parents=True, exist_ok=True)
    cfg.write_text(
        config_text(tmp_path, pub=pub, rep=rep, state=tmp_path / "state.json")
        + f'[endpoints.curve]\nserver_secret_key = "{keys / "server.key_secret"}"\n'
        f'authorized_clients = "{keys / "clients"}"\n'
    )
    log = tmp_path / "daemon.log"
    daemon = _run(cfg, log)
    good = (keys / "server.key", keys / "client.key_secret")
    stranger = (keys / "server.key", keys / "stranger.key_secret")
    ctx: zmq.Context[Any] = zmq.Context()
    try:
        deadline = time.monotonic() + 600  # includes building the test map once
        while not _gets_pose(ctx, pub, good, 2.0):
            assert daemon.poll() is None, log.read_text()[-3000:]
            assert time.monotonic() < deadline, "no pose from the CURVE daemon"
        assert _gets_reply(ctx, rep, good, 5.0)
        for who in (None, stranger):
            assert not _gets_pose(ctx, pub, who, 3.0), f"pose without the keys ({who})"
            assert not _gets_reply(ctx, rep, who, 3.0), f"reply without the keys ({who})"
        assert _gets_pose(ctx, pub, good, 5.0)
        assert "CURVE" in log.read_text()  # the banner says so
        status = _status(ctx, rep, good)  # each refused client was tried on both sockets
        assert status["pose_port"]["refused_handshakes"] >= 2, status["pose_port"]
        assert status["control_refused_handshakes"] >= 2, status
    finally:
        ctx.destroy(0)
        code = stop(daemon, signal.SIGTERM, 30)
    assert code == 0, log.read_text()[-3000:]


def _status(ctx: zmq.Context[Any], endpoint: str, keys: tuple[Path, Path]) -> dict[str, Any]:
    s = _client(ctx, zmq.REQ, endpoint, keys)
    try:
        s.send(b'{"cmd": "status"}')
        assert s.poll(5000), "no status reply"
        return json.loads(s.recv())["status"]
    finally:
        s.close(0)


@pytest.mark.parametrize("endpoint", ["tcp://0.0.0.0:5599", "tcp://*:5599", "tcp://eth0:5599"])
def test_run_refuses_a_network_endpoint_without_keys_in_one_line(tmp_path: Path, endpoint: str) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[endpoints]\npub = "{endpoint}"\n')
    t0 = time.monotonic()
    res = subprocess.run(
        [sys.executable, "-m", "services.cli", "run", "--config", str(cfg)],
        capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=60,
    )
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert endpoint in lines[0] and "endpoints.curve.server_secret_key" in lines[0]
    assert "Traceback" not in res.stderr and time.monotonic() - t0 < 30


def test_run_refuses_unreadable_keys_in_one_line(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        '[endpoints]\npub = "tcp://0.0.0.0:5599"\n[endpoints.curve]\n'
        f'server_secret_key = "{tmp_path / "missing.key_secret"}"\nauthorized_clients = "{tmp_path}"\n'
    )
    res = subprocess.run(
        [sys.executable, "-m", "services.cli", "run", "--config", str(cfg)],
        capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=60,
    )
    assert res.returncode == 2
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert "endpoints.curve.server_secret_key" in res.stderr and "missing.key_secret" in res.stderr


def test_banner_never_suggests_a_wildcard(tmp_path: Path) -> None:
    from services.commands.run import echo_command
    from services.curve_auth import CurveConfig

    keys = CurveConfig(server_secret_key=tmp_path / "server.key_secret", authorized_clients=tmp_path)
    for bind in ("tcp://0.0.0.0:5556", "tcp://*:5556", "tcp://[::]:5556"):
        line = echo_command(bind, keys)
        assert "0.0.0.0" not in line and "*" not in line and "[::]" not in line
        assert "--curve-server-key " + str(tmp_path / "server.key") in line
    assert echo_command("tcp://127.0.0.1:5556", CurveConfig()) == "lino-loc echo --topic pose"

"""CURVE on the daemon's sockets: the loopback rule, the keys, and real sockets.

Real ZeroMQ sockets on 127.0.0.1 (CURVE is used whenever keys are configured, so the rule
"required off loopback" is tested by configuration, and the authentication itself on
loopback): a client without the keys, or with a key the daemon does not know, gets no pose
and no reply; a client with them gets both. Keys come from `lino-loc keys generate`.
"""

from __future__ import annotations

import json
import os
import stat
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zmq

from services.cli import main as cli_main
from services.config import ConfigError, ServiceConfig, load_config
from services.control import ControlServer
from services.curve_auth import (
    CurveConfig,
    CurveKeyError,
    is_loopback,
    load_server_keys,
    set_client_keys,
)
from services.messages import PingReply
from services.publisher import Publisher
from services.relay_publisher import RelayedPublisher


@pytest.mark.parametrize(
    ("endpoint", "loopback"),
    [
        ("tcp://127.0.0.1:5556", True),
        ("tcp://127.1.2.3:5556", True),
        ("tcp://localhost:5556", True),
        ("tcp://[::1]:5556", True),
        ("ipc:///run/lino-loc/pose", True),
        ("inproc://pose", True),
        ("tcp://0.0.0.0:5556", False),
        ("tcp://*:5556", False),
        ("tcp://[::]:5556", False),
        ("tcp://192.168.1.20:5556", False),
        ("tcp://eth0:5556", False),
        ("tcp://robot.local:5556", False),
        ("tcp://127.0.0.1.evil.example:5556", False),
    ],
)
def test_is_loopback(endpoint: str, loopback: bool) -> None:
    assert is_loopback(endpoint) is loopback


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("keys") / "keys"
    assert cli_main(["keys", "generate", str(d)]) == 0
    assert cli_main(["keys", "generate", str(d), "--client", "stranger"]) == 0
    # the stranger's key pair is valid but not authorized
    (d / "clients" / "stranger.key").unlink()
    return {
        "dir": d,
        "server_public": d / "server.key",
        "server_secret": d / "server.key_secret",
        "clients": d / "clients",
        "client_secret": d / "client.key_secret",
        "stranger_secret": d / "stranger.key_secret",
    }


def _curve(keys: dict[str, Path]) -> CurveConfig:
    return CurveConfig(server_secret_key=keys["server_secret"], authorized_clients=keys["clients"])


# ------------------------------------------------------------------------ configuration
def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "c.toml"
    p.write_text(text, encoding="utf-8")
    return p


def test_non_loopback_without_keys_is_one_line_naming_endpoint_and_setting(tmp_path: Path) -> None:
    p = _write(tmp_path, '[endpoints]\nrep = "tcp://0.0.0.0:5557"\n')
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert "\n" not in msg
    assert "tcp://0.0.0.0:5557" in msg and "rep" in msg
    assert "endpoints.curve.server_secret_key" in msg and "0.0.0.0" not in msg.split("bind to")[-1]


def test_non_loopback_with_keys_and_loopback_without_are_accepted(tmp_path: Path, keys: dict[str, Path]) -> None:
    assert not ServiceConfig().endpoints.curve.enabled  # the defaults: loopback, no keys
    p = _write(
        tmp_path,
        '[endpoints]\npub = "tcp://0.0.0.0:5556"\n[endpoints.curve]\n'
        f'server_secret_key = "{keys["server_secret"]}"\nauthorized_clients = "{keys["clients"]}"\n',
    )
    cfg = load_config(p)
    assert cfg.endpoints.curve.enabled and cfg.endpoints.curve.authorized_clients == keys["clients"]


def test_one_curve_setting_without_the_other_is_refused(tmp_path: Path) -> None:
    p = _write(tmp_path, '[endpoints.curve]\nserver_secret_key = "/etc/lino-loc/keys/server.key_secret"\n')
    with pytest.raises(ConfigError, match="authorized_clients is not set"):
        load_config(p)


def test_unusable_key_files_are_one_line(tmp_path: Path, keys: dict[str, Path]) -> None:
    cases = [
        (CurveConfig(server_secret_key=tmp_path / "none.key_secret", authorized_clients=keys["clients"]),
         "server_secret_key: cannot read"),
        (CurveConfig(server_secret_key=keys["server_public"], authorized_clients=keys["clients"]),
         "is not a NAME.key_secret file"),
        (CurveConfig(server_secret_key=keys["server_secret"], authorized_clients=tmp_path),
         "no client public key"),
        (CurveConfig(server_secret_key=keys["server_secret"], authorized_clients=tmp_path / "nope"),
         "is not a folder"),
    ]
    for cfg, needle in cases:
        with pytest.raises(CurveKeyError, match=needle) as err:
            load_server_keys(cfg)
        assert "\n" not in str(err.value)
    assert load_server_keys(_curve(keys)).n_clients == 1


# ------------------------------------------------------------------------ keys generate
def test_keys_generate_files_are_owner_only_and_never_overwritten(tmp_path: Path, capsys: Any) -> None:
    d = tmp_path / "k"
    assert cli_main(["keys", "generate", str(d), "--json"]) == 0
    paths = json.loads(capsys.readouterr().out)
    for key in ("server_public", "server_secret", "client_public", "client_secret"):
        mode = stat.S_IMODE(os.stat(paths[key]).st_mode)
        assert mode == 0o600, (key, oct(mode))
    for folder in (d, d / "clients"):
        assert stat.S_IMODE(os.stat(folder).st_mode) == 0o700
    assert sorted(p.name for p in d.iterdir()) == ["client.key_secret", "clients", "server.key", "server.key_secret"]
    before = Path(paths["server_secret"]).read_bytes()
    assert cli_main(["keys", "generate", str(d)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "exists already" in err
    assert cli_main(["keys", "generate", str(d), "--client", "laptop"]) == 0
    assert Path(paths["server_secret"]).read_bytes() == before  # the server's pair is kept
    assert (d / "clients" / "laptop.key").is_file() and (d / "laptop.key_secret").is_file()
    assert cli_main(["keys", "generate", str(d), "--client", "../x"]) == 2


# ------------------------------------------------------------------------ real sockets
class _Daemonish:
    """A Publisher publishing ``pose`` every 20 ms and a ControlServer answering pings, both
    CURVE servers in one context (as in the daemon)."""

    def __init__(self, curve: CurveConfig, relayed: bool = False) -> None:
        from services.messages import PoseMessage

        self.ctx: zmq.Context[Any] = zmq.Context()
        kind = RelayedPublisher if relayed else Publisher
        self.pub = kind(self.ctx, "tcp://127.0.0.1:*", 10, curve)
        self.pub_ep = self.pub.last_endpoint
        self.control = ControlServer(self.ctx, "tcp://127.0.0.1:*", lambda req: PingReply(stamp=1.0), curve)
        self.rep_ep = self.control._sock.getsockopt(zmq.LAST_ENDPOINT).decode()
        self.control.start()
        self._stop = threading.Event()
        msg = PoseMessage(stamp=1.0, seq=1, pose={"x": 1.0, "y": 2.0, "theta": 0.0}, covariance=[0.0] * 9,
                          state="tracking", ess=1.0, n_particles=1)

        def loop() -> None:
            while not self._stop.wait(0.02):
                self.pub.publish("pose", msg)

        self._thread = threading.Thread(target=loop, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.control.stop()
        self.pub.close()
        self.ctx.term()  # returns: the shared ZAP handler was stopped with the last socket


def _client(ctx: zmq.Context[Any], kind: int, endpoint: str, keys: tuple[Path, Path] | None) -> zmq.Socket[Any]:
    s = ctx.socket(kind)
    s.setsockopt(zmq.LINGER, 0)
    if keys is not None:
        set_client_keys(s, *keys)
    if kind == zmq.SUB:
        s.setsockopt(zmq.SUBSCRIBE, b"pose")
    s.connect(endpoint)
    return s


def _gets_pose(ctx: zmq.Context[Any], endpoint: str, keys: tuple[Path, Path] | None, timeout_s: float) -> bool:
    s = _client(ctx, zmq.SUB, endpoint, keys)
    try:
        return bool(s.poll(int(timeout_s * 1000))) and s.recv_multipart()[0] == b"pose"
    finally:
        s.close(0)


def _gets_reply(ctx: zmq.Context[Any], endpoint: str, keys: tuple[Path, Path] | None, timeout_s: float) -> bool:
    s = _client(ctx, zmq.REQ, endpoint, keys)
    try:
        s.send(b'{"cmd": "ping"}')
        return bool(s.poll(int(timeout_s * 1000))) and json.loads(s.recv())["ok"] is True
    finally:
        s.close(0)


@pytest.mark.parametrize("relayed", [False, True], ids=["direct", "relay"])
def test_only_an_authorized_client_gets_poses_and_replies(keys: dict[str, Path], relayed: bool) -> None:
    """Both ways of binding the pose port: the daemon's own socket, and the relay process
    (services/pose_relay.py), which gets the key files' paths and counts its refusals."""
    d = _Daemonish(_curve(keys), relayed)
    ctx: zmq.Context[Any] = zmq.Context()
    good = (keys["server_public"], keys["client_secret"])
    stranger = (keys["server_public"], keys["stranger_secret"])
    wrong_server = (keys["dir"] / "clients" / "client.key", keys["client_secret"])  # not the server's key
    try:
        assert _gets_pose(ctx, d.pub_ep, good, 5.0)
        assert _gets_reply(ctx, d.rep_ep, good, 5.0)
        for who in (None, stranger, wrong_server):
            assert not _gets_pose(ctx, d.pub_ep, who, 1.5), who
            assert not _gets_reply(ctx, d.rep_ep, who, 1.5), who
        # and the authorized client still works after the refused ones
        assert _gets_pose(ctx, d.pub_ep, good, 5.0)
        assert _gets_reply(ctx, d.rep_ep, good, 5.0)
        # the refused handshakes are counted (for the status), on both sockets
        deadline = time.monotonic() + 5.0
        while d.pub.info().refused_handshakes < 3 or d.control.refused_handshakes < 3:
            assert time.monotonic() < deadline, (d.pub.info(), d.control.refused_handshakes)
            time.sleep(0.05)
    finally:
        ctx.destroy(0)
        d.close()


def test_without_keys_loopback_needs_none() -> None:
    d = _Daemonish(CurveConfig())
    ctx: zmq.Context[Any] = zmq.Context()
    try:
        assert _gets_pose(ctx, d.pub_ep, None, 5.0)
        assert _gets_reply(ctx, d.rep_ep, None, 5.0)
    finally:
        ctx.destroy(0)
        d.close()


def test_echo_reads_a_curve_daemon_only_with_its_keys(keys: dict[str, Path], capsys: Any) -> None:
    d = _Daemonish(_curve(keys))
    try:
        args = ["echo", "--endpoint", d.pub_ep, "--count", "1", "--timeout", "5"]
        assert cli_main([*args, "--curve-server-key", str(keys["server_public"]),
                         "--curve-client-key", str(keys["client_secret"])]) == 0
        assert capsys.readouterr().out.startswith("pose {")
        assert cli_main(["echo", "--endpoint", d.pub_ep, "--count", "1", "--timeout", "1.5"]) == 1
        assert capsys.readouterr().out == ""
        assert cli_main([*args, "--curve-server-key", str(keys["server_public"])]) == 2
        assert "both" in capsys.readouterr().err
    finally:
        d.close()


def test_unreadable_keys_fail_the_bind_as_oserror(tmp_path: Path, keys: dict[str, Path]) -> None:
    ctx: zmq.Context[Any] = zmq.Context()
    bad = CurveConfig(server_secret_key=tmp_path / "missing.key_secret", authorized_clients=keys["clients"])
    with pytest.raises(OSError, match="server_secret_key"):
        Publisher(ctx, "tcp://127.0.0.1:*", 10, bad)
    with pytest.raises(OSError, match="server_secret_key") as relayed:
        RelayedPublisher(ctx, "tcp://127.0.0.1:*", 10, bad)
    assert "\n" not in str(relayed.value)  # the relay's one line, as the direct bind's
    with pytest.raises(OSError, match="server_secret_key"):
        ControlServer(ctx, "tcp://127.0.0.1:*", lambda req: PingReply(stamp=1.0), bad)
    t0 = time.monotonic()
    ctx.term()  # nothing left open
    assert time.monotonic() - t0 < 2.0


def test_a_secret_key_others_can_read_is_warned_about(tmp_path: Path, keys: dict[str, Path], caplog: Any) -> None:
    import shutil

    loose = tmp_path / "server.key_secret"
    shutil.copy(keys["server_secret"], loose)
    os.chmod(loose, 0o644)
    with caplog.at_level("WARNING", logger="lino_loc.service.curve"):
        load_server_keys(CurveConfig(server_secret_key=loose, authorized_clients=keys["clients"]))
    assert "readable by other users" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="lino_loc.service.curve"):
        load_server_keys(_curve(keys))
    assert caplog.text == ""

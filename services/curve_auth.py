"""ZeroMQ CURVE on the daemon's sockets: settings, key files, the loopback rule.

CURVE (ZeroMQ RFC 26, CurveZMQ) encrypts a connection and authenticates both ends with
Curve25519 key pairs. The daemon is the CURVE *server* of its PUB and REP sockets: it holds
a secret key, and a client may connect only if it knows the server's public key and its
own public key is in the folder of authorized clients. The check is done by pyzmq's ZAP
handler (``zmq.auth.thread.ThreadAuthenticator``, ``configure_curve(domain="*",
location=folder)``), one per ZeroMQ context, shared by the sockets of that context and
stopped when the last of them is released. The folder is read once, when the handler
starts: a key added later counts after a restart. A client that fails the handshake (no
CURVE, a wrong server key, a key not in the folder) gets no message and no reply; the
daemon only logs it at DEBUG (``zmq.auth`` logger).

The rule (:func:`curve_problem`): CURVE is used whenever keys are configured (on any
address), and required when an endpoint is not loopback. Loopback means ``ipc://``,
``inproc://`` and ``tcp://`` to 127.0.0.0/8, ``::1`` or ``localhost``; anything else
(``0.0.0.0``, ``*``, an interface name, a host name, another address) can be reached from
the network.

Key files are the ZeroMQ certificate files ``zmq.auth.create_certificates`` writes
(``lino-loc keys generate DIR``): ``NAME.key`` holds the public key, ``NAME.key_secret``
both keys. The configuration::

    [endpoints.curve]
    server_secret_key  = "/etc/lino-loc/keys/server.key_secret"
    authorized_clients = "/etc/lino-loc/keys/clients"      # the clients' *.key files

Usage::

    keys = load_server_keys(cfg.endpoints.curve)           # raises CurveKeyError (one line)
    release = attach_server(ctx, sock, cfg.endpoints.curve) # before bind; call release() after close
    set_client_keys(sock, "server.key", "client.key_secret")  # a client, before connect
"""

from __future__ import annotations

import ipaddress
import logging
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zmq
import zmq.auth
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from zmq.auth.thread import ThreadAuthenticator

from lino_loc.errors import LinoLocError

log = logging.getLogger("lino_loc.service.curve")

_TCP_HOST_RE = re.compile(r"^tcp://(?:\[(?P<v6>[^\]]+)\]|(?P<host>[^:]+)):(?:\d+|\*)$")


class CurveKeyError(LinoLocError):
    """A key file or folder named in ``[endpoints.curve]`` that cannot be used."""


class CurveConfig(BaseModel):
    """``[endpoints.curve]``: the daemon's CURVE keys (module docstring). Both or neither."""

    model_config = ConfigDict(extra="forbid")

    server_secret_key: Path | None = Field(
        None, description="the daemon's NAME.key_secret file (lino-loc keys generate)"
    )
    authorized_clients: Path | None = Field(
        None, description="folder of the public NAME.key files of the clients allowed to connect"
    )

    @field_validator("server_secret_key", "authorized_clients", mode="after")
    @classmethod
    def _expand(cls, v: Path | None) -> Path | None:
        return None if v is None else v.expanduser()

    @model_validator(mode="after")
    def _both_or_neither(self) -> CurveConfig:
        if (self.server_secret_key is None) != (self.authorized_clients is None):
            missing = "authorized_clients" if self.authorized_clients is None else "server_secret_key"
            raise ValueError(f"{missing} is not set: CURVE needs both server_secret_key and authorized_clients")
        return self

    @property
    def enabled(self) -> bool:
        return self.server_secret_key is not None


def is_loopback(endpoint: str) -> bool:
    """True when ``endpoint`` can only be reached from this machine (module docstring)."""
    if endpoint.startswith(("ipc://", "inproc://")):
        return True
    m = _TCP_HOST_RE.match(endpoint)
    if m is None:
        return False
    host = m.group("v6") or m.group("host")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # an interface or host name: it may face the network
        return False


def curve_problem(endpoints: dict[str, str], curve: CurveConfig) -> str | None:
    """One line naming the first non-loopback endpoint when no keys are configured, else None.

    ``endpoints`` maps a setting's name (``pub``, ``rep``) to its address."""
    if curve.enabled:
        return None
    for name, ep in endpoints.items():
        if not is_loopback(ep):
            return (
                f"{name} = {ep!r} can be reached from the network: set endpoints.curve.server_secret_key "
                "and endpoints.curve.authorized_clients (`lino-loc keys generate DIR`), or bind to 127.0.0.1"
            )
    return None


@dataclass(frozen=True)
class ServerKeys:
    public: bytes
    secret: bytes
    clients: Path
    n_clients: int


def _load(path: Path, setting: str, *, secret: bool) -> tuple[bytes, bytes | None]:
    try:
        public, sec = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as exc:
        raise CurveKeyError(f"{setting}: cannot read the key file {path}: {exc}") from None
    if public is None or (secret and not sec):
        kind = "a NAME.key_secret file (public and secret key)" if secret else "a public NAME.key file"
        raise CurveKeyError(f"{setting}: {path} is not {kind}")
    return public, sec


def load_server_keys(cfg: CurveConfig) -> ServerKeys:
    """The server's key pair and the authorized clients' folder, checked; raises
    :class:`CurveKeyError` with one line naming the setting and the file. A secret key file
    that other users may read is used, with a warning."""
    if cfg.server_secret_key is None or cfg.authorized_clients is None:
        raise CurveKeyError("endpoints.curve: no keys configured")
    public, secret = _load(cfg.server_secret_key, "endpoints.curve.server_secret_key", secret=True)
    if cfg.server_secret_key.stat().st_mode & 0o077:
        log.warning(
            "endpoints.curve.server_secret_key: %s is readable by other users (chmod 600 it)",
            cfg.server_secret_key,
        )
    folder = cfg.authorized_clients
    if not folder.is_dir():
        raise CurveKeyError(f"endpoints.curve.authorized_clients: {folder} is not a folder")
    files = sorted(folder.glob("*.key"))
    for f in files:
        _load(f, "endpoints.curve.authorized_clients", secret=False)
    if not files:
        raise CurveKeyError(
            f"endpoints.curve.authorized_clients: no client public key (*.key) in {folder}: no client could connect"
        )
    assert secret is not None
    return ServerKeys(public=public, secret=secret, clients=folder, n_clients=len(files))


class _Authenticators:
    """One ZAP handler per context, counted by the sockets that use it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_ctx: dict[int, tuple[Any, int]] = {}

    def acquire(self, ctx: Any, clients: Path) -> Callable[[], None]:
        key = id(ctx)
        with self._lock:
            auth, n = self._by_ctx.get(key, (None, 0))
            if auth is None:
                auth = ThreadAuthenticator(ctx, log=logging.getLogger("zmq.auth"))
                auth.start()
                auth.configure_curve(domain="*", location=str(clients))
            self._by_ctx[key] = (auth, n + 1)
        released = threading.Event()

        def release() -> None:
            if released.is_set():
                return
            released.set()
            with self._lock:
                a, m = self._by_ctx[key]
                if m <= 1:
                    del self._by_ctx[key]
                    a.stop()
                else:
                    self._by_ctx[key] = (a, m - 1)

        return release


_AUTHENTICATORS = _Authenticators()


def attach_server(ctx: Any, sock: Any, cfg: CurveConfig | None) -> Callable[[], None]:
    """Make ``sock`` (not yet bound) a CURVE server with the configured keys and make sure
    the context has its ZAP handler; returns the function that releases the handler (call
    it once the socket is closed). Without keys, does nothing (the release is a no-op).
    Raises :class:`CurveKeyError` when the keys cannot be read."""
    if cfg is None or not cfg.enabled:
        return lambda: None

    keys = load_server_keys(cfg)
    release = _AUTHENTICATORS.acquire(ctx, keys.clients)
    sock.setsockopt(zmq.CURVE_SECRETKEY, keys.secret)
    sock.setsockopt(zmq.CURVE_PUBLICKEY, keys.public)
    sock.setsockopt(zmq.CURVE_SERVER, 1)
    return release


def set_client_keys(sock: Any, server_public: Path | str, client_secret: Path | str) -> None:
    """Make ``sock`` (not yet connected) a CURVE client of the server whose public key file
    is ``server_public``, with the key pair of ``client_secret`` (a NAME.key_secret file).
    Raises :class:`CurveKeyError` (one line naming the file)."""

    server_key, _ = _load(Path(server_public), "server key", secret=False)
    public, secret = _load(Path(client_secret), "client key", secret=True)
    sock.setsockopt(zmq.CURVE_SERVERKEY, server_key)
    sock.setsockopt(zmq.CURVE_PUBLICKEY, public)
    sock.setsockopt(zmq.CURVE_SECRETKEY, secret)

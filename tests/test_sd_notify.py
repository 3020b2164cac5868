"""services.sd_notify against real AF_UNIX datagram sockets (path and abstract namespace)."""

from __future__ import annotations

import os
import socket
import uuid

import pytest

from services import sd_notify
from services.sd_notify import Notifier, watchdog_period


@pytest.fixture
def receiver(tmp_path, monkeypatch):
    path = tmp_path / "n.sock"
    assert len(str(path)) < 100, "AF_UNIX paths are limited to 108 bytes"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    yield sock
    sock.close()


def _recv(sock: socket.socket) -> str:
    return sock.recv(65536).decode()


def test_ready_watchdog_status_stopping_datagrams(receiver):
    with Notifier() as n:
        assert n.enabled
        assert n.ready()
        assert _recv(receiver) == "READY=1"
        assert n.ready("tracking, 30 Hz")
        assert _recv(receiver) == "READY=1\nSTATUS=tracking, 30 Hz"
        assert n.watchdog()
        assert _recv(receiver) == "WATCHDOG=1"
        assert n.status("camera failed:\n  retrying")  # made one line
        assert _recv(receiver) == "STATUS=camera failed: retrying"
        assert n.stopping("bye")
        assert _recv(receiver) == "STOPPING=1\nSTATUS=bye"
        assert n.notify("EXTEND_TIMEOUT_USEC=5000000")
        assert _recv(receiver) == "EXTEND_TIMEOUT_USEC=5000000"


def test_module_level_functions_use_notify_socket(receiver, monkeypatch):
    monkeypatch.setattr(sd_notify, "_default", None)  # re-read $NOTIFY_SOCKET
    assert sd_notify.ready("up")
    assert _recv(receiver) == "READY=1\nSTATUS=up"
    assert sd_notify.watchdog()
    assert _recv(receiver) == "WATCHDOG=1"
    monkeypatch.setattr(sd_notify, "_default", None)


def test_abstract_namespace_socket(monkeypatch):
    name = f"lino-loc-test-{uuid.uuid4().hex[:12]}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        n = Notifier()
        assert n.watchdog()
        assert _recv(sock) == "WATCHDOG=1"
        n.close()
    finally:
        sock.close()


def test_unset_is_a_quiet_no_op(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    n = Notifier()
    assert not n.enabled
    assert n.ready("x") is False
    assert n.watchdog() is False
    assert n.stopping() is False


def test_missing_socket_never_raises(tmp_path):
    n = Notifier(str(tmp_path / "gone.sock"))
    assert n.enabled
    assert n.watchdog() is False  # ENOENT swallowed: a lost ping must not stop the loop
    n.close()


def test_unsupported_address_disables(caplog):
    n = Notifier("vsock:2:1234")
    assert not n.enabled
    assert n.ready() is False


def test_watchdog_period_is_half_of_watchdog_usec():
    assert watchdog_period({"WATCHDOG_USEC": "5000000"}) == pytest.approx(2.5)
    assert watchdog_period({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": str(os.getpid())}) == 2.5
    assert watchdog_period({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": str(os.getpid() + 1)}) is None
    assert watchdog_period({}) is None
    assert watchdog_period({"WATCHDOG_USEC": "0"}) is None
    assert watchdog_period({"WATCHDOG_USEC": "abc"}) is None

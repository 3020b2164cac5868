"""systemd service notifications (``sd_notify(3)``) without libsystemd.

Under ``Type=notify`` systemd passes ``$NOTIFY_SOCKET``: a datagram Unix socket, either a
filesystem path (``/run/systemd/notify``) or an abstract-namespace name written with a
leading ``@``. The daemon sends newline-separated ``KEY=VALUE`` assignments to it:

- ``READY=1`` once it serves (systemd then considers the start complete);
- ``WATCHDOG=1`` at least every ``WatchdogSec`` (systemd passes the period as
  ``$WATCHDOG_USEC``; ping at half of it, see :func:`watchdog_period`);
- ``STATUS=...`` a one-line human-readable status shown by ``systemctl status``;
- ``STOPPING=1`` when a clean shutdown begins.

Without ``$NOTIFY_SOCKET`` (run from a shell, in tests) every call is a cheap no-op that
returns False. Send errors are logged and swallowed: a lost notification must never stop
the localization loop (systemd's watchdog will act if the pings really stop).

Usage::

    from services import sd_notify
    notifier = sd_notify.Notifier()          # reads $NOTIFY_SOCKET once
    notifier.ready("tracking at 30 Hz")      # READY=1 + STATUS=...
    period = sd_notify.watchdog_period()     # seconds, or None when no watchdog is set
    notifier.watchdog()                      # WATCHDOG=1
    notifier.stopping()
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Mapping

log = logging.getLogger(__name__)

#: Largest datagram we send; systemd accepts much more, a status line never needs it.
MAX_DATAGRAM = 4096


def _address(raw: str) -> str | bytes | None:
    """The ``sendto`` address of a ``$NOTIFY_SOCKET`` value (None if unsupported)."""
    if raw.startswith("@"):
        # Abstract namespace: leading NUL instead of '@', no trailing NUL.
        return b"\0" + raw[1:].encode()
    if raw.startswith("/"):
        return raw
    return None  # e.g. "vsock:..." (VM guests) is not supported here


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


class Notifier:
    """Sends notifications to ``$NOTIFY_SOCKET`` (or to ``socket_path`` when given).

    Thread-safe. ``enabled`` is False when there is no socket: then every method is a no-op
    returning False.
    """

    def __init__(self, socket_path: str | None = None) -> None:
        raw = socket_path if socket_path is not None else os.environ.get("NOTIFY_SOCKET", "")
        self._address = _address(raw) if raw else None
        if raw and self._address is None:
            log.warning("NOTIFY_SOCKET=%r is not a Unix socket address; notifications disabled", raw)
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()

    @property
    def enabled(self) -> bool:
        """True when there is a socket address to send to."""
        return self._address is not None

    def notify(self, assignments: str | Mapping[str, object]) -> bool:
        """Send one datagram of ``KEY=VALUE`` lines; True if it was sent."""
        if self._address is None:
            return False
        if isinstance(assignments, Mapping):
            text = "\n".join(f"{k}={_one_line(str(v))}" for k, v in assignments.items())
        else:
            text = assignments
        data = text.encode("utf-8", errors="replace")[:MAX_DATAGRAM]
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.sendto(data, self._address)
                return True
            except OSError as exc:
                log.debug("sd_notify %r failed: %s", text, exc)
                return False

    def ready(self, status: str | None = None) -> bool:
        """``READY=1`` (and ``STATUS=`` when given)."""
        msg: dict[str, object] = {"READY": 1}
        if status is not None:
            msg["STATUS"] = status
        return self.notify(msg)

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: keep-alive ping."""
        return self.notify({"WATCHDOG": 1})

    def status(self, text: str) -> bool:
        """``STATUS=text`` (made one line)."""
        return self.notify({"STATUS": text})

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1`` (and ``STATUS=`` when given)."""
        msg: dict[str, object] = {"STOPPING": 1}
        if status is not None:
            msg["STATUS"] = status
        return self.notify(msg)

    def close(self) -> None:
        """Close the socket (opened on first send); later sends reopen it."""
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def watchdog_period(environ: Mapping[str, str] | None = None) -> float | None:
    """Seconds between ``WATCHDOG=1`` pings: half of ``$WATCHDOG_USEC``, None if unset.

    Honours ``$WATCHDOG_PID`` as ``sd_watchdog_enabled(3)`` does: if it names another
    process, the watchdog is not ours.
    """
    env = os.environ if environ is None else environ
    try:
        usec = int(env.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    if usec <= 0:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            return None
    return usec / 2e6


_default: Notifier | None = None


def _notifier() -> Notifier:
    global _default
    if _default is None:
        _default = Notifier()
    return _default


def notify(assignments: str | Mapping[str, object]) -> bool:
    """Module-level :meth:`Notifier.notify` on ``$NOTIFY_SOCKET`` (read at first use)."""
    return _notifier().notify(assignments)


def ready(status: str | None = None) -> bool:
    return _notifier().ready(status)


def watchdog() -> bool:
    return _notifier().watchdog()


def status(text: str) -> bool:
    return _notifier().status(text)


def stopping(status: str | None = None) -> bool:
    return _notifier().stopping(status)

"""Pseudo-terminals for the device emulators, with an optional stable symlink.

An emulator owns the master side; the adapter opens the slave path (``/dev/pts/N``) with the
real vendor library, exactly as it would open ``/dev/ttyUSB0``. The slave side is put in raw
mode (no echo, no line discipline) and the emulator keeps its own slave descriptor open so
that reads on the master never fail with EIO while the adapter is between opens.

A device that is unplugged and plugged back may come back under a different name. On the
robot, udev gives it a stable name (``/dev/serial/by-id/...``), a symlink to the current
``/dev/ttyUSBn``. :class:`PseudoTerminal` does the same when given ``link``: the symlink is
(re)pointed atomically at the current slave on every open and removed on disconnect, so an
adapter configured with the link path finds the device again after a reconnect.

Usage::

    pt = PseudoTerminal(link="/tmp/lino-odo")
    pt.open(); os.write(pt.master_fd, b"hello\\r\\n"); pt.close()
"""

from __future__ import annotations

import contextlib
import os
import termios
import tty


class PseudoTerminal:
    """One pseudo-terminal pair, reopenable, with an optional stable symlink to the slave."""

    def __init__(self, link: str | os.PathLike[str] | None = None) -> None:
        self.link = os.fspath(link) if link is not None else None
        self.master_fd: int | None = None
        self._slave_fd: int | None = None
        self.slave_path: str | None = None

    @property
    def is_open(self) -> bool:
        return self.master_fd is not None

    @property
    def path(self) -> str:
        """The path an adapter should open: the stable link if any, else the slave path."""
        if self.link is not None:
            return self.link
        if self.slave_path is None:
            raise RuntimeError("pseudo-terminal is not open")
        return self.slave_path

    def open(self) -> str:
        """Create a new pty pair (raw slave) and point the link at it. Returns the slave path."""
        if self.is_open:
            return self.slave_path  # type: ignore[return-value]
        master, slave = os.openpty()
        tty.setraw(slave, termios.TCSANOW)
        os.set_blocking(master, False)
        self.master_fd, self._slave_fd = master, slave
        self.slave_path = os.ttyname(slave)
        if self.link is not None:
            tmp = f"{self.link}.tmp{os.getpid()}"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            os.symlink(self.slave_path, tmp)
            os.replace(tmp, self.link)
        return self.slave_path

    def close(self) -> None:
        """Close both sides (an adapter reading the slave sees the device vanish) and remove the
        link."""
        if self.link is not None:
            with contextlib.suppress(FileNotFoundError):
                if os.path.islink(self.link) and os.readlink(self.link) == self.slave_path:
                    os.unlink(self.link)
        for fd in (self.master_fd, self._slave_fd):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master_fd = self._slave_fd = None

    def write(self, data: bytes) -> int:
        """Write to the master (towards the adapter). Returns bytes written (0 if closed/full)."""
        fd = self.master_fd
        if fd is None:
            return 0
        try:
            return os.write(fd, data)
        except (BlockingIOError, OSError):
            return 0

    def read(self, n: int = 4096) -> bytes:
        """Non-blocking read of what the adapter sent (b'' if nothing)."""
        fd = self.master_fd
        if fd is None:
            return b""
        try:
            return os.read(fd, n)
        except (BlockingIOError, OSError):
            return b""

    def __enter__(self) -> PseudoTerminal:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""Atomic file replacement: readers see the old file or the new one, never half of one.

``with atomic_write(path, "wb") as fh: ...`` writes to a temporary file in the same folder,
flushes and fsyncs it, and renames it over ``path`` when the block ends without an error;
on an error the temporary file is removed and ``path`` is untouched. With
``sync_folder=True`` the folder is fsynced too, so the rename itself survives a power cut.

The temporary file is ``.<name>.tmp-<pid>-<random>`` next to the target (:func:`temp_name`):
a process killed between creating and renaming it (``kill -9``, a power cut) leaves it
behind, and :func:`remove_stale_temps` finds such leftovers by that pattern and removes those
whose writing process is gone (a live writer's file is left alone).
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

#: ``.<name>.tmp-<pid>-<8 hex digits>``: what :func:`atomic_write` creates next to ``<name>``.
_TEMP_RE = re.compile(r"^\.(?P<name>.+)\.tmp-(?P<pid>[0-9]+)-[0-9a-f]{8}$")


def temp_name(path: Path) -> Path:
    """A fresh temporary path next to ``path``: ``.<name>.tmp-<pid>-<8 random hex digits>``."""
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")


def pid_alive(pid: int) -> bool:
    """Whether a process with this pid exists (``kill(pid, 0)``: EPERM means it does)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temps(path: str | Path) -> list[Path]:
    """Remove the temporary files :func:`atomic_write` left next to ``path`` (the pattern
    ``.<name>.tmp-<pid>-<hex>`` with ``<name>`` = ``path``'s name) whose process ``<pid>`` no
    longer runs, or is this process (a write of ours still open is never one: call this before
    writing). Other files are never touched. Returns the removed paths; a missing folder or a
    file that cannot be removed is skipped."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    removed: list[Path] = []
    try:
        entries = list(folder.iterdir())
    except OSError:
        return removed
    me = os.getpid()
    for entry in entries:
        m = _TEMP_RE.match(entry.name)
        if m is None or m.group("name") != path.name:
            continue
        pid = int(m.group("pid"))
        if pid != me and pid_alive(pid):
            continue
        with contextlib.suppress(OSError):
            if entry.is_file() and not entry.is_symlink():
                entry.unlink()
                removed.append(entry)
    return removed


def _create_temp(path: Path) -> tuple[int, Path]:
    """An exclusively created temporary file next to ``path`` (mode 0600), retried on a name
    clash."""
    for _ in range(100):
        tmp = temp_name(path)
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"{path}: no free temporary name next to it")


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb", sync_folder: bool = False, **open_kwargs: Any) -> Iterator[IO[Any]]:
    """Open a temporary file next to path in mode; on a clean exit flush, fsync and rename it
    over path (then, with sync_folder, fsync the folder, best effort). On an exception the
    temporary file is removed, path is untouched and the exception propagates.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp = _create_temp(path)
    try:
        with os.fdopen(fd, mode, **open_kwargs) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    if sync_folder:  # best effort: some file systems cannot fsync a folder
        with contextlib.suppress(OSError):
            dir_fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)

"""Atomic file replacement: readers see the old file or the new one, never half of one.

``with atomic_write(path, "wb") as fh: ...`` writes to a temporary file in the same folder,
flushes and fsyncs it, and renames it over ``path`` when the block ends without an error;
on an error the temporary file is removed and ``path`` is untouched. With
``sync_folder=True`` the folder is fsynced too, so the rename itself survives a power cut.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb", sync_folder: bool = False, **open_kwargs: Any) -> Iterator[IO[Any]]:
    """Open a temporary file next to path in mode; on a clean exit flush, fsync and rename it
    over path (then, with sync_folder, fsync the folder, best effort). On an exception the
    temporary file is removed, path is untouched and the exception propagates.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
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

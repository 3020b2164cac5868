"""A float32 data matrix on disk, written and read in chunks of rows: surveys larger than memory.

The map build (:func:`lino_loc.appearance_map.build_map`) keeps the survey's data matrix
(N images x D working-size pixels, float32) in memory while it fits the memory budget; beyond
it, the preprocessed vectors go to a :class:`RowFile` (a raw row-major float32 file in a
scratch folder, deleted on :meth:`RowFile.close`) and the PCA
(:func:`lino_loc.pca.fit_pca_streamed`) and the projection of every row read it back one
chunk of rows at a time. Chunks are read with plain positioned reads (``os.preadv`` into a
buffer), not a memory map: a mapped file's pages count in the process's resident set until
unmapped, a read chunk is freed when dropped, so the peak memory is bounded by the chunk, not
the survey (the kernel's page cache still keeps what fits, which is what makes the repeated
passes fast when the file fits in RAM).

Writes are positioned too (``os.pwrite``), so the loading threads write their chunks
concurrently in any order.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from lino_loc.errors import LinoLocError

#: Bytes of rows read per chunk by default (64 MiB: 3495 rows of 80 x 60 pixels).
DEFAULT_CHUNK_BYTES = 64 * 2**20
_ITEM = np.dtype(np.float32).itemsize


class RowFile:
    """An (n, dim) float32 matrix in a scratch file: :meth:`write` rows at any offset (thread-safe),
    :meth:`read` a range, :meth:`chunks` iterates consecutive chunks of ``chunk_rows`` rows
    (default: :data:`DEFAULT_CHUNK_BYTES` of rows). A context manager; :meth:`close` deletes the file."""

    def __init__(self, n: int, dim: int, scratch_dir: Path | str | None = None, chunk_rows: int | None = None):
        if n < 0 or dim < 1:
            raise LinoLocError(f"row file: bad shape ({n}, {dim})")
        self.n, self.dim = int(n), int(dim)
        self.chunk_rows = max(1, int(chunk_rows) if chunk_rows else DEFAULT_CHUNK_BYTES // (self.dim * _ITEM))
        folder = Path(scratch_dir) if scratch_dir is not None else Path(tempfile.gettempdir())
        try:
            fd, name = tempfile.mkstemp(prefix="lino-loc-rows-", suffix=".f32", dir=folder)
        except OSError as exc:
            raise LinoLocError(f"{folder}: cannot create the map build's scratch file ({exc.strerror})") from None
        self.path = Path(name)
        self._fd: int | None = fd
        try:
            os.ftruncate(fd, self.n * self.dim * _ITEM)
        except OSError as exc:
            self.close()
            raise LinoLocError(f"{folder}: cannot size the map build's scratch file "
                               f"({self.n * self.dim * _ITEM / 2**20:.0f} MB: {exc.strerror})") from None

    @property
    def shape(self) -> tuple[int, int]:
        return self.n, self.dim

    def _fileno(self) -> int:
        if self._fd is None:
            raise LinoLocError(f"{self.path}: row file is closed")
        return self._fd

    def write(self, lo: int, rows: np.ndarray) -> None:
        """Write ``rows`` (k, dim) as rows lo .. lo + k - 1."""
        a = np.ascontiguousarray(rows, dtype=np.float32)
        if a.ndim != 2 or a.shape[1] != self.dim or lo < 0 or lo + a.shape[0] > self.n:
            raise LinoLocError(f"{self.path}: cannot write rows of shape {a.shape} at row {lo} of {self.shape}")
        buf = memoryview(a).cast("B")
        off = lo * self.dim * _ITEM
        while buf:
            k = os.pwrite(self._fileno(), buf, off)
            buf, off = buf[k:], off + k

    def read(self, lo: int, hi: int) -> np.ndarray:
        """Rows lo .. hi - 1 as a new (hi - lo, dim) float32 array."""
        if not 0 <= lo <= hi <= self.n:
            raise LinoLocError(f"{self.path}: rows {lo}..{hi} outside 0..{self.n}")
        out = np.empty((hi - lo, self.dim), dtype=np.float32)
        buf = memoryview(out).cast("B")
        off = lo * self.dim * _ITEM
        while buf:
            k = os.preadv(self._fileno(), [buf], off)
            if k == 0:
                raise LinoLocError(f"{self.path}: scratch file truncated at byte {off}")
            buf, off = buf[k:], off + k
        return out

    def chunks(self) -> Iterator[tuple[int, np.ndarray]]:
        """``(first_row, rows)`` for consecutive chunks of ``chunk_rows`` rows, in order."""
        for lo in range(0, self.n, self.chunk_rows):
            yield lo, self.read(lo, min(lo + self.chunk_rows, self.n))

    def close(self) -> None:
        """Close and delete the scratch file (idempotent)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
            self.path.unlink(missing_ok=True)

    def __enter__(self) -> RowFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

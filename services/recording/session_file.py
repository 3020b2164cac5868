"""One session's MCAP file(s), written with the ``mcap`` library: chunked, indexed, rotated.

:class:`SessionFile` opens ``path`` with ``mcap.writer.Writer`` (zstd chunks of at most
:data:`CHUNK_BYTES`, every index, the profile ``lino-loc``), registers every topic of
:data:`services.recording.channels.TOPICS` with its schema at once, and writes the session's
metadata record (``lino-loc``: the configuration, the seed, the map's checksum, the part).
:meth:`SessionFile.flush` ends the chunk in progress and flushes the file to the operating
system (the recorder calls it every :data:`services.recording.recorder.FLUSH_PERIOD_S`): what
was flushed survives a kill -9 of the process (not a power cut: no fsync) and reads with
``mcap.stream_reader.StreamReader`` up to the cut (:mod:`services.recording.recording_reader`).
After a flush that leaves the file at ``rotate_mb`` or more, the file is finished (summary,
footer) and the next part opened: ``NAME.mcap``, ``NAME-001.mcap``, ``NAME-002.mcap``, ...
each complete in itself (schemas, channels, metadata with its ``part``, and the
``preamble``: the map's drawing, /map/survey and /map/outline).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import IO, Any

from services.recording.channels import FORMAT_VERSION, METADATA_NAME, PROFILE, TOPICS, schema_bytes

#: Uncompressed bytes after which a chunk is closed even before the next flush.
CHUNK_BYTES = 4 * 1024 * 1024


def part_path(path: Path, part: int) -> Path:
    """The file of part ``part`` (0: ``path`` itself)."""
    return path if part == 0 else path.with_name(f"{path.stem}-{part:03d}{path.suffix}")


class SessionFile:
    """The MCAP writer of one session (module docstring). Not thread-safe: one writer."""

    def __init__(self, path: Path, metadata: dict[str, Any], rotate_mb: float = 0.0,
                 preamble: list[tuple[str, int, bytes]] | None = None) -> None:
        self.path = Path(path)
        self.preamble = list(preamble or [])  # (topic, log ns, bytes) at the start of each part
        self.metadata = dict(metadata)
        self.rotate_bytes = int(rotate_mb * 1024 * 1024) if rotate_mb > 0 else 0
        self.part = 0
        self.files: list[Path] = []
        self.bytes_closed = 0  # bytes of the finished parts
        self._flushed = 0  # bytes of the open part at its last flush
        self._stream: IO[bytes] | None = None
        self._writer: Any = None
        self._ids: dict[str, int] = {}
        self._open()

    def _open(self) -> None:
        from mcap.writer import CompressionType, Writer

        path = part_path(self.path, self.part)
        path.parent.mkdir(parents=True, exist_ok=True)
        self._stream = open(path, "wb")  # noqa: SIM115 - closed in _close
        w = Writer(self._stream, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        w.start(profile=PROFILE, library="lino-loc")
        schemas: dict[tuple[str, str], int] = {}
        for topic, t in TOPICS.items():
            key = (t.schema_name, t.schema_encoding)
            if key not in schemas:
                schemas[key] = w.register_schema(t.schema_name, t.schema_encoding, schema_bytes(topic))
            self._ids[topic] = w.register_channel(topic, t.encoding, schemas[key])
        meta = {**self.metadata, "part": self.part, "format_version": FORMAT_VERSION}
        w.add_metadata(METADATA_NAME, {k: v if isinstance(v, str) else json.dumps(v)
                                       for k, v in meta.items()})
        self._writer = w
        self.files.append(path)
        for topic, log_ns, data in self.preamble:
            self.write(topic, log_ns, log_ns, data)

    def write(self, topic: str, log_ns: int, publish_ns: int, data: bytes, sequence: int = 0) -> None:
        self._writer.add_message(self._ids[topic], log_ns, data, publish_ns, sequence & 0xFFFFFFFF)

    @property
    def bytes_written(self) -> int:
        """Bytes in the files so far, the open part as of its last flush (plain integers: safe
        to read from another thread)."""
        return self.bytes_closed + self._flushed

    def flush(self) -> None:
        """End the chunk, flush to the OS; rotate when the part reached ``rotate_mb``."""
        if self._writer is None or self._stream is None:
            return
        self._writer.flush()
        size = self._stream.tell()
        self._flushed = size
        if self.rotate_bytes and size >= self.rotate_bytes:
            self.close()
            self.part += 1
            self._open()

    def close(self) -> None:
        """Finish the file (summary and footer: ``mcap.reader.make_reader`` reads it)."""
        if self._stream is None:
            return
        if self._writer is not None:
            self._writer.finish()
            self._writer = None
        size = self._stream.tell()
        self._stream.close()
        self._stream = None
        self.bytes_closed += size
        self._flushed = 0

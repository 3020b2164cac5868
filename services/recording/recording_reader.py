"""Reading a recording with the ``mcap`` library, also one that a kill -9 cut short.

:func:`read_recording` streams the records of one or more files in order with
``mcap.stream_reader.StreamReader`` (which needs no summary or footer: a file cut while being
written reads up to its last whole chunk) and stops at the first broken record, saying so
in :attr:`Recording.truncated`. Schemas and channels are kept as they come; the session's
``lino-loc`` metadata record is parsed (values that are JSON are decoded). Protobuf payloads
decode with ``mcap_protobuf``'s decoder (:func:`protobuf_decoder`), JSON ones with ``json``.

Errors (one line, :class:`lino_loc.errors.LinoLocError`): a missing file, a file that is not
MCAP, a file of a newer layout than :data:`services.recording.channels.FORMAT_VERSION`.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lino_loc.errors import LinoLocError
from services.recording.channels import FORMAT_VERSION, METADATA_NAME


@dataclass
class Message:
    topic: str
    log_ns: int
    publish_ns: int
    sequence: int
    data: bytes
    schema_name: str
    message_encoding: str


@dataclass
class Recording:
    """What was read besides the messages: the metadata, the topics seen, truncation."""

    paths: list[Path]
    metadata: dict[str, Any] = field(default_factory=dict)
    topics: dict[str, tuple[str, str]] = field(default_factory=dict)  # topic -> (schema, encoding)
    schemas: dict[str, Any] = field(default_factory=dict)  # schema name -> mcap Schema record
    truncated: str | None = None


def _parse_metadata(values: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in values.items():
        try:
            out[k] = json.loads(v)
        except ValueError:
            out[k] = v
    return out


def _open(path: Path) -> Any:
    from mcap.exceptions import McapError
    from mcap.stream_reader import StreamReader

    if not path.is_file():
        raise LinoLocError(f"{path}: no such file")
    f = open(path, "rb")  # noqa: SIM115 - closed by the caller's generator
    try:
        return f, StreamReader(f, skip_magic=False).records
    except (McapError, struct.error, ValueError) as exc:
        f.close()
        raise LinoLocError(f"{path}: not an MCAP file ({exc})") from None


def read_recording(paths: Sequence[Path], rec: Recording) -> Iterator[Message]:
    """The messages of ``paths`` in file order; fills ``rec`` as it goes (module docstring)."""
    from mcap.exceptions import InvalidMagic, McapError
    from mcap.records import Channel, Metadata, Schema
    from mcap.records import Message as McapMessage

    for path in paths:
        f, records = _open(Path(path))
        channels: dict[int, tuple[str, str, str]] = {}
        schemas: dict[int, Any] = {}
        try:
            for r in _records(records, path, rec):
                if isinstance(r, Schema):
                    schemas[r.id] = r
                    rec.schemas[r.name] = r
                elif isinstance(r, Channel):
                    name = schemas[r.schema_id].name if r.schema_id in schemas else ""
                    channels[r.id] = (r.topic, name, r.message_encoding)
                    rec.topics[r.topic] = (name, r.message_encoding)
                elif isinstance(r, Metadata) and r.name == METADATA_NAME:
                    rec.metadata = _parse_metadata(dict(r.metadata))
                    _check_version(path, rec.metadata)
                elif isinstance(r, McapMessage) and r.channel_id in channels:
                    topic, schema, enc = channels[r.channel_id]
                    yield Message(topic, r.log_time, r.publish_time, r.sequence, r.data, schema, enc)
        except InvalidMagic:
            raise LinoLocError(f"{path}: not an MCAP file") from None
        except McapError as exc:
            raise LinoLocError(f"{path}: unreadable MCAP ({exc})") from None
        finally:
            f.close()


def _records(records: Iterator[Any], path: Path, rec: Recording) -> Iterator[Any]:
    """The records, stopping at a cut: a broken record ends the stream, noted in ``rec``."""
    from mcap.exceptions import EndOfFile, InvalidMagic

    first = True
    while True:
        try:
            r = next(records)
        except StopIteration:
            return
        except InvalidMagic:
            raise
        except Exception as exc:  # noqa: BLE001 - struct/EOF/zstd errors of a half-written chunk
            if first:
                raise LinoLocError(f"{path}: not an MCAP file ({type(exc).__name__})") from None
            what = "" if isinstance(exc, EndOfFile | struct.error | EOFError | zlib.error) else f": {exc}"
            rec.truncated = f"{path}: cut short ({type(exc).__name__}{what}), read up to the last whole chunk"
            return
        first = False
        yield r


def _check_version(path: Path, meta: dict[str, Any]) -> None:
    v = meta.get("format_version")
    if isinstance(v, int) and v > FORMAT_VERSION:
        raise LinoLocError(f"{path}: recording layout {v} is newer than this lino-loc's ({FORMAT_VERSION})")


def protobuf_decoder(rec: Recording, schema_name: str) -> Callable[[bytes], Any]:
    """A decoder of ``schema_name``'s protobuf messages (mcap_protobuf's, from the file's schema)."""
    from mcap_protobuf.decoder import DecoderFactory

    dec = DecoderFactory().decoder_for("protobuf", rec.schemas[schema_name])
    if dec is None:
        raise LinoLocError(f"no protobuf decoder for {schema_name}")
    return dec

"""An MCAP file read whatever it holds (issue 44): one pass in file order, one record — and one
chunk, decompressed — in memory at a time, so a recording of any length reads in bounded
memory; and a message read again later from where the pass saw it (:class:`Where`,
:class:`ChunkCache`).

The summary is never needed: the data section is walked from the magic to its end. What can
go wrong is one line naming the file (:class:`McapFileError`): not an MCAP file (too short,
another magic), a record or a chunk over the caps (:data:`MAX_RECORD_BYTES`,
:data:`MAX_CHUNK_BYTES`, checked before anything is read or decompressed), a chunk whose
compression is unknown or whose data does not decompress to its stated size, a record that
does not parse. A file that ends inside a record, or without its footer — a recording cut
short by a full disk or a killed process — is read up to its last whole record and says so
(:attr:`Reading.cut_short`): every whole chunk before the cut is kept.
"""

from __future__ import annotations

import io
import struct
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Metadata, Schema

__all__ = ["MAX_CHUNK_BYTES", "MAX_RECORD_BYTES", "ChunkCache", "McapFileError", "Msg",
           "Reading", "Where"]

MAGIC = b"\x89MCAP0\r\n"
MAX_RECORD_BYTES = 256 << 20
"""A record's length at most (the recorder's chunks are 1 MiB by default, 64 MiB at most)."""
MAX_CHUNK_BYTES = 512 << 20
"""A chunk's decompressed size at most (a decompression bomb is refused before it runs)."""
_OP = {"schema": 0x03, "channel": 0x04, "message": 0x05, "chunk": 0x06, "metadata": 0x0C,
       "data_end": 0x0F, "footer": 0x02}


class McapFileError(ValueError):
    """The file cannot be read as MCAP; the message names it and says why, in one line."""


@dataclass(frozen=True)
class Where:
    """Where a message is: its file, the offset of its chunk record (or of the message record
    itself, ``index`` −1) and its index among the chunk's records."""

    file: int
    offset: int
    index: int


@dataclass(frozen=True)
class Msg:
    schema: Schema | None
    channel: Channel
    message: Message
    where: Where


def _decompress(chunk: Chunk, path: Path, offset: int) -> bytes:
    size = chunk.uncompressed_size
    if size > MAX_CHUNK_BYTES:
        raise McapFileError(f"{path}: a chunk at byte {offset} says it holds {size} bytes, over "
                            f"the {MAX_CHUNK_BYTES} a chunk may hold")
    try:
        if chunk.compression == "zstd":
            import zstandard

            data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=size)
        elif chunk.compression == "lz4":
            import lz4.frame

            data = lz4.frame.decompress(chunk.data)
        elif chunk.compression == "":
            data = bytes(chunk.data)
        else:
            raise McapFileError(f"{path}: a chunk at byte {offset} is compressed with "
                                f"{chunk.compression[:40]!r} (zstd, lz4 or none are read)")
    except McapFileError:
        raise
    except Exception as err:  # zstd/lz4 errors: a corrupt chunk
        raise McapFileError(f"{path}: the chunk at byte {offset} does not decompress "
                            f"({type(err).__name__})") from None
    if len(data) != size:
        raise McapFileError(f"{path}: the chunk at byte {offset} decompresses to {len(data)} "
                            f"bytes, not the {size} it says")
    return data


def _records(buf: BinaryIO, path: Path, base: int, *,
             cut: list[str] | None) -> Iterator[tuple[int, int, bytes]]:
    """(opcode, offset, body) of each record of ``buf`` (a file past its magic, or a chunk's
    records); at a record cut short: stop, noting it in ``cut`` (a file), or raise (a
    chunk)."""
    while True:
        start = base + buf.tell()
        head = buf.read(9)
        if not head:
            if cut is not None:
                cut.append(f"{path} ends at byte {start} without its footer: read up to its "
                           f"last whole record (`mcap recover` rewrites it whole)")
            return
        if len(head) < 9:
            break
        opcode, length = struct.unpack("<BQ", head)
        if length > MAX_RECORD_BYTES:
            raise McapFileError(f"{path}: a record at byte {start} says it is {length} bytes "
                                f"long, over the {MAX_RECORD_BYTES} a record may be (a cut or "
                                f"corrupt file? `mcap recover` rewrites what is whole)")
        body = buf.read(length)
        if len(body) < length:
            break
        yield opcode, start, body
        if opcode == _OP["footer"]:
            return
    if cut is None:
        raise McapFileError(f"{path}: a chunk's record at byte {start} is cut short")
    cut.append(f"{path} is cut short at byte {start}: read up to its last whole record "
               f"(`mcap recover` rewrites it whole)")


def _parse(opcode: int, body: bytes, path: Path, offset: int):
    stream = ReadDataStream(io.BytesIO(body))
    try:
        if opcode == _OP["message"]:
            return Message.read(stream, len(body))
        for name, cls in (("schema", Schema), ("channel", Channel), ("chunk", Chunk),
                          ("metadata", Metadata), ("data_end", DataEnd), ("footer", Footer)):
            if opcode == _OP[name]:
                return cls.read(stream)
    except Exception as err:  # struct.error, EndOfFile, UnicodeDecodeError, …
        raise McapFileError(f"{path}: the record at byte {offset} (opcode {opcode}) does not "
                            f"parse ({type(err).__name__})") from None
    return None  # indexes, statistics, attachments, unknown opcodes: not needed


class Reading:
    """One pass over ``paths`` (a recording's segments, each a whole or cut MCAP file):
    iterate :meth:`messages`; :attr:`metadata` and :attr:`cut_short` fill on the way."""

    def __init__(self, paths: list[Path]) -> None:
        self.paths = [Path(p) for p in paths]
        self.metadata: list[Metadata] = []
        self.cut_short: list[str] = []
        self.schemas_seen: dict[str, str] = {}  # name → encoding, every file
        self.messages_read = 0

    def messages(self) -> Iterator[Msg]:
        for i, path in enumerate(self.paths):
            yield from self._file(i, path)

    def _file(self, i: int, path: Path) -> Iterator[Msg]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        try:
            f = open(path, "rb")  # noqa: SIM115 - closed below (a generator)
        except OSError as err:
            raise McapFileError(f"{path}: cannot read it ({err.strerror or err})") from None
        with f:
            magic = f.read(8)
            if magic != MAGIC:
                size = path.stat().st_size
                raise McapFileError(f"{path} is not an MCAP file ({size} bytes"
                                    f"{'' if size < 8 else ', another magic'}; an MCAP file "
                                    f"starts with {MAGIC!r})")
            for opcode, offset, body in _records(f, path, 0, cut=self.cut_short):
                record = _parse(opcode, body, path, offset)
                if isinstance(record, DataEnd | Footer):
                    return
                if isinstance(record, Chunk):
                    data = _decompress(record, path, offset)
                    inner = _records(io.BytesIO(data), path, 0, cut=None)
                    for k, (op, _o, b) in enumerate(inner):
                        got = self._take(_parse(op, b, path, offset), schemas, channels,
                                         Where(i, offset, k))
                        if got is not None:
                            yield got
                else:
                    got = self._take(record, schemas, channels, Where(i, offset, -1))
                    if got is not None:
                        yield got

    def _take(self, record, schemas: dict[int, Schema], channels: dict[int, Channel],
              where: Where) -> Msg | None:
        if isinstance(record, Schema):
            schemas[record.id] = record
            self.schemas_seen[record.name] = record.encoding
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Metadata):
            self.metadata.append(record)
        elif isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None:
                return None  # a message before its channel: nothing says what it is
            self.messages_read += 1
            return Msg(schemas.get(channel.schema_id), channel, record, where)
        return None


class ChunkCache:
    """Messages read again by :class:`Where`: the chunks last used stay decompressed (at
    most ``chunks`` of them)."""

    def __init__(self, paths: list[Path], chunks: int = 4) -> None:
        self.paths = [Path(p) for p in paths]
        self._chunks: OrderedDict[tuple[int, int], list[tuple[int, int, bytes]]] = \
            OrderedDict()
        self._size = chunks

    def message(self, where: Where) -> Message:
        path = self.paths[where.file]
        if where.index < 0:
            body = self._record(where, path)
            return _parse(_OP["message"], body, path, where.offset)
        key = (where.file, where.offset)
        records = self._chunks.get(key)
        if records is None:
            chunk = _parse(_OP["chunk"], self._record(where, path), path, where.offset)
            data = _decompress(chunk, path, where.offset)
            records = list(_records(io.BytesIO(data), path, 0, cut=None))
            self._chunks[key] = records
            while len(self._chunks) > self._size:
                self._chunks.popitem(last=False)
        else:
            self._chunks.move_to_end(key)
        opcode, _offset, body = records[where.index]
        return _parse(opcode, body, path, where.offset)

    @staticmethod
    def _record(where: Where, path: Path) -> bytes:
        with open(path, "rb") as f:
            f.seek(where.offset)
            head = f.read(9)
            _op, length = struct.unpack("<BQ", head)
            return f.read(min(length, MAX_RECORD_BYTES))

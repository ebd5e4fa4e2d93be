"""Walking an MCAP file record by record with the ``mcap`` library, through damage.

The library's readers stop at the first damaged record, and its indexed reader needs the
summary at the end of the file, which a crash never writes. :class:`McapScan` walks the data
section with the library's record readers (:mod:`mcap.records`,
:func:`mcap.stream_reader.breakup_chunk`) and, where a record is damaged, says what was lost
(:class:`Damage`) and carries on after it where the file allows:

- ``truncated``: the file ends inside a record, or without its data-end record: everything
  before is read.
- ``bad_crc``, ``bad_compression``: a chunk whose data fails its CRC or does not decompress:
  skipped; the walk goes on after it.
- ``bad_length``: a chunk whose record length disagrees with its own content (a damaged
  length field): the chunk is read by its content (its CRC checks it) and the walk goes on
  where the content ends.
- ``bad_record``: a record that cannot be parsed, or bytes that are no record: skipped up to
  the next chunk that can be found and passes its CRC.

An intact chunk comes back whole (:class:`ChunkRecords`): its records are read by the
library's record readers from the decompressed bytes through :class:`_ChunkStream`, which
reads the fixed-size fields with ``struct.unpack_from`` in place; the library's own
stream (a ``BytesIO`` behind a Python wrapper) took twice as long per message, and a
markers-only recording holds four messages per frame.
"""

from __future__ import annotations

import mmap
import os
import re
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, BinaryIO

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Header, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, read_magic

try:  # as the library: lz4 chunks need the optional lz4 package
    import lz4.frame as lz4
except ImportError:  # pragma: no cover - lz4 ships with the environment
    lz4 = None

DAMAGE_KINDS = ("truncated", "bad_crc", "bad_compression", "bad_length", "bad_record")
_RECORD_HEAD = 9  # opcode u8, record length u64
_PARSE_ERRORS = (McapError, ValueError, struct.error)
_CHUNK_ERRORS = (*_PARSE_ERRORS, zstandard.ZstdError, RuntimeError)  # lz4 raises RuntimeError
_READERS: dict[int, Callable[[ReadDataStream], Any]] = {
    Opcode.HEADER: Header.read,
    Opcode.METADATA: Metadata.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
}
"""Records of the data section that a recording needs, besides chunks and messages; the
others (message indexes, attachments) are skipped by their length, as the spec says."""
_OPCODES = {int(op) for op in Opcode}
_CHUNK_CANDIDATE = re.compile(
    rb"\x06(?=.{36}(?:\x00\x00\x00\x00|\x04\x00\x00\x00zstd|\x03\x00\x00\x00lz4))", re.S
)
"""Where a chunk record may start: its opcode, then 36 bytes of lengths, times, size and CRC,
then the length-prefixed compression name."""


@dataclass(frozen=True)
class Damage:
    """A part of the file that could not be read.

    Parameters
    ----------
    kind : str
        One of :data:`DAMAGE_KINDS`.
    offset, end : int
        The damaged bytes ``[offset, end)``: the walk read again from ``end`` (the file size
        when nothing after the damage could be read).
    start_ns, end_ns : int, optional
        Log times of the messages lost (from the damaged chunk's header), when known.
    detail : str
        What was wrong, in a few words.
    lost : bool
        Whether messages were lost (a chunk with a bad length is still read).
    """

    kind: str
    offset: int
    end: int
    start_ns: int | None = None
    end_ns: int | None = None
    detail: str = ""
    lost: bool = True


@dataclass(frozen=True)
class Located:
    """A record of the data section outside chunks (``chunk_offset`` -1), or one record of the
    chunk at ``chunk_offset``, at ``index`` among its records."""

    record: Any
    chunk_offset: int = -1
    index: int = -1


@dataclass(frozen=True)
class ChunkRecords:
    """The records of an intact chunk, in order: one item per chunk rather than per record
    (the reader walks the list itself). ``records[index]`` is what
    :meth:`McapScan.chunk_records` gives again for the chunk at ``offset``."""

    offset: int
    records: list


class _Bounded:
    """The file as the library's :class:`ReadDataStream` reads it: a read that would pass
    ``limit`` raises :class:`EndOfFile` (a damaged length must not allocate gigabytes, nor
    yield a short field), and the offset is known."""

    def __init__(self, f: BinaryIO, size: int) -> None:
        self._f = f
        self.size = self.limit = size
        self.offset = 0

    def seek(self, offset: int, limit: int | None = None) -> None:
        self._f.seek(offset)
        self.offset = offset
        self.limit = self.size if limit is None else min(limit, self.size)

    def read(self, n: int) -> bytes:
        if self.offset + n > self.limit:
            raise EndOfFile()
        data = self._f.read(n)
        self.offset += len(data)
        return data


class McapScan:
    """The records of an MCAP file's data section, read through damage.

    Parameters
    ----------
    f : binary file
        Open for reading; kept open by the caller (chunks are read again for images).

    Raises
    ------
    mcap.exceptions.McapError
        The file does not start with the MCAP magic bytes.
    """

    def __init__(self, f: BinaryIO) -> None:
        self.size = os.fstat(f.fileno()).st_size
        self._file = _Bounded(f, self.size)
        self._stream = ReadDataStream(self._file)
        self._f = f
        self._file.seek(0)
        read_magic(self._stream)
        self._start = self._file.offset

    def records(self) -> Iterator[Located | ChunkRecords | Damage]:
        """Every record of the data section in file order (those of a chunk together, as
        :class:`ChunkRecords`), and a :class:`Damage` wherever something was lost."""
        offset = self._start
        while offset is not None:
            offset = yield from self._record(offset)

    def chunk_records(self, chunk_offset: int) -> list:
        """The records of the (intact) chunk whose record starts at ``chunk_offset``."""
        self._file.seek(chunk_offset + _RECORD_HEAD)
        return _unpack(Chunk.read(self._stream))

    # ---------------------------------------------------------------- one record
    def _record(self, offset: int):
        """Yield what the record at ``offset`` holds; return where the next one starts
        (None: the walk is over)."""
        size = self.size
        if offset >= size:
            yield Damage("truncated", offset, size, detail="no data-end record")
            return None
        self._file.seek(offset)
        try:
            opcode, length = self._stream.read1(), self._stream.read8()
        except EndOfFile:
            yield Damage("truncated", offset, size, detail="an incomplete record header")
            return None
        end = offset + _RECORD_HEAD + length
        if opcode in (Opcode.DATA_END, Opcode.FOOTER):
            return None  # the data section is complete: the summary follows
        if opcode == Opcode.CHUNK:
            return (yield from self._chunk(offset, end))
        if opcode not in _OPCODES and opcode < 0x80:  # reserved: no record starts here
            return (yield from self._resync(offset, f"opcode 0x{opcode:02X} is reserved"))
        reader = _READERS.get(opcode)
        if opcode == Opcode.MESSAGE:
            reader = lambda stream: Message.read(stream, length)  # noqa: E731
        if reader is None:  # an index or attachment, or a private record: skipped
            if end > size:
                return (yield from self._overrun(offset, "the file ends inside a record"))
            return end
        try:
            record = reader(self._stream)
        except EndOfFile:
            if end > size:
                return (yield from self._overrun(offset, "the file ends inside a record"))
            return (yield from self._resync(offset, "a record longer than its length", end))
        except _PARSE_ERRORS as exc:
            detail = f"a record that cannot be read ({exc})"
            return (yield from self._resync(offset, detail, end))
        yield Located(record)
        content_end = self._file.offset
        if end <= size and (content_end <= end):
            return end  # a record may be longer than the fields read (later MCAP versions)
        yield Damage(
            "bad_length", offset, content_end, detail="the record length is damaged", lost=False
        )
        return content_end

    def _chunk(self, offset: int, end: int):
        size = self.size
        try:
            chunk = Chunk.read(self._stream)
        except EndOfFile:
            if end > size:
                times = self._chunk_times(offset)
                return (yield from self._overrun(offset, "the file ends inside a chunk", *times))
            detail = "a chunk longer than its record length"
            return (yield from self._resync(offset, detail, end))
        except _PARSE_ERRORS as exc:
            return (yield from self._resync(offset, f"a chunk that cannot be read ({exc})", end))
        content_end = self._file.offset
        times = (chunk.message_start_time, chunk.message_end_time)
        try:
            records = _unpack(chunk)
        except CRCValidationError:
            problem = ("bad_crc", "CRC mismatch")
        except _CHUNK_ERRORS as exc:
            problem = ("bad_compression", f"{chunk.compression or 'uncompressed'}: {exc}")
        else:
            yield ChunkRecords(offset, records)
            if content_end == end:
                return end
            length = end - offset - _RECORD_HEAD
            yield Damage(
                "bad_length",
                offset,
                content_end,
                *times,
                f"record length {length} for {content_end - offset - _RECORD_HEAD} bytes",
                lost=False,
            )
            return content_end
        # The chunk's data is lost. Which of its two lengths is damaged is unknown: go on
        # where a record starts.
        resume = self._resume(offset, end, content_end)
        yield Damage(problem[0], offset, size if resume is None else resume, *times, problem[1])
        return resume

    def _chunk_times(self, offset: int) -> tuple[int | None, int | None]:
        """Log times of the messages of the (incomplete) chunk at ``offset``, if readable."""
        self._file.seek(offset + _RECORD_HEAD)
        try:
            return self._stream.read8(), self._stream.read8()
        except EndOfFile:
            return None, None

    def _overrun(self, offset: int, detail: str, start_ns=None, end_ns=None):
        """The record at ``offset`` runs past the end of the file: the file is truncated
        there, unless a chunk follows (then the record's length is damaged)."""
        resume = self._find_chunk(offset + 1)
        if resume is None:
            yield Damage("truncated", offset, self.size, start_ns, end_ns, detail)
            return None
        detail = f"its length runs past the end of the file, yet a chunk follows at byte {resume}"
        yield Damage("bad_length", offset, resume, start_ns, end_ns, detail)
        return resume

    def _resync(self, offset: int, detail: str, *candidates: int):
        """Skip a damaged record: yield its Damage, return where the walk goes on."""
        resume = self._resume(offset, *candidates)
        end = self.size if resume is None else resume
        yield Damage("bad_record", offset, end, detail=detail)
        return resume

    def _resume(self, offset: int, *candidates: int) -> int | None:
        """Where to go on after damage at ``offset``: the first candidate where a record
        starts, else the next chunk that passes its CRC (None: none)."""
        for candidate in candidates:
            if candidate > offset and self._starts_record(candidate):
                return candidate
        return self._find_chunk(offset + 1)

    def _starts_record(self, offset: int) -> bool:
        """Whether a record can start at ``offset`` (or the file ends there)."""
        if offset > self.size:
            return False
        if offset + _RECORD_HEAD > self.size:
            return True  # the end of the file, or a truncated record header
        self._file.seek(offset)
        return self._stream.read1() in _OPCODES

    def _find_chunk(self, start: int) -> int | None:
        """Offset of the next chunk record from ``start`` that reads and passes its CRC."""
        if start >= self.size:
            return None
        with mmap.mmap(self._f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            for match in _CHUNK_CANDIDATE.finditer(data, start):
                offset = match.start()
                self._file.seek(offset + 1)
                end = offset + _RECORD_HEAD + self._stream.read8()
                self._file.seek(offset + _RECORD_HEAD, limit=end)
                try:
                    chunk = Chunk.read(self._stream)
                    if self._file.offset == end:
                        _unpack(chunk)
                        return offset
                except _CHUNK_ERRORS:
                    continue
        return None


def _unpack(chunk: Chunk) -> list:
    """The records of a chunk, its CRC checked: :func:`mcap.stream_reader.breakup_chunk`
    (the same decompression, CRC check and record readers) over :class:`_ChunkStream`."""
    if chunk.compression == "zstd":
        data = zstandard.decompress(chunk.data, chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        if lz4 is None:
            raise McapError("unsupported compression 'lz4' (the lz4 package is missing)")
        data = lz4.decompress(chunk.data)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise McapError(f"unsupported compression {chunk.compression!r}")
    if chunk.uncompressed_crc != 0:
        crc = zlib.crc32(data)
        if crc != chunk.uncompressed_crc:
            raise CRCValidationError(expected=chunk.uncompressed_crc, actual=crc, record=chunk)
    stream = _ChunkStream(data)
    read_message, size = Message.read, len(data)
    records: list = []
    append = records.append
    while stream.count < size:
        opcode, length = stream.read_head()
        if opcode == Opcode.MESSAGE:
            append(read_message(stream, length))
        elif opcode == Opcode.CHANNEL:
            append(Channel.read(stream))
        elif opcode == Opcode.SCHEMA:
            append(Schema.read(stream))
        else:  # another record type inside a chunk: skipped by its length, as the library does
            stream.read(length)
    return records


_U16, _U32, _U64, _HEAD = (struct.Struct(f).unpack_from for f in ("<H", "<I", "<Q", "<BQ"))


def _fixed_size_field(n: int, unpack: Callable) -> Callable[[_ChunkStream], int]:
    """A ``readN`` method of :class:`_ChunkStream`: one closure per size rather than a shared
    method with the size as an argument (one call less, five times per message)."""

    def read(self: _ChunkStream) -> int:
        start = self._count
        if start + n > self._size:
            self._short(n)
        self._count = start + n
        return unpack(self._data, start)[0]

    return read


class _ChunkStream(ReadDataStream):
    """The decompressed bytes of a chunk as the library's record readers read them.

    It behaves as :class:`mcap.data_stream.ReadDataStream` over a ``BytesIO`` does: a read at
    the end raises :class:`EndOfFile`, a read past it gives the bytes that are there (a
    fixed-size field then raises ``struct.error``). A chunk whose records disagree with its
    length therefore fails (or reads) exactly as with the library's own stream.
    """

    def __init__(self, data: bytes) -> None:
        self._data = data
        self._size = len(data)
        self._count = 0
        self._crc = None

    def read(self, length: int) -> bytes:
        start = self._count
        if length == 0:
            return b""
        if start >= self._size:
            raise EndOfFile()
        # A negative length reads to the end, as BytesIO.read does (a message record shorter
        # than its header asks for one).
        data = self._data[start : start + length] if length > 0 else self._data[start:]
        self._count = start + len(data)
        return data

    def read_head(self) -> tuple[int, int]:
        """A record's opcode and length (``read1``, ``read8``) in one call."""
        start = self._count
        if start + _RECORD_HEAD > self._size:
            return self.read1(), self.read8()
        self._count = start + _RECORD_HEAD
        return _HEAD(self._data, start)

    def read1(self) -> int:
        start = self._count
        if start >= self._size:
            raise EndOfFile()
        self._count = start + 1
        return self._data[start]

    read2 = _fixed_size_field(2, _U16)
    read4 = _fixed_size_field(4, _U32)
    read8 = _fixed_size_field(8, _U64)

    def _short(self, n: int) -> None:
        """A field past the end: what the library's stream raises there."""
        if self._count >= self._size:
            raise EndOfFile()
        self._count = self._size
        raise struct.error(f"unpack requires a buffer of {n} bytes")

"""A tolerant MCAP reader: reads what can be read from closed, cut or damaged files, and says
what it could not read.

The ``mcap`` package's indexed reader needs the summary and footer that a writer adds when it
is closed; a recording cut by SIGKILL or a full disk has neither. Its stream reader stops at
the first damaged byte. :func:`scan` walks the data section record by record instead:

* a file that is empty or does not start with the MCAP magic is refused at once
  (:class:`McapFileError`, with the reason);
* a closed file's summary (statistics, schemas, channels) is read first, so the report can
  compare what was read with what was indexed;
* a chunk that cannot be decompressed or fails its CRC is skipped and counted, and reading
  goes on at the next record; after a damaged record header reading resynchronises on the
  next chunk;
* a file without footer ("not closed") is read up to its last complete record.

Everything that was not read is listed in the :class:`ReadReport`. :func:`recover` rewrites a
file as a finalised, indexed MCAP file from what is readable (MCAP's own "recover" idea).
"""

from __future__ import annotations

import mmap
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

MAGIC = b"\x89MCAP0\r\n"

_FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK = 0x02, 0x03, 0x04, 0x05, 0x06
#: Record opcodes the scan yields (``scan`` gives (opcode, record) pairs).
SCHEMA, CHANNEL, MESSAGE = _SCHEMA, _CHANNEL, _MESSAGE
_STATISTICS, _DATA_END = 0x0B, 0x0F
_KNOWN = set(range(0x01, 0x10))
_FOOTER_SIZE = 1 + 8 + 20


class McapFileError(ValueError):
    """The file is not an MCAP file (empty, wrong magic) or holds nothing readable."""


@dataclass
class ReadReport:
    """What a tolerant read of one MCAP file got, and what it could not read."""

    path: str
    size: int = 0
    #: The file has its summary and footer (the writer was closed properly).
    closed: bool = False
    messages: int = 0
    #: Message count from the summary's statistics (None: no summary).
    messages_indexed: int | None = None
    #: Messages per topic read, and indexed (closed files).
    topic_messages: dict[str, int] = field(default_factory=dict)
    topic_indexed: dict[str, int] = field(default_factory=dict)
    chunks: int = 0
    chunks_indexed: int | None = None
    chunks_skipped: int = 0
    #: Bytes of the data section that could not be read (damaged, or cut at the end).
    bytes_skipped: int = 0
    messages_undecodable: int = 0
    problems: list[str] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        """Closed, nothing skipped, every indexed message read."""
        return (
            self.closed
            and not self.problems
            and not self.messages_undecodable
            and (self.messages_indexed is None or self.messages >= self.messages_indexed)
        )

    def summary(self, hint: bool = True) -> str:
        """One line: what was read and what was lost (``hint``: how to recover the file)."""
        name = Path(self.path).name
        parts = [f"{name}: read {self.messages} messages"]
        if self.messages_indexed is not None:
            parts[0] += f" of {self.messages_indexed} indexed"
        if self.chunks_skipped:
            parts.append(f"{self.chunks_skipped} damaged chunk(s) skipped")
        if self.bytes_skipped:
            parts.append(f"{self.bytes_skipped} bytes unreadable")
        if self.messages_undecodable:
            parts.append(f"{self.messages_undecodable} undecodable message(s)")
        if not self.closed:
            text = "not closed (no summary or footer: the recorder was killed or the disk filled)"
            if hint:
                text += "; `bubble-rt recover` rewrites it as a finalised file"
            parts.append(text)
        return "; ".join(parts)


def _u8(b: Any, o: int) -> int:
    return int(b[o])


def _u16(b: Any, o: int) -> int:
    return int(struct.unpack_from("<H", b, o)[0])


def _u32(b: Any, o: int) -> int:
    return int(struct.unpack_from("<I", b, o)[0])


def _u64(b: Any, o: int) -> int:
    return int(struct.unpack_from("<Q", b, o)[0])


def _chunk_plausible(mm: Any, pos: int, size: int) -> bool:
    """Does a chunk record start at ``pos`` (opcode, length and inner lengths all agree)?"""
    if pos + 9 + 40 > size or mm[pos] != _CHUNK:
        return False
    length = _u64(mm, pos + 1)
    if pos + 9 + length > size or length < 40:
        return False
    body = pos + 9
    comp_len = _u32(mm, body + 28)
    if comp_len not in (0, 3, 4):
        return False
    comp = bytes(mm[body + 32 : body + 32 + comp_len])
    if comp not in (b"", b"lz4", b"zstd"):
        return False
    data_len = _u64(mm, body + 32 + comp_len)
    return data_len == length - (40 + comp_len)


def _resync(mm: Any, start: int, end: int) -> int:
    """Offset of the next plausible chunk record after ``start`` (``end`` if none)."""
    pos = start
    while True:
        pos = mm.find(bytes([_CHUNK]), pos + 1, end)
        if pos < 0:
            return end
        if _chunk_plausible(mm, pos, end):
            return pos


def _records_in(data: bytes) -> Iterator[tuple[int, Any]]:
    """(opcode, record) of Schema, Channel and Message records in a chunk's payload."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Message, Schema

    stream = ReadDataStream(BytesIO(data))
    n = len(data)
    while stream.count < n:
        opcode = stream.read1()
        length = stream.read8()
        if stream.count + length > n:
            raise ValueError(f"record of {length} bytes overruns the chunk")
        start = stream.count
        if opcode == _SCHEMA:
            yield opcode, Schema.read(stream)
        elif opcode == _CHANNEL:
            yield opcode, Channel.read(stream)
        elif opcode == _MESSAGE:
            yield opcode, Message.read(stream, length)
        used = stream.count - start
        if length > used:
            stream.read(length - used)


def _chunk_records(body: bytes) -> list[tuple[int, Any]]:
    """Decompress and CRC-check one chunk record body; all its records or an exception."""
    import zlib

    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk

    chunk = Chunk.read(ReadDataStream(BytesIO(body)))
    if chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size
        )
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ValueError(f"unknown chunk compression {chunk.compression!r}")
    if len(data) != chunk.uncompressed_size:
        raise ValueError(f"{len(data)} bytes after decompression, {chunk.uncompressed_size} stored")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("CRC mismatch")
    return list(_records_in(data))


def _read_summary(mm: Any, size: int, report: ReadReport) -> tuple[list[tuple[int, Any]], int]:
    """Schema and channel records of a closed file's summary, and where its data section ends."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Schema, Statistics

    if size < 8 + _FOOTER_SIZE + 8 or bytes(mm[size - 8 :]) != MAGIC:
        return [], size
    f = size - 8 - _FOOTER_SIZE
    if mm[f] != _FOOTER or _u64(mm, f + 1) != 20:
        return [], size
    summary_start = _u64(mm, f + 9)
    if summary_start == 0:  # closed without a summary section
        report.closed = True
        return [], f
    if not 8 < summary_start <= f:
        report.problems.append(f"footer points outside the file (summary at {summary_start})")
        return [], size
    out: list[tuple[int, Any]] = []
    pos = summary_start
    topics: dict[int, str] = {}
    counts: dict[int, int] = {}
    try:
        while pos < f:
            opcode, length = _u8(mm, pos), _u64(mm, pos + 1)
            body = bytes(mm[pos + 9 : pos + 9 + length])
            stream = ReadDataStream(BytesIO(body))
            if opcode == _SCHEMA:
                out.append((opcode, Schema.read(stream)))
            elif opcode == _CHANNEL:
                ch = Channel.read(stream)
                topics[ch.id] = ch.topic
                out.append((opcode, ch))
            elif opcode == _STATISTICS:
                st = Statistics.read(stream)
                report.messages_indexed = st.message_count
                report.chunks_indexed = st.chunk_count
                counts = dict(st.channel_message_counts)
            pos += 9 + length
    except Exception as exc:
        report.problems.append(f"summary unreadable at byte {pos}: {exc}")
        return out, size
    report.closed = True
    report.topic_indexed = {topics.get(cid, str(cid)): n for cid, n in counts.items()}
    return out, summary_start


def check_mcap_file(path: str | Path) -> None:
    """Raise :class:`McapFileError` at once if ``path`` is empty or not an MCAP file."""
    from bubble_rt._validate import PathError, regular_file

    p = Path(path)
    try:
        regular_file("recording", p)  # a FIFO would block the open, a device never end
    except PathError as exc:
        raise McapFileError(str(exc)) from None
    try:
        with open(p, "rb") as f:
            head = f.read(len(MAGIC))
    except OSError as exc:
        raise McapFileError(f"{p}: cannot read: {exc}") from exc
    if not head:
        raise McapFileError(f"{p}: empty file (0 bytes), not an MCAP recording")
    if head != MAGIC:
        raise McapFileError(
            f"{p}: not an MCAP file (starts with {head!r}; MCAP files start with {MAGIC!r})"
        )


def scan(path: str | Path, report: ReadReport | None = None) -> Iterator[tuple[int, Any]]:
    """(opcode, record) of every readable Schema, Channel and Message record, in file order.

    ``report`` (a :class:`ReadReport`) is filled in while iterating: complete once the
    iterator is exhausted. Raises :class:`McapFileError` before yielding anything for an
    empty or non-MCAP file.
    """
    p = Path(path)
    report = report if report is not None else ReadReport(str(p))
    check_mcap_file(p)
    topics: dict[int, str] = {}

    def counted(items: list[tuple[int, Any]]) -> Iterator[tuple[int, Any]]:
        for opcode, rec in items:
            if opcode == _CHANNEL:
                topics[rec.id] = rec.topic
            elif opcode == _MESSAGE:
                report.messages += 1
                t = topics.get(rec.channel_id, str(rec.channel_id))
                report.topic_messages[t] = report.topic_messages.get(t, 0) + 1
            yield opcode, rec

    with open(p, "rb") as fh:
        size = report.size = int(Path(p).stat().st_size)
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            summary_records, data_end = _read_summary(mm, size, report)
            for opcode, rec in summary_records:
                if opcode == _CHANNEL:
                    topics[rec.id] = rec.topic
                yield opcode, rec
            pos = len(MAGIC)
            while pos < data_end:
                if pos + 9 > data_end:
                    report.bytes_skipped += data_end - pos
                    report.problems.append(
                        f"file ends inside a record header at byte {pos} ({data_end - pos} "
                        "bytes unreadable: the file was cut)"
                    )
                    break
                opcode, length = mm[pos], _u64(mm, pos + 1)
                end = pos + 9 + length
                if opcode not in _KNOWN or end > data_end:
                    pos = _skip_damaged(mm, pos, data_end, opcode, report)
                    continue
                if opcode in (_DATA_END, _FOOTER):
                    break
                yield from counted(_records_at(mm, pos, opcode, length, report))
                pos = end
    _final_problems(report)


def _skip_damaged(mm: Any, pos: int, data_end: int, opcode: int, report: ReadReport) -> int:
    """Past a record header that is damaged or runs beyond the data: the next byte where a
    record header reads well (``_resync``), the skip reported."""
    nxt = _resync(mm, pos, data_end)
    report.bytes_skipped += nxt - pos
    if nxt >= data_end and opcode in _KNOWN:
        report.problems.append(
            f"file ends inside a record at byte {pos} (the last {nxt - pos} "
            "bytes are unreadable: the file was cut)"
        )
    else:
        report.problems.append(f"damaged record header at byte {pos}: skipped {nxt - pos} bytes")
    return nxt


def _records_at(
    mm: Any, pos: int, opcode: int, length: int, report: ReadReport
) -> list[tuple[int, Any]]:
    """The Schema, Channel and Message records of the record at ``pos`` (a chunk's, or the
    record itself); a damaged one is reported and gives none."""
    body = bytes(mm[pos + 9 : pos + 9 + length])
    if opcode == _CHUNK:
        try:
            records = _chunk_records(body)
        except Exception as exc:
            report.chunks_skipped += 1
            report.bytes_skipped += 9 + length
            report.problems.append(
                f"damaged chunk at byte {pos} ({9 + length} bytes) skipped: "
                f"{type(exc).__name__}: {exc}"
            )
            return []
        report.chunks += 1
        return records
    if opcode not in (_SCHEMA, _CHANNEL, _MESSAGE):
        return []
    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Message, Schema

    stream = ReadDataStream(BytesIO(body))
    try:
        if opcode == _SCHEMA:
            rec: Any = Schema.read(stream)
        elif opcode == _CHANNEL:
            rec = Channel.read(stream)
        else:
            rec = Message.read(stream, length)
    except Exception as exc:
        report.bytes_skipped += 9 + length
        report.problems.append(f"damaged record at byte {pos}: {exc}")
        return []
    return [(opcode, rec)]


def _final_problems(report: ReadReport) -> None:
    """What the whole read says: no summary or footer, or indexed messages not read."""
    if not report.closed:
        report.problems.insert(0, "not closed (no summary or footer)")
    elif report.messages_indexed is not None and report.messages < report.messages_indexed:
        report.problems.append(
            f"{report.messages_indexed - report.messages} of {report.messages_indexed} indexed "
            "messages not read"
        )

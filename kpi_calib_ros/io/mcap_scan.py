"""Record-level reading of an MCAP file that recovers everything before damage.

The mcap library's readers stop at (or raise on) the first incomplete record, so a
recording cut inside a chunk loses the whole chunk. This scanner walks the records
itself: complete chunks are CRC-checked and split into their messages, a chunk cut by
the end of the file yields every message completely inside the part that exists, and
a chunk whose CRC does not match is skipped. Every skipped byte is counted, so the
caller can say how much was unreadable.

Messages are not decoded here: each is kept as ``(buffer, start, end)`` with its
header stamp, read straight from the CDR bytes (every stream type we read starts with
a ``std_msgs/Header``), so a reader can pick the messages it needs before decoding.
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from io import BytesIO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Metadata, Schema

from kpi_calib_ros.core.errors import KpiCalibError

MAGIC = b'\x89MCAP0\r\n'
_RECORD = struct.Struct('<BQ')
# Message record after opcode+length: channel, sequence, log time, publish time; then the
# CDR payload: encapsulation (2 bytes + 2 options), header stamp sec, nanosec.
_MESSAGE = struct.Struct('<BQHIQQ2s2xiI')
_MESSAGE_MIN = _MESSAGE.size - 9
_CHUNK_HEAD = struct.Struct('<QQQII')


class BagError(KpiCalibError, ValueError):
    """A bag that cannot be read (or written) as asked; the message names the file, the
    topic and the fix."""


@dataclass
class ChannelMessages:
    """The messages of one channel, in file order: payload ``buffers[b][start:end]``
    and header stamp (ns; ``None`` where the payload is not little-endian CDR)."""

    buffer: list[int] = field(default_factory=list)
    start: list[int] = field(default_factory=list)
    end: list[int] = field(default_factory=list)
    stamp_ns: list[int | None] = field(default_factory=list)
    order: list[int] = field(default_factory=list)  # position among all messages read


@dataclass
class ScannedBag:
    """Everything readable in one MCAP file, undecoded."""

    size: int
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: list[Metadata] = field(default_factory=list)
    buffers: list[bytes] = field(default_factory=list)
    messages: dict[int, ChannelMessages] = field(default_factory=dict)
    finalised: bool = False
    unreadable_bytes: int = 0
    problems: list[str] = field(default_factory=list)
    count: int = 0

    def payload(self, channel_id: int, i: int) -> bytes:
        m = self.messages[channel_id]
        return self.buffers[m.buffer[i]][m.start[i]:m.end[i]]


def _decompress(path, compression: str, data: bytes, size: int) -> bytes:
    if compression == '':
        return data
    if compression == 'lz4':
        import lz4.frame
        return lz4.frame.decompress(data)
    if compression == 'zstd':
        try:
            import zstandard
        except ImportError:
            raise BagError(f'{path}: chunks are compressed with zstd which is not installed; '
                           'pip install zstandard, or re-record with the default storage '
                           'preset (no compression)') from None
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    raise BagError(f"{path}: chunks are compressed with '{compression}', which no MCAP "
                   'reader knows; re-record with the default storage preset')


def _partial_lz4(data: bytes) -> bytes:
    import lz4.frame
    try:
        return lz4.frame.LZ4FrameDecompressor().decompress(data)
    except RuntimeError:
        return b''


def _records(bag: ScannedBag, buf: bytes, pos: int, end: int, top: bool, path) -> int:
    """Walk the records of ``buf[pos:end]``; returns where the complete ones stop."""
    b = len(bag.buffers)
    bag.buffers.append(buf)
    messages = bag.messages
    unpack_message, unpack_record = _MESSAGE.unpack_from, _RECORD.unpack_from
    while pos + 9 <= end:
        opcode, length = unpack_record(buf, pos)
        stop = pos + 9 + length
        if stop > end:
            if top and opcode == Opcode.CHUNK:  # cut inside a chunk: keep what is whole
                bag.unreadable_bytes += _chunk(bag, buf, pos, end, path)
                return end
            break
        if opcode == Opcode.MESSAGE and length >= 22:
            if length >= _MESSAGE_MIN:
                _, _, channel, _, _, _, encapsulation, sec, nanosec = unpack_message(buf, pos)
                stamp = sec * 1_000_000_000 + nanosec if encapsulation == b'\x00\x01' else None
            else:
                (channel,) = struct.unpack_from('<H', buf, pos + 9)
                stamp = None
            m = messages.get(channel)
            if m is None:
                m = messages[channel] = ChannelMessages()
            m.buffer.append(b)
            m.start.append(pos + 31)
            m.end.append(stop)
            m.stamp_ns.append(stamp)
            m.order.append(bag.count)
            bag.count += 1
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA):
            stream = ReadDataStream(BytesIO(buf[pos + 9:stop]))
            try:
                if opcode == Opcode.SCHEMA:
                    schema = Schema.read(stream)
                    bag.schemas[schema.id] = schema
                elif opcode == Opcode.CHANNEL:
                    channel_record = Channel.read(stream)
                    bag.channels[channel_record.id] = channel_record
                else:
                    bag.metadata.append(Metadata.read(stream))
            except (McapError, struct.error, UnicodeDecodeError, ValueError) as error:
                raise BagError(f'{path}: corrupt MCAP record at byte {pos} ({error!r}); '
                               're-copy or re-record the file') from error
        elif top and opcode == Opcode.CHUNK:
            bag.unreadable_bytes += _chunk(bag, buf, pos, stop, path)
        elif top and opcode == Opcode.FOOTER:
            bag.finalised = True
            return stop
        pos = stop
    return pos


def _chunk(bag: ScannedBag, buf: bytes, pos: int, stop: int, path) -> int:
    """Read the chunk record at ``buf[pos:stop]`` (``stop`` short of its declared end when
    the file was cut inside it); returns the bytes of it that could not be used."""
    p = pos + 9
    if p + _CHUNK_HEAD.size > stop:
        return stop - pos
    _, _, size, crc, name_length = _CHUNK_HEAD.unpack_from(buf, p)
    p += _CHUNK_HEAD.size
    if p + name_length + 8 > stop:
        return stop - pos
    compression = buf[p:p + name_length].decode('utf-8', 'replace')
    p += name_length
    (data_length,) = struct.unpack_from('<Q', buf, p)
    p += 8
    complete = p + data_length <= stop
    data = buf[p:min(p + data_length, stop)]
    if complete:
        inner = _decompress(path, compression, data, size)
        if crc and zlib.crc32(inner) != crc:
            bag.problems.append(f'a chunk at byte {pos} fails its CRC check')
            return stop - pos
    elif compression == '':
        inner = data
    elif compression == 'lz4':
        inner = _partial_lz4(data)
    else:
        return stop - pos
    used = _records(bag, inner, 0, len(inner), False, path)
    if compression == '':
        return stop - (p + used)
    return 0 if complete else stop - pos


def scan(path, data: bytes) -> ScannedBag:
    """Every complete record of the MCAP bytes ``data`` read from ``path``.

    ``unreadable_bytes`` counts what could not be used: a torn record at the end, the
    unusable part of a chunk cut by the end of the file, chunks failing their CRC.
    """
    bag = ScannedBag(size=len(data))
    used = _records(bag, data, len(MAGIC), len(data), True, path)
    if not bag.finalised:
        bag.unreadable_bytes += len(data) - used
    return bag


__all__ = ['BagError', 'ChannelMessages', 'MAGIC', 'ScannedBag', 'scan']

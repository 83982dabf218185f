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

import mmap
import struct
import zlib
from dataclasses import dataclass, field
from io import BytesIO
from typing import Sequence, Union

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Metadata, Schema

from kpi_calib_ros.core.errors import KpiCalibError

MAGIC = b'\x89MCAP0\r\n'
# What records are read from: the file's bytes or its memory map, a view into a chunk of
# it, or a chunk's decompressed bytes.
Buffer = Union[bytes, memoryview, mmap.mmap]
_RECORD = struct.Struct('<BQ')
# Message record after opcode+length: channel, sequence, log time, publish time; then the
# CDR payload: encapsulation (2 bytes + 2 options), header stamp sec, nanosec.
_MESSAGE = struct.Struct('<BQHIQQ2s2xiI')
_MESSAGE_MIN = _MESSAGE.size - 9
_CHUNK_HEAD = struct.Struct('<QQQII')


class BagError(KpiCalibError, ValueError):
    """A bag that cannot be read (or written) as asked; the message names the file, the
    topic and the fix."""


class ChannelMessages:
    """The messages of one channel: payload ``buffers[buffer[i]][start[i]:end[i]]``,
    header stamp ``stamp_ns[i]`` (valid where ``stamped[i]``: little-endian CDR), and
    file order by ``(major[i], minor[i])`` (record position, position inside a chunk)."""

    def __init__(self) -> None:
        self._walked: list[tuple[int, int, int, int, bool, int, int]] = []
        self._segments: list[tuple[np.ndarray, ...]] = []

    def add(self, buffer: int, start: int, end: int, stamp: int, stamped: bool, major: int,
            minor: int) -> None:
        self._walked.append((buffer, start, end, stamp, stamped, major, minor))

    def add_many(self, *columns: np.ndarray) -> None:
        self._segments.append(columns)

    def finish(self) -> None:
        columns = [np.concatenate([seg[k] for seg in self._segments]
                                  + [np.array([w[k] for w in self._walked],
                                              dtype=bool if k == 4 else np.int64)])
                   for k in range(7)]
        (self.buffer, self.start, self.end, self.stamp_ns, self.stamped, self.major,
         self.minor) = columns
        self.stamped = self.stamped.astype(bool)
        self._walked, self._segments = [], []

    def __len__(self) -> int:
        return len(self.buffer)


@dataclass
class ScannedBag:
    """Everything readable in one MCAP file, undecoded."""

    size: int
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: list[Metadata] = field(default_factory=list)
    buffers: list = field(default_factory=list)
    messages: dict[int, ChannelMessages] = field(default_factory=dict)
    finalised: bool = False
    unreadable_bytes: int = 0
    problems: list[str] = field(default_factory=list)

    def channel(self, channel_id: int) -> ChannelMessages:
        m = self.messages.get(channel_id)
        if m is None:
            m = self.messages[channel_id] = ChannelMessages()
        return m

    def payload(self, channel_id: int, i: int) -> bytes:
        m = self.messages[channel_id]
        return bytes(self.buffers[m.buffer[i]][m.start[i]:m.end[i]])


def _decompress(path, compression: str, data: memoryview, size: int) -> Buffer:
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


def _partial_lz4(data: memoryview) -> bytes:
    import lz4.frame
    try:
        return lz4.frame.LZ4FrameDecompressor().decompress(data)
    except RuntimeError:
        return b''


def _records(bag: ScannedBag, buf, pos: int, end: int, top: bool, path,
             major: int | None = None) -> int:
    """Walk the records of ``buf[pos:end]``; returns where the complete ones stop.
    ``major``: file position of the chunk ``buf`` came from (None: ``buf`` is the file)."""
    b = len(bag.buffers)
    bag.buffers.append(buf)
    unpack_message, unpack_record = _MESSAGE.unpack_from, _RECORD.unpack_from
    while pos + 9 <= end:
        opcode, length = unpack_record(buf, pos)
        stop = pos + 9 + length
        if stop > end:
            if top and opcode == Opcode.CHUNK:  # cut inside a chunk: keep what is whole
                bag.unreadable_bytes += _chunk(bag, buf, pos, end, path, [])
                return end
            break
        if opcode == Opcode.MESSAGE and length >= 22:
            if length >= _MESSAGE_MIN:
                _, _, channel, _, _, _, encapsulation, sec, nanosec = unpack_message(buf, pos)
                stamped = encapsulation == b'\x00\x01'
                stamp = sec * 1_000_000_000 + nanosec if stamped else 0
            else:
                (channel,) = struct.unpack_from('<H', buf, pos + 9)
                stamp, stamped = 0, False
            bag.channel(channel).add(b, pos + 31, stop, stamp, stamped,
                                     pos if major is None else major,
                                     0 if major is None else pos + 1)
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA):
            stream = ReadDataStream(BytesIO(bytes(buf[pos + 9:stop])))
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
            indexes = []  # the chunk's message indexes follow it (rosbag2, mcap writers)
            after = stop
            while after + 9 <= end:
                next_opcode, next_length = unpack_record(buf, after)
                if next_opcode != Opcode.MESSAGE_INDEX or after + 9 + next_length > end:
                    break
                indexes.append(buf[after + 9:after + 9 + next_length])
                after += 9 + next_length
            bag.unreadable_bytes += _chunk(bag, buf, pos, stop, path, indexes)
            _release(buf, pos, stop)
            stop = after
        elif top and opcode == Opcode.FOOTER:
            bag.finalised = True
            return stop
        pos = stop
    return pos


def _release(buf, start: int, stop: int) -> None:
    """Give back the pages of a mapped file range already scanned: memory stays that of
    the index, not of the file (the few payloads decoded later are paged in again)."""
    if isinstance(buf, mmap.mmap):
        first = start // mmap.PAGESIZE * mmap.PAGESIZE
        buf.madvise(mmap.MADV_DONTNEED, first, stop - first)


def _indexed(bag: ScannedBag, inner, chunk_pos: int, indexes: list, path) -> bool:
    """Locate a chunk's messages from its message indexes, vectorised; False if the
    indexes do not describe the chunk (then it is walked record by record)."""
    offsets = []
    for index in indexes:
        if len(index) < 6:
            return False
        (n,) = struct.unpack_from('<I', index, 2)
        if n % 16 or 6 + n > len(index):
            return False
        offsets.append(np.frombuffer(index, '<u8', n // 8, 6)[1::2])
    if not offsets:
        return False
    o = np.sort(np.concatenate(offsets)).astype(np.int64)
    data = np.frombuffer(inner, np.uint8)
    if len(o) == 0 or o[-1] + 31 + 12 > len(data) or o[0] < 0:
        return False

    def gather(offset: int, width: int, dtype: str) -> np.ndarray:
        return data[(o + offset)[:, None] + np.arange(width)].copy().view(dtype).ravel()

    if not (data[o] == Opcode.MESSAGE).all():
        return False
    length = gather(1, 8, '<u8').astype(np.int64)
    stop = o + 9 + length
    if (stop > len(data)).any() or (length < _MESSAGE_MIN).any() or (stop[:-1] > o[1:]).any():
        return False
    channel = gather(9, 2, '<u2')
    stamped = (data[o + 31] == 0) & (data[o + 32] == 1)
    stamp = (gather(35, 4, '<i4').astype(np.int64) * 1_000_000_000
             + gather(39, 4, '<u4').astype(np.int64))
    b = len(bag.buffers)
    bag.buffers.append(inner)
    for c in np.unique(channel):
        k = channel == c
        bag.channel(int(c)).add_many(np.full(k.sum(), b), o[k] + 31, stop[k], stamp[k],
                                     stamped[k], np.full(k.sum(), chunk_pos), o[k] + 1)
    # What the indexes do not cover (schemas, channels) is walked.
    starts = np.concatenate([[0], stop])
    ends = np.concatenate([o, [len(data)]])
    for gap_start, gap_end in zip(starts[starts < ends], ends[starts < ends]):
        _records(bag, inner, int(gap_start), int(gap_end), False, path, chunk_pos)
    return True


def _chunk(bag: ScannedBag, buf, pos: int, stop: int, path, indexes: list) -> int:
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
    data = memoryview(buf)[p:min(p + data_length, stop)]  # no copy of the file
    inner: Buffer
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
    if complete and _indexed(bag, inner, pos, indexes, path):
        return 0
    used = _records(bag, inner, 0, len(inner), False, path, pos)
    if compression == '':
        return stop - (p + used)
    return 0 if complete else stop - pos


def scan(path, data: Buffer) -> ScannedBag:
    """Every complete record of the MCAP bytes ``data`` read from ``path``.

    ``unreadable_bytes`` counts what could not be used: a torn record at the end, the
    unusable part of a chunk cut by the end of the file, chunks failing their CRC.
    """
    bag = ScannedBag(size=len(data))
    used = _records(bag, data, len(MAGIC), len(data), True, path)
    if not bag.finalised:
        bag.unreadable_bytes += len(data) - used
    for messages in bag.messages.values():
        messages.finish()
    return bag


def side_messages(bag: ScannedBag, skip: Sequence[str]
                  ) -> tuple[list[tuple[int, str, str, bytes]], list[str]]:
    """Return the messages of every other topic of a scanned bag, as recorded, for a player.

    Returns [(header stamp ns, topic, ROS type, CDR payload)] of the topics not in ``skip``
    (the joint, point and pose topics a player rebuilds), in stamp order, and the topics it
    cannot give (not CDR, or a message without a header stamp to place it in time).
    """
    out: list[tuple[int, str, str, bytes]] = []
    unsent: list[str] = []
    for cid, channel in sorted(bag.channels.items()):
        messages = bag.messages.get(cid)
        if channel.topic in set(skip) or messages is None or not len(messages):
            continue
        schema = bag.schemas.get(channel.schema_id)
        if (schema is None or channel.message_encoding != 'cdr'
                or not bool(np.all(messages.stamped))):
            unsent.append(channel.topic)
            continue
        out += [(int(messages.stamp_ns[i]), channel.topic, schema.name, bag.payload(cid, i))
                for i in range(len(messages))]
    out.sort(key=lambda m: m[0])
    return out, sorted(set(unsent))


__all__ = ['BagError', 'ChannelMessages', 'MAGIC', 'ScannedBag', 'scan', 'side_messages']

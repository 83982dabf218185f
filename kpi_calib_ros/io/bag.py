"""MCAP bags of joint states and tracker points, and the node's durable measurement log.

Bags are written the way ``ros2 bag record -s mcap`` (Jazzy, default storage
preset) writes them: profile ``ros2``, one ``ros2msg`` schema per type holding the
complete message definition (the ``.msg`` texts of the type and of every type it
uses, joined with rosbag2's ``====`` / ``MSG: pkg/Type`` delimiters), ``cdr``
channels carrying ``offered_qos_profiles`` and ``topic_type_hash`` metadata,
uncompressed chunks, and log time = publish time = header stamp.

Reading is a single linear pass over complete records, so a bag whose writer was
killed mid-recording (no summary, no footer, a torn last record) still yields every
message that was completely written.
"""
from __future__ import annotations

import functools
import importlib.util
import io
import json
import os
import re
import struct
import sys
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np
from mcap.exceptions import EndOfFile, McapError, UnsupportedCompressionError
from mcap.opcode import Opcode
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory
# The encoder that mcap_ros2.writer.Writer uses internally; that Writer cannot set
# channel metadata or disable chunking, both of which we need.
from mcap_ros2._dynamic import serialize_dynamic

from kpi_calib_ros.core.errors import KpiCalibError
from kpi_calib_ros.core.streams import JointSample, PointSample
from kpi_calib_ros.io.names import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC  # noqa: F401  (re-exported)

JOINT_STATE_TYPE = 'sensor_msgs/msg/JointState'
POINT_STAMPED_TYPE = 'geometry_msgs/msg/PointStamped'

_MAGIC = b'\x89MCAP0\r\n'
_LIBRARY = f'kpi_calib_ros; {LIBRARY_IDENTIFIER}'
_ROSBAG2_CHUNK_SIZE = 768 * 1024  # libmcap's default, which rosbag2 keeps
# What a default reliable/volatile publisher offers, as rosbag2 (metadata v9) writes it.
_INFINITE = '\n    sec: 9223372036\n    nsec: 854775807'
_OFFERED_QOS = (
    '- history: keep_last\n  depth: 10\n  reliability: reliable\n  durability: volatile\n'
    f'  deadline:{_INFINITE}\n  lifespan:{_INFINITE}\n  liveliness: automatic\n'
    f'  liveliness_lease_duration:{_INFINITE}\n  avoid_ros_namespace_conventions: false'
)
# rosbag2's LocalMessageDefinitionSource: the first token of each line is a field type.
_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_PRIMITIVES = frozenset({'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16',
                         'uint16', 'int32', 'uint32', 'int64', 'uint64', 'string'})


class BagError(KpiCalibError, ValueError):
    """A bag that cannot be read (or written) as asked; the message names the file, the
    topic and the fix."""


def _share_prefixes(package: str) -> list[Path]:
    prefixes = [Path(p) for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    spec = importlib.util.find_spec(package)
    if spec is not None and spec.origin:
        parents = Path(spec.origin).resolve().parents
        if len(parents) > 4:  # <prefix>/lib/pythonX.Y/site-packages/<package>/__init__.py
            prefixes.append(parents[4])
    prefixes.append(Path(sys.prefix))
    return prefixes


@functools.lru_cache(maxsize=None)
def _definition_file(type_name: str, extension: str) -> Path:
    parts = type_name.split('/')
    package, interface = parts[0], (parts[1] if len(parts) == 3 else 'msg')
    for prefix in _share_prefixes(package):
        candidate = prefix / 'share' / package / interface / (parts[-1] + extension)
        if candidate.is_file():
            return candidate
    raise BagError(f"no {extension} file for '{type_name}' under share/{package}/{interface} "
                   f'of AMENT_PREFIX_PATH or {sys.prefix}; install {package} '
                   '(ROS 2 Jazzy) or source its setup file')


@functools.lru_cache(maxsize=None)
def message_definition(type_name: str) -> str:
    """The complete ``ros2msg`` definition of ``type_name``, exactly as rosbag2 stores it.

    The type's own ``.msg`` text comes first; each dependency not yet included follows
    depth-first, in sorted order, after a line of 80 ``=`` and a ``MSG: pkg/Type`` line.

    Parameters
    ----------
    type_name : str
        e.g. ``'sensor_msgs/msg/JointState'``.
    """
    seen: set[str] = set()

    def text_with_dependencies(name: str) -> str:
        text = _definition_file(name, '.msg').read_bytes().decode('utf-8')  # bytes as stored
        package = name.split('/')[0]
        dependencies = set()
        for match in _FIELD_TYPE.finditer(text):
            field_type = match.group(1)
            if field_type not in _PRIMITIVES:
                dependencies.add(field_type if '/' in field_type else f'{package}/{field_type}')
        for dependency in sorted(dependencies):
            if dependency not in seen:
                seen.add(dependency)
                text += f"\n{'=' * 80}\nMSG: {dependency}\n" + text_with_dependencies(dependency)
        return text

    return text_with_dependencies(type_name)


@functools.lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """The ``RIHS01_…`` type description hash rosidl generated for ``type_name``, or ``''``
    where rosidl generated none (rosbag2 then records it empty too)."""
    try:
        description = json.loads(_definition_file(type_name, '.json').read_bytes())
    except BagError:
        return ''
    return next((h['hash_string'] for h in description.get('type_hashes', [])
                 if h['type_name'] == type_name), '')


def _ros_time(stamp_ns: int) -> dict[str, int]:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    if not -2 ** 31 <= sec < 2 ** 31:
        raise ValueError(f'stamp {stamp_ns} ns does not fit builtin_interfaces/Time')
    return {'sec': sec, 'nanosec': nanosec}


class _Recorder:
    """Writes JointState and PointStamped messages to one MCAP stream."""

    def __init__(self, stream, joint_topic: str, point_topic: str, chunked: bool,
                 chunk_size: int = _ROSBAG2_CHUNK_SIZE) -> None:
        if joint_topic == point_topic:
            raise ValueError(f"joint_topic and point_topic must differ, both are '{joint_topic}'")
        self._writer = McapWriter(stream, chunk_size=chunk_size,
                                  compression=CompressionType.NONE, use_chunking=chunked)
        self._writer.start(profile='ros2', library=_LIBRARY)
        self._channels = {}
        for topic, type_name in ((joint_topic, JOINT_STATE_TYPE),
                                 (point_topic, POINT_STAMPED_TYPE)):
            text = message_definition(type_name)
            schema_id = self._writer.register_schema(type_name, SchemaEncoding.ROS2, text.encode())
            channel_id = self._writer.register_channel(
                topic, MessageEncoding.CDR, schema_id,
                {'offered_qos_profiles': _OFFERED_QOS, 'topic_type_hash': type_hash(type_name)})
            self._channels[type_name] = [channel_id, serialize_dynamic(type_name, text)[type_name],
                                         0]

    def _write(self, type_name: str, stamp_ns: int, message: dict) -> None:
        entry = self._channels[type_name]
        entry[2] += 1
        self._writer.add_message(channel_id=entry[0], log_time=int(stamp_ns),
                                 publish_time=int(stamp_ns), sequence=entry[2],
                                 data=entry[1](message))

    def write_joint(self, sample: JointSample) -> None:
        velocity = [] if sample.velocities is None else sample.velocities.tolist()
        self._write(JOINT_STATE_TYPE, sample.stamp_ns, {
            'header': {'stamp': _ros_time(sample.stamp_ns), 'frame_id': ''},
            'name': list(sample.names), 'position': sample.positions.tolist(),
            'velocity': velocity, 'effort': []})

    def write_point(self, sample: PointSample) -> None:
        x, y, z = sample.xyz.tolist()
        self._write(POINT_STAMPED_TYPE, sample.stamp_ns, {
            'header': {'stamp': _ros_time(sample.stamp_ns), 'frame_id': sample.frame_id},
            'point': {'x': x, 'y': y, 'z': z}})

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, data)

    def finish(self) -> None:
        self._writer.finish()


def write_bag(
    path: str | os.PathLike,
    joint_samples: Iterable[JointSample],
    point_samples: Iterable[PointSample],
    joint_topic: str = DEFAULT_JOINT_TOPIC,
    point_topic: str = DEFAULT_POINT_TOPIC,
    chunk_size: int = _ROSBAG2_CHUNK_SIZE,
) -> Path:
    """Write joint states and tracker points to an MCAP bag, in stamp order.

    Parameters
    ----------
    path : path-like
        The ``.mcap`` file to create (overwritten if present).
    joint_samples, point_samples : iterables of JointSample / PointSample
        Published as ``sensor_msgs/msg/JointState`` on ``joint_topic`` and
        ``geometry_msgs/msg/PointStamped`` on ``point_topic``.
    chunk_size : int
        Bytes per chunk before it is closed (rosbag2's default unless given).

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    stream = [(s.stamp_ns, 0, s) for s in joint_samples] + [(p.stamp_ns, 1, p)
                                                            for p in point_samples]
    stream.sort(key=lambda item: item[:2])
    with open(path, 'wb') as f:
        recorder = _Recorder(f, joint_topic, point_topic, chunked=True, chunk_size=chunk_size)
        for _, kind, sample in stream:
            (recorder.write_point if kind else recorder.write_joint)(sample)
        recorder.finish()
    return path


class _Prefix:
    """The first ``length`` bytes of a file: what the reader is allowed to see."""

    def __init__(self, f, length: int) -> None:
        self._f, self._left = f, length

    def read(self, n: int = -1) -> bytes:
        n = self._left if n < 0 else min(n, self._left)
        data = self._f.read(n)
        self._left -= len(data)
        return data


def _complete_prefix(f) -> tuple[int, bool]:
    """Length of the longest prefix made of whole records, and whether it ends the file
    properly (a footer). Seeks only: record headers are 9 bytes (opcode, length)."""
    size = f.seek(0, io.SEEK_END)
    position = len(_MAGIC)
    while position + 9 <= size:
        f.seek(position)
        opcode, length = struct.unpack('<BQ', f.read(9))
        if position + 9 + length > size:
            break
        if opcode == Opcode.FOOTER:
            if position + 9 + length + len(_MAGIC) <= size:
                return size, True
            break  # torn inside the closing magic: read up to the footer
        position += 9 + length
    return position, False


def _checked_path(path: str | os.PathLike) -> Path:
    path = Path(path)
    if path.is_dir():
        inside = sorted(p.name for p in path.glob('*.mcap'))
        raise BagError(f'{path} is a directory (a rosbag2 bag folder?); pass one of its .mcap '
                       f'files: {inside}' if inside else f'{path} is a directory with no .mcap '
                       'file; record one with `ros2 bag record -s mcap`')
    if not path.exists():
        raise BagError(f'{path}: no such file; pass the path of an .mcap bag '
                       '(e.g. recorded with `ros2 bag record -s mcap`)')
    return path


def _messages(path: Path, wanted: dict[str, tuple[str, str]], seen: dict[str, str],
              allow_empty: bool = False) -> Iterator[tuple[str, Any]]:
    """Yield ``(topic, decoded message)`` for the ``wanted`` topics (topic -> (type, argument
    name)) in file order; fill ``seen`` with every topic -> type met. Closes the file."""
    with open(path, 'rb') as f:
        magic = f.read(len(_MAGIC))
        if magic != _MAGIC:
            if allow_empty and _MAGIC.startswith(magic):
                return  # created, then killed before the header was written
            raise BagError(f'{path} is not an MCAP file (no MCAP magic); convert a SQLite '
                           'bag with `ros2 bag convert` or record with `ros2 bag record -s mcap`')
        end, finalised = _complete_prefix(f)
        f.seek(0)
        records = StreamReader(_Prefix(f, end), validate_crcs=True).records
        schemas: dict[int, Schema] = {}
        decoders: dict[int, tuple[str, Any]] = {}
        factory = DecoderFactory()
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except EndOfFile:
                if finalised:
                    raise BagError(f'{path}: MCAP file ends inside a record; the file is '
                                   'corrupt, re-copy or re-record it') from None
                return  # unfinalised: every complete record has been read
            except UnsupportedCompressionError as error:
                raise BagError(f'{path}: chunks are compressed with {error} which is not '
                               'installed; pip install it, or re-record with the default '
                               'storage preset (no compression)') from error
            except (McapError, ValueError, struct.error) as error:
                raise BagError(f'{path}: corrupt MCAP data ({error})') from error
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                schema = schemas.get(record.schema_id)
                type_name = schema.name if schema is not None else ''
                seen[record.topic] = type_name
                if record.topic not in wanted:
                    continue
                expected, argument = wanted[record.topic]
                if type_name != expected:
                    raise BagError(f"{path}: topic '{record.topic}' carries "
                                   f"'{type_name or 'no schema'}', expected '{expected}'; pass "
                                   f'{argument}= naming the topic that carries {expected}')
                decoder = factory.decoder_for(record.message_encoding, schema)
                if decoder is None:
                    raise BagError(f"{path}: topic '{record.topic}' is encoded as "
                                   f"'{record.message_encoding}' with a '{schema.encoding}' "
                                   "schema; only 'cdr' with 'ros2msg' schemas can be decoded")
                decoders[record.id] = (record.topic, decoder)
            elif isinstance(record, Message) and record.channel_id in decoders:
                topic, decoder = decoders[record.channel_id]
                try:
                    message = decoder(record.data)
                except Exception as error:  # any decoder failure means a corrupt message
                    raise BagError(f"{path}: message on '{topic}' logged at {record.log_time} "
                                   f'ns does not decode ({error!r})') from error
                yield topic, message


def stamp_ns(header) -> int:
    """Header stamp as integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def joint_sample_from_message(message) -> JointSample:
    """A sensor_msgs/JointState (rclpy message or decoded bag record) as a JointSample.

    The one conversion for files and the live node, stamped with the header stamp.
    A position array whose length differs from ``name`` becomes all-NaN, so the
    pairer counts it as ``non_finite_joint_state`` instead of it vanishing here;
    velocities of the wrong length, or none, become None.
    """
    names = tuple(message.name)
    positions = np.asarray(message.position, dtype=float)
    if positions.shape != (len(names),):
        positions = np.full(len(names), np.nan)
    velocities = np.asarray(message.velocity, dtype=float)
    return JointSample(stamp_ns(message.header), names, positions,
                       velocities if velocities.shape == (len(names),) else None)


def point_sample_from_message(message) -> PointSample:
    """A geometry_msgs/PointStamped (rclpy or decoded) as a PointSample (m, header frame)."""
    p = message.point
    return PointSample(stamp_ns(message.header), message.header.frame_id, [p.x, p.y, p.z])


def _read(path: Path, joint_topic: str, point_topic: str, require_topics: bool):
    if joint_topic == point_topic:
        raise ValueError(f"joint_topic and point_topic must differ, both are '{joint_topic}'")
    wanted = {joint_topic: (JOINT_STATE_TYPE, 'joint_topic'),
              point_topic: (POINT_STAMPED_TYPE, 'point_topic')}
    seen: dict[str, str] = {}
    messages = []
    for topic, message in _messages(path, wanted, seen, allow_empty=not require_topics):
        messages.append(joint_sample_from_message(message) if topic == joint_topic
                        else point_sample_from_message(message))
    for topic, (type_name, argument) in wanted.items():
        if require_topics and topic not in seen:
            present = ', '.join(f"'{t}' ({seen[t]})" for t in sorted(seen)) or 'none'
            raise BagError(f"{path}: topic '{topic}' is not in the bag; topics present: "
                           f'{present}. Pass {argument}= naming the {type_name} topic')
    return messages


def read_bag(
    path: str | os.PathLike,
    joint_topic: str = DEFAULT_JOINT_TOPIC,
    point_topic: str = DEFAULT_POINT_TOPIC,
) -> tuple[list[JointSample], list[PointSample]]:
    """Read joint states and tracker points from an MCAP bag, in file (recording) order.

    An unfinalised bag (recorder killed) yields every completely written message.

    Raises
    ------
    BagError
        File missing or not MCAP, a topic absent (the topics present are listed),
        or a topic carrying another message type.
    """
    messages = _read(_checked_path(path), joint_topic, point_topic, require_topics=True)
    return ([m for m in messages if isinstance(m, JointSample)],
            [m for m in messages if isinstance(m, PointSample)])


__all__ = ['BagError', 'DEFAULT_JOINT_TOPIC', 'DEFAULT_POINT_TOPIC', 'JOINT_STATE_TYPE',
           'POINT_STAMPED_TYPE', 'joint_sample_from_message', 'message_definition',
           'point_sample_from_message', 'read_bag', 'stamp_ns', 'type_hash', 'write_bag']

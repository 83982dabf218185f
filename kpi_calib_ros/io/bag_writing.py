"""Writing MCAP bags of joint states and tracker points as ``ros2 bag record -s mcap`` does.

Tracked 6-DoF poses (point samples with a rotation) go to a third topic as
``geometry_msgs/msg/PoseStamped``; a bag without any has no such channel. Cell
temperatures, where a table gives them, go to their own ``sensor_msgs/msg/Temperature``
topic, measured inputs (named values) to the inputs topic as ``sensor_msgs/msg/JointState``
(name = covariate, position = value). A bag is written under a temporary name beside
``path`` and renamed when complete, so a failed write leaves nothing behind.

Profile ``ros2``, one ``ros2msg`` schema per type holding the complete message
definition (the ``.msg`` texts of the type and of every type it uses, joined with
rosbag2's ``====`` / ``MSG: pkg/Type`` delimiters), ``cdr`` channels carrying
``offered_qos_profiles`` and ``topic_type_hash`` metadata, uncompressed chunks
(Jazzy's default storage preset), and log time = publish time = header stamp.
"""
from __future__ import annotations

import functools
import importlib.util
import json
import os
import re
import struct
import sys
import tempfile
from pathlib import Path
from types import TracebackType
from typing import Iterable

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType
from mcap.writer import Writer as McapWriter

# The encoder that mcap_ros2.writer.Writer uses internally; that Writer cannot set
# channel metadata, which rosbag2 readers expect.
from mcap_ros2._dynamic import serialize_dynamic

from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
from kpi_calib_ros.io.mcap_scan import BagError
from kpi_calib_ros.io.names import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC, DEFAULT_POSE_TOPIC
from kpi_calib_ros.io.ros_messages import (
    point_stamped_fields,
    pose_stamped_fields,
    stamp_fields,
    temperature_fields,
    vector3_stamped_fields,
)

JOINT_STATE_TYPE = 'sensor_msgs/msg/JointState'
POINT_STAMPED_TYPE = 'geometry_msgs/msg/PointStamped'
POSE_STAMPED_TYPE = 'geometry_msgs/msg/PoseStamped'
TEMPERATURE_TYPE = 'sensor_msgs/msg/Temperature'
VECTOR3_STAMPED_TYPE = 'geometry_msgs/msg/Vector3Stamped'   # a point's stated σ (m)

LIBRARY = f'kpi_calib_ros; {LIBRARY_IDENTIFIER}'
# The metadata record of a bag whose stamps number the rows of a table without times.
ROW_ORDER_METADATA = 'kpi_calib_ros_stamps'
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


class StreamEncoders:
    """Schema texts, channel metadata and CDR encoders of the stream topics (the pose,
    temperature, point-σ and inputs topics only when given)."""

    def __init__(self, joint_topic: str, point_topic: str, pose_topic: str | None = None,
                 temperature_topic: str | None = None, sigma_topic: str | None = None,
                 inputs_topic: str | None = None) -> None:
        if joint_topic == point_topic:
            raise ValueError(f"joint_topic and point_topic must differ, both are '{joint_topic}'")
        if pose_topic in (joint_topic, point_topic):
            raise ValueError(f"pose_topic '{pose_topic}' must differ from the joint and point "
                             'topics')
        if temperature_topic is not None and temperature_topic in (joint_topic, point_topic,
                                                                   pose_topic):
            raise ValueError(f"temperature_topic '{temperature_topic}' must differ from the "
                             'joint, point and pose topics')
        if sigma_topic is not None and sigma_topic in (joint_topic, point_topic, pose_topic,
                                                       temperature_topic):
            raise ValueError(f"sigma_topic '{sigma_topic}' must differ from the other topics")
        if inputs_topic is not None and inputs_topic in (joint_topic, point_topic, pose_topic,
                                                         temperature_topic, sigma_topic):
            raise ValueError(f"inputs_topic '{inputs_topic}' must differ from the other topics")
        self.topics: tuple[tuple[str, str], ...] = (
            (joint_topic, JOINT_STATE_TYPE), (point_topic, POINT_STAMPED_TYPE))
        if pose_topic is not None:
            self.topics += ((pose_topic, POSE_STAMPED_TYPE),)
        if temperature_topic is not None:
            self.topics += ((temperature_topic, TEMPERATURE_TYPE),)
        if sigma_topic is not None:
            self.topics += ((sigma_topic, VECTOR3_STAMPED_TYPE),)
        if inputs_topic is not None:
            self.topics += ((inputs_topic, JOINT_STATE_TYPE),)
        self.text = {t: message_definition(t) for _, t in self.topics}
        self.metadata = {t: {'offered_qos_profiles': _OFFERED_QOS, 'topic_type_hash': type_hash(t)}
                         for _, t in self.topics}
        # JointState (joint states and inputs) by joint_state_cdr; the others by mcap_ros2.
        self._encode = {t: serialize_dynamic(t, self.text[t])[t] for _, t in self.topics
                        if t != JOINT_STATE_TYPE}

    def joint(self, sample: JointSample) -> bytes:
        return joint_state_cdr(sample)

    def point(self, sample: PointSample) -> bytes:
        return self._encode[POINT_STAMPED_TYPE](point_stamped_fields(sample))

    def pose(self, sample: PointSample) -> bytes:
        return self._encode[POSE_STAMPED_TYPE](pose_stamped_fields(sample))

    def temperature(self, stamp_ns: int, frame_id: str, celsius: float) -> bytes:
        return self._encode[TEMPERATURE_TYPE](temperature_fields(stamp_ns, frame_id, celsius))

    def point_sigma(self, stamp_ns: int, frame_id: str, sigma: np.ndarray) -> bytes:
        return self._encode[VECTOR3_STAMPED_TYPE](vector3_stamped_fields(stamp_ns, frame_id,
                                                                         sigma))

    def inputs(self, stamp_ns: int, names: tuple[str, ...], values: np.ndarray) -> bytes:
        return joint_state_cdr(JointSample(stamp_ns, names, np.asarray(values, float)))


def _cdr_uint32(out: bytearray, value: int) -> None:
    """Append a uint32 at 4-byte alignment (counted after the 4-byte encapsulation)."""
    out += b'\0' * (-(len(out) - 4) % 4)
    out += struct.pack('<I', value)


def _cdr_string(out: bytearray, text: str) -> None:
    """Append a CDR string: uint32 length with the NUL, UTF-8, NUL."""
    data = text.encode('utf-8')
    _cdr_uint32(out, len(data) + 1)
    out += data + b'\0'


def _cdr_float64s(out: bytearray, values: np.ndarray | None) -> None:
    """Append a CDR sequence<float64>: its length, then the values at 8-byte alignment."""
    n = 0 if values is None else len(values)
    _cdr_uint32(out, n)
    if n:
        out += b'\0' * (-(len(out) - 4) % 8)
        out += np.asarray(values, dtype='<f8').tobytes()


def joint_state_cdr(sample: JointSample) -> bytes:
    """``sample`` as a sensor_msgs/msg/JointState in little-endian CDR.

    The bytes of mcap_ros2's dynamic encoder for
    :func:`~kpi_calib_ros.io.ros_messages.joint_state_fields` (a test holds
    them equal), written straight: that encoder, element by element in Python, took most of
    the time of writing a bag (joint states outnumber the points a hundred to one).
    """
    sec, nanosec = stamp_fields(sample.stamp_ns)
    out = bytearray(b'\x00\x01\x00\x00')  # CDR_LE encapsulation; alignment counts after it
    out += struct.pack('<iI', sec, nanosec)
    _cdr_string(out, '')  # header.frame_id
    _cdr_uint32(out, len(sample.names))
    for name in sample.names:
        _cdr_string(out, name)
    _cdr_float64s(out, sample.positions)
    _cdr_float64s(out, sample.velocities)
    _cdr_float64s(out, sample.efforts)
    return bytes(out)


class _Recorder:
    """Writes JointState and PointStamped messages to one chunked MCAP stream."""

    def __init__(self, stream, joint_topic: str, point_topic: str,
                 chunk_size: int = _ROSBAG2_CHUNK_SIZE, pose_topic: str | None = None,
                 temperature_topic: str | None = None, sigma_topic: str | None = None,
                 inputs_topic: str | None = None) -> None:
        self.encoders = StreamEncoders(joint_topic, point_topic, pose_topic, temperature_topic,
                                       sigma_topic, inputs_topic)
        self.inputs_topic = inputs_topic
        self._writer = McapWriter(stream, chunk_size=chunk_size,
                                  compression=CompressionType.NONE, use_chunking=True)
        self._writer.start(profile='ros2', library=LIBRARY)
        # channels by topic; the stream topics by their type (the first topic of a type: the
        # joint states before the inputs topic)
        self._channels: dict[str, list[int]] = {}
        self._topic_of: dict[str, str] = {}
        schemas: dict[str, int] = {}
        for topic, type_name in self.encoders.topics:
            if type_name not in schemas:
                schemas[type_name] = self._writer.register_schema(
                    type_name, SchemaEncoding.ROS2, self.encoders.text[type_name].encode())
            self._channels[topic] = [self._writer.register_channel(
                topic, MessageEncoding.CDR, schemas[type_name],
                self.encoders.metadata[type_name]), 0]
            self._topic_of.setdefault(type_name, topic)

    def _write(self, type_name: str, stamp_ns: int, data: bytes, topic: str | None = None
               ) -> None:
        entry = self._channels[topic or self._topic_of[type_name]]
        entry[1] += 1
        self._writer.add_message(channel_id=entry[0], log_time=int(stamp_ns),
                                 publish_time=int(stamp_ns), sequence=entry[1], data=data)

    def write_joint(self, sample: JointSample) -> None:
        self._write(JOINT_STATE_TYPE, sample.stamp_ns, self.encoders.joint(sample))

    def write_joint_held(self, sample: JointSample, stamps_ns: Iterable[int]) -> None:
        """``sample`` once at each of ``stamps_ns`` (a posture held still): encoded once,
        the header stamp rewritten in place (little-endian CDR: ``sec`` int32 and
        ``nanosec`` uint32 right after the 4-byte encapsulation header)."""
        data = bytearray(self.encoders.joint(sample))
        if data[:2] != b'\x00\x01':
            raise BagError(f'unexpected CDR encapsulation {bytes(data[:4])!r} of a JointState')
        for stamp in stamps_ns:
            data[4:12] = struct.pack('<iI', *stamp_fields(stamp))
            self._write(JOINT_STATE_TYPE, stamp, bytes(data))

    def write_point(self, sample: PointSample) -> None:
        """A plain point as PointStamped, a point with a rotation as PoseStamped."""
        if sample.rotation is not None:
            self._write(POSE_STAMPED_TYPE, sample.stamp_ns, self.encoders.pose(sample))
        else:
            self._write(POINT_STAMPED_TYPE, sample.stamp_ns, self.encoders.point(sample))

    def write_temperature(self, stamp_ns: int, frame_id: str, celsius: float) -> None:
        self._write(TEMPERATURE_TYPE, stamp_ns,
                    self.encoders.temperature(stamp_ns, frame_id, celsius))

    def write_point_sigma(self, sample: PointSample, sigma: np.ndarray) -> None:
        """The tracker's stated σ (3,) (m) of ``sample``, on the point-σ topic with the
        point's stamp and frame id (:func:`kpi_calib_ros.io.names.point_sigma_topic`)."""
        self._write(VECTOR3_STAMPED_TYPE, sample.stamp_ns,
                    self.encoders.point_sigma(sample.stamp_ns, sample.frame_id, sigma))

    def write_inputs(self, stamp_ns: int, names: tuple[str, ...], values: np.ndarray) -> None:
        """Measured inputs ``names`` (covariate names) = ``values`` (SI) at ``stamp_ns``, on the
        inputs topic as named values."""
        if self.inputs_topic is None:
            raise ValueError('this bag was opened without an inputs topic')
        self._write(JOINT_STATE_TYPE, stamp_ns, self.encoders.inputs(stamp_ns, names, values),
                    self.inputs_topic)

    def mark_row_order_stamps(self) -> None:
        """Say in the bag that its stamps number the rows of a table that had none: they are
        no clock (:data:`ROW_ORDER_METADATA`)."""
        self._writer.add_metadata(ROW_ORDER_METADATA, {'stamps': 'row_order'})

    def finish(self) -> None:
        self._writer.finish()


class BagStream:
    """A bag written message by message, in stamp order, under a temporary name beside
    ``path`` and renamed to ``path`` on a clean exit; removed when the block raises.

    Memory does not grow with the number of messages (chunks go to disk as they fill)::

        with BagStream(path, pose_topic=...) as bag:
            bag.write_joint(sample)
            bag.write_point(point)
    """

    def __init__(self, path: str | os.PathLike, joint_topic: str = DEFAULT_JOINT_TOPIC,
                 point_topic: str = DEFAULT_POINT_TOPIC, pose_topic: str | None = None,
                 temperature_topic: str | None = None,
                 chunk_size: int = _ROSBAG2_CHUNK_SIZE, sigma_topic: str | None = None,
                 inputs_topic: str | None = None) -> None:
        self.path = Path(path)
        self._options = (joint_topic, point_topic, chunk_size, pose_topic, temperature_topic,
                         sigma_topic, inputs_topic)

    def __enter__(self) -> _Recorder:
        (joint_topic, point_topic, chunk_size, pose_topic, temperature_topic,
         sigma_topic, inputs_topic) = self._options
        # Checked before any file is created: bad topics leave nothing behind.
        StreamEncoders(joint_topic, point_topic, pose_topic, temperature_topic, sigma_topic,
                       inputs_topic)
        fd, name = tempfile.mkstemp(prefix=f'.{self.path.name}.', suffix='.partial',
                                    dir=self.path.parent)
        self._tmp = Path(name)
        self._file = os.fdopen(fd, 'wb')
        try:
            self._recorder = _Recorder(self._file, joint_topic, point_topic,
                                       chunk_size=chunk_size, pose_topic=pose_topic,
                                       temperature_topic=temperature_topic,
                                       sigma_topic=sigma_topic, inputs_topic=inputs_topic)
            return self._recorder
        except BaseException:
            self._discard()
            raise

    def _discard(self) -> None:
        self._file.close()
        self._tmp.unlink(missing_ok=True)

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if kind is not None:
            self._discard()
            return
        try:
            self._recorder.finish()
            self._file.close()
            os.chmod(self._tmp, 0o666 & ~_umask())
            # Fails for a folder (IsADirectoryError) or a mount point (EBUSY): no
            # hidden .partial may stay behind either way.
            os.replace(self._tmp, self.path)
        except BaseException:
            self._discard()
            raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_bag(
    path: str | os.PathLike,
    joint_samples: Iterable[JointSample],
    point_samples: Iterable[PointSample],
    joint_topic: str = DEFAULT_JOINT_TOPIC,
    point_topic: str = DEFAULT_POINT_TOPIC,
    chunk_size: int = _ROSBAG2_CHUNK_SIZE,
    pose_topic: str = DEFAULT_POSE_TOPIC,
) -> Path:
    """Write joint states and tracker points to an MCAP bag, in stamp order.

    Parameters
    ----------
    path : path-like
        The ``.mcap`` file to create (overwritten if present).
    joint_samples, point_samples : iterables of JointSample / PointSample
        Published as ``sensor_msgs/msg/JointState`` on ``joint_topic`` and
        ``geometry_msgs/msg/PointStamped`` on ``point_topic``; point samples with a
        rotation (tracked 6-DoF bodies) as ``geometry_msgs/msg/PoseStamped`` on
        ``pose_topic`` (a channel created only when there are some).
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
    poses = any(isinstance(s, PointSample) and s.rotation is not None for _, _, s in stream)
    with BagStream(path, joint_topic, point_topic, pose_topic=pose_topic if poses else None,
                   chunk_size=chunk_size) as recorder:
        for _, _, sample in stream:
            if isinstance(sample, PointSample):
                recorder.write_point(sample)
            else:
                recorder.write_joint(sample)
    return path


__all__ = ['BagStream', 'DEFAULT_JOINT_TOPIC', 'DEFAULT_POINT_TOPIC', 'JOINT_STATE_TYPE',
           'LIBRARY', 'POINT_STAMPED_TYPE', 'POSE_STAMPED_TYPE', 'ROW_ORDER_METADATA',
           'StreamEncoders',
           'TEMPERATURE_TYPE', 'message_definition', 'type_hash', 'write_bag']

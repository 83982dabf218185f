"""MCAP bags of joint states and tracker points: reading, and the writer's names.

Bags are written as ``ros2 bag record -s mcap`` writes them
(:mod:`kpi_calib_ros.io.bag_writing`, re-exported here).

Reading is a linear pass over records (:mod:`kpi_calib_ros.io.mcap_scan`), so a bag
whose writer was killed, or a copy cut anywhere (inside a chunk too), still yields
every message completely written before the cut, with a :class:`BagWarning` saying how
many bytes were unreadable. For pairing, :func:`read_for_pairing` decodes the points
first and then only the joint states around them. A measurement log
(:class:`~kpi_calib_ros.io.measurement_log.MeasurementLog`) marks itself with the
``kpi_calib_ros`` metadata record (``content: measurement_log``); its joint states are
the stored configurations of its points, already paired.
"""
from __future__ import annotations

import functools
import inspect
import mmap
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from mcap_ros2.decoder import DecoderFactory

from kpi_calib_ros.core.acquisition.pairing import Pairer
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
from kpi_calib_ros.core.measurement.covariates import InputSample, TemperatureSample
from kpi_calib_ros.io.bag_writing import (
    DEFAULT_JOINT_TOPIC,
    DEFAULT_POINT_TOPIC,
    JOINT_STATE_TYPE,
    LIBRARY,
    POINT_STAMPED_TYPE,
    POSE_STAMPED_TYPE,
    ROW_ORDER_METADATA,
    TEMPERATURE_TYPE,
    VECTOR3_STAMPED_TYPE,
    StreamEncoders,
    message_definition,
    type_hash,
    write_bag,
)
from kpi_calib_ros.io.mcap_scan import MAGIC, BagError, ScannedBag, scan
from kpi_calib_ros.io.names import (
    DEFAULT_POSE_TOPIC,
    DEFAULT_TEMPERATURE_TOPIC,
    point_sigma_topic,
)
from kpi_calib_ros.io.ros_messages import (
    FieldPath,
    JointStateDecoder,
    input_samples_from_message,
    named_values_from_message,
    point_sample_from_message,
    point_sigma_from_message,
    pose_sample_from_message,
    temperature_sample_from_message,
)

# The metadata record by which a measurement log marks itself (see read_for_pairing).
LOG_METADATA = 'kpi_calib_ros'
LOG_CONTENT = 'measurement_log'


class BagWarning(UserWarning):
    """Part of a bag could not be read (cut or damaged); everything else was."""


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


@dataclass
class _Topic:
    channel_ids: list[int]
    decode: Callable[[bytes], Any]


def _point_decoder(decoder: Callable[[bytes], Any]) -> Callable[[bytes], PointSample]:
    """CDR bytes of a PointStamped -> PointSample, through ``decoder``."""
    return lambda data: point_sample_from_message(decoder(data))


def _pose_decoder(decoder: Callable[[bytes], Any]) -> Callable[[bytes], PointSample]:
    """CDR bytes of a PoseStamped -> PointSample with a rotation, through ``decoder``."""
    return lambda data: pose_sample_from_message(decoder(data))


def _topic_option(argument: str) -> str:
    """How each front end names the topic: the command-line option, the cell key, the
    node parameter and the Python argument."""
    cli, cell, node = {
        'joint_topic': ('--joint-topic', 'topics.joint_states', 'joint_states_topic'),
        'point_topic': ('--point-topic', 'topics.point', 'point_topic'),
        'pose_topic': ('--pose-topic', 'topics.pose', 'pose_topic')}[argument]
    return (f'Pass {cli} (kpi-calib), set {cell} in the cell file, the node parameter '
            f'{node}, or {argument}= (Python)')


def _open(path: Path, joint_topic: str, point_topic: str, require_topics: bool,
          pose_topic: str | None = None) -> tuple[ScannedBag, _Topic, _Topic, _Topic] | None:
    """Scan ``path`` and check the topics; None for an empty log (killed before its
    header was written, ``require_topics`` False). The pose topic is optional; a bag
    with tracked poses on it needs no point topic."""
    if joint_topic == point_topic:
        raise ValueError(f"joint_topic and point_topic must differ, both are '{joint_topic}'")
    if pose_topic in (joint_topic, point_topic):
        raise ValueError(f"pose_topic '{pose_topic}' must differ from the joint and point "
                         'topics')
    with open(path, 'rb') as f:
        size = os.fstat(f.fileno()).st_size
        # Mapped, not read: pages of chunks already indexed are given back (see scan).
        data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b''
    if data[:len(MAGIC)] != MAGIC:
        if not require_topics and MAGIC.startswith(data[:len(MAGIC)]):
            return None
        raise BagError(f'{path} is not an MCAP file (no MCAP magic); convert a SQLite '
                       'bag with `ros2 bag convert` or record with `ros2 bag record -s mcap`')
    bag = scan(path, data)
    if bag.unreadable_bytes or bag.problems:
        why = '; '.join(bag.problems) or 'the file is cut or damaged'
        warnings.warn(f'{path}: {bag.unreadable_bytes} of {bag.size} bytes unreadable ({why}); '
                      'every complete message before them was read', BagWarning, stacklevel=3)
    factory = DecoderFactory()
    topics = {}
    seen = {c.topic: bag.schemas[c.schema_id].name if c.schema_id in bag.schemas else ''
            for c in bag.channels.values()}
    first: dict[str, int] = {}
    for c in sorted(bag.channels):  # check topics in the order the file declares them
        first.setdefault(bag.channels[c].topic, c)
    wanted = [(joint_topic, JOINT_STATE_TYPE, 'joint_topic'),
              (point_topic, POINT_STAMPED_TYPE, 'point_topic')]
    if pose_topic is not None:
        wanted.append((pose_topic, POSE_STAMPED_TYPE, 'pose_topic'))
    has_poses = pose_topic is not None and pose_topic in seen
    for topic, expected, argument in sorted(
            wanted, key=lambda t: first.get(t[0], len(first) + len(bag.channels) + 1)):
        if topic not in seen:
            optional = (argument == 'pose_topic'
                        or (argument == 'point_topic' and has_poses))
            if require_topics and not optional:
                present = ', '.join(f"'{t}' ({seen[t]})" for t in sorted(seen)) or 'none'
                raise BagError(f"{path}: topic '{topic}' is not in the bag; topics present: "
                               f'{present}. {_topic_option(argument)} naming the {expected} '
                               'topic')
            topics[topic] = _Topic([], lambda data: None)
            continue
        if seen[topic] != expected:
            raise BagError(f"{path}: topic '{topic}' carries '{seen[topic] or 'no schema'}', "
                           f"expected '{expected}'; {_topic_option(argument).lower()} naming "
                           f'the topic that carries {expected}')
        ids = sorted(c.id for c in bag.channels.values() if c.topic == topic)
        channel = bag.channels[ids[0]]
        schema = bag.schemas[channel.schema_id]
        decoder = factory.decoder_for(channel.message_encoding, schema)
        if decoder is None:
            raise BagError(f"{path}: topic '{topic}' is encoded as "
                           f"'{channel.message_encoding}' with a '{schema.encoding}' "
                           "schema; only 'cdr' with 'ros2msg' schemas can be decoded")
        if expected == JOINT_STATE_TYPE:
            topics[topic] = _Topic(ids, JointStateDecoder(decoder))
        elif expected == POSE_STAMPED_TYPE:
            topics[topic] = _Topic(ids, _pose_decoder(decoder))
        else:
            topics[topic] = _Topic(ids, _point_decoder(decoder))
    poses = topics[pose_topic] if pose_topic is not None else _Topic([], lambda data: None)
    return bag, topics[joint_topic], topics[point_topic], poses


def _indices(bag: ScannedBag, topic: _Topic) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(channel ids, indices, file-order keys)`` of the topic's messages, in file order."""
    parts = [(np.full(len(bag.messages[c]), c), np.arange(len(bag.messages[c])),
              bag.messages[c].major, bag.messages[c].minor)
             for c in topic.channel_ids if c in bag.messages]
    if not parts:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, np.zeros((0, 2), dtype=np.int64)
    channel, index, major, minor = (np.concatenate(col) for col in zip(*parts))
    order = np.lexsort((minor, major))
    return channel[order], index[order], np.stack([major[order], minor[order]], axis=1)


def _decode(path: Path, bag: ScannedBag, topic: _Topic, channel: np.ndarray,
            index: np.ndarray, undecodable: list[int]) -> list[Any]:
    payloads = [bag.payload(int(c), int(i)) for c, i in zip(channel, index)]
    many = getattr(topic.decode, 'decode_many', None)
    if many is not None:
        out = many(payloads)
    else:
        out = []
        for data in payloads:
            try:
                out.append(topic.decode(data))
            except Exception:  # any decoder failure means a corrupt message
                out.append(None)
    undecodable += [1 for m in out if m is None]
    return [m for m in out if m is not None]


def _warn_undecodable(path: Path, undecodable: list[int]) -> None:
    if undecodable:
        warnings.warn(f'{path}: {len(undecodable)} message(s) do not decode and were skipped',
                      BagWarning, stacklevel=3)


def read_bag(
    path: str | os.PathLike,
    joint_topic: str = DEFAULT_JOINT_TOPIC,
    point_topic: str = DEFAULT_POINT_TOPIC,
    pose_topic: str = DEFAULT_POSE_TOPIC,
) -> tuple[list[JointSample], list[PointSample]]:
    """Every joint state and tracker point of an MCAP bag, in file (recording) order;
    tracked poses (``pose_topic``, if in the bag) follow the points, as point samples
    with a rotation.

    A bag cut or damaged anywhere yields every message completely written before the
    damage, with a :class:`BagWarning` giving the unreadable byte count.

    Raises
    ------
    BagError
        File missing or not MCAP, a topic absent (the topics present are listed),
        or a topic carrying another message type.
    """
    joint_samples, point_samples, _ = read_bag_with_sigma(path, joint_topic, point_topic,
                                                          pose_topic)
    return joint_samples, point_samples


def read_bag_with_sigma(
    path: str | os.PathLike,
    joint_topic: str = DEFAULT_JOINT_TOPIC,
    point_topic: str = DEFAULT_POINT_TOPIC,
    pose_topic: str = DEFAULT_POSE_TOPIC,
) -> tuple[list[JointSample], list[PointSample], dict[tuple[int, str], np.ndarray]]:
    """:func:`read_bag`, and the points' stated σ (3,) (m) by (stamp ns, frame id) from
    ``point_sigma_topic(point_topic)`` ({} when the bag has none)."""
    path = _checked_path(path)
    opened = _open(path, joint_topic, point_topic, require_topics=True, pose_topic=pose_topic)
    assert opened is not None
    bag, joints, points, poses = opened
    bad: list[int] = []
    result = (_decode(path, bag, joints, *_indices(bag, joints)[:2], bad),
              _decode(path, bag, points, *_indices(bag, points)[:2], bad)
              + _decode(path, bag, poses, *_indices(bag, poses)[:2], bad),
              _point_sigma(path, bag, point_topic))
    _warn_undecodable(path, bad)
    return result


@dataclass(frozen=True, eq=False)
class BagContents:
    """What pairing needs from one bag.

    ``joints`` and ``points`` in stamp order. For a recording (``measurement_log``
    False) ``joints`` holds only the joint states around the points; for a
    measurement log ``joints[i]`` is the configuration stored with ``points[i]``.
    ``unreadable_bytes``: bytes of a cut or damaged file that could not be used.
    ``point_sigma``: the tracker's stated σ (3,) (m) of points by (stamp ns, frame id),
    from the point topic's companion ``<point topic>/sigma`` (empty when the bag has none).
    ``topics``: every topic the bag has (whether to read measured inputs).
    ``row_order_stamps``: the stamps number the rows of a table that had no times
    (``kpi-calib import-csv``); they are no clock.
    """

    joints: list[JointSample]
    points: list[PointSample]
    measurement_log: bool
    unreadable_bytes: int
    point_sigma: dict[tuple[int, str], np.ndarray] = field(default_factory=dict)
    topics: frozenset[str] = frozenset()
    row_order_stamps: bool = False


def _point_sigma(path: Path, bag: ScannedBag, point_topic: str
                 ) -> dict[tuple[int, str], np.ndarray]:
    """The stated σ (3,) (m) of the points by (stamp ns, frame id), from the
    Vector3Stamped messages on ``point_sigma_topic(point_topic)``; {} without that topic."""
    topic = point_sigma_topic(point_topic)
    ids = sorted(c.id for c in bag.channels.values() if c.topic == topic)
    if not ids:
        return {}
    schema = bag.schemas.get(bag.channels[ids[0]].schema_id)
    if schema is None or schema.name != VECTOR3_STAMPED_TYPE:
        raise BagError(f"{path}: topic '{topic}' carries "
                       f"'{schema.name if schema else 'no schema'}', expected "
                       f"'{VECTOR3_STAMPED_TYPE}' (each point's sigma per axis, m, with the "
                       'point\'s stamp and frame id); rename or drop that topic')
    decoder = DecoderFactory().decoder_for(bag.channels[ids[0]].message_encoding, schema)
    if decoder is None:
        raise BagError(f"{path}: topic '{topic}' is not CDR with a ros2msg schema")
    out: dict[tuple[int, str], np.ndarray] = {}
    for c in (c for c in ids if c in bag.messages):
        for i in range(len(bag.messages[c])):
            stamp, frame_id, sigma = point_sigma_from_message(decoder(bag.payload(c, i)))
            key = (stamp, frame_id)
            if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
                raise BagError(f"{path}: topic '{topic}', stamp {key[0]} ns, frame "
                               f"'{key[1]}': sigma {sigma.tolist()} is not > 0 and finite "
                               '(per axis, m)')
            out[key] = sigma
    return out


def is_measurement_log(bag: ScannedBag) -> bool:
    return any(m.name == LOG_METADATA and m.metadata.get('content') == LOG_CONTENT
               for m in bag.metadata)


def _stored_pairs(path: Path, bag: ScannedBag, joints: _Topic, points: _Topic,
                  bad: list[int], poses: _Topic | None = None
                  ) -> tuple[list[JointSample], list[PointSample]]:
    """A log's measurements: a joint state directly followed by its point or tracked
    pose (same stamp); anything else (an append torn by a kill or a full disk) is
    skipped and counted."""
    jc, ji, jo = _indices(bag, joints)
    pc, pi, po = _indices(bag, points)
    merged = sorted([(tuple(o), 0, int(c), int(i)) for c, i, o in zip(jc, ji, jo)]
                    + [(tuple(o), 1, int(c), int(i)) for c, i, o in zip(pc, pi, po)])
    if poses is not None:
        sc, si, so = _indices(bag, poses)
        merged = sorted(merged + [(tuple(o), 2, int(c), int(i)) for c, i, o in zip(sc, si, so)])
    stored_joints: list[JointSample] = []
    stored_points: list[PointSample] = []
    skipped = 0
    k = 0
    while k < len(merged):
        _, kind, c, i = merged[k]
        if kind == 0 and k + 1 < len(merged) and merged[k + 1][1] in (1, 2):
            _, next_kind, pc_k, pi_k = merged[k + 1]
            joint = _decode(path, bag, joints, np.array([c]), np.array([i]), bad)
            source = points if next_kind == 1 else poses
            assert source is not None
            point = _decode(path, bag, source, np.array([pc_k]), np.array([pi_k]), bad)
            if joint and point and joint[0].stamp_ns == point[0].stamp_ns:
                stored_joints += joint
                stored_points += point
                k += 2
                continue
        skipped += 1
        k += 1
    if skipped:
        warnings.warn(f'{path}: {skipped} record(s) of this measurement log are not a '
                      'complete measurement (torn by a kill or a full disk) and were skipped',
                      BagWarning, stacklevel=3)
    return stored_joints, stored_points


def _around(joint_stamps: np.ndarray, point_stamps: np.ndarray, window_ns: int) -> np.ndarray:
    """Mask of the joint states within ±window_ns of a point, plus the first one after
    each window (the pairer decides a point when a later joint state arrives)."""
    order = np.argsort(joint_stamps, kind='stable')
    s = joint_stamps[order]
    lo = np.searchsorted(s, point_stamps - window_ns, side='left')
    hi = np.searchsorted(s, point_stamps + window_ns, side='right') + 1
    marks = np.zeros(len(s) + 1, dtype=np.int64)
    np.add.at(marks, lo, 1)
    np.add.at(marks, np.minimum(hi, len(s)), -1)
    mask = np.empty(len(s), dtype=bool)
    mask[order] = np.cumsum(marks[:-1]) > 0
    return mask


def read_for_pairing(
    path: str | os.PathLike,
    joint_topic: str = DEFAULT_JOINT_TOPIC,
    point_topic: str = DEFAULT_POINT_TOPIC,
    window_ns: int | None = None,
    pose_topic: str = DEFAULT_POSE_TOPIC,
) -> BagContents:
    """The points of a bag and the joint states pairing needs, or a log's stored pairs.

    Points are read first; then only joint states within ±``window_ns`` of a point
    (and the first one after each window) are decoded, so pairing the result equals
    pairing the whole bag with the same window, at a fraction of the time. Joint
    states far from every point are not decoded, so a broken one there is not counted.
    Tracked poses on ``pose_topic`` (if the bag has it) are points with a rotation.

    Parameters
    ----------
    window_ns : int, optional
        The pairer's half-window (ns); default
        :class:`~kpi_calib_ros.core.acquisition.pairing.Pairer`'s.
    """
    if window_ns is None:
        window_ns = inspect.signature(Pairer).parameters['window_ns'].default
    path = _checked_path(path)
    opened = _open(path, joint_topic, point_topic, require_topics=True, pose_topic=pose_topic)
    assert opened is not None
    bag, joints, points, poses = opened
    bad: list[int] = []
    sigma = _point_sigma(path, bag, point_topic)
    if is_measurement_log(bag):
        stored_joints, stored_points = _stored_pairs(path, bag, joints, points, bad, poses)
        _warn_undecodable(path, bad)
        return BagContents(stored_joints, stored_points, True, bag.unreadable_bytes, sigma,
                           _topics(bag))
    point_samples = (_decode(path, bag, points, *_indices(bag, points)[:2], bad)
                     + _decode(path, bag, poses, *_indices(bag, poses)[:2], bad))
    channel, index, _ = _indices(bag, joints)
    stamped = np.zeros(len(channel), dtype=bool)
    stamps = np.zeros(len(channel), dtype=np.int64)
    for c in np.unique(channel):
        k = channel == c
        stamped[k] = bag.messages[int(c)].stamped[index[k]]
        stamps[k] = bag.messages[int(c)].stamp_ns[index[k]]
    wanted = ~stamped  # a stamp not read from the bytes: decode to know
    if len(point_samples) and stamped.any():
        point_stamps = np.array(sorted(p.stamp_ns for p in point_samples), dtype=np.int64)
        wanted[stamped] = _around(stamps[stamped], point_stamps, int(window_ns))
    joint_samples = _decode(path, bag, joints, channel[wanted], index[wanted], bad)
    _warn_undecodable(path, bad)
    joint_samples.sort(key=lambda j: j.stamp_ns)
    point_samples.sort(key=lambda p: p.stamp_ns)
    row_order = any(m.name == ROW_ORDER_METADATA and m.metadata.get('stamps') == 'row_order'
                    for m in bag.metadata)
    return BagContents(joint_samples, point_samples, False, bag.unreadable_bytes, sigma,
                       _topics(bag), row_order)


def _topics(bag: ScannedBag) -> frozenset[str]:
    return frozenset(c.topic for c in bag.channels.values())


def read_log(path: str | os.PathLike, joint_topic: str = DEFAULT_JOINT_TOPIC,
             point_topic: str = DEFAULT_POINT_TOPIC,
             pose_topic: str = DEFAULT_POSE_TOPIC) -> list[tuple[JointSample, PointSample]]:
    """The measurements of one log file, in append order; torn appends skipped with a
    :class:`BagWarning`, a file killed before its header was written is empty."""
    return read_log_with_sigma(path, joint_topic, point_topic, pose_topic)[0]


def read_log_with_sigma(path: str | os.PathLike, joint_topic: str = DEFAULT_JOINT_TOPIC,
                        point_topic: str = DEFAULT_POINT_TOPIC,
                        pose_topic: str = DEFAULT_POSE_TOPIC
                        ) -> tuple[list[tuple[JointSample, PointSample]],
                                   dict[tuple[int, str], np.ndarray]]:
    """:func:`read_log`, and the points' stated σ (3,) (m) by (stamp ns, frame id) the log
    holds on ``point_sigma_topic(point_topic)`` ({} for a log written without any)."""
    path = Path(path)
    opened = _open(path, joint_topic, point_topic, require_topics=False, pose_topic=pose_topic)
    if opened is None:
        return [], {}
    bag, joints, points, poses = opened
    bad: list[int] = []
    pairs = list(zip(*_stored_pairs(path, bag, joints, points, bad, poses)))
    _warn_undecodable(path, bad)
    return pairs, _point_sigma(path, bag, point_topic)



def scanned_bag(path: str | os.PathLike) -> tuple[Path, ScannedBag]:
    """The checked path and the record-level scan of the MCAP bag at ``path`` (mapped, not
    read), for the readers of one side topic (temperatures, measured inputs).

    Raises
    ------
    BagError
        File missing or not MCAP.
    """
    path = _checked_path(path)
    with open(path, 'rb') as f:
        size = os.fstat(f.fileno()).st_size
        data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b''
    if data[:len(MAGIC)] != MAGIC:
        raise BagError(f'{path} is not an MCAP file (no MCAP magic)')
    return path, scan(path, data)

def read_temperatures(path: str | os.PathLike,
                      topic: str = DEFAULT_TEMPERATURE_TOPIC) -> list[TemperatureSample]:
    """Every ``sensor_msgs/Temperature`` on ``topic`` (°C, each with its sensor's frame id),
    in stamp order; [] when the bag has no such topic (a recording without temperature).

    Raises
    ------
    BagError
        File missing or not MCAP, or ``topic`` carrying another message type.
    """
    path, bag = scanned_bag(path)
    ids = sorted(c.id for c in bag.channels.values() if c.topic == topic)
    if not ids:
        return []
    channel = bag.channels[ids[0]]
    schema = bag.schemas.get(channel.schema_id)
    if schema is None or schema.name != TEMPERATURE_TYPE:
        raise BagError(f"{path}: topic '{topic}' carries "
                       f"'{schema.name if schema else 'no schema'}', expected "
                       f"'{TEMPERATURE_TYPE}'; set temperature.topic in the cell file to the "
                       'topic of the temperature sensors')
    decoder = DecoderFactory().decoder_for(channel.message_encoding, schema)
    if decoder is None:
        raise BagError(f"{path}: topic '{topic}' is not 'cdr' with a 'ros2msg' schema")
    topic_ids = _Topic(ids, lambda raw: temperature_sample_from_message(decoder(raw)))
    bad: list[int] = []
    samples = _decode(path, bag, topic_ids, *_indices(bag, topic_ids)[:2], bad)
    _warn_undecodable(path, bad)
    return sorted(samples, key=lambda s: s.stamp_ns)


def _source_samples(fields: tuple[tuple[str, FieldPath], ...], message: Any
                    ) -> list[InputSample]:
    return input_samples_from_message(message, fields)


def _converted(convert: Callable[[Any], list[InputSample]], decoder: Callable[[bytes], Any],
               raw: bytes) -> list[InputSample]:
    return convert(decoder(raw))


def read_inputs(path: str | os.PathLike, named_topic: str,
                sources: Sequence[tuple[str, str, tuple[tuple[str, FieldPath], ...]]] = ()
                ) -> tuple[list[InputSample], set[str]]:
    """Every measured input reading of a bag, in stamp order, and the topics it has.

    ``named_topic``: named values (``sensor_msgs/msg/JointState``, name = covariate, position
    = value), read when the bag has the topic. ``sources``: (topic, ROS type, ((covariate
    name, field path), ...)) of other stamped messages, each field one input
    (:func:`~kpi_calib_ros.io.ros_messages.field_value`). A topic the bag lacks gives nothing
    (the caller says what is missing).

    Raises
    ------
    BagError
        File missing or not MCAP, a topic carrying another type than stated, or a field the
        type does not have.
    """
    path, bag = scanned_bag(path)
    present = {c.topic for c in bag.channels.values()}
    wanted: list[tuple[str, str, Callable[[Any], list[InputSample]], str]] = []
    if named_topic in present:
        wanted.append((named_topic, JOINT_STATE_TYPE, named_values_from_message,
                       f'inputs.topic {named_topic}'))
    for topic, type_name, fields in sources:
        if topic in present:
            wanted.append((topic, type_name, functools.partial(_source_samples, fields),
                           f'the inputs source on {topic}'))
    out: list[InputSample] = []
    bad: list[int] = []
    for topic, type_name, convert, what in wanted:
        ids = sorted(c.id for c in bag.channels.values() if c.topic == topic)
        channel = bag.channels[ids[0]]
        schema = bag.schemas.get(channel.schema_id)
        name = schema.name if schema else 'no schema'
        if name.replace('/msg/', '/') != type_name.replace('/msg/', '/') or schema is None:
            raise BagError(f"{path}: topic '{topic}' carries '{name}', but {what} states "
                           f"'{type_name}'; give the topic's type in the cell's inputs:")
        decoder = DecoderFactory().decoder_for(channel.message_encoding, schema)
        if decoder is None:
            raise BagError(f"{path}: topic '{topic}' is not 'cdr' with a 'ros2msg' schema")
        channel_ids, index = _indices(bag, _Topic(ids, decoder))[:2]
        if len(index):
            try:  # a field the type lacks is an error of the cell, not of one message
                convert(decoder(bag.payload(int(channel_ids[0]), int(index[0]))))
            except ValueError as exc:
                raise BagError(f"{path}: topic '{topic}' ({type_name}): {exc}; fix the field "
                               "paths of the cell's inputs: source") from None
            except Exception:  # a corrupt first message: counted with the others below
                pass
        decoded = _decode(path, bag, _Topic(ids, functools.partial(_converted, convert, decoder)),
                          channel_ids, index, bad)
        out += [s for batch in decoded for s in batch]
    _warn_undecodable(path, bad)
    return sorted(out, key=lambda s: s.stamp_ns), present


__all__ = ['BagContents', 'BagError', 'BagWarning', 'LIBRARY', 'StreamEncoders',
           'DEFAULT_JOINT_TOPIC', 'DEFAULT_POINT_TOPIC', 'JOINT_STATE_TYPE', 'LOG_CONTENT',
           'LOG_METADATA', 'POINT_STAMPED_TYPE', 'is_measurement_log', 'message_definition',
           'read_bag', 'read_bag_with_sigma', 'read_for_pairing', 'read_log',
           'read_inputs', 'read_log_with_sigma', 'read_temperatures', 'scanned_bag', 'type_hash',
           'write_bag']

"""The one conversion between ROS stream messages and samples, and stamps and ROS time.

Used by the bag reader and writer (decoded records, plain dicts for the CDR encoder)
and by the live node (rclpy messages), so recorded and live data become the same
samples. A small struct-based decoder reads ``sensor_msgs/msg/JointState`` CDR
without building a message object, which is what makes reading 1 kHz bags fast.

Units: stamps in integer nanoseconds; positions as published (rad, m).
"""
from __future__ import annotations

import struct
from typing import Any, Callable

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import (
    Point,
    PointStamped,
    Pose,
    PoseStamped,
    Quaternion,
    Vector3,
    Vector3Stamped,
)
from sensor_msgs.msg import JointState
from std_msgs.msg import Header

from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
from kpi_calib_ros.core.measurement.covariates import InputSample, TemperatureSample

_NS = 1_000_000_000


# ------------------------------------------------------------------ time
def stamp_ns(header: Any) -> int:
    """``header.stamp`` (rclpy or decoded record) as integer nanoseconds."""
    return int(header.stamp.sec) * _NS + int(header.stamp.nanosec)


def stamp_fields(ns: int) -> tuple[int, int]:
    """``(sec, nanosec)`` of a builtin_interfaces/Time for ``ns``; nanosec in [0, 1e9).

    Raises
    ------
    ValueError
        If ``sec`` does not fit the message's int32.
    """
    sec, nanosec = divmod(int(ns), _NS)
    if not -2 ** 31 <= sec < 2 ** 31:
        raise ValueError(f'stamp {ns} ns does not fit builtin_interfaces/Time (int32 sec)')
    return sec, nanosec


def time_msg(ns: int) -> Time:
    """builtin_interfaces/Time for a stamp in ns."""
    sec, nanosec = stamp_fields(ns)
    return Time(sec=sec, nanosec=nanosec)


# ------------------------------------------------------------------ message -> sample
def point_sigma_from_message(message: Any) -> tuple[int, str, np.ndarray]:
    """A geometry_msgs/Vector3Stamped (rclpy message or decoded bag record) carrying a
    point's stated σ per axis (m) as (stamp ns, frame id, σ (3,)); not validated here."""
    v = message.vector
    return (stamp_ns(message.header), str(message.header.frame_id),
            np.array([v.x, v.y, v.z], dtype=float))


def joint_sample_from_message(message: Any) -> JointSample:
    """A sensor_msgs/JointState (rclpy message or decoded bag record) as a JointSample.

    Stamped with the header stamp. A position array whose length differs from
    ``name`` becomes all-NaN, so the pairer counts it as ``non_finite_joint_state``
    instead of it vanishing here; velocities of the wrong length, or none, become None.
    """
    names = tuple(message.name)
    positions = np.asarray(message.position, dtype=float)
    if positions.shape != (len(names),):
        positions = np.full(len(names), np.nan)
    velocities = np.asarray(message.velocity, dtype=float)
    return JointSample(stamp_ns(message.header), names, positions,
                       velocities if velocities.shape == (len(names),) else None)


def point_sample_from_message(message: Any) -> PointSample:
    """A geometry_msgs/PointStamped (rclpy or decoded) as a PointSample (m, header frame)."""
    p = message.point
    return PointSample(stamp_ns(message.header), message.header.frame_id,
                       np.array([p.x, p.y, p.z], dtype=float))


def pose_sample_from_message(message: Any) -> PointSample:
    """A geometry_msgs/PoseStamped (rclpy or decoded) as a PointSample with an
    ``orientation``: the tracked body's origin (m) and quaternion in the header frame,
    as received. A quaternion that is not finite and of unit length is rejected when
    paired (``invalid_orientation``), never silently normalised."""
    p, o = message.pose.position, message.pose.orientation
    return PointSample(stamp_ns(message.header), message.header.frame_id,
                       np.array([p.x, p.y, p.z], dtype=float),
                       np.array([o.x, o.y, o.z, o.w], dtype=float))


# ------------------------------------------------------------------ sample -> message
def temperature_sample_from_message(message: Any) -> TemperatureSample:
    """A ``sensor_msgs/Temperature`` (°C) as a sample: header stamp, frame id (the sensor)."""
    return TemperatureSample(stamp_ns(message.header), str(message.header.frame_id),
                             float(message.temperature))


def named_values_from_message(message: Any) -> list[InputSample]:
    """The named values of a ``sensor_msgs/JointState`` on the inputs topic (name = covariate,
    position = value, SI) as samples; a message whose counts differ gives NaN values (never
    used, counted)."""
    names = [str(n) for n in message.name]
    values = np.asarray(message.position, dtype=float)
    if values.shape != (len(names),):
        values = np.full(len(names), np.nan)
    stamp = stamp_ns(message.header)
    return [InputSample(stamp, n, float(v)) for n, v in zip(names, values)]


FieldPath = tuple[tuple[str, 'str | None'], ...]


def field_value(message: Any, path: FieldPath) -> float:
    """The number at ``path`` (steps (attribute, index | name | None), see
    :func:`kpi_calib_ros.io.cell_inputs.field_path`) of ``message``; NaN where this message
    lacks the element (an index past the end, a name it does not list, counts that differ).

    Raises
    ------
    ValueError
        The message type has no such attribute, or the field is not a number.
    """
    value: Any = message
    for attribute, index in path:
        parent = value
        try:
            value = getattr(parent, attribute)
        except AttributeError:
            raise ValueError(f'{type(parent).__name__} has no field {attribute!r}') from None
        if index is None:
            continue
        items = list(value)
        if index.isdigit():
            position = int(index)
        else:
            names = [str(n) for n in getattr(parent, 'name', ())]
            if index not in names or len(names) != len(items):
                return float('nan')
            position = names.index(index)
        if position >= len(items):
            return float('nan')
        value = items[position]
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ValueError(f'the field is a {type(value).__name__}, not a number')
    return float(value)


def input_samples_from_message(message: Any, fields: tuple[tuple[str, FieldPath], ...]
                               ) -> list[InputSample]:
    """A stamped message of an input source as one sample per (covariate name, field path),
    stamped with its header (:func:`field_value`)."""
    stamp = stamp_ns(message.header)
    return [InputSample(stamp, name, field_value(message, path)) for name, path in fields]


def joint_state_fields(sample: JointSample) -> dict[str, Any]:
    """A JointSample as the nested fields of a JointState (empty velocity, effort when none)."""
    sec, nanosec = stamp_fields(sample.stamp_ns)
    return {'header': {'stamp': {'sec': sec, 'nanosec': nanosec}, 'frame_id': ''},
            'name': list(sample.names), 'position': [float(x) for x in sample.positions],
            'velocity': [] if sample.velocities is None else
            [float(x) for x in sample.velocities],
            'effort': [] if sample.efforts is None else [float(x) for x in sample.efforts]}


def point_stamped_fields(sample: PointSample) -> dict[str, Any]:
    """A PointSample as the nested fields of a PointStamped."""
    sec, nanosec = stamp_fields(sample.stamp_ns)
    x, y, z = (float(v) for v in sample.xyz)
    return {'header': {'stamp': {'sec': sec, 'nanosec': nanosec},
                       'frame_id': sample.frame_id}, 'point': {'x': x, 'y': y, 'z': z}}


def pose_stamped_fields(sample: PointSample) -> dict[str, Any]:
    """A PointSample with an orientation as the nested fields of a PoseStamped."""
    if sample.orientation is None:
        raise ValueError('a PoseStamped needs the sample\'s orientation')
    sec, nanosec = stamp_fields(sample.stamp_ns)
    x, y, z = (float(v) for v in sample.xyz)
    qx, qy, qz, qw = (float(v) for v in sample.orientation)
    return {'header': {'stamp': {'sec': sec, 'nanosec': nanosec}, 'frame_id': sample.frame_id},
            'pose': {'position': {'x': x, 'y': y, 'z': z},
                     'orientation': {'x': qx, 'y': qy, 'z': qz, 'w': qw}}}


def vector3_stamped_fields(stamp_ns: int, frame_id: str, xyz: np.ndarray) -> dict[str, Any]:
    """A vector (3,) as the nested fields of a Vector3Stamped (a point's σ per axis, m)."""
    sec, nanosec = stamp_fields(stamp_ns)
    x, y, z = (float(v) for v in xyz)
    return {'header': {'stamp': {'sec': sec, 'nanosec': nanosec}, 'frame_id': frame_id},
            'vector': {'x': x, 'y': y, 'z': z}}


def temperature_fields(stamp_ns: int, frame_id: str, celsius: float) -> dict[str, Any]:
    """A temperature (°C, as sensor_msgs/Temperature carries it) as the nested fields of
    that message; variance 0 (unknown)."""
    sec, nanosec = stamp_fields(stamp_ns)
    return {'header': {'stamp': {'sec': sec, 'nanosec': nanosec}, 'frame_id': frame_id},
            'temperature': float(celsius), 'variance': 0.0}


def _header(fields: dict[str, Any]) -> Header:
    return Header(stamp=Time(**fields['stamp']), frame_id=fields['frame_id'])


def joint_state_msg(sample: JointSample) -> JointState:
    """JointSample -> JointState (empty velocity when the sample has none)."""
    f = joint_state_fields(sample)
    return JointState(header=_header(f['header']), name=f['name'], position=f['position'],
                      velocity=f['velocity'])


def point_stamped_msg(sample: PointSample) -> PointStamped:
    """PointSample -> PointStamped."""
    f = point_stamped_fields(sample)
    return PointStamped(header=_header(f['header']), point=Point(**f['point']))


def vector3_stamped_msg(stamp_ns: int, frame_id: str, xyz: np.ndarray) -> Vector3Stamped:
    """A vector (3,) -> Vector3Stamped (a point's σ per axis, m, with its stamp and frame)."""
    f = vector3_stamped_fields(stamp_ns, frame_id, xyz)
    return Vector3Stamped(header=_header(f['header']), vector=Vector3(**f['vector']))


def pose_stamped_msg(sample: PointSample) -> PoseStamped:
    """PointSample with a rotation -> PoseStamped."""
    f = pose_stamped_fields(sample)
    return PoseStamped(header=_header(f['header']),
                       pose=Pose(position=Point(**f['pose']['position']),
                                 orientation=Quaternion(**f['pose']['orientation'])))


# ------------------------------------------------------------------ fast CDR
_CDR_LE = b'\x00\x01'  # encapsulation: plain CDR, little endian (what rmw/rosbag2 write)
_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iI')
_F8 = np.dtype('<f8')


def _aligned(p: int, k: int) -> int:
    # CDR aligns relative to the payload start, i.e. after the 4-byte encapsulation.
    return 4 + (p - 4 + k - 1) // k * k


def _float64_sequence(data: bytes, p: int) -> tuple[int, int, int]:
    """(count, data start, data end) of the float64 sequence whose length is at ``p``."""
    p = _aligned(p, 4)
    (count,) = _U32.unpack_from(data, p)
    p += 4
    if count == 0:
        return 0, p, p
    p = _aligned(p, 8)
    end = p + 8 * count
    if end > len(data):
        raise ValueError('float64 sequence runs past the message end')
    return count, p, end


class JointStateDecoder:
    """Decode JointState CDR straight into JointSamples; the same result as decoding the
    message and calling :func:`joint_sample_from_message`.

    ``fallback`` (the generic decoder) takes messages that are not little-endian CDR or
    do not parse. :meth:`decode_many` decodes every message laid out like the first
    of its length (same names, same array lengths: one driver) with numpy at once.
    """

    def __init__(self, fallback: Callable[[bytes], Any]) -> None:
        self._fallback = fallback
        self._names: dict[bytes, tuple[str, ...]] = {}

    def __call__(self, data: bytes) -> JointSample:
        if data[:2] == _CDR_LE:
            try:
                return self._sample(data, self._parse(data))
            except (ValueError, struct.error, UnicodeDecodeError):
                pass  # unusual layout: the generic decoder decides (and reports) it
        return joint_sample_from_message(self._fallback(data))

    def _parse(self, data: bytes) -> tuple:
        """(stamp ns, names, positions (start, end), velocities (start, end), end)."""
        sec, nanosec = _STAMP.unpack_from(data, 4)
        (n,) = _U32.unpack_from(data, 12)
        p = _aligned(16 + n, 4)                    # after frame_id (length includes NUL)
        start = p
        (count,) = _U32.unpack_from(data, p)
        p += 4
        spans = []
        for _ in range(count):
            p = _aligned(p, 4)
            (n,) = _U32.unpack_from(data, p)
            if n == 0 or p + 4 + n > len(data):
                raise ValueError('bad string length')
            spans.append((p + 4, n))
            p += 4 + n
        block = bytes(data[start:p])
        names = self._names.get(block)
        if names is None:
            names = tuple(bytes(data[q:q + n - 1]).decode('utf-8') for q, n in spans)
            if len(self._names) < 64:  # bounded: a few drivers, not one entry per message
                self._names[block] = names
        _, p0, p1 = _float64_sequence(data, p)
        _, v0, v1 = _float64_sequence(data, p1)
        _, _, end = _float64_sequence(data, v1)  # effort: validated, not used
        return int(sec) * _NS + nanosec, names, (p0, p1), (v0, v1), end

    @staticmethod
    def _sample(data, parsed) -> JointSample:
        stamp, names, (p0, p1), (v0, v1), _ = parsed
        return _joint_sample(stamp, names, np.frombuffer(data, _F8, (p1 - p0) // 8, p0),
                             np.frombuffer(data, _F8, (v1 - v0) // 8, v0))

    def decode_many(self, payloads: list[bytes]) -> list[JointSample | None]:
        """Decode each payload (None where it does not decode), in order."""
        out: list[JointSample | None] = [None] * len(payloads)
        lengths = np.array([len(d) for d in payloads], dtype=np.int64)
        for length in np.unique(lengths):
            members = np.flatnonzero(lengths == length)
            template = payloads[members[0]]
            try:
                parsed = self._parse(template) if template[:2] == _CDR_LE else None
            except (ValueError, struct.error, UnicodeDecodeError):
                parsed = None
            if parsed is None or parsed[4] != length:
                rest = members
            else:
                rest = self._decode_alike(payloads, members, template, parsed, out)
            for k in rest:
                try:
                    out[k] = self(payloads[k])
                except Exception:  # a corrupt message: the caller counts it
                    out[k] = None
        return out

    def _decode_alike(self, payloads, members, template, parsed, out) -> np.ndarray:
        """Decode the members laid out like ``template``; returns those that are not."""
        _, names, (p0, p1), (v0, v1), _ = parsed
        rows = np.frombuffer(b''.join(payloads[k] for k in members), np.uint8).reshape(
            len(members), -1)
        reference = np.frombuffer(template, np.uint8)
        alike = np.ones(len(members), dtype=bool)
        for a, b in ((0, 4), (12, p0), (p1, v0), (v1, len(reference))):
            alike &= (rows[:, a:b] == reference[a:b]).all(axis=1)
        stamps = (rows[:, 4:8].copy().view('<i4').ravel().astype(np.int64) * _NS
                  + rows[:, 8:12].copy().view('<u4').ravel())
        positions = rows[:, p0:p1].copy().view(_F8)
        velocities = rows[:, v0:v1].copy().view(_F8)
        for r in np.flatnonzero(alike):
            out[members[r]] = _joint_sample(int(stamps[r]), names, positions[r], velocities[r])
        return members[~alike]


def _joint_sample(stamp: int, names: tuple[str, ...], positions: np.ndarray,
                  velocities: np.ndarray) -> JointSample:
    # The same length rules as joint_sample_from_message.
    if positions.shape != (len(names),):
        positions = np.full(len(names), np.nan)
    return JointSample(stamp, names, positions,
                       velocities if velocities.shape == (len(names),) else None)


__all__ = ['FieldPath', 'field_value', 'input_samples_from_message', 'named_values_from_message',
           'JointStateDecoder', 'joint_sample_from_message',
           'joint_state_fields',
           'joint_state_msg', 'point_sample_from_message', 'point_stamped_fields',
           'point_stamped_msg', 'pose_sample_from_message', 'pose_stamped_fields',
           'pose_stamped_msg', 'stamp_fields', 'stamp_ns', 'temperature_fields', 'time_msg']

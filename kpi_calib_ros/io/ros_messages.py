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
from geometry_msgs.msg import Point, PointStamped
from sensor_msgs.msg import JointState
from std_msgs.msg import Header

from kpi_calib_ros.core.streams import JointSample, PointSample

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
    return PointSample(stamp_ns(message.header), message.header.frame_id, [p.x, p.y, p.z])


# ------------------------------------------------------------------ sample -> message
def joint_state_fields(sample: JointSample) -> dict[str, Any]:
    """A JointSample as the nested fields of a JointState (empty velocity when none)."""
    sec, nanosec = stamp_fields(sample.stamp_ns)
    return {'header': {'stamp': {'sec': sec, 'nanosec': nanosec}, 'frame_id': ''},
            'name': list(sample.names), 'position': [float(x) for x in sample.positions],
            'velocity': [] if sample.velocities is None else
            [float(x) for x in sample.velocities], 'effort': []}


def point_stamped_fields(sample: PointSample) -> dict[str, Any]:
    """A PointSample as the nested fields of a PointStamped."""
    sec, nanosec = stamp_fields(sample.stamp_ns)
    x, y, z = (float(v) for v in sample.xyz)
    return {'header': {'stamp': {'sec': sec, 'nanosec': nanosec},
                       'frame_id': sample.frame_id}, 'point': {'x': x, 'y': y, 'z': z}}


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


# ------------------------------------------------------------------ fast CDR
_CDR_LE = b'\x00\x01'  # encapsulation: plain CDR, little endian (what rmw/rosbag2 write)
_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iI')
_F8 = np.dtype('<f8')


def _aligned(p: int, k: int) -> int:
    # CDR aligns relative to the payload start, i.e. after the 4-byte encapsulation.
    return 4 + (p - 4 + k - 1) // k * k


def _float64_sequence(data: bytes, p: int) -> tuple[np.ndarray, int]:
    p = _aligned(p, 4)
    (count,) = _U32.unpack_from(data, p)
    p += 4
    if count == 0:
        return np.empty(0), p
    p = _aligned(p, 8)
    end = p + 8 * count
    if end > len(data):
        raise ValueError('float64 sequence runs past the message end')
    return np.frombuffer(data, _F8, count, p), end


class JointStateDecoder:
    """Decode JointState CDR straight into a JointSample; the same result as decoding the
    message and calling :func:`joint_sample_from_message`.

    ``fallback`` (the generic decoder) takes messages that are not little-endian CDR or
    do not parse. Name blocks are cached (a driver sends the same names every time).
    """

    def __init__(self, fallback: Callable[[bytes], Any]) -> None:
        self._fallback = fallback
        self._names: dict[bytes, tuple[str, ...]] = {}

    def __call__(self, data: bytes) -> JointSample:
        if data[:2] == _CDR_LE:
            try:
                return self._fast(data)
            except (ValueError, struct.error, UnicodeDecodeError):
                pass  # unusual layout: the generic decoder decides (and reports) it
        return joint_sample_from_message(self._fallback(data))

    def _fast(self, data: bytes) -> JointSample:
        sec, nanosec = _STAMP.unpack_from(data, 4)
        (n,) = _U32.unpack_from(data, 12)
        p = _aligned(16 + n, 4)                    # after frame_id (length includes NUL)
        start = p
        (count,) = _U32.unpack_from(data, p)
        p += 4
        lengths = []
        for _ in range(count):
            p = _aligned(p, 4)
            (n,) = _U32.unpack_from(data, p)
            if n == 0 or p + 4 + n > len(data):
                raise ValueError('bad string length')
            lengths.append((p + 4, n))
            p += 4 + n
        block = data[start:p]
        names = self._names.get(block)
        if names is None:
            names = tuple(data[q:q + n - 1].decode('utf-8') for q, n in lengths)
            if len(self._names) < 64:  # bounded: a few drivers, not one entry per message
                self._names[block] = names
        positions, p = _float64_sequence(data, p)
        velocities, p = _float64_sequence(data, p)
        _float64_sequence(data, p)  # effort: validated, not used
        if positions.shape != (len(names),):
            positions = np.full(len(names), np.nan)
        return JointSample(int(sec) * _NS + nanosec, names, positions,
                           velocities if velocities.shape == (len(names),) else None)


__all__ = ['JointStateDecoder', 'joint_sample_from_message', 'joint_state_fields',
           'joint_state_msg', 'point_sample_from_message', 'point_stamped_fields',
           'point_stamped_msg', 'stamp_fields', 'stamp_ns', 'time_msg']

"""The cell file's ``temperature:`` section: which topic carries the arm's temperature,
which sensors (by frame id) stand for it, and the reference it is counted from.

::

    temperature:
      topic: /cell/temperature        # sensor_msgs/Temperature, °C
      sensors: [upper_arm, forearm]   # frame ids; their mean is the arm's temperature
      reference: 20.0                 # °C; ΔT = mean − reference (ISO 1: 20 °C)
      max_gap: 120.0                  # s: the largest gap bridged by interpolation
      valid_range: [-50.0, 150.0]     # °C: a reading outside is a sensor fault, never used

``sensors`` may also say which joints each sensor stands for, frame id -> joint names::

    temperature:
      sensors:                       # a UR arm: the link before a joint is its origin
        upper_arm: [elbow_joint]     # the upper arm, shoulder to elbow
        forearm: [wrist_1_joint]     # the forearm, elbow to wrist

The thermal effects of a listed joint read that sensor's own ΔT
(``delta_temperature.<frame_id>``): ``thermal_link_growth:J`` and ``thermal_growth`` grow the
link before joint J, ``thermal_zero_drift:J`` drifts J's zero, with the temperature where they
are. Joints not listed read the mean of every sensor named (the keys), which stays the arm's
temperature ``delta_temperature``. A joint name is matched against the robot's chain when the
cell model is built (:func:`joint_temperatures`); a joint may stand under one sensor only.

A reading outside ``valid_range`` (or not finite) is set aside with a count and a warning
(:func:`kpi_calib_ros.core.measurement.covariates.plausible_readings`); the node does not log
it, and one already in a log is set aside when the readings are paired.

Without the section no temperature is read and the thermal effects are not candidates.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.covariates import (
    ABSOLUTE_ZERO_C,
    DEFAULT_MAX_GAP_NS,
    REFERENCE_TEMPERATURE_C,
    TEMPERATURE_LIMIT_C,
    TEMPERATURE_RANGE_C,
    delta_temperature_name,
)
from kpi_calib_ros.io.names import DEFAULT_TEMPERATURE_TOPIC

TEMPERATURE_KEYS = ('topic', 'sensors', 'reference', 'max_gap', 'valid_range')


@dataclass(frozen=True)
class TemperatureSettings:
    """The validated ``temperature:`` section (°C, s).

    ``joints``: the mapping form of ``sensors``, (frame id, joint names) per sensor that
    stands for joints; () in the list form. Its joint names are checked against the chain by
    :func:`joint_temperatures`.
    """

    topic: str = DEFAULT_TEMPERATURE_TOPIC
    sensors: tuple[str, ...] = ()          # empty: every sensor on the topic
    reference_c: float = REFERENCE_TEMPERATURE_C
    max_gap_s: float = DEFAULT_MAX_GAP_NS / 1e9
    joints: tuple[tuple[str, tuple[str, ...]], ...] = ()
    valid_range_c: tuple[float, float] = TEMPERATURE_RANGE_C

    @property
    def max_gap_ns(self) -> int:
        """The largest gap bridged by interpolation, ns."""
        return int(round(self.max_gap_s * 1e9))


def joint_temperatures(settings: TemperatureSettings | None,
                       joint_names: Sequence[str]) -> dict[str, str]:
    """Joint name -> the ΔT covariate its thermal effects read (``delta_temperature.<frame>``).

    Empty without a section or in the list form (every joint reads the mean).

    Raises
    ------
    ConfigError
        ``temperature.sensors.<frame_id>`` naming a joint not on the chain, with the chain's
        joints.
    """
    out: dict[str, str] = {}
    for frame_id, joints in (settings.joints if settings is not None else ()):
        for joint in joints:
            if joint not in joint_names:
                raise ConfigError(f'temperature.sensors.{frame_id}', f'{joint!r} is not a '
                                  f'joint of the robot chain; name joints of '
                                  f'{list(joint_names)}')
            out[joint] = delta_temperature_name(frame_id)
    return out


def temperature_settings(raw: Any) -> TemperatureSettings | None:
    """The ``temperature:`` section; None when absent (no temperature read).

    Raises
    ------
    ConfigError
        Naming the key: not a mapping, an unknown key, a bad topic, sensor list or number.
    """
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise ConfigError('temperature', f'must be a mapping with keys {list(TEMPERATURE_KEYS)}')
    unknown = sorted(set(raw) - set(TEMPERATURE_KEYS))
    if unknown:
        raise ConfigError(f'temperature.{unknown[0]}', f'unknown key; allowed: '
                          f'{list(TEMPERATURE_KEYS)}')
    topic = raw.get('topic', DEFAULT_TEMPERATURE_TOPIC)
    if not isinstance(topic, str) or not topic.strip() or ' ' in topic:
        raise ConfigError('temperature.topic', 'must be a topic name such as '
                          f'{DEFAULT_TEMPERATURE_TOPIC!r} (sensor_msgs/Temperature), got '
                          f'{topic!r}')
    sensors, joints = _sensors(raw.get('sensors'))
    values = {}
    for key, default, unit, low, high in (('reference', REFERENCE_TEMPERATURE_C, '°C', -50, 150),
                                          ('max_gap', DEFAULT_MAX_GAP_NS / 1e9, 's', 0, 86400)):
        value = raw.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not np.isfinite(value) or not low <= value <= high:
            raise ConfigError(f'temperature.{key}', f'must be a number in [{low}, {high}] '
                              f'{unit}, got {value!r}')
        values[key] = float(value)
    return TemperatureSettings(topic, sensors, values['reference'], values['max_gap'], joints,
                               _valid_range(raw.get('valid_range', list(TEMPERATURE_RANGE_C))))


def _valid_range(raw: Any) -> tuple[float, float]:
    """``temperature.valid_range``: [low, high] °C, physically possible, low < high."""
    fix = (f'give [low, high] in °C with {ABSOLUTE_ZERO_C} <= low < high <= '
           f'{TEMPERATURE_LIMIT_C:g} (default {list(TEMPERATURE_RANGE_C)})')
    if not isinstance(raw, (list, tuple)) or len(raw) != 2 or any(
            isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v)
            for v in raw):
        raise ConfigError('temperature.valid_range', f'{fix}, got {raw!r}')
    low, high = float(raw[0]), float(raw[1])
    if low < ABSOLUTE_ZERO_C:
        raise ConfigError('temperature.valid_range', f'low {low:g} °C is below absolute zero; '
                          f'{fix}')
    if high > TEMPERATURE_LIMIT_C or not low < high:
        raise ConfigError('temperature.valid_range', f'[{low:g}, {high:g}] °C is not a range '
                          f'a robot cell can read; {fix}')
    return low, high


def _sensors(raw: Any) -> tuple[tuple[str, ...], tuple[tuple[str, tuple[str, ...]], ...]]:
    """``temperature.sensors``: the frame ids, and (frame id, joint names) in the mapping form."""
    if isinstance(raw, dict):
        if not raw:
            raise ConfigError('temperature.sensors', 'an empty mapping names no sensor: give '
                              'frame_id: [joint names], or leave the key out (every sensor)')
        joints: list[tuple[str, tuple[str, ...]]] = []
        seen: dict[str, str] = {}
        for frame_id, names in raw.items():
            if not _is_frame_id(frame_id):
                raise ConfigError('temperature.sensors', f'{frame_id!r} is not a frame id: a key '
                                  'is the header frame_id of a sensor\'s messages (text without '
                                  'spaces), its value the joints it stands for')
            key = f'temperature.sensors.{frame_id}'
            if not isinstance(names, list) or not names:
                raise ConfigError(key, 'must be a non-empty list of joint names (the joints '
                                  'whose thermal effects read this sensor), got '
                                  f'{names!r}; a sensor that stands for no joint goes in the '
                                  'mean only: list it in the list form')
            for name in names:
                if not isinstance(name, str) or not name.strip():
                    raise ConfigError(key, f'{name!r} is not a joint name; give the URDF '
                                      'joint names as text')
                if name in seen:
                    raise ConfigError(key, f'joint {name!r} is given twice (also under '
                                      f'{seen[name]!r}); a joint reads one sensor: keep it '
                                      'under the sensor on its link')
                seen[name] = frame_id
            joints.append((frame_id, tuple(names)))
        return tuple(f for f, _ in joints), tuple(joints)
    sensors = raw or []
    if isinstance(sensors, str):
        sensors = [sensors]
    if not isinstance(sensors, list) or not all(_is_frame_id(s) for s in sensors):
        raise ConfigError('temperature.sensors', 'must be a list of frame ids (the header '
                          f'frame_id of each sensor\'s messages), or a mapping frame_id: '
                          f'[joint names], got {sensors!r}')
    return tuple(sensors), ()


def _is_frame_id(value: Any) -> bool:
    """A header frame id: non-empty text without whitespace."""
    return isinstance(value, str) and bool(value) and not any(c.isspace() for c in value)

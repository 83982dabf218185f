"""The cell file's ``temperature:`` section: which topic carries the arm's temperature,
which sensors (by frame id) stand for it, and the reference it is counted from.

::

    temperature:
      topic: /cell/temperature        # sensor_msgs/Temperature, °C
      sensors: [upper_arm, forearm]   # frame ids; their mean is the arm's temperature
      reference: 20.0                 # °C; ΔT = mean − reference (ISO 1: 20 °C)
      max_gap: 120.0                  # s: the largest gap bridged by interpolation

Without the section no temperature is read and the thermal effects are not candidates.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.covariates import DEFAULT_MAX_GAP_NS, REFERENCE_TEMPERATURE_C
from kpi_calib_ros.io.names import DEFAULT_TEMPERATURE_TOPIC

TEMPERATURE_KEYS = ('topic', 'sensors', 'reference', 'max_gap')


@dataclass(frozen=True)
class TemperatureSettings:
    """The validated ``temperature:`` section (°C, s)."""

    topic: str = DEFAULT_TEMPERATURE_TOPIC
    sensors: tuple[str, ...] = ()          # empty: every sensor on the topic
    reference_c: float = REFERENCE_TEMPERATURE_C
    max_gap_s: float = DEFAULT_MAX_GAP_NS / 1e9

    @property
    def max_gap_ns(self) -> int:
        """The largest gap bridged by interpolation, ns."""
        return int(round(self.max_gap_s * 1e9))


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
    sensors = raw.get('sensors') or []
    if isinstance(sensors, str):
        sensors = [sensors]
    if not isinstance(sensors, list) or not all(isinstance(s, str) and s for s in sensors):
        raise ConfigError('temperature.sensors', 'must be a list of frame ids (the header '
                          f'frame_id of each sensor\'s messages), got {sensors!r}')
    values = {}
    for key, default, unit, low, high in (('reference', REFERENCE_TEMPERATURE_C, '°C', -50, 150),
                                          ('max_gap', DEFAULT_MAX_GAP_NS / 1e9, 's', 0, 86400)):
        value = raw.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not np.isfinite(value) or not low <= value <= high:
            raise ConfigError(f'temperature.{key}', f'must be a number in [{low}, {high}] '
                              f'{unit}, got {value!r}')
        values[key] = float(value)
    return TemperatureSettings(topic, tuple(sensors), values['reference'], values['max_gap'])

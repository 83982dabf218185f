"""The cell file's ``inputs:`` and ``compliance:`` sections: measured quantities beside the
joint state, and which torques the compliance reads.

::

    inputs:
      topic: /kpi_calib/inputs        # named values (sensor_msgs/JointState: name = covariate,
                                      # position = value, SI); import-csv and the node's log
                                      # write here; read whenever a bag has it
      max_gap: 10.0                   # s: the largest gap between readings bridged
      expect: [payload.mass]          # names the topic must give every point (optional)
      sources:                        # other topics, each field one covariate
        - topic: /column_tilt
          type: geometry_msgs/msg/Vector3Stamped
          fields: {tilt.column.x: vector.x, tilt.column.y: vector.y}
    compliance:
      torque_source: model            # model: gravity torques of the URDF and payload;
                                      # measured: the joint states' effort, per row

A source is any stamped message (a ``header``): each field is a dotted path to a number,
with ``[i]`` for an array element or ``[name]`` for the element of a message's ``name`` list
(``effort[joint_2]`` of a ``sensor_msgs/msg/JointState``). Readings are paired with the points
by their header stamps as temperatures are (:func:`~kpi_calib_ros.core.measurement.
covariates.input_covariates`); a reading that is not finite is never used (counted and
warned), a point with no reading of an input within ``max_gap`` is refused with the reason. A
payload (``payload.*``) is held from a reading to the next, not interpolated: it steps.
``expect`` names the covariates the named-values topic must give: one that never arrives
stops the job (a payload published on another topic was fitted as the cell's 0 kg, a
compliance 4.7σ off published as a success), a point without one is refused.

``torque_source: measured`` records each chain joint's ``effort`` from the joint-state topic
as ``effort.<joint>`` and uses them as the rows' torques (``Measurements.tau``) in place of the
model's gravity torques: the joint states must name every chain joint with one effort each.
The node logs them per accepted measurement
(:class:`kpi_calib_ros.ros.measurement_store.MeasurementStore`, ``record_efforts``).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.covariates import (
    DEFAULT_INPUT_MAX_GAP_NS,
    DELTA_TEMPERATURE,
    EFFORT_PREFIX,
    TEMPERATURE_PREFIX,
)
from kpi_calib_ros.core.measurement.payload import payload_name_error
from kpi_calib_ros.io.names import DEFAULT_INPUTS_TOPIC

__all__ = ['INPUT_KEYS', 'SOURCE_KEYS', 'TORQUE_SOURCES', 'InputSource', 'InputSettings',
           'input_settings', 'torque_source', 'check_covariate_name', 'field_path']

INPUT_KEYS = ('topic', 'max_gap', 'expect', 'sources')
SOURCE_KEYS = ('topic', 'type', 'fields')
TORQUE_SOURCES = ('model', 'measured')
MAX_INPUT_GAP_S = 24 * 3600.0
_NAME = re.compile(r'^[A-Za-z][A-Za-z0-9_]*(\.[A-Za-z0-9_-]+)*$')
_TYPE = re.compile(r'^[A-Za-z][A-Za-z0-9_]*/msg/[A-Z][A-Za-z0-9]*$')
_STEP = re.compile(r'^([a-z][a-z0-9_]*)(?:\[([^\[\]]+)\])?$')


@dataclass(frozen=True)
class InputSource:
    """One topic of measured inputs: its ROS type and {covariate name: field path}."""

    topic: str
    type: str
    fields: tuple[tuple[str, str], ...]


@dataclass(frozen=True)
class InputSettings:
    """The validated ``inputs:`` section (s) and ``compliance.torque_source``."""

    topic: str = DEFAULT_INPUTS_TOPIC
    max_gap_s: float = DEFAULT_INPUT_MAX_GAP_NS / 1e9
    sources: tuple[InputSource, ...] = field(default_factory=tuple)
    torque_source: str = 'model'
    expect: tuple[str, ...] = ()

    @property
    def max_gap_ns(self) -> int:
        return int(round(self.max_gap_s * 1e9))

    @property
    def names(self) -> tuple[str, ...]:
        """Covariate names the sources give and the named-values topic must (``expect``;
        it may give more)."""
        return tuple(name for s in self.sources for name, _ in s.fields) + self.expect


def check_covariate_name(name: Any, key: str) -> str:
    """A measured input's covariate name, or ConfigError naming ``key``.

    Dotted words (``tilt.column.x``, ``payload.mass``); not a temperature's (the
    ``temperature:`` section reads those) nor a measured torque's (``compliance``).
    """
    if not isinstance(name, str) or not _NAME.match(name):
        raise ConfigError(key, f'{name!r} is not a covariate name: dotted words such as '
                          'tilt.column.x or payload.mass (letters, digits, _ and -)')
    misspelled = payload_name_error(name)
    if misspelled:
        raise ConfigError(key, misspelled)
    if name.startswith((TEMPERATURE_PREFIX, DELTA_TEMPERATURE, EFFORT_PREFIX)):
        raise ConfigError(key, f'{name!r}: temperatures come from the temperature: section and '
                          'measured torques from compliance.torque_source: measured; name the '
                          'input otherwise')
    return name


def field_path(path: Any, key: str) -> tuple[tuple[str, str | None], ...]:
    """A source field (``vector.x``, ``effort[joint_2]``, ``data[3]``) as its steps
    (attribute, index or name or None), or ConfigError naming ``key``."""
    steps = []
    for part in (path.split('.') if isinstance(path, str) and path else [None]):
        found = _STEP.match(part) if part else None
        if found is None or found.group(1) == 'header':
            raise ConfigError(key, f'{path!r} is not a field path: attributes joined by ".", an '
                              'element as [i] or [name] (vector.x, effort[joint_2]); not in '
                              'the header')
        steps.append((found.group(1), found.group(2)))
    return tuple(steps)


def _source(raw: Any, key: str) -> InputSource:
    if not isinstance(raw, dict) or set(raw) - set(SOURCE_KEYS) or not raw.get('fields'):
        raise ConfigError(key, 'must be {topic: /name, type: pkg/msg/Type, fields: {covariate '
                          'name: field path}}')
    topic = raw.get('topic')
    if not isinstance(topic, str) or not topic.startswith('/'):
        raise ConfigError(f'{key}.topic', f'{topic!r}: an absolute topic name such as '
                          '/column_tilt')
    kind = raw.get('type')
    if not isinstance(kind, str) or not _TYPE.match(kind):
        raise ConfigError(f'{key}.type', f'{kind!r}: a ROS message type pkg/msg/Type with a '
                          'header, such as geometry_msgs/msg/Vector3Stamped')
    fields = raw['fields']
    if not isinstance(fields, dict):
        raise ConfigError(f'{key}.fields', 'must map covariate names to field paths')
    out = []
    for name, path in fields.items():
        check_covariate_name(name, f'{key}.fields')
        field_path(path, f'{key}.fields.{name}')
        out.append((name, path))
    return InputSource(topic, kind, tuple(out))


def input_settings(raw: Any, compliance: Any = None) -> InputSettings:
    """Validate the ``inputs:`` section (None: defaults) and the ``compliance:`` section."""
    source = torque_source(compliance)
    if raw is None:
        return InputSettings(torque_source=source)
    if not isinstance(raw, dict):
        raise ConfigError('inputs', 'must be a mapping with topic, max_gap, sources')
    unknown = sorted(set(raw) - set(INPUT_KEYS))
    if unknown:
        raise ConfigError(f'inputs.{unknown[0]}', f'unknown key; allowed {list(INPUT_KEYS)}')
    topic = raw.get('topic', DEFAULT_INPUTS_TOPIC)
    if not isinstance(topic, str) or not topic.startswith('/'):
        raise ConfigError('inputs.topic', f'{topic!r}: an absolute topic name')
    gap = raw.get('max_gap', DEFAULT_INPUT_MAX_GAP_NS / 1e9)
    if isinstance(gap, bool) or not isinstance(gap, (int, float)) \
            or not 0 < gap <= MAX_INPUT_GAP_S:
        raise ConfigError('inputs.max_gap', f'{gap!r}: seconds in (0, {MAX_INPUT_GAP_S:g}], the '
                          'largest gap between readings bridged by interpolation')
    sources = raw.get('sources') or []
    if not isinstance(sources, list):
        raise ConfigError('inputs.sources', 'must be a list of {topic, type, fields}')
    parsed = tuple(_source(s, f'inputs.sources[{i}]') for i, s in enumerate(sources))
    expect = raw.get('expect') or []
    if not isinstance(expect, list):
        raise ConfigError('inputs.expect', f'{expect!r}: a list of covariate names the '
                          f'named-values topic {topic} must give every point, such as '
                          '[payload.mass]')
    expect = [check_covariate_name(n, 'inputs.expect') for n in expect]
    names = [n for s in parsed for n, _ in s.fields] + expect
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ConfigError('inputs.sources', f'covariate {twice[0]!r} is given by two fields '
                          '(or a field and inputs.expect); name each input once')
    if any(s.topic == topic for s in parsed):
        raise ConfigError('inputs.sources', f'{topic} is inputs.topic, read as named values; '
                          'give a source another topic')
    return InputSettings(topic, float(gap), parsed, source, tuple(expect))


def torque_source(raw: Any) -> str:
    """``compliance.torque_source`` of the ``compliance:`` section (None: ``model``)."""
    if raw is None:
        return 'model'
    if not isinstance(raw, dict) or set(raw) - {'torque_source'}:
        raise ConfigError('compliance', 'must be {torque_source: model | measured}')
    value = raw.get('torque_source', 'model')
    if value not in TORQUE_SOURCES:
        raise ConfigError('compliance.torque_source', f'{value!r}: model (the gravity torques '
                          'of the URDF and payload) or measured (the joint states\' effort)')
    return str(value)

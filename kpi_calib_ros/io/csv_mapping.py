"""The column mapping of a posture table: which columns are joints, points, 6-DoF
orientations, per-point σ, stamps (and their format), the cell temperature and measured
inputs (covariates: a tilt, a payload mass, any recorded quantity).

A small YAML file (``kpi-calib import-csv --mapping``) or flags, validated here in one
place; every error is a :class:`~kpi_calib_ros.core.errors.ConfigError` naming the key
and the fix. Nothing about a robot is built in.
"""
from __future__ import annotations

import math
import zoneinfo
from dataclasses import dataclass, field
from datetime import tzinfo
from pathlib import Path
from typing import Any, Callable

import numpy as np
from scipy.spatial.transform import Rotation

from kpi_calib_ros.core.acquisition.reflector_frames import REFLECTOR_SEPARATOR
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.cell_inputs import check_covariate_name
from kpi_calib_ros.io.csv_table import DECIMALS, DELIMITERS
from kpi_calib_ros.io.yaml_bounded import read_yaml_file

STAMP_FORMATS = ('unix', 'iso8601', 'serial')
# The units a table may give a covariate in, by the covariate's kind (its name's start), each
# with its factor to SI; a covariate of another kind is written as the table gives it.
COVARIATE_UNITS = {
    'tilt.': {'rad': 1.0, 'mrad': 1e-3, 'urad': 1e-6, 'µrad': 1e-6, 'deg': math.pi / 180},
    'payload.mass': {'kg': 1.0, 'g': 1e-3},
    'payload.com.': {'m': 1.0, 'mm': 1e-3},
}


@dataclass(frozen=True)
class CovariateColumn:
    """A measured input's column, its unit as written and the factor to SI."""

    column: str
    unit: str = ''
    scale: float = 1.0


@dataclass(frozen=True)
class MarkerColumns:
    """Columns of one marker: ``position`` (x, y, z) in ``point_unit``; ``orientation``
    () for a plain point, three Euler angles (``euler`` sequence, SciPy's convention:
    upper case intrinsic) in ``angle_unit`` or a quaternion x, y, z, w; ``sigma`` ()
    or the per-point standard deviations of x, y, z in ``point_unit``."""

    position: tuple[str, str, str]
    orientation: tuple[str, ...] = ()
    euler: str = 'XYZ'
    sigma: tuple[str, ...] = ()

    @property
    def columns(self) -> tuple[str, ...]:
        return self.position + self.orientation + self.sigma


@dataclass(frozen=True)
class CsvMapping:
    """Which columns of a posture table are what.

    Attributes
    ----------
    joints : dict {joint name: column}
        Joint values, in ``joint_unit`` unless ``joint_units`` gives the joint its own.
    joint_units : dict {joint name: unit}
        A joint's own unit (``rad``, ``deg``, ``m``, ``mm``): a prismatic joint of a table in
        degrees is in m or mm, and says so here (the table does not know the robot).
    markers : dict {marker name: MarkerColumns}
        Points (poses) in ``frame_id``; names as in the cell's ``reflectors:``.
    frame_id : str
        Frame the points are expressed in (the cell's ``tracker.frame_id``).
    stamp_columns : tuple of str
        Column(s) whose mean is the row's stamp; () for the row order (synthetic stamps
        4 s apart).
    stamp_format : str
        ``unix`` (seconds), ``iso8601``, ``serial`` (spreadsheet days since 1899-12-30)
        or a ``strptime`` pattern such as ``%Y%m%d%H%M%S``.
    stamp_timezone : str
        IANA zone of stamps written without an offset (``Europe/Berlin``); UTC default.
    point_unit, joint_unit, angle_unit : str
        ``m`` or ``mm``; ``rad`` or ``deg``; ``rad`` or ``deg`` (Euler angles).
    temperatures : dict of str to str
        Temperature sensor frame id -> its column (°C), each reading written to the
        temperature topic with that frame id; {} for none. The document's ``temperature:``
        is one column (the sensor is then named by ``frame_id``) or ``{frame id: column}``.
    delimiter, decimal : str or None
        Separator and decimal mark; None: detected.
    covariates : dict of str to CovariateColumn
        Measured inputs: covariate name (``tilt.column.x``, ``payload.mass``) -> its column
        and unit, each row's value written (SI) to the inputs topic; {} for none.
    efforts : dict of str to CovariateColumn
        Measured joint torques: joint -> its column and unit (N m, or N for a prismatic
        joint; ``kN m``, ``mN m`` scaled), written as the joint states' ``effort``, which
        ``compliance.torque_source: measured`` reads; {} for none.
    """

    joints: dict[str, str]
    markers: dict[str, MarkerColumns]
    frame_id: str
    stamp_columns: tuple[str, ...] = ()
    point_unit: str = 'm'
    joint_unit: str = 'rad'
    stamp_format: str = 'unix'
    stamp_timezone: str = 'UTC'
    angle_unit: str = 'rad'
    temperatures: dict[str, str] = field(default_factory=dict)
    delimiter: str | None = None
    decimal: str | None = None
    covariates: dict[str, CovariateColumn] = field(default_factory=dict)
    joint_units: dict[str, str] = field(default_factory=dict)
    efforts: dict[str, CovariateColumn] = field(default_factory=dict)

    def joint_scales(self) -> np.ndarray:
        """SI factor of each joint column, in the order of ``joints``."""
        return np.array([JOINT_UNITS[self.joint_units.get(j, self.joint_unit)]
                         for j in self.joints])

    @property
    def columns(self) -> list[str]:
        return (list(self.joints.values()) + [c for m in self.markers.values()
                                              for c in m.columns]
                + list(self.stamp_columns) + list(self.temperatures.values())
                + [c.column for c in self.covariates.values()]
                + [c.column for c in self.efforts.values()])

    @property
    def has_poses(self) -> bool:
        return any(m.orientation for m in self.markers.values())


_KEYS = ('frame_id', 'joints', 'markers', 'stamp_columns', 'stamp_format', 'stamp_timezone',
         'point_unit', 'joint_unit', 'angle_unit', 'temperature', 'delimiter', 'decimal',
         'covariates', 'efforts')


def mapping_from_dict(doc: Any) -> CsvMapping:
    """Validate a mapping document::

        frame_id: mocap
        joints: [torso_lift_joint, arm_1_joint]      # column = joint name, or {joint: column}
        # a joint in its own unit (a prismatic one in a table in degrees):
        # joints: {torso_lift_joint: {column: lift, unit: mm}, arm_1_joint: a1}
        markers: {m1: [x1, y1, z1], m2: [x2, y2, z2]}
        # or a 6-DoF body: {probe: {position: [x, y, z], orientation: [rx, ry, rz],
        #                           euler: XYZ, sigma: [sx, sy, sz]}}   # sigma optional
        stamp_columns: [t_start, t_end]              # optional
        stamp_format: unix                            # unix | iso8601 | serial | '%Y%m%d%H%M%S'
        stamp_timezone: UTC                           # of stamps without an offset
        point_unit: m                                 # m | mm
        joint_unit: rad                               # rad | deg
        angle_unit: rad                               # rad | deg (Euler angles)
        temperature: t_cell                           # optional, °C; several sensors:
                                                      # {upper_arm: t_upper, forearm: t_fore}
        delimiter: ';'                                # optional: detected
        decimal: ','                                  # optional: detected
        covariates:                                   # optional: measured inputs per row
          tilt.column.x: {column: incl_x, unit: mrad} # tilt.*: rad | mrad | urad | deg
          payload.mass: {column: load, unit: kg}      # kg | g; payload.com.*: m | mm
          shift_hours: hours                          # any other quantity, as written
        efforts: {arm_1_joint: tau1}                  # optional: measured joint torques,
                                                      # N m (N prismatic) or {column, unit}
    """
    if not isinstance(doc, dict):
        raise ConfigError('mapping', 'must be a mapping with joints, markers, frame_id')
    unknown = set(doc) - set(_KEYS)
    if unknown:
        raise ConfigError(f'mapping.{sorted(unknown)[0]}',
                          f'unknown key; allowed {sorted(_KEYS)}')
    joints = doc.get('joints')
    if isinstance(joints, list):
        joints = {str(j): str(j) for j in joints}
    if not isinstance(joints, dict) or not joints:
        raise ConfigError('mapping.joints',
                          'give the joint columns: [name, ...] or {joint: column}')
    joints, joint_units = _joint_columns(joints)
    markers = doc.get('markers')
    if not isinstance(markers, dict) or not markers:
        raise ConfigError('mapping.markers', 'give {marker name: [x column, y column, z column]}')
    out_markers = {str(name): _marker(str(name), cols) for name, cols in markers.items()}
    frame = doc.get('frame_id')
    if not isinstance(frame, str) or not frame or REFLECTOR_SEPARATOR in frame:
        raise ConfigError('mapping.frame_id', "the points' frame (the cell's tracker.frame_id)")
    units = {key: doc.get(key, 'm' if key == 'point_unit' else 'rad')
             for key in ('point_unit', 'joint_unit', 'angle_unit')}
    for key, allowed in (('point_unit', ('m', 'mm')), ('joint_unit', ('rad', 'deg')),
                         ('angle_unit', ('rad', 'deg'))):
        if units[key] not in allowed:
            raise ConfigError(f'mapping.{key}', f'{allowed[0]!r} or {allowed[1]!r}, got '
                              f'{units[key]!r}')
    stamps = doc.get('stamp_columns') or ()
    if isinstance(stamps, str):
        stamps = (stamps,)
    stamp_format = str(doc.get('stamp_format', 'unix'))
    if stamp_format not in STAMP_FORMATS and '%' not in stamp_format:
        raise ConfigError('mapping.stamp_format', f'{stamp_format!r}: give one of '
                          f"{list(STAMP_FORMATS)} or a strptime pattern such as '%Y%m%d%H%M%S'")
    zone = str(doc.get('stamp_timezone', 'UTC'))
    time_zone(zone)
    temperatures = _temperatures(doc.get('temperature'), frame)
    delimiter, decimal = doc.get('delimiter'), doc.get('decimal')
    if delimiter is not None and delimiter not in DELIMITERS:
        raise ConfigError('mapping.delimiter', f'{delimiter!r}: one of {list(DELIMITERS)}')
    if decimal is not None and decimal not in DECIMALS:
        raise ConfigError('mapping.decimal', f'{decimal!r}: one of {list(DECIMALS)}')
    return CsvMapping(joints, out_markers, frame,
                      tuple(str(s) for s in stamps), units['point_unit'], units['joint_unit'],
                      stamp_format, zone, units['angle_unit'], temperatures, delimiter, decimal,
                      _covariates(doc.get('covariates')), joint_units,
                      _efforts(doc.get('efforts'), joints))


EFFORT_UNITS = {'N m': 1.0, 'N': 1.0, 'kN m': 1e3, 'mN m': 1e-3, 'kN': 1e3}


def _efforts(raw: Any, joints: dict[str, str]) -> dict[str, CovariateColumn]:
    """The ``efforts:`` key: {joint: column, or {column: ..., unit: ...}}, joints of the
    mapping's ``joints``."""
    def joint_of_the_table(joint: Any, key: str) -> None:
        if str(joint) not in joints:
            raise ConfigError(key, f'{joint!r} is not in mapping.joints {list(joints)}: an '
                              'effort belongs to a joint of the table')
    out = {}
    for joint, key, spec in _column_entries(
            raw, 'mapping.efforts', '{joint: column} or {joint: {column: ..., unit: N m}}, '
            'one entry per joint of mapping.joints whose torque the table records',
            joint_of_the_table):
        unit = spec.get('unit', 'N m')
        if unit not in EFFORT_UNITS:
            raise ConfigError(f'{key}.unit', f'{unit!r}: one of {list(EFFORT_UNITS)}')
        out[joint] = CovariateColumn(spec['column'], str(unit), EFFORT_UNITS[unit])
    return out


JOINT_UNITS = {'rad': 1.0, 'deg': np.pi / 180.0, 'm': 1.0, 'mm': 1e-3}


def _joint_columns(raw: dict) -> tuple[dict[str, str], dict[str, str]]:
    """``mapping.joints`` {joint: column or {column, unit}}: the columns and the joints' own
    units; one column read as two joints is refused (a copy-paste slip, not a coupling: a
    coupled joint's value comes from the cell's ``robot.joint_coupling``)."""
    columns, units = {}, {}
    for joint, value in raw.items():
        key = f'mapping.joints.{joint}'
        if isinstance(value, dict):
            if set(value) - {'column', 'unit'} or not isinstance(value.get('column'), str):
                raise ConfigError(key, 'give a column, or {column: name, unit: rad|deg|m|mm}')
            if value.get('unit') is not None:
                if value['unit'] not in JOINT_UNITS:
                    raise ConfigError(f'{key}.unit', f'{value["unit"]!r}: one of '
                                      f'{list(JOINT_UNITS)} (m or mm for a prismatic joint)')
                units[str(joint)] = str(value['unit'])
            value = value['column']
        if not isinstance(value, (str, int)) or isinstance(value, bool) or value == '':
            raise ConfigError(key, f'{value!r}: give the column holding this joint')
        columns[str(joint)] = str(value)
    twice = sorted({c for c in columns.values() if list(columns.values()).count(c) > 1})
    if twice:
        both = [j for j, c in columns.items() if c == twice[0]]
        raise ConfigError('mapping.joints', f'column {twice[0]!r} is read as joints {both}: '
                          'give each joint its own column')
    return columns, units


def _column_entries(raw: Any, section: str, fix: str, check: Callable[[Any, str], Any]
                    ) -> list[tuple[str, str, dict[str, Any]]]:
    """The entries of a ``{name: column, or {column: ..., unit: ...}}`` section as
    (name, its key, {column, unit}); [] when the section is absent. ``check(name, key)``
    refuses a name first; a section or an entry of another shape is refused naming it, with
    ``fix``."""
    if raw is None:
        return []
    if not isinstance(raw, dict) or not raw:
        raise ConfigError(section, fix)
    out = []
    for name, spec in raw.items():
        key = f'{section}.{name}'
        check(name, key)
        if isinstance(spec, str):
            spec = {'column': spec}
        if not isinstance(spec, dict) or set(spec) - {'column', 'unit'} \
                or not isinstance(spec.get('column'), str) or not spec['column']:
            raise ConfigError(key, fix)
        out.append((str(name), key, spec))
    return out


def _covariates(raw: Any) -> dict[str, CovariateColumn]:
    """The ``covariates:`` key: {covariate name: column, or {column: ..., unit: ...}}."""
    out = {}
    for name, key, spec in _column_entries(
            raw, 'mapping.covariates', '{covariate name: column} or {covariate name: '
            '{column: ..., unit: ...}}, e.g. {tilt.column.x: {column: incl_x, unit: mrad}}',
            lambda name, _: check_covariate_name(name, 'mapping.covariates')):
        unit = spec.get('unit')
        kind = next((units for prefix, units in COVARIATE_UNITS.items()
                     if name.startswith(prefix)), None)
        if kind is None:
            if unit is not None and not isinstance(unit, str):
                raise ConfigError(f'{key}.unit', f'{unit!r}: the unit as text')
            out[name] = CovariateColumn(spec['column'], unit or '', 1.0)
            continue
        unit = next(iter(kind)) if unit is None else unit
        if unit not in kind:
            raise ConfigError(f'{key}.unit', f'{unit!r}: {name} is given in one of '
                              f'{list(kind)} (written in SI, {next(iter(kind))})')
        out[name] = CovariateColumn(spec['column'], unit, kind[unit])
    return out


def _temperatures(raw: Any, frame_id: str) -> dict[str, str]:
    """The ``temperature:`` key: one column (the sensor named ``frame_id``) or
    ``{sensor frame id: column}``."""
    if raw is None:
        return {}
    if isinstance(raw, str) and raw:
        return {frame_id: raw}
    fix = ('the column of the cell temperature (°C), or {sensor frame id: column} for several '
           'sensors (the frame ids the cell\'s temperature.sensors names)')
    if not isinstance(raw, dict) or not raw:
        raise ConfigError('mapping.temperature', fix)
    out = {}
    for sensor, column in raw.items():
        if not isinstance(sensor, str) or not sensor.strip() or ' ' in sensor:
            raise ConfigError('mapping.temperature', f'{sensor!r} is not a frame id; {fix}')
        if not isinstance(column, str) or not column:
            raise ConfigError(f'mapping.temperature.{sensor}', f'give its column; {fix}')
        out[sensor] = column
    return out


def _marker(name: str, cols: Any) -> MarkerColumns:
    key = f'mapping.markers.{name}'
    if not name or REFLECTOR_SEPARATOR in name:
        raise ConfigError(key, f'a non-empty name without {REFLECTOR_SEPARATOR!r}')
    if isinstance(cols, (list, tuple)):
        cols = {'position': cols}
    if not isinstance(cols, dict) or set(cols) - {'position', 'orientation', 'euler', 'sigma'}:
        raise ConfigError(key, 'must be [x column, y column, z column] or {position: [x, y, '
                          'z], orientation: [rx, ry, rz] or [qx, qy, qz, qw], euler: XYZ, '
                          'sigma: [sx, sy, sz]}')

    def columns(sub: str, sizes: tuple[int, ...]) -> tuple[str, ...]:
        value = cols.get(sub, [] if sub != 'position' else None)
        if not isinstance(value, (list, tuple)) or len(value) not in sizes:
            raise ConfigError(f'{key}.{sub}', f'give {" or ".join(map(str, sizes))} columns')
        return tuple(str(c) for c in value)

    position = columns('position', (3,))
    orientation = columns('orientation', (0, 3, 4))
    euler = str(cols.get('euler', 'XYZ'))
    if len(orientation) == 3:
        try:
            Rotation.from_euler(euler, [0.0, 0.0, 0.0])
        except ValueError:
            raise ConfigError(f'{key}.euler', f"{euler!r}: three of x, y, z, upper case "
                              "intrinsic ('XYZ'), lower case extrinsic ('xyz')") from None
    return MarkerColumns((position[0], position[1], position[2]), orientation, euler,
                         columns('sigma', (0, 3)))


def time_zone(name: str) -> tzinfo:
    """The IANA time zone ``name``; ConfigError naming ``mapping.stamp_timezone``."""
    try:
        return zoneinfo.ZoneInfo(name)
    except (zoneinfo.ZoneInfoNotFoundError, ValueError):
        raise ConfigError('mapping.stamp_timezone', f'{name!r}: an IANA time zone such as '
                          "'UTC' or 'Europe/Berlin'") from None


def load_mapping(path: str | Path) -> CsvMapping:
    """A :class:`CsvMapping` from a YAML file (see :func:`mapping_from_dict`)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError('mapping', f'file {str(path)!r} does not exist')
    doc = read_yaml_file(path, 'mapping', 'give a column mapping (see import-csv in the '
                         'README)', max_bytes=2 ** 20, max_nodes=100_000)
    return mapping_from_dict(doc)



__all__ = ['COVARIATE_UNITS', 'CovariateColumn', 'CsvMapping', 'MarkerColumns', 'STAMP_FORMATS',
           'load_mapping', 'mapping_from_dict', 'time_zone']

"""Static-posture tables (CSV) into MCAP bags every command reads.

A posture table has one row per still posture: joint values and the points (or 6-DoF
poses) of one or several reflectors / markers measured there. :func:`import_csv`
writes, for every row, joint states held still (zero velocity, ``rate_hz``) for
``±hold_s`` around the row's stamp and one ``PointStamped`` per marker at that stamp
(a ``PoseStamped`` on the pose topic for a marker with orientation columns), with
``header.frame_id = '<frame_id>#<marker name>'`` (the several-points convention of
:mod:`kpi_calib_ros.core.pairing`), and the row's cell temperature, if mapped, as a
``sensor_msgs/Temperature``. Which columns mean what is given by a :class:`CsvMapping`
(flags or a small YAML file); nothing about a robot is built in. Separator, decimal
mark and encoding are detected (:mod:`kpi_calib_ros.io.csv_table`). Rows stream into
the bag: memory does not grow with the table, and a failed import leaves no file.
"""
from __future__ import annotations

import heapq
import itertools
import zoneinfo
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone, tzinfo
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.pairing import REFLECTOR_SEPARATOR
from kpi_calib_ros.core.streams import JointSample, PointSample
from kpi_calib_ros.io.bag_writing import BagStream
from kpi_calib_ros.io.csv_table import TableFormat, detect_format, read_table
from kpi_calib_ros.io.names import (DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC, DEFAULT_POSE_TOPIC,
                                    DEFAULT_TEMPERATURE_TOPIC)

# Synthetic stamps when the table has none: one posture every few seconds from here.
_START_NS = 1_700_000_000_000_000_000
_PERIOD_NS = 4_000_000_000
_UNITS = {'m': 1.0, 'mm': 1e-3, 'rad': 1.0, 'deg': np.pi / 180.0}
_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)
_SPREADSHEET_EPOCH = datetime(1899, 12, 30)  # serial day 0 of Excel / LibreOffice dates
_MAX_S = 2 ** 31 - 1     # builtin_interfaces/Time: int32 seconds
STAMP_FORMATS = ('unix', 'iso8601', 'serial')


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
        Joint values, in ``joint_unit`` (prismatic joints always in m).
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
    temperature : str or None
        Column of the cell temperature (°C), written to its own topic.
    delimiter, decimal : str or None
        Separator and decimal mark; None: detected.
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
    temperature: str | None = None
    delimiter: str | None = None
    decimal: str | None = None

    @property
    def columns(self) -> list[str]:
        return (list(self.joints.values()) + [c for m in self.markers.values()
                                              for c in m.columns]
                + list(self.stamp_columns) + ([self.temperature] if self.temperature else []))

    @property
    def has_poses(self) -> bool:
        return any(m.orientation for m in self.markers.values())


_KEYS = ('frame_id', 'joints', 'markers', 'stamp_columns', 'stamp_format', 'stamp_timezone',
         'point_unit', 'joint_unit', 'angle_unit', 'temperature', 'delimiter', 'decimal')


def mapping_from_dict(doc: Any) -> CsvMapping:
    """Validate a mapping document::

        frame_id: mocap
        joints: [torso_lift_joint, arm_1_joint]      # column = joint name, or {joint: column}
        markers: {m1: [x1, y1, z1], m2: [x2, y2, z2]}
        # or a 6-DoF body: {probe: {position: [x, y, z], orientation: [rx, ry, rz],
        #                           euler: XYZ, sigma: [sx, sy, sz]}}   # sigma optional
        stamp_columns: [t_start, t_end]              # optional
        stamp_format: unix                            # unix | iso8601 | serial | '%Y%m%d%H%M%S'
        stamp_timezone: UTC                           # of stamps without an offset
        point_unit: m                                 # m | mm
        joint_unit: rad                               # rad | deg
        angle_unit: rad                               # rad | deg (Euler angles)
        temperature: t_cell                           # optional, °C
        delimiter: ';'                                # optional: detected
        decimal: ','                                  # optional: detected
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
    _zone(zone)
    temperature = doc.get('temperature')
    if temperature is not None and (not isinstance(temperature, str) or not temperature):
        raise ConfigError('mapping.temperature', 'the column of the cell temperature (°C)')
    delimiter, decimal = doc.get('delimiter'), doc.get('decimal')
    if delimiter is not None and delimiter not in (',', ';', '\t', '|'):
        raise ConfigError('mapping.delimiter', f"{delimiter!r}: one of ',', ';', '\\t', '|'")
    if decimal is not None and decimal not in ('.', ','):
        raise ConfigError('mapping.decimal', f"{decimal!r}: '.' or ','")
    return CsvMapping({str(k): str(v) for k, v in joints.items()}, out_markers, frame,
                      tuple(str(s) for s in stamps), units['point_unit'], units['joint_unit'],
                      stamp_format, zone, units['angle_unit'], temperature, delimiter, decimal)


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


def _zone(name: str) -> tzinfo:
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
    try:
        doc = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ConfigError('mapping', f'{path}: not a YAML file ({exc})') from None
    return mapping_from_dict(doc)


@dataclass(frozen=True)
class Posture:
    """One row: ``stamp_ns`` (None: row order), joint values (n,) SI, and per marker
    (name, xyz (3,) m, quaternion [x, y, z, w] or None, σ (3,) m or None)."""

    path: Path
    line: int
    stamp_ns: int | None
    q: np.ndarray
    points: tuple[tuple[str, np.ndarray, np.ndarray | None, np.ndarray | None], ...]
    temperature: float | None


def read_postures(path: str | Path, mapping: CsvMapping, fmt: TableFormat | None = None
                  ) -> Iterator[Posture]:
    """The rows of one table, one :class:`Posture` at a time (in the file's order).

    Raises
    ------
    DataError
        A missing column (the columns present and the format read are listed), a value
        that is not a finite number or a stamp that is none (line and column named).
    """
    path = Path(path)
    fmt = fmt or detect_format(path, mapping.delimiter, mapping.decimal)
    rows = read_table(path, fmt)
    present = list(next(rows)[1])
    missing = [c for c in dict.fromkeys(mapping.columns) if c not in present]
    if missing:
        raise DataError(f'{path}: columns {missing} are not in the file; columns present: '
                        f'{present} (read as {fmt.describe()}). Fix the mapping, or give '
                        '--delimiter / --decimal')
    zone = _zone(mapping.stamp_timezone)
    joint_scale, point_scale = _UNITS[mapping.joint_unit], _UNITS[mapping.point_unit]
    degrees = mapping.angle_unit == 'deg'
    for line, row in rows:
        cell = _Cells(path, line, row, fmt)
        points = []
        for name, m in mapping.markers.items():
            quaternion = None
            if len(m.orientation) == 3:
                quaternion = Rotation.from_euler(m.euler, cell.vector(m.orientation),
                                                 degrees=degrees).as_quat()
            elif m.orientation:
                quaternion = cell.vector(m.orientation)
            sigma = cell.vector(m.sigma) * point_scale if m.sigma else None
            points.append((name, cell.vector(m.position) * point_scale, quaternion, sigma))
        stamp = None
        if mapping.stamp_columns:
            stamp = int(round(np.mean([_stamp_s(path, line, c, row[c], mapping, fmt, zone)
                                       for c in mapping.stamp_columns]) * 1e9))
        yield Posture(path, line, stamp,
                      cell.vector(tuple(mapping.joints.values())) * joint_scale, tuple(points),
                      cell.value(mapping.temperature) if mapping.temperature else None)


@dataclass(frozen=True)
class _Cells:
    """The numbers of one row; a field that is none is an error naming line and column."""

    path: Path
    line: int
    row: dict[str, str]
    fmt: TableFormat

    def value(self, column: str) -> float:
        try:
            v = self.fmt.number(self.row[column])
        except ValueError:
            v = np.nan
        if not np.isfinite(v):
            raise DataError(f'{self.path}: line {self.line}, column {column!r}: '
                            f'{self.row[column]!r} is not a finite number (read as '
                            f'{self.fmt.describe()})')
        return v

    def vector(self, columns: tuple[str, ...]) -> np.ndarray:
        return np.array([self.value(c) for c in columns])


def _stamp_s(path: Path, line: int, column: str, text: str, mapping: CsvMapping,
             fmt: TableFormat, zone: tzinfo) -> float:
    """The stamp of one field (s since the Unix epoch)."""
    how = mapping.stamp_format
    fix = (f'fix the value or stamp_format ({how!r}), or give no stamp_columns: the time '
           'axis is then the row order')
    try:
        if how in ('unix', 'serial'):
            number = fmt.number(text)
            if how == 'unix':
                seconds = number
            else:
                moment = (_SPREADSHEET_EPOCH + timedelta(days=number)).replace(tzinfo=zone)
                seconds = (moment - _EPOCH) / timedelta(seconds=1)
        else:
            moment = (datetime.fromisoformat(text.strip()) if how == 'iso8601'
                      else datetime.strptime(text.strip(), how))
            if moment.tzinfo is None:
                moment = moment.replace(tzinfo=zone)
            seconds = (moment - _EPOCH) / timedelta(seconds=1)
    except (ValueError, OverflowError):
        raise DataError(f'{path}: line {line}, column {column!r}: {text!r} is not a stamp '
                        f'of format {how!r}; {fix}') from None
    if not (0 <= seconds < _MAX_S):
        raise DataError(f'{path}: line {line}, column {column!r}: {text!r} is '
                        f'{seconds:.6g} s since 1970, outside 1970-2038 (int32 seconds of a '
                        f'ROS stamp); {fix}')
    return seconds


@dataclass
class ImportSummary:
    """What :func:`import_csv` wrote and read: the bag, the postures, points and poses,
    how every table was read, the time axis, per-point σ and temperatures."""

    path: Path
    postures: int = 0
    points: int = 0
    poses: int = 0
    formats: dict[str, str] = field(default_factory=dict)
    time_axis: str = ''
    reordered: list[str] = field(default_factory=list)
    sigma_mean_m: dict[str, np.ndarray] = field(default_factory=dict)
    sigma_max_m: dict[str, np.ndarray] = field(default_factory=dict)
    temperature_range_c: tuple[float, float] | None = None

    def lines(self) -> list[str]:
        out = [f'written: {self.path} ({self.postures} postures, {self.points} points'
               + (f', of which {self.poses} 6-DoF poses' if self.poses else '') + ')']
        out += [f'read {name}: {how}' for name, how in self.formats.items()]
        out.append(f'time axis: {self.time_axis}')
        if self.reordered:
            out.append(f'{len(self.reordered)} row(s) out of stamp order kept at their '
                       f'stamps: {", ".join(self.reordered[:5])}'
                       + (' ...' if len(self.reordered) > 5 else ''))
        for name, mean in self.sigma_mean_m.items():
            out.append(f"per-point σ of {name}: mean {np.round(mean * 1e6, 1).tolist()} µm, "
                       f'max {np.round(self.sigma_max_m[name] * 1e6, 1).tolist()} µm (x, y, '
                       "z); not used by identify, which weighs every point by the cell's "
                       'noise.sigma')
        if self.temperature_range_c:
            low, high = self.temperature_range_c
            out.append(f'cell temperature: {low:.2f} to {high:.2f} °C')
        return out


def import_csv(csv_path: str | Path | list, out_path: str | Path, mapping: CsvMapping,
               rate_hz: float = 50.0, hold_s: float = 0.5,
               joint_topic: str = DEFAULT_JOINT_TOPIC,
               point_topic: str = DEFAULT_POINT_TOPIC,
               pose_topic: str = DEFAULT_POSE_TOPIC,
               temperature_topic: str = DEFAULT_TEMPERATURE_TOPIC,
               delimiter: str | None = None, decimal: str | None = None) -> ImportSummary:
    """Write the postures of ``csv_path`` (one table, or a list of tables of one
    campaign, e.g. several sessions) as an MCAP bag, row by row.

    With stamp columns the tables' rows are merged by stamp; without, they follow one
    another in the given order, :data:`_PERIOD_NS` apart. ``delimiter`` / ``decimal``
    override the mapping's and the detection.

    Rows are written as they come (memory does not grow with them but for 16 bytes of
    stamp, table and line a row); rows out of stamp order (a pose measured again, or
    rows appended later) are listed in the summary.

    Raises
    ------
    DataError
        Anything :func:`read_postures` refuses, two rows with one stamp or whose holds
        overlap (files and lines named). ``out_path`` is then left as it was.
    """
    paths = [Path(p) for p in (csv_path if isinstance(csv_path, list) else [csv_path])]
    if not paths:
        raise DataError('import-csv: give at least one table')
    summary = ImportSummary(Path(out_path))
    formats = {}
    for p in paths:
        fmt = detect_format(p, delimiter or mapping.delimiter, decimal or mapping.decimal)
        formats[p] = fmt
        summary.formats[str(p)] = fmt.describe()
    streams = [read_postures(p, mapping, formats[p]) for p in paths]
    table = {p: k for k, p in enumerate(paths)}
    rows: Iterator[Posture] = itertools.chain(*streams)
    if mapping.stamp_columns:
        # Tables of several sessions interleave by stamp (each in its own order).
        rows = heapq.merge(*streams, key=lambda r: r.stamp_ns or 0)
    names = tuple(mapping.joints)
    period = int(round(1e9 / rate_hz))
    hold = int(hold_s * 1e9)
    offsets = np.arange(-hold, hold + 1, period)
    zeros = np.zeros(len(names))
    sigma_sum: dict[str, np.ndarray] = {}
    temperatures = [np.inf, -np.inf]
    stamps = _Stamps(paths)
    if not Path(out_path).parent.is_dir():
        raise DataError(f'--out {out_path}: the folder {Path(out_path).parent} does not '
                        'exist; create it first')
    with BagStream(out_path, joint_topic, point_topic,
                   pose_topic if mapping.has_poses else None,
                   temperature_topic if mapping.temperature else None) as bag:
        for i, row in enumerate(rows):
            t = row.stamp_ns if row.stamp_ns is not None else _START_NS + i * _PERIOD_NS
            stamps.add(t, row, table[row.path])
            held = JointSample(t, names, row.q, zeros)
            bag.write_joint_held(held, (int(t + dt) for dt in offsets[offsets <= 0]))
            for name, xyz, quaternion, sigma in row.points:
                bag.write_point(PointSample(t, f'{mapping.frame_id}{REFLECTOR_SEPARATOR}{name}',
                                            xyz, quaternion))
                summary.points += 1
                summary.poses += quaternion is not None
                if sigma is not None:
                    sigma_sum[name] = sigma_sum.get(name, 0.0) + sigma
                    summary.sigma_max_m[name] = np.maximum(
                        summary.sigma_max_m.get(name, sigma), sigma)
            if row.temperature is not None:
                bag.write_temperature(t, mapping.frame_id, row.temperature)
                temperatures = [min(temperatures[0], row.temperature),
                                max(temperatures[1], row.temperature)]
            bag.write_joint_held(held, (int(t + dt) for dt in offsets[offsets > 0]))
            summary.postures += 1
        if not summary.postures:
            raise DataError(f'{", ".join(map(str, paths))}: no data rows')
        first, last = stamps.check(hold_s)
    summary.reordered = stamps.reordered
    summary.sigma_mean_m = {k: v / summary.postures for k, v in sigma_sum.items()}
    if mapping.temperature:
        summary.temperature_range_c = (temperatures[0], temperatures[1])
    summary.time_axis = _time_axis(mapping, first, last)
    return summary


class _Stamps:
    """Every row's stamp (8 bytes) and its table and line (4 + 4 bytes), kept in blocks to
    check at the end that no two postures' holds overlap; rows need not come in stamp
    order (MCAP readers order messages by stamp)."""

    _BLOCK = 1 << 16

    def __init__(self, paths: list[Path]) -> None:
        self.paths = paths
        self._stamps: list[np.ndarray] = []
        self._places: list[np.ndarray] = []
        self._fill = self._BLOCK
        self.latest: int | None = None
        self.reordered: list[str] = []

    def add(self, stamp: int, row: Posture, table: int) -> None:
        if self.latest is not None and stamp < self.latest:
            self.reordered.append(f'{row.path.name} line {row.line}')
        self.latest = stamp if self.latest is None else max(self.latest, stamp)
        if self._fill == self._BLOCK:
            self._stamps.append(np.empty(self._BLOCK, dtype=np.int64))
            self._places.append(np.empty((self._BLOCK, 2), dtype=np.int32))
            self._fill = 0
        self._stamps[-1][self._fill] = stamp
        self._places[-1][self._fill] = (table, row.line)
        self._fill += 1

    def check(self, hold_s: float) -> tuple[int, int]:
        """(first, last) stamp; DataError naming both rows when two postures' stamps are
        equal or their ±hold_s holds overlap."""
        self._stamps[-1] = self._stamps[-1][:self._fill]
        stamps = np.concatenate(self._stamps) if len(self._stamps) > 1 else self._stamps[0]
        order = np.argsort(stamps, kind='stable')
        gaps = np.diff(stamps[order])
        if len(gaps) and gaps.min() <= 2 * hold_s * 1e9:
            k = int(np.argmin(gaps))
            (t0, l0), (t1, l1) = (self._places[i // self._BLOCK][i % self._BLOCK]
                                  for i in (int(order[k]), int(order[k + 1])))
            where = (f'{self.paths[t0]} line {l0} and {self.paths[t1]} line {l1} have '
                     f'stamps {gaps[k] / 1e9:g} s apart')
            if gaps[k] <= 0:
                raise DataError(f'{where}: stamps truncated or repeated? give no '
                                'stamp_columns: the time axis is then the row order')
            raise DataError(f'{where}, within the ±{hold_s} s hold of the joint states; '
                            'reduce hold_s')
        return int(stamps[order[0]]), int(stamps[order[-1]])


def _time_axis(mapping: CsvMapping, first_ns: int, last_ns: int) -> str:
    if not mapping.stamp_columns:
        return (f'row order (no stamp_columns): postures {_PERIOD_NS / 1e9:g} s apart from '
                f'{datetime.fromtimestamp(first_ns / 1e9, timezone.utc).isoformat()}')
    zone = _zone(mapping.stamp_timezone)
    return (f'stamps of {list(mapping.stamp_columns)} ({mapping.stamp_format}, '
            f'{mapping.stamp_timezone}): '
            f'{datetime.fromtimestamp(first_ns / 1e9, zone).isoformat()} to '
            f'{datetime.fromtimestamp(last_ns / 1e9, zone).isoformat()}')


__all__ = ['CsvMapping', 'ImportSummary', 'MarkerColumns', 'Posture', 'STAMP_FORMATS',
           'import_csv', 'load_mapping', 'mapping_from_dict', 'read_postures']

"""Static-posture tables (CSV) into MCAP bags every command reads.

A posture table has one row per still posture: joint values and the points (or 6-DoF
poses) of one or several reflectors / markers measured there. A row may carry only some of
the markers (two marker mounts in one table): a marker whose position fields are empty (or
NaN) on a row has no point there; a row with no marker at all is refused. :func:`import_csv`
writes, for every row, joint states held still (zero velocity, ``rate_hz``) for
``±hold_s`` around the row's stamp and one ``PointStamped`` per marker at that stamp
(a ``PoseStamped`` on the pose topic for a marker with orientation columns), with
``header.frame_id = '<frame_id>#<marker name>'`` (the several-points convention of
:mod:`kpi_calib_ros.core.acquisition.reflector_frames`), and the row's cell temperature, if
mapped, as a ``sensor_msgs/Temperature``, and its measured inputs (covariates: a tilt, a
payload mass, any recorded quantity; converted to SI) as named values on the inputs topic
(:data:`~kpi_calib_ros.io.names.DEFAULT_INPUTS_TOPIC`). Which columns mean what is given by a
:class:`~kpi_calib_ros.io.csv_mapping.CsvMapping` (flags or a small YAML file). Separator, decimal
mark and encoding are detected (:mod:`kpi_calib_ros.io.csv_table`). Rows stream into
the bag (memory grows only by a 16-byte stamp index a row: 142 MiB peak RSS for 1e6
rows, bench/csv_import_large.py), and a failed import leaves no file.
"""
from __future__ import annotations

import heapq
import itertools
import os
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone, tzinfo
from pathlib import Path
from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from kpi_calib_ros.core.acquisition.reflector_frames import reflector_frame
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.measurement.covariates import (
    ABSOLUTE_ZERO_C,
    TEMPERATURE_LIMIT_C,
    covariate_unit,
    plausible_temperature,
)
from kpi_calib_ros.core.measurement.payload import PAYLOAD_COM_LIMIT_M, PAYLOAD_MASS_LIMIT_KG
from kpi_calib_ros.io.bag_writing import BagStream
from kpi_calib_ros.io.csv_mapping import (
    CsvMapping,
    MarkerColumns,
    load_mapping,
    mapping_from_dict,
    time_zone,
)
from kpi_calib_ros.io.csv_table import TableFormat, detect_format, read_table
from kpi_calib_ros.io.names import (
    DEFAULT_INPUTS_TOPIC,
    DEFAULT_JOINT_TOPIC,
    DEFAULT_POINT_TOPIC,
    DEFAULT_POSE_TOPIC,
    DEFAULT_TEMPERATURE_TOPIC,
    point_sigma_topic,
)

# Synthetic stamps when the table has none: one posture every few seconds from here.
_START_NS = 1_700_000_000_000_000_000
_PERIOD_NS = 4_000_000_000
_UNITS = {'m': 1.0, 'mm': 1e-3, 'rad': 1.0, 'deg': np.pi / 180.0}
_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)
_SPREADSHEET_EPOCH = datetime(1899, 12, 30)  # serial day 0 of Excel / LibreOffice dates
_MAX_S = 2 ** 31 - 1     # builtin_interfaces/Time: int32 seconds


# What a table's temperature may be, whatever the cell (which may read a narrower
# ``temperature.valid_range`` when the bag is identified): absolute zero to the limit no
# cell's range exceeds. A reading outside is not written.
PHYSICAL_RANGE_C = (ABSOLUTE_ZERO_C, TEMPERATURE_LIMIT_C)


@dataclass(frozen=True)
class Posture:
    """One row: ``stamp_ns`` (None: row order), joint values (n,) SI, and per marker
    (name, xyz (3,) m, quaternion [x, y, z, w] or None, σ (3,) m or None)."""

    path: Path
    line: int
    stamp_ns: int | None
    q: np.ndarray
    points: tuple[tuple[str, np.ndarray, np.ndarray | None, np.ndarray | None], ...]
    temperatures: dict[str, float]  # sensor frame id -> °C
    inputs: dict[str, float] = field(default_factory=dict)  # covariate name -> value, SI
    efforts: dict[str, float] = field(default_factory=dict)  # joint -> measured torque, SI


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
    zone = time_zone(mapping.stamp_timezone)
    joint_scale, point_scale = mapping.joint_scales(), _UNITS[mapping.point_unit]
    degrees = mapping.angle_unit == 'deg'
    for line, row in rows:
        cell = _Cells(path, line, row, fmt)
        points = []
        for name, m in mapping.markers.items():
            if cell.missing(m.position):
                continue  # this row's mount does not carry the marker: no point for it
            quaternion = None
            if len(m.orientation) == 3:
                quaternion = Rotation.from_euler(m.euler, cell.vector(m.orientation),
                                                 degrees=degrees).as_quat()
            elif m.orientation:
                quaternion = cell.vector(m.orientation)
            sigma = cell.vector(m.sigma) * point_scale if m.sigma else None
            if sigma is not None and np.any(sigma <= 0):
                column = m.sigma[int(np.argmax(sigma <= 0))]
                raise DataError(f'{path}: line {line}, column {column!r}: a point\'s sigma '
                                f'must be > 0 ({mapping.point_unit}, the '
                                "tracker's stated standard deviation); leave the sigma "
                                'columns out of the mapping if the table has none')
            points.append((name, cell.vector(m.position) * point_scale, quaternion, sigma))
        if not points:
            columns = [c for m in mapping.markers.values() for c in m.position]
            raise DataError(f'{path}: line {line}: no marker has a value (columns {columns} '
                            'all empty): a row needs the point of at least one marker; '
                            'remove the row, or fill in its marker')
        stamp = None
        if mapping.stamp_columns:
            stamp = int(round(np.mean([_stamp_s(path, line, c, row[c], mapping, fmt, zone)
                                       for c in mapping.stamp_columns]) * 1e9))
        yield Posture(path, line, stamp,
                      cell.vector(tuple(mapping.joints.values())) * joint_scale, tuple(points),
                      {sensor: cell.value(column)
                       for sensor, column in mapping.temperatures.items()},
                      {name: _plausible_input(cell, name, c.column, c.unit,
                                              cell.value(c.column) * c.scale)
                       for name, c in mapping.covariates.items()},
                      {joint: cell.value(c.column) * c.scale
                       for joint, c in mapping.efforts.items()})


# The size a measured input of a known kind may have (SI): beyond, a unit slip or a fault.
_INPUT_LIMITS = (('tilt.', -0.5, 0.5, 'rad: a column leaning by more than 0.5 rad is no '
                  'lean'), ('payload.mass', 0.0, PAYLOAD_MASS_LIMIT_KG, 'kg'),
                 ('payload.com.', -PAYLOAD_COM_LIMIT_M, PAYLOAD_COM_LIMIT_M,
                  'm from the tip frame'))


def _plausible_input(cell: _Cells, name: str, column: str, unit: str, value: float) -> float:
    """``value`` (SI) of covariate ``name``, or DataError naming line, column and range."""
    for prefix, low, high, what in _INPUT_LIMITS:
        if name.startswith(prefix) and not low <= value <= high:
            raise DataError(f'{cell.path}: line {cell.line}, column {column!r}: {name} = '
                            f'{value:g} in SI, outside [{low:g}, {high:g}] {what}; give the '
                            f"column's unit in mapping.covariates.{name}.unit (now "
                            f'{unit or "SI"})')
    return value


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

    def missing(self, columns: tuple[str, ...]) -> bool:
        """Every field of ``columns`` is empty or NaN: the row has no value for them."""
        for column in columns:
            text = self.row[column].strip()
            if not text:
                continue
            try:
                if np.isnan(self.fmt.number(text)):
                    continue
            except ValueError:
                pass
            return False
        return True

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
    temperature_range_c: dict[str, tuple[float, float]] = field(default_factory=dict)
    # Readings no arm can have, not written: sensor -> (count, the first one's line and value).
    temperature_rejected: dict[str, tuple[int, str]] = field(default_factory=dict)
    sigma_topic: str = ''
    # measured inputs: name -> (lowest, highest) in SI, and the topic they were written to
    input_range: dict[str, tuple[float, float]] = field(default_factory=dict)
    inputs_topic: str = ''
    # the tracker frame and the markers the points are written for ('<frame_id>#<marker>'):
    # what the cell's reflectors must name
    frame_id: str = ''
    markers: tuple[str, ...] = ()

    def lines(self) -> list[str]:
        out = [f'written: {self.path} ({self.postures} postures, {self.points} points'
               + (f', of which {self.poses} 6-DoF poses' if self.poses else '') + ')']
        out += [f'read {name}: {how}' for name, how in self.formats.items()]
        if self.markers:
            frames = [reflector_frame(self.frame_id, n) for n in self.markers]
            out.append(f'points written with frame_id {", ".join(map(repr, frames))}: '
                       'the cell names these reflectors, reflectors: ['
                       + ', '.join(f'{{name: {n}}}' for n in self.markers) + '] (a cell with '
                       'one reflector: without a name reads plain frame ids only)')
        out.append(f'time axis: {self.time_axis}')
        if self.reordered:
            out.append(f'{len(self.reordered)} row(s) out of stamp order kept at their '
                       f'stamps: {", ".join(self.reordered[:5])}'
                       + (' ...' if len(self.reordered) > 5 else ''))
        for name, mean in self.sigma_mean_m.items():
            out.append(f"per-point σ of {name}: mean {np.round(mean * 1e6, 1).tolist()} µm, "
                       f'max {np.round(self.sigma_max_m[name] * 1e6, 1).tolist()} µm (x, y, '
                       f'z), written to {self.sigma_topic}: identify weighs each point by it')
        for sensor, (low, high) in self.temperature_range_c.items():
            out.append(f'temperature {sensor}: {low:.2f} to {high:.2f} °C')
        for name, (low, high) in self.input_range.items():
            out.append(f'input {name}: {low:.6g} to {high:.6g} {covariate_unit(name)}'.rstrip()
                       + f', written to {self.inputs_topic}')
        for sensor, (count, first) in self.temperature_rejected.items():
            out.append(f'temperature {sensor}: {count} reading(s) outside '
                       f'[{PHYSICAL_RANGE_C[0]:g}, {PHYSICAL_RANGE_C[1]:g}] °C not written '
                       f'(first: {first}): a fault of the sensor; the points are paired with '
                       'the readings around them')
        return out


def import_csv(csv_path: str | Path | list, out_path: str | Path, mapping: CsvMapping,
               rate_hz: float = 50.0, hold_s: float = 0.5,
               joint_topic: str = DEFAULT_JOINT_TOPIC,
               point_topic: str = DEFAULT_POINT_TOPIC,
               pose_topic: str = DEFAULT_POSE_TOPIC,
               temperature_topic: str = DEFAULT_TEMPERATURE_TOPIC,
               delimiter: str | None = None, decimal: str | None = None,
               inputs_topic: str = DEFAULT_INPUTS_TOPIC) -> ImportSummary:
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
    summary.frame_id, summary.markers = mapping.frame_id, tuple(mapping.markers)
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
    sigma_rows: dict[str, int] = {}
    stamps = _Stamps(paths)
    out = Path(out_path)
    if not out.parent.is_dir() or out.is_dir() or not os.access(out.parent, os.W_OK):
        raise DataError(f'--out {out}: give a .mcap file in an existing folder this user can '
                        'write (' + ('it is a folder' if out.is_dir() else
                                     f'{out.parent} does not exist' if not out.parent.is_dir()
                                     else f'{out.parent} is not writable') + ')')
    has_sigma = any(m.sigma for m in mapping.markers.values())
    summary.sigma_topic = point_sigma_topic(point_topic)
    with BagStream(out_path, joint_topic, point_topic,
                   pose_topic if mapping.has_poses else None,
                   temperature_topic if mapping.temperatures else None,
                   sigma_topic=point_sigma_topic(point_topic) if has_sigma else None,
                   inputs_topic=inputs_topic if mapping.covariates else None) as bag:
        summary.inputs_topic = inputs_topic
        if not mapping.stamp_columns:  # stamps numbering the rows: no clock
            bag.mark_row_order_stamps()
        for i, row in enumerate(rows):
            t = row.stamp_ns if row.stamp_ns is not None else _START_NS + i * _PERIOD_NS
            stamps.add(t, row, table[row.path])
            held = JointSample(t, names, row.q, zeros,
                               np.array([row.efforts.get(j, np.nan) for j in names])
                               if mapping.efforts else None)
            bag.write_joint_held(held, (int(t + dt) for dt in offsets[offsets <= 0]))
            for name, xyz, quaternion, sigma in row.points:
                sample = PointSample(t, reflector_frame(mapping.frame_id, name), xyz,
                                     quaternion)
                bag.write_point(sample)
                summary.points += 1
                summary.poses += quaternion is not None
                if sigma is not None:
                    bag.write_point_sigma(sample, sigma)
                    sigma_sum[name] = sigma_sum.get(name, 0.0) + sigma
                    sigma_rows[name] = sigma_rows.get(name, 0) + 1
                    summary.sigma_max_m[name] = np.maximum(
                        summary.sigma_max_m.get(name, sigma), sigma)
            for sensor, celsius in row.temperatures.items():
                if not plausible_temperature(celsius, PHYSICAL_RANGE_C):
                    count, where = summary.temperature_rejected.get(
                        sensor, (0, f'{row.path}: line {row.line}, {celsius:g} °C'))
                    summary.temperature_rejected[sensor] = (count + 1, where)
                    continue
                bag.write_temperature(t, sensor, celsius)
                low, high = summary.temperature_range_c.get(sensor, (np.inf, -np.inf))
                summary.temperature_range_c[sensor] = (min(low, celsius), max(high, celsius))
            if row.inputs:
                bag.write_inputs(t, tuple(row.inputs), np.array(list(row.inputs.values())))
                for name, value in row.inputs.items():
                    low, high = summary.input_range.get(name, (np.inf, -np.inf))
                    summary.input_range[name] = (min(low, value), max(high, value))
            bag.write_joint_held(held, (int(t + dt) for dt in offsets[offsets > 0]))
            summary.postures += 1
        if not summary.postures:
            raise DataError(f'{", ".join(map(str, paths))}: no data rows')
        first, last = stamps.check(hold_s)
    summary.reordered = stamps.reordered
    summary.sigma_mean_m = {k: v / sigma_rows[k] for k, v in sigma_sum.items()}
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
    zone = time_zone(mapping.stamp_timezone)
    return (f'stamps of {list(mapping.stamp_columns)} ({mapping.stamp_format}, '
            f'{mapping.stamp_timezone}): '
            f'{datetime.fromtimestamp(first_ns / 1e9, zone).isoformat()} to '
            f'{datetime.fromtimestamp(last_ns / 1e9, zone).isoformat()}')


# The mapping's names, for callers that import everything of an import from here.
__all__ = ['CsvMapping', 'ImportSummary', 'MarkerColumns', 'Posture', 'import_csv',
           'load_mapping', 'mapping_from_dict', 'read_postures']

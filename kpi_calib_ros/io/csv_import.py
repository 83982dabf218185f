"""Static-posture tables (CSV) into MCAP bags every command reads.

A posture table has one row per still posture: joint values and the points of one
or several reflectors / markers measured there. :func:`import_csv` writes, for
every row, joint states held still (zero velocity, ``rate_hz``) for ``±hold_s``
around the row's stamp and one ``PointStamped`` per marker at that stamp, with
``header.frame_id = '<frame_id>#<marker name>'`` (the several-points convention of
:mod:`kpi_calib_ros.core.pairing`). Which columns mean what is given by a
:class:`CsvMapping` (flags or a small YAML file); nothing about a robot is built in.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.pairing import REFLECTOR_SEPARATOR
from kpi_calib_ros.core.streams import JointSample, PointSample
from kpi_calib_ros.io.bag_writing import write_bag
from kpi_calib_ros.io.names import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC

# Synthetic stamps when the table has none: one posture every few seconds from here.
_START_NS = 1_700_000_000_000_000_000
_UNITS = {'m': 1.0, 'mm': 1e-3, 'rad': 1.0, 'deg': np.pi / 180.0}


@dataclass(frozen=True)
class CsvMapping:
    """Which columns of a posture table are what.

    Attributes
    ----------
    joints : dict {joint name: column}
        Joint values, in ``joint_unit`` (prismatic joints always in m).
    markers : dict {marker name: (x column, y column, z column)}
        Points in ``frame_id``, in ``point_unit``; names as in the cell's ``reflectors:``.
    frame_id : str
        Frame the points are expressed in (the cell's ``tracker.frame_id``).
    stamp_columns : tuple of str
        Column(s) in Unix seconds whose mean is the row's stamp; () for synthetic
        stamps ``period_s`` apart.
    point_unit, joint_unit : str
        ``m`` or ``mm``; ``rad`` or ``deg``.
    """

    joints: dict[str, str]
    markers: dict[str, tuple[str, str, str]]
    frame_id: str
    stamp_columns: tuple[str, ...] = ()
    point_unit: str = 'm'
    joint_unit: str = 'rad'


def mapping_from_dict(doc: Any) -> CsvMapping:
    """Validate a mapping document::

        frame_id: mocap
        joints: [torso_lift_joint, arm_1_joint]      # column = joint name, or {joint: column}
        markers: {m1: [x1, y1, z1], m2: [x2, y2, z2]}
        stamp_columns: [t_start, t_end]              # optional, Unix s
        point_unit: m                                 # m | mm
        joint_unit: rad                               # rad | deg
    """
    if not isinstance(doc, dict):
        raise ConfigError('mapping', 'must be a mapping with joints, markers, frame_id')
    allowed = {'frame_id', 'joints', 'markers', 'stamp_columns', 'point_unit', 'joint_unit'}
    unknown = set(doc) - allowed
    if unknown:
        raise ConfigError(f'mapping.{sorted(unknown)[0]}',
                          f'unknown key; allowed {sorted(allowed)}')
    joints = doc.get('joints')
    if isinstance(joints, list):
        joints = {str(j): str(j) for j in joints}
    if not isinstance(joints, dict) or not joints:
        raise ConfigError('mapping.joints',
                          'give the joint columns: [name, ...] or {joint: column}')
    markers = doc.get('markers')
    if not isinstance(markers, dict) or not markers:
        raise ConfigError('mapping.markers', 'give {marker name: [x column, y column, z column]}')
    out_markers = {}
    for name, cols in markers.items():
        if not isinstance(cols, (list, tuple)) or len(cols) != 3:
            raise ConfigError(f'mapping.markers.{name}', 'must be [x column, y column, z column]')
        if not str(name) or REFLECTOR_SEPARATOR in str(name):
            raise ConfigError(f'mapping.markers.{name}', f'a non-empty name without '
                              f'{REFLECTOR_SEPARATOR!r}')
        out_markers[str(name)] = (str(cols[0]), str(cols[1]), str(cols[2]))
    frame = doc.get('frame_id')
    if not isinstance(frame, str) or not frame or REFLECTOR_SEPARATOR in frame:
        raise ConfigError('mapping.frame_id', "the points' frame (the cell's tracker.frame_id)")
    point_unit, joint_unit = doc.get('point_unit', 'm'), doc.get('joint_unit', 'rad')
    if point_unit not in ('m', 'mm'):
        raise ConfigError('mapping.point_unit', f"'m' or 'mm', got {point_unit!r}")
    if joint_unit not in ('rad', 'deg'):
        raise ConfigError('mapping.joint_unit', f"'rad' or 'deg', got {joint_unit!r}")
    stamps = doc.get('stamp_columns') or ()
    if isinstance(stamps, str):
        stamps = (stamps,)
    return CsvMapping({str(k): str(v) for k, v in joints.items()}, out_markers, frame,
                      tuple(str(s) for s in stamps), point_unit, joint_unit)


def load_mapping(path: str | Path) -> CsvMapping:
    """A :class:`CsvMapping` from a YAML file (see :func:`mapping_from_dict`)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError('mapping', f'file {str(path)!r} does not exist')
    return mapping_from_dict(yaml.safe_load(path.read_text()))


def read_postures(path: str | Path, mapping: CsvMapping
                  ) -> tuple[list[str], np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """Joint names, joint values (N, n) in SI, marker points {name: (N, 3)} m, stamps (N,) ns.

    Raises
    ------
    DataError
        A missing column (the columns present are listed), a value that is not a
        finite number (row and column named), or stamps that do not increase.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f'{path}: no such file')
    with open(path, newline='') as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise DataError(f'{path}: no data rows')
    present = list(rows[0])
    needed = list(mapping.joints.values()) + [c for cols in mapping.markers.values()
                                              for c in cols] + list(mapping.stamp_columns)
    missing = [c for c in needed if c not in present]
    if missing:
        raise DataError(f'{path}: columns {missing} are not in the file; columns present: '
                        f'{present}. Fix the mapping')

    def column(name: str) -> np.ndarray:
        values = []
        for i, row in enumerate(rows):
            try:
                v = float(row[name])
            except (TypeError, ValueError):
                v = np.nan
            if not np.isfinite(v):
                raise DataError(f'{path}: row {i + 2}, column {name!r}: {row[name]!r} is not a '
                                'finite number')
            values.append(v)
        return np.array(values)

    joint_names = list(mapping.joints)
    q = np.stack([column(c) for c in mapping.joints.values()], axis=1)
    q *= _UNITS[mapping.joint_unit]
    points = {m: np.stack([column(c) for c in cols], axis=1) * _UNITS[mapping.point_unit]
              for m, cols in mapping.markers.items()}
    if mapping.stamp_columns:
        stamps = np.round(np.mean([column(c) for c in mapping.stamp_columns], axis=0)
                          * 1e9).astype(np.int64)
        if np.any(np.diff(stamps) <= 0):
            raise DataError(f'{path}: the stamps of {list(mapping.stamp_columns)} do not increase '
                            'row by row; give no stamp columns for synthetic stamps')
    else:
        stamps = _START_NS + np.arange(len(rows), dtype=np.int64) * 4_000_000_000
    return joint_names, q, points, stamps


def import_csv(csv_path: str | Path | list, out_path: str | Path, mapping: CsvMapping,
               rate_hz: float = 50.0, hold_s: float = 0.5,
               joint_topic: str = DEFAULT_JOINT_TOPIC,
               point_topic: str = DEFAULT_POINT_TOPIC) -> tuple[Path, int, int]:
    """Write the postures of ``csv_path`` (one table, or a list of tables of one
    campaign, e.g. several sessions) as an MCAP bag.

    Returns
    -------
    (Path, int, int)
        The bag, the number of postures and of points written.
    """
    tables = [read_postures(p, mapping) for p in
              (csv_path if isinstance(csv_path, list) else [csv_path])]
    names = tables[0][0]
    order = np.argsort(np.concatenate([t[3] for t in tables]), kind='stable')
    q = np.concatenate([t[1] for t in tables])[order]
    stamps = np.concatenate([t[3] for t in tables])[order]
    points = {m: np.concatenate([t[2][m] for t in tables])[order] for m in mapping.markers}
    if len(tables) > 1 and not mapping.stamp_columns:
        stamps = _START_NS + np.arange(len(q), dtype=np.int64) * 4_000_000_000
    gaps = np.diff(stamps)
    if len(gaps) and gaps.min() <= 2 * hold_s * 1e9:
        raise DataError(f'{csv_path}: postures {int(gaps.min())} ns apart overlap the '
                        f'±{hold_s} s hold; reduce hold_s')
    period = int(round(1e9 / rate_hz))
    offsets = np.arange(-int(hold_s * 1e9), int(hold_s * 1e9) + 1, period)
    joints = [JointSample(int(t + dt), tuple(names), qi, np.zeros(len(names)))
              for t, qi in zip(stamps, q) for dt in offsets]
    pts = [PointSample(int(t), f'{mapping.frame_id}{REFLECTOR_SEPARATOR}{m}', xyz[i])
           for m, xyz in points.items() for i, t in enumerate(stamps)]
    path = write_bag(out_path, joints, pts, joint_topic, point_topic)
    return path, len(q), len(pts)


__all__ = ['CsvMapping', 'import_csv', 'load_mapping', 'mapping_from_dict', 'read_postures']

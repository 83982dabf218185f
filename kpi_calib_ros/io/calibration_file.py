"""Reading a calibration.yaml from outside: a bounded YAML load and a check of every field
the package computes with, so a damaged or edited file is a :class:`ConfigError` naming
the file, the field and the fix, never a crash or a NaN in a result.

The YAML load is bounded (:mod:`kpi_calib_ros.io.yaml_bounded`: the file size and the
size of the document with every alias expanded), so an alias bomb in
``parameter_covariance.matrix`` is refused before anything is built.

A checked document becomes the core's typed objects here: the prior of a previous
calibration (:func:`prior_from_calibration`) and its drift state
(:func:`drift_state_from_dict`).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.estimation.drift_state import DriftState
from kpi_calib_ros.core.estimation.prior import PLACEMENT_PREFIXES, Prior
from kpi_calib_ros.core.measurement.recordings import NAME_PATTERN, Recording, stated_conditions
from kpi_calib_ros.core.model.parameters import RECORDING_PREFIX
from kpi_calib_ros.io.yaml_bounded import FIX, read_yaml_file


def read_calibration_document(path: str | Path, key: str = 'calibration',
                              required: tuple[str, ...] = ('parameter_covariance',)
                              ) -> dict[str, Any]:
    """A calibration.yaml as a dict, loaded bounded
    (:func:`kpi_calib_ros.io.yaml_bounded.read_yaml_file`) and checked
    field by field (:func:`check_calibration_document`); ``required``: the sections the
    caller computes with. ConfigError names ``key`` (the option that gave the path), the
    file and the field."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(key, f'file {str(path)!r} does not exist; give a calibration.yaml '
                          'written by kpi-calib identify')
    doc = read_yaml_file(path, key, FIX)
    if not isinstance(doc, dict) or 'parameters' not in doc:
        raise ConfigError(key, f'{path} is not a calibration document (no parameters:)')
    check_calibration_document(doc, f'{key} {path}', required)
    return doc


def calibration_recordings(doc: dict[str, Any], where: str) -> list[Recording]:
    """The recordings a calibration was identified from (its ``recordings:`` section), each
    with whether its probe was remounted and the conditions stated for it (its constant
    covariates, e.g. ``payload.mass``); [] for a calibration of one recording. ConfigError
    names the field."""
    section = doc.get('recordings')
    if section is None:
        return []
    if not isinstance(section, list) or not section:
        raise ConfigError('recordings', f'in {where}: must be a non-empty list; {FIX}')
    out = []
    for i, entry in enumerate(section):
        if not isinstance(entry, dict) or not isinstance(entry.get('name'), str) \
                or not NAME_PATTERN.match(entry['name']):
            raise ConfigError(f'recordings[{i}].name', f'in {where}: must be a recording name '
                              f'(a letter, then letters, digits, _ or -); {FIX}')
        remounted = entry.get('reflector_remounted', False)
        if not isinstance(remounted, bool):
            raise ConfigError(f'recordings[{i}].reflector_remounted', f'in {where}: must be '
                              f'true or false; {FIX}')
        conditions = stated_conditions(entry.get('covariates') or {},
                                       f'recordings[{i}].covariates', f'in {where}: ')
        out.append(Recording(entry['name'], remounted, conditions))
    names = [r.name for r in out]
    if len(set(names)) != len(names):
        raise ConfigError('recordings', f'in {where}: names a recording twice; {FIX}')
    return out


def check_calibration_document(doc: dict[str, Any], where: str,
                               required: tuple[str, ...] = ()) -> None:
    """Check every field of a calibration document the package reads (types, shapes,
    finite values, ranges); ConfigError's key is the field (``precision.covariance_scale``,
    ``training_joint_ranges.joint_1``), its message names ``where`` and the fix.

    ``required``: top-level sections that must be present (the others are optional, as
    older files lack them).
    """
    def bad(field: str, what: str) -> ConfigError:
        return ConfigError(field, f'in {where}: {what}; {FIX}')

    for name in required:
        if name not in doc:
            raise bad(name, 'missing (identify again with this version to write it)')
    parameters = doc['parameters']
    if not isinstance(parameters, list) or not parameters:
        raise bad('parameters', 'must be a non-empty list of {name, value, ...}')
    names = []
    for i, entry in enumerate(parameters):
        if not isinstance(entry, dict) or not isinstance(entry.get('name'), str):
            raise bad(f'parameters[{i}]', 'must be a mapping with a name (text) and a value')
        value = entry.get('value')
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise bad(f'parameters[{i}].value', f"{entry['name']} must be a finite number, "
                      f'got {value!r}')
        names.append(entry['name'])
    if len(set(names)) != len(names):
        raise bad('parameters', 'names a parameter twice')
    known = set(names)
    placed = {f'{RECORDING_PREFIX}{r.name}.base.x' for r in calibration_recordings(doc, where)[1:]}
    if placed - known:
        raise bad('recordings', f'lists recordings whose placement {sorted(placed - known)} '
                  'is not among the parameters')
    if 'parameter_covariance' in doc:
        cov = doc['parameter_covariance']
        if not isinstance(cov, dict) or not isinstance(cov.get('names'), list) \
                or not all(isinstance(n, str) for n in cov['names']):
            raise bad('parameter_covariance', 'must be a mapping with names (a list of '
                      'parameter names) and matrix')
        cnames = cov['names']
        if len(set(cnames)) != len(cnames) or any(n not in known for n in cnames):
            raise bad('parameter_covariance.names', 'must be unique names of parameters')
        matrix = _matrix(cov.get('matrix'), (len(cnames), len(cnames)),
                         'parameter_covariance.matrix', bad)
        _covariance(matrix, 'parameter_covariance.matrix', bad)
    if 'noise_sigma_m' in doc:
        sigma = doc['noise_sigma_m']
        values = sigma if isinstance(sigma, list) else [sigma]
        if not values or len(values) > 3:
            raise bad('noise_sigma_m', 'must be one to three numbers (m)')
        for i, s in enumerate(values):
            if _finite(s, f'noise_sigma_m[{i}]', bad) <= 0:
                raise bad(f'noise_sigma_m[{i}]', f'must be > 0 m, got {s!r}')
    if 'precision' in doc:
        precision = doc['precision']
        if not isinstance(precision, dict):
            raise bad('precision', f'must be a mapping (covariance_scale, basis), got '
                      f'{precision!r}')
        for key in ('covariance_scale', 'noise_scale'):
            if key in precision and _finite(precision[key], f'precision.{key}', bad) <= 0:
                raise bad(f'precision.{key}', f'must be > 0, got {precision[key]!r}')
    adequacy = doc.get('model_adequacy')
    if adequacy is not None:
        if not isinstance(adequacy, dict):
            raise bad('model_adequacy', f'must be a mapping (chi2, dof, ...), got {adequacy!r}')
        dof = adequacy.get('dof', 0)
        if not isinstance(dof, int) or isinstance(dof, bool) or dof < 0:
            raise bad('model_adequacy.dof', f'must be an integer >= 0, got {dof!r}')
    if 'identified_at_ns' in doc:
        stamp = doc['identified_at_ns']
        if not isinstance(stamp, int) or isinstance(stamp, bool) or stamp < 0:
            raise bad('identified_at_ns', 'must be an integer time stamp (ns since the Unix '
                      f'epoch, the last measurement of the calibration), got {stamp!r}')
    if doc.get('training_joint_ranges') is not None:
        ranges = doc['training_joint_ranges']
        if not isinstance(ranges, dict):
            raise bad('training_joint_ranges', 'must be a mapping joint: [lower, upper]')
        for joint, pair in ranges.items():
            field = f'training_joint_ranges.{joint}'
            if not isinstance(pair, list) or len(pair) != 2:
                raise bad(field, f'must be [lower, upper] (rad or m), got {pair!r}')
            lo, hi = (_finite(x, field, bad) for x in pair)
            if lo > hi:
                raise bad(field, f'lower {lo} is above upper {hi}')
    if doc.get('training_payload_kg') is not None:
        pair = doc['training_payload_kg']
        if not isinstance(pair, list) or len(pair) != 2:
            raise bad('training_payload_kg', 'must be [lightest, heaviest] payload measured '
                      f'(kg), got {pair!r}')
        lo, hi = (_finite(x, 'training_payload_kg', bad) for x in pair)
        if not 0.0 <= lo <= hi:
            raise bad('training_payload_kg', f'must be 0 <= lightest <= heaviest (kg), got '
                      f'{pair!r}')
    if doc.get('training_configurations') is not None:
        conf = doc['training_configurations']
        joints = conf.get('joints') if isinstance(conf, dict) else None
        if not isinstance(joints, list) or not all(isinstance(j, str) for j in joints):
            raise bad('training_configurations', 'must be a mapping with joints (names) '
                      'and q (one row of values per pose)')
        rows = conf.get('q') or []
        _matrix(rows, (len(rows) if isinstance(rows, list) else -1, len(joints)),
                'training_configurations.q', bad)
    effects = doc.get('effects')
    if effects is not None and (not isinstance(effects, list)
                                or not all(isinstance(e, str) for e in effects)):
        raise bad('effects', f'must be a list of effect specs (text), got {effects!r}')
    if doc.get('rms_m') is not None:
        _finite(doc['rms_m'], 'rms_m', bad)
    if 'drift_state' in doc:
        _drift_state(doc['drift_state'], list((doc.get('parameter_covariance') or {})
                                              .get('names') or ()), bad)


def _finite(value: Any, field: str, bad: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value):
        raise bad(field, f'must be a finite number, got {value!r}')
    return float(value)


def _matrix(value: Any, shape: tuple[int, int], field: str, bad: Any) -> np.ndarray:
    rows, cols = shape
    if not isinstance(value, list) or len(value) != rows or not all(
            isinstance(r, list) and len(r) == cols for r in value):
        raise bad(field, f'must be {rows} rows of {cols} numbers')
    for i, row in enumerate(value):
        for j, x in enumerate(row):
            _finite(x, f'{field}[{i}][{j}]', bad)
    return np.array(value, dtype=float).reshape(rows, cols)


def _covariance(matrix: np.ndarray, field: str, bad: Any) -> None:
    """Symmetric to round-off and positive semi-definite, as a KKT solve writes it."""
    diag = np.diag(matrix)
    if np.any(diag < 0):
        raise bad(field, f'has a negative variance on its diagonal (row {int(np.argmin(diag))})')
    scale = np.sqrt(np.outer(diag, diag))
    if not np.all(np.abs(matrix - matrix.T) <= 1e-6 * scale + 1e-300):
        raise bad(field, 'is not symmetric')
    if len(matrix) and np.min(np.linalg.eigvalsh(0.5 * (matrix + matrix.T))) \
            < -1e-9 * max(float(np.max(diag)), 1e-300):
        raise bad(field, 'is not positive semi-definite (a covariance)')


def _drift_state(state: Any, prior_names: list[str], bad: Any) -> None:
    if not isinstance(state, dict):
        raise bad('drift_state', 'must be a mapping (names, values, covariance, '
                  'cross_covariance)')
    names = state.get('names')
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names) \
            or len(set(names)) != len(names):
        raise bad('drift_state.names', 'must be a list of unique parameter names')
    unknown = [n for n in names if n not in prior_names]
    if unknown:
        raise bad('drift_state.names', f'{unknown[:3]} are not in parameter_covariance.names')
    order = [prior_names.index(n) for n in names]
    if order != sorted(order):
        raise bad('drift_state.names', 'are not in the order of parameter_covariance.names '
                  '(the state rows would be paired with the wrong parameters)')
    k = len(names)
    values = state.get('values')
    if not isinstance(values, list) or len(values) != 2 * k:
        raise bad('drift_state.values', f'must be {2 * k} numbers (deviations, then rates)')
    for i, x in enumerate(values):
        _finite(x, f'drift_state.values[{i}]', bad)
    cov = _matrix(state.get('covariance'), (2 * k, 2 * k), 'drift_state.covariance', bad)
    _covariance(cov, 'drift_state.covariance', bad)
    _matrix(state.get('cross_covariance'), (k, 2 * k), 'drift_state.cross_covariance', bad)


def prior_from_calibration(doc: dict, keep_placement: bool = False) -> Prior:
    """Prior from a calibration document (the dict of calibration.yaml): the identified
    parameters' values and ``parameter_covariance``.

    The base and reflector placements are left out unless ``keep_placement``: a tracker
    or mocap frame moved between campaigns would otherwise pull the robot's parameters.

    Raises
    ------
    DataError
        The document lacks ``parameters`` or ``parameter_covariance``, or they disagree.
    """
    try:
        values = {p['name']: float(p['value']) for p in doc['parameters']}
        cov_doc = doc['parameter_covariance']
        names = list(cov_doc['names'])
        matrix = np.array(cov_doc['matrix'], dtype=float)
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f'prior calibration lacks or mangles {exc}: give a calibration.yaml '
                        'written by `kpi-calib identify` (parameters, parameter_covariance)'
                        ) from None
    if matrix.shape != (len(names), len(names)) or any(n not in values for n in names):
        raise DataError('prior calibration: parameter_covariance names and matrix do not '
                        'fit the parameters; give an unedited calibration.yaml')
    # A covariance computed through a KKT solve is symmetric to round-off only (relative
    # to its correlation scale); a larger asymmetry is an edited or damaged file.
    scale = np.sqrt(np.outer(np.abs(np.diag(matrix)), np.abs(np.diag(matrix))))
    if not np.all(np.abs(matrix - matrix.T) <= 1e-6 * scale):
        raise DataError('prior calibration: parameter_covariance is not symmetric; give an '
                        'unedited calibration.yaml')
    matrix = 0.5 * (matrix + matrix.T)
    # A further recording's placement belongs to that campaign's set-up only.
    keep = [i for i, n in enumerate(names) if not n.startswith(RECORDING_PREFIX)
            and (keep_placement or not n.startswith(PLACEMENT_PREFIXES))]
    if not keep:
        raise DataError('prior calibration identified no robot parameter to use as prior')
    kept = [names[i] for i in keep]
    return Prior(tuple(kept), np.array([values[n] for n in kept]),
                 matrix[np.ix_(keep, keep)])


def drift_state_from_dict(section: Any) -> DriftState:
    """The ``drift_state`` section of calibration.yaml; DataError names the field."""
    if not isinstance(section, dict):
        raise DataError('drift_state must be a mapping (names, values, covariance, '
                        'cross_covariance); give an unedited calibration.yaml')
    missing = [k for k in ('names', 'values', 'covariance', 'cross_covariance')
               if k not in section]
    if missing:
        raise DataError(f'drift_state lacks {missing}; give an unedited calibration.yaml')
    names = section['names']
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names) \
            or len(set(names)) != len(names):
        raise DataError('drift_state.names must be a list of unique parameter names')
    try:
        arrays = [np.array(section[k], dtype=float)
                  for k in ('values', 'covariance', 'cross_covariance')]
    except (TypeError, ValueError) as exc:
        raise DataError(f'drift_state: values, covariance and cross_covariance must be '
                        f'numbers ({exc})') from None
    return DriftState(tuple(names), *arrays)

"""learned_residual.yaml: the learned residual stored beside calibration.yaml.

The calibrated URDF cannot carry a correction over joint space, so the Gaussian process
(:mod:`kpi_calib_ros.core.diagnosis.learned_residual`) is stored as plain numbers: its
training joint values and residuals, its kernel's hyperparameters and its output and noise
shapes (it is rebuilt exactly from them, no pickle), with the physical calibration it
corrects (the effects of its model, those ``identification.model: auto`` added included,
parameter values and the covariance of the estimated ones), so a TCP prediction needs this
file and the cell alone. Every field is checked on reading: a damaged or edited file is a
:class:`ConfigError` naming the field.

The covariances are written symmetrised and read with a tolerance relative to their
diagonal (:data:`SYMMETRY_RTOL`), so the file identify writes is always read back. A file
is bounded before it is parsed (:data:`MAX_FILE_BYTES`, :data:`MAX_FILE_ITEMS`) and its
training rows after (:data:`~kpi_calib_ros.core.diagnosis.learned_residual.MAX_TRAINING_ROWS`,
which identify fits at most); the kernel matrix is factored once when it is read, and a
singular one is refused by name.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from kpi_calib_ros.core.diagnosis.learned_residual import (
    MAX_TRAINING_ROWS,
    MAX_VARIANCE_M2,
    LearnedResidual,
    ResidualChoice,
    SingularKernelError,
    checked_shape,
)
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.io.names import LEARNED_RESIDUAL_FILE
from kpi_calib_ros.io.results import write_atomic
from kpi_calib_ros.io.yaml_bounded import dump_yaml, read_yaml_file

FORMAT = 'kpi_calib_ros learned_residual 3'
FIX = 'give a learned_residual.yaml written by kpi-calib identify --learned-residual (unedited)'
# A covariance is symmetric when |C_ij - C_ji| <= SYMMETRY_RTOL * sqrt(C_ii C_jj): the
# arithmetic of identify leaves ~1e-11 of it (the file is written symmetrised).
SYMMETRY_RTOL = 1e-8
# What identify writes at MAX_TRAINING_ROWS: each row's joint values and residual (~30
# bytes and one or two YAML items a number) and two covariances of the k estimated
# parameters (k^2 numbers each). Seven joints and k = 70: 1.1 MB and 46 000 items; ten
# joints and k = 150: 2.3 MB and 91 000 items. Parsing costs per item, and a hostile item
# costs two bytes, so the items bound the time to read a file (about that of the largest
# honest one), the bytes what is read to count them.
MAX_FILE_BYTES = 8 * 2 ** 20
MAX_FILE_ITEMS = 120_000
# The parameter values of the calibration it corrects, as written (exact round trip):
# any larger difference is another calibration.
VALUES_ATOL = 1e-12


@dataclass(frozen=True)
class StoredResidual:
    """A learned residual with the physical calibration it corrects.

    Attributes
    ----------
    residual : LearnedResidual
    names : tuple of str
        Every parameter of the physical model, in vector order.
    values : (n_p,) ndarray
        Their calibrated values.
    estimated : tuple of str
        The identified ones.
    covariance : (k, k) ndarray
        Their covariance with the noise the learned residual leaves
        (:func:`kpi_calib_ros.core.diagnosis.learned_residual.residual_noise_scale`).
    covariance_outside : (k, k) ndarray
        Their covariance when the misfit is the learned field, which applies far from the
        training poses
        (:func:`kpi_calib_ros.core.diagnosis.learned_residual.field_parameter_covariance`).
    effects : tuple of str
        The effect specs of the physical model, in its order: the cell's and those
        ``identification.model: auto`` added.
    """

    residual: LearnedResidual
    names: tuple[str, ...]
    values: np.ndarray
    estimated: tuple[str, ...]
    covariance: np.ndarray
    covariance_outside: np.ndarray
    effects: tuple[str, ...] = ()

    def other_calibration(self, names: Sequence[str], values: np.ndarray) -> str:
        """Why this learned residual does not correct the calibration of parameters
        ``names`` with ``values`` ('' : it does): it was written for another model or
        other parameter values (another robot, or a later identification)."""
        values = np.asarray(values, float).reshape(-1)
        if tuple(names) != self.names:
            return (f'{LEARNED_RESIDUAL_FILE} was written for another calibration than the '
                    f'one in use (its model has {len(self.names)} parameters and effects '
                    f'{list(self.effects)}, the calibration\'s {len(names)}): identify again')
        # Both are the numbers identify wrote (YAML floats read back exactly).
        differ = np.flatnonzero(np.abs(values - self.values) > VALUES_ATOL)
        if len(differ):
            i = int(differ[0])
            return (f'{LEARNED_RESIDUAL_FILE} was written for another calibration than the '
                    f'one in use ({len(differ)} parameter values differ, e.g. {names[i]} '
                    f'{self.values[i]:.6g} against {values[i]:.6g}): identify again')
        return ''

    def check_model(self, model: MeasurementModel, key: str = LEARNED_RESIDUAL_FILE) -> None:
        """ConfigError unless ``model`` has these parameters, in this order, and the
        learned residual's joints (the cell and effects the file was written with)."""
        effects = [e.name for e in model.effects]
        if tuple(model.params.names) != self.names:
            raise ConfigError(key, f'was written for a model with parameters '
                              f'{list(self.names)[:4]}... ({len(self.names)}) and effects '
                              f'{list(self.effects)}, the '
                              f'cell gives {len(model.params.names)} with effects {effects}: '
                              'identify again with this cell')
        if tuple(model.robot.joint_names) != tuple(self.residual.joint_names):
            raise ConfigError(key, f'was learned over the joints '
                              f'{list(self.residual.joint_names)}, the cell\'s chain has '
                              f'{list(model.robot.joint_names)}: identify again with this cell')


def residual_document(choice: ResidualChoice, result: CalibrationResult,
                      covariance: np.ndarray, covariance_outside: np.ndarray,
                      effects: Sequence[str]) -> dict[str, Any]:
    """The learned_residual.yaml document of ``choice`` for calibration ``result``;
    ``covariance`` and ``covariance_outside`` (k, k) of ``result.estimated``, as used with
    the learned residual inside and far from the fitted region; ``effects`` the specs of
    the effects of ``result``'s model, in its order (the cell's and those ``auto`` added)."""
    model = choice.model
    return {
        'format': FORMAT,
        'choice': choice.to_dict(),
        'joint_names': list(model.joint_names),
        'kernel': {'type': '(ConstantKernel * RBF (one length scale per joint) + WhiteKernel)'
                           ' * output_shape',
                   'amplitude_m2': model.amplitude_m2,
                   'length_scales': [float(x) for x in model.length_scales],
                   'noise_m2': model.noise_m2,
                   'output_shape': np.asarray(model.output_shape, float).tolist(),
                   'noise_shape': np.asarray(model.noise_shape, float).tolist()},
        'training': {'q': model.q.tolist(), 'residual_m': model.residual_m.tolist()},
        'physical': {'effects': [str(e) for e in effects],
                     'names': list(result.names),
                     'values': [float(x) for x in result.values],
                     'estimated': list(result.estimated),
                     # Symmetrised: the product that made them leaves ~1e-11 of asymmetry.
                     'covariance': _symmetrised(covariance),
                     'covariance_outside': _symmetrised(covariance_outside)}}


def residual_text(doc: dict[str, Any]) -> str:
    """learned_residual.yaml's text of ``doc``."""
    return dump_yaml(doc)


def write_residual(out_dir: str | Path, doc: dict[str, Any]) -> Path:
    """Write ``doc`` atomically as learned_residual.yaml in ``out_dir``."""
    return write_atomic(Path(out_dir) / LEARNED_RESIDUAL_FILE, residual_text(doc))


def read_residual(path: str | Path, key: str = 'learned_residual') -> StoredResidual:
    """A learned_residual.yaml read back, every field checked, the Gaussian process rebuilt.

    Raises
    ------
    ConfigError
        Missing file or a field of the wrong type, shape or range (named in the message).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(key, f'file {str(path)!r} does not exist; {FIX}')
    doc = read_yaml_file(path, key, FIX, max_bytes=MAX_FILE_BYTES,
                         max_nodes=2 * MAX_FILE_ITEMS + 1, max_items=MAX_FILE_ITEMS)

    def bad(field: str, what: str) -> ConfigError:
        return ConfigError(field, f'in {key} {path}: {what}; {FIX}')

    if not isinstance(doc, dict) or doc.get('format') != FORMAT:
        raise bad('format', f'must be {FORMAT!r} (not a learned residual of this version)')
    joints = _names(doc.get('joint_names'), 'joint_names', bad)
    kernel = doc.get('kernel')
    if not isinstance(kernel, dict):
        raise bad('kernel', 'must be a mapping')
    amplitude = _variance(kernel.get('amplitude_m2'), 'kernel.amplitude_m2', bad)
    noise = _variance(kernel.get('noise_m2'), 'kernel.noise_m2', bad)
    scales = _vector(kernel.get('length_scales'), len(joints), 'kernel.length_scales', bad)
    if np.any(scales <= 0):
        raise bad('kernel.length_scales', 'must be positive')
    shapes = []
    for field in ('output_shape', 'noise_shape'):
        shape = _matrix(kernel.get(field), (3, 3), f'kernel.{field}', bad)
        try:
            shapes.append(checked_shape(shape))
        except ValueError as exc:
            raise bad(f'kernel.{field}', str(exc)) from None
    training = doc.get('training')
    if not isinstance(training, dict) or not isinstance(training.get('q'), list) \
            or not training['q']:
        raise bad('training.q', 'must be a non-empty list of joint-value rows')
    m = len(training['q'])
    if m > MAX_TRAINING_ROWS:
        raise bad('training.q', f'has {m} rows, more than the {MAX_TRAINING_ROWS} a learned '
                  'residual is fitted on')
    q = _matrix(training['q'], (m, len(joints)), 'training.q', bad)
    y = _matrix(training.get('residual_m'), (m, 3), 'training.residual_m', bad)
    physical = doc.get('physical')
    if not isinstance(physical, dict):
        raise bad('physical', 'must be a mapping')
    effects = physical.get('effects')
    if not isinstance(effects, list) or not all(isinstance(e, str) for e in effects):
        raise bad('physical.effects', 'must be a list of effect specs (text; [] for none)')
    names = _names(physical.get('names'), 'physical.names', bad)
    values = _vector(physical.get('values'), len(names), 'physical.values', bad)
    estimated = _names(physical.get('estimated'), 'physical.estimated', bad)
    if not set(estimated) <= set(names):
        raise bad('physical.estimated', 'names a parameter physical.names lacks')
    covs = []
    for field in ('covariance', 'covariance_outside'):
        cov = _matrix(physical.get(field), (len(estimated), len(estimated)),
                      f'physical.{field}', bad)
        if not symmetric(cov):
            raise bad(f'physical.{field}', 'must be symmetric (to a relative '
                      f'{SYMMETRY_RTOL:g} of sqrt(C_ii C_jj)) with a non-negative diagonal')
        covs.append(0.5 * (cov + cov.T))
    try:
        residual = LearnedResidual(joints, q, y, amplitude, scales, noise, *shapes)
    except SingularKernelError as exc:
        raise bad('kernel', f'{exc}: kernel.amplitude_m2, kernel.length_scales and '
                  'kernel.noise_m2 do not make a kernel over training.q that can be '
                  'factored') from None
    return StoredResidual(residual, names, values, estimated, covs[0], covs[1],
                          tuple(effects))


def symmetric(cov: np.ndarray) -> bool:
    """A covariance's diagonal is non-negative and it is symmetric to
    :data:`SYMMETRY_RTOL` of sqrt(C_ii C_jj) (the scale of each entry)."""
    diag = np.diag(cov)
    if np.any(diag < 0):
        return False
    scale = np.sqrt(np.outer(diag, diag))
    return bool(np.all(np.abs(cov - cov.T) <= SYMMETRY_RTOL * scale))


def _symmetrised(cov: np.ndarray) -> list[list[float]]:
    cov = np.asarray(cov, float)
    return (0.5 * (cov + cov.T)).tolist()


def _names(value: Any, field: str, bad: Any) -> tuple[str, ...]:
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        raise bad(field, 'must be a non-empty list of names')
    if len(set(value)) != len(value):
        raise bad(field, 'names one twice')
    return tuple(value)


def _number(value: Any, field: str, bad: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value):
        raise bad(field, f'must be a finite number, got {value!r}')
    return float(value)


def _positive(value: Any, field: str, bad: Any) -> float:
    number = _number(value, field, bad)
    if number <= 0:
        raise bad(field, f'must be positive, got {number!r}')
    return number


def _variance(value: Any, field: str, bad: Any) -> float:
    number = _positive(value, field, bad)
    if number > MAX_VARIANCE_M2:
        raise bad(field, f'must be at most {MAX_VARIANCE_M2:g} m^2 (the bound identify fits '
                  f'it within), got {number!r}')
    return number


def _vector(value: Any, n: int, field: str, bad: Any) -> np.ndarray:
    if not isinstance(value, list) or len(value) != n:
        raise bad(field, f'must be a list of {n} numbers')
    return np.array([_number(v, f'{field}[{i}]', bad) for i, v in enumerate(value)])


def _matrix(value: Any, shape: tuple[int, int], field: str, bad: Any) -> np.ndarray:
    rows, cols = shape
    if not isinstance(value, list) or len(value) != rows or not all(
            isinstance(r, list) and len(r) == cols for r in value):
        raise bad(field, f'must be {rows} rows of {cols} numbers')
    return np.array([[_number(x, f'{field}[{i}][{j}]', bad) for j, x in enumerate(row)]
                     for i, row in enumerate(value)]).reshape(rows, cols)


__all__ = ['FORMAT', 'MAX_FILE_BYTES', 'MAX_FILE_ITEMS', 'SYMMETRY_RTOL', 'StoredResidual',
           'read_residual', 'residual_document', 'residual_text', 'symmetric', 'write_residual']

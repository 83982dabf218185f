"""learned_residual.yaml: the learned residual stored beside calibration.yaml.

The calibrated URDF cannot carry a correction over joint space, so the Gaussian process
(:mod:`kpi_calib_ros.core.diagnosis.learned_residual`) is stored as plain numbers: its
training joint values and residuals, its kernel's hyperparameters and its output and noise
shapes (it is rebuilt exactly from them, no pickle), with the physical calibration it
corrects (the effects of its model, those ``identification.model: auto`` added included,
parameter values and the covariance of the estimated ones), so a TCP prediction needs this
file and the cell alone. Every field is checked on reading: a damaged or edited file is a
:class:`ConfigError` naming the field.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import yaml

from kpi_calib_ros.core.diagnosis.learned_residual import (
    LearnedResidual,
    ResidualChoice,
    checked_shape,
)
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.io.names import LEARNED_RESIDUAL_FILE
from kpi_calib_ros.io.results import write_atomic
from kpi_calib_ros.io.yaml_bounded import read_yaml_file

FORMAT = 'kpi_calib_ros learned_residual 3'
FIX = 'give a learned_residual.yaml written by kpi-calib identify --learned-residual (unedited)'


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
                     'covariance': np.asarray(covariance, float).tolist(),
                     'covariance_outside': np.asarray(covariance_outside, float).tolist()}}


def residual_text(doc: dict[str, Any]) -> str:
    """learned_residual.yaml's text of ``doc``."""
    return yaml.safe_dump(doc, sort_keys=False)


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
    doc = read_yaml_file(path, key, FIX)

    def bad(field: str, what: str) -> ConfigError:
        return ConfigError(field, f'in {key} {path}: {what}; {FIX}')

    if not isinstance(doc, dict) or doc.get('format') != FORMAT:
        raise bad('format', f'must be {FORMAT!r} (not a learned residual of this version)')
    joints = _names(doc.get('joint_names'), 'joint_names', bad)
    kernel = doc.get('kernel')
    if not isinstance(kernel, dict):
        raise bad('kernel', 'must be a mapping')
    amplitude = _positive(kernel.get('amplitude_m2'), 'kernel.amplitude_m2', bad)
    noise = _positive(kernel.get('noise_m2'), 'kernel.noise_m2', bad)
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
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=0.0) or np.any(np.diag(cov) < 0):
            raise bad(f'physical.{field}', 'must be symmetric with a non-negative diagonal')
        covs.append(cov)
    residual = LearnedResidual(joints, q, y, amplitude, scales, noise, *shapes)
    return StoredResidual(residual, names, values, estimated, covs[0], covs[1],
                          tuple(effects))


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


__all__ = ['FORMAT', 'StoredResidual', 'read_residual', 'residual_document', 'residual_text',
           'write_residual']

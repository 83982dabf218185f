"""Model size: which parameters to identify, and the choice by the predicted error.

Levels, each the free parameters of :func:`~kpi_calib_ros.core.estimation.least_squares.identify`
(the identifiable subset is then chosen by QR as always; effect parameters are free at every
level):

* ``registration``  -- ``base.*`` and ``reflector.*``: the nominal robot placed in the
  tracker frame, the reflector found on the tip (9);
* ``joint_offsets`` -- registration and every ``<joint>.offset``;
* ``geometric``     -- every geometric parameter (placements too): the full model.

``auto`` fits every level once and predicts its rms error of new measurements from the
fit itself (:mod:`kpi_calib_ros.core.diagnosis.out_of_sample`, no refits), and picks the smallest
level whose predicted rms is within `PARSIMONY` of the best: a larger model must predict
new measurements measurably better to be chosen. A level that leaves no degrees of freedom
has no figure and is not chosen. K-fold refits are not used for the choice: on a
one-joint-at-a-time campaign a fold holding out one joint's poses leaves parameters
without excitation and judged the model 7x too pessimistically.
:func:`cross_validated_level_rms` (full nonlinear k-fold refits) remains for comparison.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from kpi_calib_ros.core.diagnosis.out_of_sample import METHOD, out_of_sample_error
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.estimation.residuals import validation_rms
from kpi_calib_ros.core.measurement.tracker import MeasurementModel, Measurements
from kpi_calib_ros.core.model.parameters import ParameterSet

__all__ = [
    'LEVELS', 'MODEL_CHOICES', 'PARSIMONY', 'DEFAULT_FOLDS', 'level_free', 'ModelChoice',
    'cross_validated_level_rms', 'choose_model',
]

LEVELS = ('registration', 'joint_offsets', 'geometric')
MODEL_CHOICES = ('auto',) + LEVELS
PARSIMONY = 0.05
DEFAULT_FOLDS = 5


def level_free(params: ParameterSet, level: str, n_geometric: int | None = None) -> list[str]:
    """Free parameter names of ``level``.

    The parameters after the first ``n_geometric`` (effects) are free at every level.

    Parameters
    ----------
    params : ParameterSet
        The model's parameters (geometric first, then effects).
    level : {'registration', 'joint_offsets', 'geometric'}
    n_geometric : int, optional
        Number of geometric parameters (default: every name that is not an effect's is
        recognised by its form).
    """
    if level not in LEVELS:
        raise ValueError(f'model level must be one of {LEVELS}, got {level!r}')
    names = list(params.names)
    n_geo = len(names) if n_geometric is None else n_geometric
    geometric, effects = names[:n_geo], names[n_geo:]

    def wanted(name: str) -> bool:
        if level == 'geometric':
            return True
        if name.startswith(('base.', 'reflector.')):
            return True
        return level == 'joint_offsets' and name.endswith('.offset')
    return [n for n in geometric if wanted(n)] + effects


@dataclass(frozen=True)
class ModelChoice:
    """The chosen level, every level's predicted and cross-validated rms, and why.

    Predicted out-of-sample rms in m (None: not fitted or no degrees of freedom); the
    cross-validated rms where folds keep every identified parameter determined (None: not
    estimable from this design).
    """

    level: str
    requested: str
    predicted_rms_m: dict[str, float | None]
    cv_rms_m: dict[str, float | None]
    folds: int
    reason: str
    method: str = ''
    # Effects ``auto`` added on the training data (core.diagnosis.effect_selection) and its record.
    effects: tuple[str, ...] = ()
    effect_selection: dict | None = None
    held: tuple[str, ...] = ()  # effect shape parameters held at their selected values

    def to_dict(self) -> dict:
        """YAML-ready form: the level chosen, its reason and the rms figures (m) per level."""
        def figures(values: dict[str, float | None]) -> dict[str, float | None]:
            return {k: (None if v is None else float(v)) for k, v in values.items()}
        return {'level': self.level, 'requested': self.requested, 'method': self.method,
                'predicted_rms_m': figures(self.predicted_rms_m), 'folds': self.folds,
                'cv_rms_m': figures(self.cv_rms_m), 'reason': self.reason,
                'effects': list(self.effects), 'held': list(self.held),
                'effect_selection': self.effect_selection}


Fit = Callable[[Measurements, list[str]], CalibrationResult]


def cross_validated_level_rms(model: MeasurementModel, data: Measurements, fit: Fit,
                              free: list[str], folds: int = DEFAULT_FOLDS,
                              seed: int = 0) -> float | None:
    """k-fold CV rms (m) of refitting ``free`` on the training folds.

    The rms of predicting the held-out measurements; None when a fold cannot be fitted.
    """
    q, eta = np.atleast_2d(data.q), np.atleast_2d(data.eta)
    # A pose's rows (one per reflector) share q: a fold holds out whole poses, else the
    # other reflectors of a held-out pose would be in the training set.
    _, pose = np.unique(q, axis=0, return_inverse=True)
    pose = pose.ravel()
    n = int(pose.max()) + 1 if len(pose) else 0
    folds = min(folds, n)
    if folds < 2:
        return None
    pose_fold = np.empty(n, dtype=int)
    pose_fold[np.random.default_rng(seed).permutation(n)] = np.arange(n) % folds
    ids = pose_fold[pose]
    held = np.empty_like(eta)
    for k in range(folds):
        test = ids == k
        train = data.subset(~test)
        try:
            result = fit(train, free)
        except (DataError, np.linalg.LinAlgError):
            return None
        if not np.all(np.isfinite(result.values)):
            return None
        held[test] = eta[test] - model.predict(
            result.values, q[test], None if data.tau is None else data.tau[test],
            None if data.reflector is None else data.reflector[test],
            None if data.rotation is None else data.rotation[test],
            data.subset(test).covariates)
    return float(np.sqrt(np.mean(np.sum(held ** 2, axis=1))))


def choose_model(model: MeasurementModel, data: Measurements, fit: Fit, requested: str,
                 n_geometric: int | None = None, folds: int = DEFAULT_FOLDS,
                 seed: int = 0, prior: Prior | None = None) -> ModelChoice:
    """Every level's predicted out-of-sample rms and the level to use.

    Each level is fitted once on all of ``data``; its predicted rms error of new
    measurements at the measured configurations
    (:func:`kpi_calib_ros.core.diagnosis.out_of_sample.out_of_sample_error`, domain
    ``like_measured``: σ̂² (3 + tr(J C Jᵀ)/σ²) with σ̂² from χ²/dof, an FPE-like criterion
    that charges a larger model its extra parameters and a smaller one its misfit) decides.
    ``requested`` is a level (used as given; the figures are still reported) or
    ``'auto'`` (the smallest level within `PARSIMONY` of the best). Beside it, the
    cross-validated rms over ``folds`` folds of poses
    (:func:`kpi_calib_ros.core.estimation.residuals.validation_rms`, folds that keep every
    identified parameter determined, else None: not estimable from this design) is
    reported, not used.

    Raises
    ------
    DataError
        ``auto`` and no level leaves degrees of freedom (too few measurements).
    """
    if requested not in MODEL_CHOICES:
        raise ValueError(f'model must be one of {MODEL_CHOICES}, got {requested!r}')
    predicted: dict[str, float | None] = {}
    cv: dict[str, float | None] = {}
    n_poses = len(np.unique(np.atleast_2d(data.q), axis=0))
    used = min(folds, n_poses)
    unconverged: dict[str, str] = {}  # level: why its fit stopped
    for level in LEVELS:
        free = level_free(model.params, level, n_geometric)
        predicted[level] = cv[level] = None
        try:
            result = fit(data, free)
        except (DataError, np.linalg.LinAlgError):
            continue
        if not np.all(np.isfinite(result.values)) or result.dof <= 0:
            continue
        if not result.converged:
            unconverged[level] = result.message
        oos = out_of_sample_error(model, data, result, free, prior, seed,
                                  domains=('like_measured',)).domains['like_measured']
        predicted[level] = oos.rms_m if oos.estimable else None
        if used >= 2:
            value = validation_rms(model, data, result, used, seed)
            cv[level] = value if np.isfinite(value) else None
    if requested != 'auto':
        return ModelChoice(requested, requested, predicted, cv, used,
                           f'{requested} as configured', METHOD)
    # A level whose fit did not converge is judged by its last iterate, not its minimum:
    # it is neither chosen nor the best the others are measured against.
    finite = {k: v for k, v in predicted.items() if v is not None and k not in unconverged}
    compared_unconverged = not finite
    if compared_unconverged:  # none converged: compare them, and say so
        finite = {k: v for k, v in predicted.items() if v is not None}
    if not finite:
        raise DataError(f'{len(data)} measurements are too few to fit even the registration '
                        'model with degrees of freedom left; measure more poses')
    best = min(finite.values())
    level = next(k for k in LEVELS if k in finite and finite[k] <= (1 + PARSIMONY) * best)
    figures = ', '.join(f'{k} {"n/a" if v is None else f"{v * 1e6:.1f} µm"}'
                        for k, v in predicted.items())
    larger = [k for k in LEVELS[LEVELS.index(level) + 1:]]
    why = (f'smallest level within {PARSIMONY:.0%} of the best predicted out-of-sample rms '
           f'at the measured configurations ({figures})')
    if larger:
        unfit = [k for k in larger if predicted[k] is None]
        worse = [k for k in larger if predicted[k] is not None and k in finite]
        if unfit:
            why += f'; {", ".join(unfit)} leaves no degrees of freedom (too few poses)'
        if worse:
            why += f'; {", ".join(worse)} predicts new measurements no better'
    if compared_unconverged and unconverged:
        why = ('WARNING: no level\'s fit converged; compared by their last iterates, not '
               'their minima (raise identification.max_iterations / --max-iterations): '
               + why)
    else:
        for k, message in unconverged.items():
            why += f'; {k} not compared: its fit did not converge ({message})'
    return ModelChoice(level, 'auto', predicted, cv, used, why, METHOD)

"""Model size: which parameters to identify, and the choice by cross-validation.

Levels, each the free parameters of :func:`~kpi_calib_ros.core.estimation.identify` (the
identifiable subset is then chosen by QR as always; effect parameters are free at every
level):

* ``registration``  -- ``base.*`` and ``reflector.*``: the nominal robot placed in the
  tracker frame, the reflector found on the tip (9);
* ``joint_offsets`` -- registration and every ``<joint>.offset``;
* ``geometric``     -- every geometric parameter (placements too): the full model.

``auto`` fits every level on k-1 folds of the measurements and predicts the held-out fold
(full nonlinear refits, seeded; folds over poses: the rows of one pose, e.g. several
reflectors measured at the same joint values, are held out together), and picks the smallest level
whose cross-validated rms is within `PARSIMONY` of the best: a larger model must predict
new poses measurably better to be chosen. A level that cannot be fitted on some fold
(fewer equations than parameters) has no CV rms and is not chosen.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation import CalibrationResult
from kpi_calib_ros.core.measurement import MeasurementModel, Measurements
from kpi_calib_ros.core.parameters import ParameterSet

LEVELS = ('registration', 'joint_offsets', 'geometric')
MODEL_CHOICES = ('auto',) + LEVELS
PARSIMONY = 0.05
DEFAULT_FOLDS = 5


def level_free(params: ParameterSet, level: str, n_geometric: int | None = None) -> list[str]:
    """Free parameter names of ``level``; the parameters after the first ``n_geometric``
    (effects) are free at every level.

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
    """The chosen level, every level's cross-validated rms (m; None: not fitted) and why."""

    level: str
    requested: str
    cv_rms_m: dict[str, float | None]
    folds: int
    reason: str

    def to_dict(self) -> dict:
        return {'level': self.level, 'requested': self.requested, 'folds': self.folds,
                'cv_rms_m': {k: (None if v is None else float(v))
                             for k, v in self.cv_rms_m.items()},
                'reason': self.reason}


Fit = Callable[[Measurements, list[str]], CalibrationResult]


def cross_validated_level_rms(model: MeasurementModel, data: Measurements, fit: Fit,
                              free: list[str], folds: int = DEFAULT_FOLDS,
                              seed: int = 0) -> float | None:
    """k-fold CV rms (m) of refitting ``free`` on the training folds and predicting the
    held-out measurements; None when a fold cannot be fitted."""
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
            None if data.rotation is None else data.rotation[test])
    return float(np.sqrt(np.mean(np.sum(held ** 2, axis=1))))


def choose_model(model: MeasurementModel, data: Measurements, fit: Fit, requested: str,
                 n_geometric: int | None = None, folds: int = DEFAULT_FOLDS,
                 seed: int = 0) -> ModelChoice:
    """Every level's CV rms and the level to use.

    ``requested`` is a level (used as given; the CV rms are still reported) or ``'auto'``
    (the smallest level within `PARSIMONY` of the best CV rms).

    Raises
    ------
    DataError
        ``auto`` and no level can be cross-validated (too few measurements).
    """
    if requested not in MODEL_CHOICES:
        raise ValueError(f'model must be one of {MODEL_CHOICES}, got {requested!r}')
    cv = {level: cross_validated_level_rms(model, data, fit,
                                           level_free(model.params, level, n_geometric),
                                           folds, seed)
          for level in LEVELS}
    used = min(folds, len(np.unique(np.atleast_2d(data.q), axis=0)))
    if requested != 'auto':
        return ModelChoice(requested, requested, cv, used, f'{requested} as configured')
    finite = {k: v for k, v in cv.items() if v is not None}
    if not finite:
        raise DataError(f'{len(data)} measurements are too few to cross-validate even the '
                        'registration model; measure more poses')
    best = min(finite.values())
    level = next(k for k in LEVELS if k in finite and finite[k] <= (1 + PARSIMONY) * best)
    figures = ', '.join(f'{k} {"n/a" if v is None else f"{v * 1e6:.1f} µm"}'
                        for k, v in cv.items())
    larger = [k for k in LEVELS[LEVELS.index(level) + 1:]]
    why = (f'smallest level within {PARSIMONY:.0%} of the best cross-validated rms '
           f'({used}-fold over poses: {figures})')
    if larger:
        unfit = [k for k in larger if cv[k] is None]
        worse = [k for k in larger if cv[k] is not None]
        if unfit:
            why += f'; {", ".join(unfit)} cannot be fitted on the folds (too few poses)'
        if worse:
            why += f'; {", ".join(worse)} predicts held-out poses no better'
    return ModelChoice(level, 'auto', cv, used, why)

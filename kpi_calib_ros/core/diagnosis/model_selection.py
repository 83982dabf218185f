"""Model size: which parameters to identify, and the choice by a test of the held-out gain.

Levels, each the free parameters of :func:`~kpi_calib_ros.core.estimation.least_squares.identify`
(the identifiable subset is then chosen by QR as always; effect parameters are free at every
level):

* ``registration``  -- ``base.*`` and ``reflector.*``: the nominal robot placed in the
  tracker frame, the reflector found on the tip (9);
* ``joint_offsets`` -- registration and every ``<joint>.offset``;
* ``geometric``     -- every geometric parameter (placements too): the full model.

``auto`` fits every level once and, from the smallest up, takes a larger level only when
it lowers the misfit of the measured poses beyond what its extra parameters and the noise
explain (:func:`level_test`: the nested F-test of the two fits, one-sided at
:data:`HELD_OUT_ALPHA`, Bonferroni over the larger levels compared): the error at the
measured configurations, where a robot that works at its measured poses is judged. Beside
it, each level's predicted rms error of new measurements from the fit itself
(:mod:`kpi_calib_ros.core.diagnosis.out_of_sample`) and its cross-validated rms over folds
that hold out whole regions of joint space
(:func:`~kpi_calib_ros.core.estimation.cross_validation.region_validation`, k-means blocks
in normalised joint space that keep every identified parameter determined) are reported.
The region figure decides the *effects*
(:mod:`~kpi_calib_ros.core.diagnosis.effect_selection`, :func:`holds_elsewhere`), not the
level: on the real TIAGo's 37 postures it put the registration before the geometric level,
which predicts the held-out days far better. :func:`cross_validated_level_rms`
(full nonlinear k-fold refits) remains for comparison.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.special
import scipy.stats

from kpi_calib_ros.core.diagnosis.nominal_comparison import (
    TIE_M,
    NominalComparison,
    against_nominal,
)
from kpi_calib_ros.core.diagnosis.out_of_sample import METHOD, out_of_sample_error
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.cross_validation import (
    RegionValidation,
    region_validation,
    validation_folds,
    validation_rms,
)
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.precision import (
    fit_prior,
)
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.model.parameters import ParameterSet

__all__ = [
    'LEVELS', 'MODEL_CHOICES', 'PARSIMONY', 'DEFAULT_FOLDS', 'HELD_OUT_ALPHA', 'FOLD_ALPHA',
    'level_free', 'ModelChoice', 'cross_validated_level_rms', 'choose_model',
    'holds_elsewhere', 'HeldOutGain', 'held_out_gain', 'level_test', 'TIE_M',
    'NominalComparison', 'against_nominal',
]

LEVELS = ('registration', 'joint_offsets', 'geometric')
MODEL_CHOICES = ('auto',) + LEVELS
# The screen ranks a general effect before the named ones only when it predicts held-out
# poses this much better (core.diagnosis.screening): a ranking, not a choice.
PARSIMONY = 0.05
DEFAULT_FOLDS = 5
# The largest z a level's F-test states (a p-value of 1e-308, the smallest double's order).
Z_MAX = 37.5
# An effect is added only when it lowers the held-out error over regions of joint space by
# more than the held-out noise can (held_out_gain: a one-sided test at HELD_OUT_ALPHA,
# Bonferroni over the trials compared for one choice), and is worse in no held-out fold
# beyond what the noise can do there (family-wise FOLD_ALPHA over the folds). The false
# alarms of auto are held by the effect screen's family-wise F-test first: an effect is
# tried only when it passes there.
HELD_OUT_ALPHA = 0.01
FOLD_ALPHA = 0.05



@dataclass(frozen=True)
class HeldOutGain:
    """How much a richer model lowers the held-out error, in units of what noise can do.

    Two models judged on the same held-out folds, e_b and e_a the held-out weighted
    residuals of the model before and after (unit noise variance per row), d = e_b − e_a
    the change of the held-out predictions. The gain of a fold is
    Δ = Σ e_b² − Σ e_a² = Σ (2 e_b·d − d²). Given the training rows, d is fixed and the
    held-out noise ε enters Δ as 2 ε·d, with standard deviation 2 s ‖d‖ (s the noise
    scale): z = Δ / (2 s ‖d‖). Where the richer model only fits noise, the rest of Δ is the
    extra variance of its prediction, negative on average, so z exceeds the normal
    quantile no more often than the normal law says; the screen chose the effect for fitting
    this very noise, so after its choice z passes more often (a shoulder_pan scale fitted to
    the noise of a clean UR10 came out at 2.80): the false-alarm level of ``auto`` is the
    screen's family-wise α, which an effect must pass before it is tried, and this test asks
    of it a gain where no pose was measured. ``z``: over the region blocks pooled
    (every pose held out once); ``fold_z``: each held-out fold (region blocks, then each
    joint's range ends), NaN where a fold is not compared; ``scale``: s, the rms of the
    richer model's held-out weighted residuals over the region blocks, at least 1 (a
    misfit the richer model leaves counts as noise).
    """

    z: float
    fold_z: tuple[float, ...]
    scale: float

    @staticmethod
    def threshold(tests: int = 1) -> float:
        """Return the pooled z above which the gain is beyond noise.

        One-sided, Bonferroni over the ``tests`` compared for one choice.
        """
        return float(scipy.stats.norm.isf(HELD_OUT_ALPHA / max(tests, 1)))

    def fold_threshold(self) -> float:
        """Return the fold z below which a fold is worse beyond noise (family-wise)."""
        return float(scipy.stats.norm.isf(FOLD_ALPHA / max(self.compared, 1)))

    @property
    def compared(self) -> int:
        """Folds compared."""
        return int(np.sum(np.isfinite(self.fold_z)))

    @property
    def worse(self) -> int:
        """Folds the richer model predicts worse beyond noise."""
        limit = -self.fold_threshold()
        return int(sum(z < limit for z in self.fold_z if np.isfinite(z)))

    def holds(self, tests: int = 1) -> bool:
        """Whether the gain over held-out regions is beyond noise and no fold is worse."""
        return bool(np.isfinite(self.z) and self.z > self.threshold(tests)
                    and not self.worse)

    def to_dict(self, tests: int = 1) -> dict:
        """YAML-ready figures (``tests``: the Bonferroni count of the pooled test)."""
        return {'z': float(self.z) if np.isfinite(self.z) else None,
                'z_needed': self.threshold(tests), 'tests': int(tests),
                'fold_z': [float(z) if np.isfinite(z) else None for z in self.fold_z],
                'fold_z_worse_below': -self.fold_threshold(),
                'folds_worse': self.worse, 'folds_compared': self.compared,
                'noise_scale': float(self.scale), 'holds': self.holds(tests)}


def held_out_gain(new: RegionValidation, old: RegionValidation) -> HeldOutGain:
    """Return the :class:`HeldOutGain` of ``new`` over ``old``, judged on the same folds.

    NaN z (never holds) when the region blocks are not estimable for either model.
    """
    a_res, b_res = new.held_out_residuals, old.held_out_residuals
    if len(a_res) != len(b_res):
        raise ValueError(f'held-out folds must pair: {len(a_res)} after, {len(b_res)} before')
    blocks = new.blocks
    pairs = [(a, b) if a is not None and b is not None and len(a) == len(b) else None
             for a, b in zip(a_res, b_res)]
    region = pairs[:blocks]
    if not blocks or any(p is None for p in region):
        return HeldOutGain(float('nan'), tuple(float('nan') for _ in pairs), 1.0)
    rows = np.concatenate([a for a, _ in region])  # type: ignore[misc]
    scale = max(1.0, float(np.sqrt(np.mean(rows ** 2)))) if len(rows) else 1.0

    def z(members: list[tuple[np.ndarray, np.ndarray]]) -> float:
        gain = sum(float(b @ b - a @ a) for a, b in members)
        spread = np.sqrt(sum(float((b - a) @ (b - a)) for a, b in members))
        if spread == 0.0:
            return 0.0
        return float(gain / (2.0 * scale * spread))
    return HeldOutGain(z(region),  # type: ignore[arg-type]
                       tuple(float('nan') if p is None else z([p]) for p in pairs), scale)


def holds_elsewhere(new: RegionValidation, old: RegionValidation, tests: int = 1) -> bool:
    """Return whether ``new`` predicts held-out regions better than ``old`` beyond noise.

    :func:`held_out_gain` on the same folds: the pooled gain over the region blocks above
    the normal quantile at :data:`HELD_OUT_ALPHA` (Bonferroni over the ``tests`` compared
    for one choice),
    and worse beyond noise in NO held-out fold (each region block, each joint's range end,
    family-wise :data:`FOLD_ALPHA`): one fold that a new effect fits cannot carry it while it
    hurts another. False when the region blocks are not estimable.
    """
    return held_out_gain(new, old).holds(tests)


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
        if name.startswith(('base.', 'reflector.', 'recording.')):
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
    # Cross-validated rms (m) of folds that hold out whole regions of joint space, per
    # level (None: not estimable), and the number of regions.
    other_region_rms_m: dict[str, float | None] = dataclasses.field(default_factory=dict)
    region_blocks: int = 0
    # Levels whose fit did not converge (left out of the comparison).
    unconverged: tuple[str, ...] = ()
    # z of each larger level's F-test (level_test; None: not computed) over the level taken
    # before it was compared (a level whose fit did not converge: over the level chosen),
    # and the z a larger level needed.
    level_z: dict[str, float | None] = dataclasses.field(default_factory=dict)
    z_needed: float | None = None

    @property
    def unsettled_larger(self) -> tuple[str, ...]:
        """Larger levels left out, whose fit did not converge, that fit better beyond noise.

        Their last iterate lowers the misfit of the measured poses beyond what its extra
        parameters explain (:func:`level_test` above :attr:`z_needed`): the chosen level's
        misfit holds geometry these poses need and cannot settle, and an effect fitted on
        it takes that geometry up.
        """
        if self.level not in LEVELS or self.z_needed is None:
            return ()
        return tuple(k for k in LEVELS[LEVELS.index(self.level) + 1:]
                     if k in self.unconverged and (z := self.level_z.get(k)) is not None
                     and z > self.z_needed)

    def to_dict(self) -> dict:
        """YAML-ready form: the level chosen, its reason and the rms figures (m) per level."""
        def figures(values: dict[str, float | None]) -> dict[str, float | None]:
            return {k: (None if v is None else float(v)) for k, v in values.items()}
        return {'level': self.level, 'requested': self.requested, 'method': self.method,
                'predicted_rms_m': figures(self.predicted_rms_m), 'folds': self.folds,
                'cv_rms_m': figures(self.cv_rms_m),
                'other_region_rms_m': figures(self.other_region_rms_m),
                'region_blocks': self.region_blocks, 'reason': self.reason,
                'level_z': figures(self.level_z), 'z_needed': self.z_needed,
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
                 seed: int = 0, prior: Prior | None = None,
                 balanced: bool = False) -> ModelChoice:
    """Every level's out-of-sample figures and the level to use.

    Each level is fitted once on all of ``data``. ``requested`` is a level (used as given;
    the figures are still reported) or ``'auto'``: from the smallest level up, a larger
    level is taken when it lowers the misfit of the measured poses beyond noise
    (:func:`level_test`, z above :meth:`HeldOutGain.threshold`, Bonferroni over the larger
    levels compared), a level whose fit did not converge left out while another converged.
    The predicted rms error of new measurements at the measured configurations
    (:func:`kpi_calib_ros.core.diagnosis.out_of_sample.out_of_sample_error`,
    ``like_measured``) is reported. Every level's cross-validated rms over
    held-out regions of joint space (on the regions of the largest fitted level, which keep
    the rank of the smaller ones) is reported beside it, not used: it decides the effects
    (:func:`holds_elsewhere`). Beside them, the cross-validated rms over ``folds`` folds of
    poses
    (:func:`kpi_calib_ros.core.estimation.cross_validation.validation_rms`) is reported. ``prior``:
    the prior ``fit`` uses (``balanced``: a tolerance prior ``fit`` balances against the
    noise, :func:`~kpi_calib_ros.core.estimation.precision.fit_prior`); every fold's refit
    keeps it.

    Raises
    ------
    DataError
        ``auto`` and no level leaves degrees of freedom (too few measurements).
    """
    if requested not in MODEL_CHOICES:
        raise ValueError(f'model must be one of {MODEL_CHOICES}, got {requested!r}')
    predicted: dict[str, float | None] = {}
    cv: dict[str, float | None] = {}
    region: dict[str, RegionValidation] = {}
    n_poses = len(np.unique(np.atleast_2d(data.q), axis=0))
    used = min(folds, n_poses)
    unconverged: dict[str, str] = {}  # level: why its fit stopped
    fits: dict[str, CalibrationResult] = {}
    same_folds = None
    for level in reversed(LEVELS):  # the largest first: its region folds serve every level
        free = level_free(model.params, level, n_geometric)
        predicted[level] = cv[level] = None
        try:
            result = fit(data, free)
        except (DataError, np.linalg.LinAlgError):
            continue
        if not np.all(np.isfinite(result.values)) or result.dof <= 0:
            continue
        fits[level] = result
        if not result.converged:
            unconverged[level] = result.message
        used_prior = fit_prior(prior, result, balanced)
        oos = out_of_sample_error(model, data, result, free, prior, seed,
                                  domains=('like_measured',)).domains['like_measured']
        predicted[level] = oos.rms_m if oos.estimable else None
        if used >= 2:
            value = validation_rms(model, data, result, used, seed, used_prior)
            cv[level] = value if np.isfinite(value) else None
        if same_folds is None or same_folds[1] is None:
            same_folds = validation_folds(model, data, result, used_prior, seed=seed)
        region[level] = region_validation(model, data, result, used_prior, seed=seed,
                                          pose_folds=same_folds)
    predicted = {k: predicted[k] for k in LEVELS}
    cv = {k: cv[k] for k in LEVELS}
    other = {k: (float(region[k].other_region_m) if k in region
                 and np.isfinite(region[k].other_region_m) else None) for k in LEVELS}
    blocks = max((v.blocks for v in region.values()), default=0)
    if requested != 'auto':
        return ModelChoice(requested, requested, predicted, cv, used,
                           f'{requested} as configured', METHOD,
                           other_region_rms_m=other, region_blocks=blocks,
                           unconverged=tuple(unconverged))
    # A level whose fit did not converge is judged by its last iterate, not its minimum:
    # it is neither chosen nor the level the others are measured against.
    finite = {k: v for k, v in predicted.items() if v is not None and k not in unconverged}
    compared_unconverged = not finite
    if compared_unconverged:  # none converged: compare them, and say so
        finite = {k: v for k, v in predicted.items() if v is not None}
    if not finite:
        raise DataError(f'{len(data)} measurements are too few to fit even the registration '
                        'model with degrees of freedom left; measure more poses')
    # From the smallest level up, a larger level is taken when it lowers the misfit of the
    # measured poses beyond noise (not by a margin on the predicted rms: a 5 % step took a
    # larger level whose gain was chance on few poses and left one whose gain was certain
    # on many). Not by held-out poses: five folds of poses put the real TIAGo's
    # registration (4.49 mm) before its geometric level (4.72 mm), and the region blocks
    # likewise (4.9 against 6.2 mm), while the geometric level predicts the held-out days,
    # which repeat the measured postures, far better. The region figures are reported.
    order = [k for k in LEVELS if k in finite]
    needed = HeldOutGain.threshold(len(order) - 1)
    level = order[0]
    level_z: dict[str, float | None] = {}
    for k in order[1:]:
        z = level_test(fits[level], fits[k])
        level_z[k] = z if np.isfinite(z) else None
        if z > needed:
            level = k
    for k in LEVELS[LEVELS.index(level) + 1:]:  # left out: judged against the level taken
        if k in unconverged and k in fits and k not in level_z:
            z = level_test(fits[level], fits[k])
            level_z[k] = z if np.isfinite(z) else None
    pfig = ', '.join(f'{k} {"n/a" if v is None else f"{v * 1e6:.1f} µm"}'
                     for k, v in predicted.items())
    figures = ', '.join(f'{k} {"n/a" if v is None else f"{v * 1e6:.1f} µm"}'
                        for k, v in other.items())
    zfig = ', '.join(f'{k} {"n/a" if v is None else f"{v:.1f}"}' for k, v in level_z.items())
    why = (f'the largest level that lowers the misfit of the measured poses beyond noise '
           f'(F-test z of each larger level over the smaller taken: {zfig or "none compared"}; '
           f'needed > {needed:.2f}); predicted out-of-sample rms '
           f'at the measured configurations: {pfig}; cross-validated rms over held-out '
           f'regions of joint space ({blocks} regions): {figures}')
    worse = [k for k in LEVELS[LEVELS.index(level) + 1:] if k in finite]
    if worse:
        why += f'; {", ".join(worse)} fits the measured poses no better beyond noise'
    larger = [k for k in LEVELS[LEVELS.index(level) + 1:]]
    unfit = [k for k in larger if predicted[k] is None]
    if unfit:
        why += f'; {", ".join(unfit)} leaves no degrees of freedom (too few poses)'
    if compared_unconverged and unconverged:
        why = ('WARNING: no level\'s fit converged; compared by their last iterates, not '
               'their minima (raise identification.max_iterations / --max-iterations): '
               + why)
    else:
        for k, message in unconverged.items():
            why += f'; {k} not compared: its fit did not converge ({message})'
    return ModelChoice(level, 'auto', predicted, cv, used, why, METHOD,
                       other_region_rms_m=other, region_blocks=blocks,
                       unconverged=tuple(unconverged), level_z=level_z, z_needed=needed)


def level_test(old: CalibrationResult, new: CalibrationResult) -> float:
    """Return z of ``new`` (a larger level) lowering ``old``'s misfit beyond noise.

    The nested F-test of the two fits on the same rows, F = (Δχ² / Δdof) / (χ²_new / dof_new)
    (the misfit ``new`` leaves is the noise scale), as the normal quantile of its p-value,
    at most :data:`Z_MAX` (a p-value below the smallest double). NaN when ``new`` frees
    nothing more or leaves no degrees of freedom.
    """
    if old.dof <= new.dof or new.dof <= 0 or new.chi2 <= 0:
        return float('nan')
    f = ((old.chi2 - new.chi2) / (old.dof - new.dof)) / (new.chi2 / new.dof)
    log_p = float(scipy.stats.f.logsf(f, old.dof - new.dof, new.dof))
    return Z_MAX if log_p == -np.inf else min(Z_MAX, float(-scipy.special.ndtri_exp(log_p)))

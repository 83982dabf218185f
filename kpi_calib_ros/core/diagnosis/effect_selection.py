"""Which physical effects ``auto`` adds to the chosen model level, from the training data.

Forward selection, one effect per round, by the criterion that chose the level
(:func:`kpi_calib_ros.core.diagnosis.model_selection.choose_model`): the predicted out-of-sample rms
at the measured configurations (:mod:`kpi_calib_ros.core.diagnosis.out_of_sample`), which charges
every added parameter its variance.

Each round:

1. the diagnosis screens every library effect × joint and the general effects (link bending,
   the periodic joint error at each joint's periodogram peak, the search counted in its
   p-value) against the current fit
   (:func:`kpi_calib_ros.core.diagnosis.screening.screen_effects`: distinguishable from the
   geometry, F-test Bonferroni-corrected over the candidates at the family-wise level
   ``alpha``, candidates with the same signature merged); only candidates that are
   **significant and physically plausible**
   (:func:`kpi_calib_ros.core.effects.registry.implausible`) go on;
2. the best :data:`TRIALS` of them (by their cross-validated rms) are fitted with the full
   nonlinear identification at the chosen level; a fit that does not converge, leaves an
   effect parameter unidentified or fits an implausible value is refused;
3. each trial and the current model are cross-validated on the same folds that hold out
   whole regions of joint space and each joint's range ends
   (:func:`~kpi_calib_ros.core.estimation.cross_validation.region_validation`, the fit's prior kept
   in every refit); a trial passes when it lowers the held-out error over the regions by
   more than the held-out noise can (a one-sided test at
   :data:`~kpi_calib_ros.core.diagnosis.model_selection.HELD_OUT_ALPHA`, Bonferroni over the
   round's trials) and is worse beyond noise in no held-out fold
   (:func:`~kpi_calib_ros.core.diagnosis.model_selection.held_out_gain`), and of those the
   one with the lowest predicted out-of-sample rms is added; none passing, selection stops.
   An effect that lowers the error where the poses were measured and raises it elsewhere
   (a scale error only a grid's corner needs, an aliased second frequency) is not added.

On data the geometric model explains, step 1 passes a candidate with probability at most
``alpha`` per round, and step 3 then still asks for a better prediction of other regions
beyond noise (bench/auto_false_alarms.py measures both).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Mapping

import numpy as np

from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.diagnosis.model_selection import (
    HeldOutGain,
    held_out_gain,
    level_free,
)
from kpi_calib_ros.core.diagnosis.out_of_sample import out_of_sample_error
from kpi_calib_ros.core.diagnosis.screening import default_candidates, screen_effects
from kpi_calib_ros.core.diagnosis.verdict import beyond_bound_candidates, bound_text
from kpi_calib_ros.core.effects.registry import BoundEffect, implausible
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.cross_validation import (
    RegionValidation,
    fold_kinds,
    region_validation,
    validation_folds,
)
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.plausibility import Tolerances, Violation, gate
from kpi_calib_ros.core.estimation.precision import fit_prior
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import row_torques

__all__ = [
    'MAX_EFFECTS', 'TRIALS', 'EffectTrial', 'EffectChoice', 'choose_effects', 'effect_start',
]

MAX_EFFECTS = 3  # rounds: more effects than this on one campaign is a model to rethink
TRIALS = 3       # significant, plausible candidates refitted per round

# fit_for(model)(data, free) -> the identification of ``model`` with the cell's settings
# (and a start vector p0 of ``model``'s parameters)
FitFor = Callable[[MeasurementModel], Callable[..., CalibrationResult]]


@dataclass(frozen=True)
class EffectTrial:
    """One candidate effect refitted in a round.

    Its fitted values, the predicted out-of-sample rms (m, None when refused before) and the
    outcome.
    """

    spec: str
    round: int
    values: dict[str, float]
    std: dict[str, float]
    predicted_rms_m: float | None
    added: bool
    reason: str
    # Shape parameters held at their screened value, and why the free fit was refused.
    held: tuple[str, ...] = ()
    previous: str = ''
    # Cross-validated rms of the model before and with the trial, on the same folds
    # (in-region and over held-out regions of joint space).
    region_before: RegionValidation | None = None
    region_after: RegionValidation | None = None
    # Per round, the significant candidates that fit better than the best plausible one
    # but beyond their physical bound, with the cell key that states a softer arm.
    beyond_bounds: tuple[str, ...] = ()
    # Its gain over held-out regions and folds in noise units, and the trials compared in
    # its round (the Bonferroni count of the pooled test).
    gain: HeldOutGain | None = None
    tests: int = 1

    def to_dict(self) -> dict:
        """YAML-ready form of the trial (values and std in SI units)."""
        return {'spec': self.spec, 'round': self.round, 'values': dict(self.values),
                'std': dict(self.std),
                'predicted_rms_m': None if self.predicted_rms_m is None
                else float(self.predicted_rms_m),
                'cross_validated_before': None if self.region_before is None
                else self.region_before.to_dict(),
                'cross_validated_after': None if self.region_after is None
                else self.region_after.to_dict(),
                'held_out_gain': None if self.gain is None
                else self.gain.to_dict(self.tests),
                'added': self.added, 'reason': self.reason, 'held': list(self.held),
                'free_fit_refused': self.previous or None}


@dataclass(frozen=True)
class EffectChoice:
    """The effects added (in order), the model with them, and the predicted rms before and after.

    The predicted out-of-sample rms is in m; also every trial and why selection stopped.
    """

    effects: tuple[BoundEffect, ...]
    model: MeasurementModel
    values: dict[str, float]  # the added effects' fitted values (a start for the final fit)
    predicted_before_m: float | None
    predicted_after_m: float | None
    trials: tuple[EffectTrial, ...]
    reason: str
    held: tuple[str, ...] = ()  # shape parameters held at their screened values
    # The cross-validated rms (in-region, other regions) before the first effect and of the
    # model chosen, each on the folds of its own comparison.
    region_before: RegionValidation | None = None
    region_after: RegionValidation | None = None
    # Per round, the significant candidates that fit better than the best plausible one
    # but beyond their physical bound, with the cell key that states a softer arm.
    beyond_bounds: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        """YAML-ready form: the effects added, held, the trials and the predicted rms (m)."""
        return {'added': [e.name for e in self.effects], 'held': list(self.held),
                'predicted_rms_before_m': self.predicted_before_m,
                'predicted_rms_after_m': self.predicted_after_m,
                'cross_validated_before': None if self.region_before is None
                else self.region_before.to_dict(),
                'cross_validated_after': None if self.region_after is None
                else self.region_after.to_dict(),
                'trials': [t.to_dict() for t in self.trials], 'reason': self.reason,
                'beyond_bounds': list(self.beyond_bounds)}


def _predicted(model: MeasurementModel, data: Measurements, result: CalibrationResult,
               free: list[str], prior: Prior | None, seed: int) -> float | None:
    if not np.all(np.isfinite(result.values)) or result.dof <= 0:
        return None
    oos = out_of_sample_error(model, data, result, free, prior, seed,
                              domains=('like_measured',)).domains['like_measured']
    return float(oos.rms_m) if oos.estimable else None


def choose_effects(model: MeasurementModel, data: Measurements, fit_for: FitFor, level: str,
                   n_geometric: int, prior: Prior | None = None,
                   alpha: float = ADEQUACY_ALPHA, seed: int = 0,
                   max_effects: int = MAX_EFFECTS, general: bool = True,
                   tolerances: Tolerances | None = None,
                   reference: np.ndarray | None = None,
                   balanced: bool = False,
                   q_work: np.ndarray | None = None) -> EffectChoice:
    """Forward selection of physical effects on top of ``model`` at ``level``.

    See the module docstring. ``n_geometric``: the number of geometric parameters of ``model``
    (its effects' parameters follow and are free at every level). With ``general``, the
    general effects join each round's screen as they join the diagnosis's
    (:func:`~kpi_calib_ros.core.diagnosis.screening.default_candidates`). ``prior``: the
    prior the fits use (``balanced``: balanced against the noise by them,
    :func:`~kpi_calib_ros.core.estimation.precision.fit_prior`), kept in every fold's refit.

    ``tolerances`` (the cell's; default ones when None) and ``reference`` (n_geometric,) (the
    placement and geometry the identification started from; default the model's nominal):
    a trial whose fit moves a placement or geometric parameter beyond its tolerance or leaves
    it undetermined, or whose effects are beyond their bounds or undetermined
    (:func:`kpi_calib_ros.core.estimation.plausibility.gate`), is refused with that reason
    (quantities the current model already breaks do not count against it).

    ``q_work`` (t, n): the working poses (chain order). A candidate whose correction is a
    function of one joint's angle (a periodic or cyclic error, a scale) is not tried when a
    working pose sets that joint outside its measured range (:func:`extrapolated`): no
    held-out fold can check the function there, and a periodic error fitted on 0.7 rad of
    the real UR10's shoulder put the working pose 6 mm off, predicted at 0.35 mm.

    Returns the choice; ``choice.model`` is ``model`` with the added effects appended.
    """
    tolerances = tolerances or Tolerances()
    reference = (np.asarray(model.params.nominal[:n_geometric], float) if reference is None
                 else np.asarray(reference, float))
    fit = fit_for(model)
    free = level_free(model.params, level, n_geometric)
    try:
        current = fit(data, free)
    except (DataError, np.linalg.LinAlgError) as exc:
        return EffectChoice((), model, {}, None, None, (), f'no effect screened: {exc}')
    if not current.converged:
        return EffectChoice((), model, {}, None, None, (), 'no effect screened: the fit at '
                            f'level {level} did not converge ({current.message}); effects are '
                            'not compared against its last iterate')
    first = _predicted(model, data, current, free, prior, seed)
    if first is None:
        return EffectChoice((), model, {}, None, None, (), 'no effect screened: the level leaves '
                            'no degrees of freedom to judge an effect by')
    best_rms = before = first
    region_first: RegionValidation | None = None
    region_now: RegionValidation | None = None
    held: list[str] = []
    added: list[BoundEffect] = []
    trials: list[EffectTrial] = []
    bounded: list[str] = []  # candidates that fit better beyond their physical bound
    reason = f'at most {max_effects} effects'
    for rnd in range(1, max_effects + 1):
        pool = {e.name: e for e in default_candidates(model, data, current, general)[0]}
        ranked, _ = screen_effects(model, data, current, list(pool.values()), alpha=alpha,
                                   seed=seed, tolerances=tolerances)
        known = {v.quantity for v in _violations(model, data, current, reference, tolerances,
                                                 n_geometric)}
        passed = [c for c in ranked if c.significant and c.plausible]
        beyond = {c.spec: extrapolated(pool[c.spec], data.q, q_work) for c in passed}
        passed = [c for c in passed if not beyond[c.spec]]
        refused = beyond_bound_candidates(ranked, passed[0] if passed else None)
        if refused:
            bounded.append(f'round {rnd}: ' + bound_text(refused) + (
                f' fit these poses better than {passed[0].spec} but only beyond their '
                f'physical bound: {passed[0].spec} may stand in for what they explain'
                if passed else ' are significant only beyond their physical bound'))
        trials += [EffectTrial(spec, rnd, {}, {}, None, False, f'not tried: {why}')
                   for spec, why in beyond.items() if why]
        if not passed:
            out = [spec for spec, why in beyond.items() if why]
            significant = [c.spec for c in ranked if c.significant and not c.plausible]
            reason = ('no candidate effect is significant and physically plausible'
                      + (f' (significant but implausible: {", ".join(significant)})'
                         if significant else ''))
            if out:  # significant and plausible, but a working pose lies beyond their data
                reason = (f'no candidate effect is tried: {", ".join(out)} significant and '
                          f'plausible, but {beyond[out[0]]}'
                          + (f'; significant but implausible: {", ".join(significant)}'
                             if significant else ''))
            break
        round_trials: list[tuple[EffectTrial, MeasurementModel | None,
                                 CalibrationResult | None]] = []
        for cand in passed[:TRIALS]:
            record, aug, res = _judged(_trial(
                model, data, fit_for, current, pool[cand.spec], cand.values, level,
                n_geometric, held, prior, seed, rnd, (tolerances, reference, known)),
                model, data, current, prior, balanced, seed)
            round_trials.append((record, aug, res))
        compared = max(sum(_comparable(t[0]) for t in round_trials), 1)
        round_trials = [(replace(t[0], tests=compared),) + t[1:] for t in round_trials]
        usable = [t for t in round_trials if _comparable(t[0])]
        if not usable:
            trials += [t[0] for t in round_trials]
            reason = ('no significant, plausible candidate survived its nonlinear fit with '
                      'an error over held-out regions of joint space')
            break
        # The gate is the held-out regions; among the trials that pass it, the one the fit
        # predicts best (a lower-variance figure: thermal_growth and thermal_link_growth of
        # one link hold elsewhere alike, the prediction tells the link).
        passing = [t for t in usable if _holds(t[0])]
        best = (min(passing, key=lambda t: t[0].predicted_rms_m or np.inf) if passing
                else max(usable, key=lambda t: _z(t[0])))
        after_region, before_region = best[0].region_after, best[0].region_before
        assert after_region is not None and before_region is not None
        improves = _holds(best[0])
        for trial, *_ in round_trials:
            if trial is best[0] and improves:
                trial = replace(trial, added=True, reason=(
                    f'added: {_region_text(trial)}'
                    + (f'; {", ".join(trial.held)} held at the best plausible point of its '
                       'grid (free fit refused: ' + trial.previous + ')' if trial.held else '')))
            elif not trial.reason:
                trial = replace(trial, reason=(
                    f'predicts held-out regions less well than {best[0].spec}'
                    if trial is not best[0] else
                    'not better on held-out regions of joint space beyond noise, or worse '
                    'beyond noise in a held-out fold: ' + _region_text(trial)))
            trials.append(trial)
        if not improves:
            reason = (f'{best[0].spec} fails the held-out test (it asks: better over '
                      'held-out regions of joint space beyond noise, and worse beyond noise in '
                      f'no held-out fold): {_region_text(best[0])}')
            break
        if region_first is None:
            region_first = before_region
        region_now = after_region
        trial, aug_model, aug_result = best
        held += trial.held
        assert aug_model is not None and aug_result is not None
        model, current = aug_model, aug_result
        added.append(pool[best[0].spec])
        best_rms = best[0].predicted_rms_m or best_rms
    regions = ('' if region_first is None or region_now is None else
               f'cross-validated rms over held-out regions of joint space '
               f'{_um(region_first.other_region_m)} -> {_um(region_now.other_region_m)} µm, '
               f'where measured {_um(region_first.in_region_m)} -> '
               f'{_um(region_now.in_region_m)} µm; ')
    text = (f'added {", ".join(e.name for e in added)} ({regions}predicted out-of-sample rms '
            f'{before * 1e6:.1f} -> {best_rms * 1e6:.1f} µm); stopped: {reason}'
            if added else f'no effect added: {reason}')
    values = {n: float(current.value(n)) for e in added for n in e.parameter_names}
    return EffectChoice(tuple(added), model, values, before, best_rms, tuple(trials), text,
                        tuple(held), region_first, region_now, tuple(bounded))


# A working pose beyond a joint's measured range by more than this fraction of the range
# (and RANGE_TOLERANCE, rad or m) sets an effect of that joint's angle where no pose checked
# it. A hidden gear error fitted on half of joint 1's range predicts the other half (the
# working pose 0.0 rad at the measured range's end: bench/region_holdout.py); fitted on
# 0.68 rad of the real UR10's shoulder it put a working pose 0.37 rad beyond at 6 mm.
RANGE_TOLERANCE = 1e-3
EXTRAPOLATION_FRACTION = 0.1


def extrapolated(effect: object, q: np.ndarray, q_work: np.ndarray | None) -> str:
    """Why ``effect`` would be extrapolated at the working poses ``q_work``, or ''.

    An effect whose joint correction is a function of its joint's angle alone (not of a
    torque or a measured input) predicts the working poses from its fit over the measured
    range of that joint (``q`` (N, n) the measured poses): a working pose beyond that range
    by more than :data:`EXTRAPOLATION_FRACTION` of it is a value of the function no pose
    measured.
    """
    if not isinstance(effect, BoundEffect):
        return ''  # an effect of the cell's own code: its function is unknown here
    j = effect.joint_index
    if (q_work is None or not len(q_work) or j is None
            or effect.kind.joint_function is None or effect.uses_torque or effect.kind.inputs):
        return ''
    lo, hi = float(np.min(q[:, j])), float(np.max(q[:, j]))
    margin = max(RANGE_TOLERANCE, EXTRAPOLATION_FRACTION * (hi - lo))
    work = np.atleast_2d(q_work)[:, j]
    out = work[(work < lo - margin) | (work > hi + margin)]
    if not len(out):
        return ''
    return (f'a working pose sets {effect.joint} to {float(out[0]):.3g}, outside '
            f'its measured range [{lo:.3g}, {hi:.3g}] by more than a tenth of it: the '
            'effect would be extrapolated '
            'there, where no held-out fold can check it (measure poses over the joint\'s '
            'working range)')


def _comparable(trial: EffectTrial) -> bool:
    """Whether the trial was fitted and both models have an error over held-out regions."""
    a, b = trial.region_after, trial.region_before
    return (trial.predicted_rms_m is not None and a is not None and b is not None
            and bool(np.isfinite(a.other_region_m)) and bool(np.isfinite(b.other_region_m)))


def _holds(trial: EffectTrial) -> bool:
    """Whether the trial passes the held-out test among the trials it was judged with."""
    return trial.gain is not None and trial.gain.holds(trial.tests)


def _z(trial: EffectTrial) -> float:
    """Return the trial's pooled gain over held-out regions in noise units (−inf: none)."""
    if trial.gain is None or not np.isfinite(trial.gain.z):
        return -np.inf
    return trial.gain.z


def _um(metres: float) -> str:
    return f'{metres * 1e6:.1f}' if np.isfinite(metres) else 'n/a'


def _region_text(trial: EffectTrial) -> str:
    """Say the trial's cross-validated rms before -> after, in other regions and in region."""
    b, a = trial.region_before, trial.region_after
    if a is None or b is None:
        return 'no cross-validated rms'
    gain = trial.gain
    z = ('n/a' if gain is None or not np.isfinite(gain.z) else
         f'{gain.z:.2f} (needed > {gain.threshold(trial.tests):.2f}, '
         f'{trial.tests} compared)')
    worse, compared = (0, 0) if gain is None else (gain.worse, gain.compared)
    recorded = (f', over recordings held out whole {_um(b.other_recording_m)} -> '
                f'{_um(a.other_recording_m)} µm (each one\'s placement registered)'
                if a.recordings else '')
    return (f'cross-validated rms over held-out regions of joint space '
            f'{_um(b.other_region_m)} -> {_um(a.other_region_m)} µm ({a.blocks} regions), '
            f'where measured {_um(b.in_region_m)} -> {_um(a.in_region_m)} µm{recorded}, gain '
            f'over held-out regions in noise units z = {z}, worse beyond noise in '
            f'{worse} of {compared} held-out folds {fold_kinds(a.recordings)}')


def _judged(trial: tuple[EffectTrial, MeasurementModel | None, CalibrationResult | None],
            model: MeasurementModel, data: Measurements, current: CalibrationResult,
            prior: Prior | None, balanced: bool, seed: int
            ) -> tuple[EffectTrial, MeasurementModel | None, CalibrationResult | None]:
    """Return the trial with the region figures of the current model and its own, same folds.

    The folds of the larger model (with the effect) keep the rank of the current one.
    """
    record, aug, res = trial
    if aug is None or res is None or record.predicted_rms_m is None:
        return trial
    aug_prior = fit_prior(prior, res, balanced)
    folds = validation_folds(aug, data, res, aug_prior, seed=seed)
    after = region_validation(aug, data, res, aug_prior, seed=seed, pose_folds=folds)
    before = region_validation(model, data, current, fit_prior(prior, current, balanced),
                               seed=seed, pose_folds=folds)
    return replace(record, region_before=before, region_after=after,
                   gain=held_out_gain(after, before)), aug, res


def _violations(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                reference: np.ndarray, tolerances: Tolerances, n_geometric: int
                ) -> tuple[Violation, ...]:
    """Return the plausibility gate of a fit (reflector offsets judged against ``reference``)."""
    q = np.atleast_2d(data.q)
    tau = row_torques(model, data)
    return gate(model, result, reference, tolerances, True, q, tau, n_geometric)


def _implausible_fit(effects: tuple, result: CalibrationResult,
                     tau: np.ndarray | None, bounds: Mapping[str, tuple[float, ...]] | None = None
                     ) -> str:
    """Why the fitted values of ``effects`` are not physically plausible at the measured torques.

    ``effects`` are the new one and those added before, which the refit moves too; '' when they
    are plausible. ``bounds``: the cell's ``identification.bounds``.
    """
    for e in reversed([e for e in effects if isinstance(e, BoundEffect)]):
        why = implausible(e, [float(result.value(n)) for n in e.parameter_names], tau, bounds)
        if why:
            return why if e is effects[-1] else f'it moves {e.name} out of its plausible ' \
                f'range ({why})'
    return ''


def effect_start(values: np.ndarray, effect: BoundEffect, screened: np.ndarray) -> np.ndarray:
    """Start of a fit with ``effect`` appended to a fit's ``values``.

    Its size parameters at 0 and its shape parameters at their ``screened`` values. The screened
    size came with a geometry that moved too (the linear screen refits both); added to the old
    geometry it starts far off (TIAGo: 5.9 mm rms from a 2.2 mm fit), while from size 0 the
    geometry and the size are fitted together and the shape is freed once the size is not 0.
    """
    k = effect.kind.n_shape
    size = np.zeros(len(effect.parameter_names) - k)
    return np.concatenate([values, size, np.asarray(screened, float)[len(size):]])


def _trial(model: MeasurementModel, data: Measurements, fit_for: FitFor,
           current: CalibrationResult, effect: BoundEffect, screened: np.ndarray, level: str,
           n_geometric: int, held: list[str], prior: Prior | None, seed: int, rnd: int,
           gating: tuple[Tolerances, np.ndarray, set[str]] | None = None
           ) -> tuple[EffectTrial, MeasurementModel | None, CalibrationResult | None]:
    """Fit ``model`` + ``effect`` from the current fit and the screened values; judge it.

    An effect with shape parameters (nonlinear, e.g. joint_play's τ0) is fitted with them
    free first; when that fit does not converge or leaves the plausible range, they are
    held at the screened value (the best plausible point of their grid) and only the size
    is fitted: the plausible-constrained estimate on the grid. ``gating``: the tolerances,
    the reference geometry and the quantities the current fit already breaks; a fit that
    breaks another (:func:`_violations`) is refused with the first.
    """
    aug = augmented_model(model, (effect,))
    names = list(effect.parameter_names)
    shape = list(effect.shape_names)
    p0 = effect_start(current.values, effect, screened)
    tau = row_torques(aug, data)
    attempts = [list(held), list(held) + shape] if shape else [list(held)]
    trial: tuple[EffectTrial, MeasurementModel | None, CalibrationResult | None] = (
        EffectTrial(effect.name, rnd, {}, {}, None, False, 'not fitted'), None, None)
    for fixed in attempts:
        free = [n for n in level_free(aug.params, level, n_geometric) if n not in fixed]
        try:
            res = fit_for(aug)(data, free, p0)
        except (DataError, np.linalg.LinAlgError) as exc:
            trial = (EffectTrial(effect.name, rnd, {}, {}, None, False, f'fit failed: {exc}'),
                     None, None)
            continue
        values = {n: float(res.value(n)) for n in names}
        std = {n: float(v) for n, v in zip(res.estimated, res.std) if n in names}
        wanted = [n for n in names if n not in fixed]
        if not res.converged:
            why = f'the fit did not converge ({res.message})'
        elif any(n not in std for n in wanted):
            why = 'not identified with the geometry at this level'
        else:
            why = _implausible_fit(aug.effects, res, tau,
                                   None if gating is None else gating[0].bounds)
        if not why and gating is not None:
            new = [v for v in _violations(aug, data, res, gating[1], gating[0], n_geometric)
                   if v.quantity not in gating[2]]
            why = f'not plausible: {new[0].text()}' if new else ''
        pred = None if why else _predicted(aug, data, res, free, prior, seed)
        if not why and pred is None:
            why = 'no degrees of freedom left'
        now = [n for n in shape if n in fixed]
        trial = (EffectTrial(effect.name, rnd, values, std, pred, False, why, tuple(now),
                             previous=trial[0].reason if now else ''), aug, res)
        if not why:
            break
    return trial

"""Screening of candidate effects against a geometric fit, ranked best first.

For every candidate effect × joint (:func:`default_candidates`: the library's effects and
the general ones): is its signature distinguishable from the geometric parameters with this
data (:mod:`~kpi_calib_ros.core.diagnosis.effect_signature`)? If so, fit the augmented model
(:mod:`~kpi_calib_ros.core.diagnosis.candidate_fit`), score it by k-fold cross-validated rms
over held-out poses and an F-test against the geometric fit, Bonferroni-corrected over the
candidates so that data the geometric model explains claims no effect at the family-wise
level ``alpha``, and judge whether it is plausible
(:mod:`~kpi_calib_ros.core.diagnosis.candidate_plausibility`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from kpi_calib_ros.core.diagnosis.candidate_fit import (
    CandidateFit,
    fit_candidate,
    merge_same_signature,
    nested_alternatives,
    torque_effect_notes,
)
from kpi_calib_ros.core.diagnosis.candidate_plausibility import (
    backlash_unloaded,
    effect_undetermined,
    geometry_undetermined,
)
from kpi_calib_ros.core.diagnosis.effect_signature import (
    absorbed_by,
    effect_columns,
    effect_std,
)
from kpi_calib_ros.core.diagnosis.model_selection import PARSIMONY
from kpi_calib_ros.core.diagnosis.periodic_search import (
    Periodogram,
    periodic_candidates,
    periodograms,
)
from kpi_calib_ros.core.effects.general import aliased_frequency, general_candidates
from kpi_calib_ros.core.effects.registry import BoundEffect, candidate_effects, implausible
from kpi_calib_ros.core.estimation.cross_validation import linear_validation_rms
from kpi_calib_ros.core.estimation.folds import identifiable_folds
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.plausibility import Tolerances
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA, linearized_fit
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.payload import payload_torques
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import point_rms, point_rows, unweighted

__all__ = ['DEPENDENCE_TOLERANCE', 'NO_EFFECT_M', 'Candidate', 'default_candidates',
           'screen_effects']

DEPENDENCE_TOLERANCE = 1e-4  # unique fraction of a signature below this: absorbed
NO_EFFECT_M = 1e-9           # a typical-size effect moving no point by 1 nm has no effect


@dataclass(frozen=True)
class Candidate:
    """One effect × joint, screened against the geometric fit.

    Fitted values, their std and the statistics are NaN when the candidate is
    not distinguishable. ``p_value`` is Bonferroni-adjusted over the
    distinguishable candidates; ``p_value_raw`` is the single F-test.
    """

    effect: str
    joint: str | None
    spec: str
    parameter_names: tuple[str, ...]
    units: tuple[str, ...]
    distinguishable: bool
    values: np.ndarray
    std: np.ndarray
    rms_after_m: float
    validation_rms_after_m: float
    delta_chi2: float
    f_statistic: float
    p_value_raw: float
    p_value: float
    significant: bool
    correlation: float
    driver_correlation: float
    unique_fraction: float
    absorbed_by: dict[str, float]
    explanation: str
    # Plausibility (see effects.implausible), candidates with the same signature merged
    # into this one, and a note comparing torque-driven candidates of the same joint.
    plausible: bool = True
    plausibility: str = ''
    also_explained_by: tuple[str, ...] = ()
    note: str = ''
    # ``std`` are from the stated σ (1) or scaled by χ²/dof of the augmented fit when it
    # fails the χ² test, as identify reports (core.estimation.precision.chi2_scale).
    covariance_scale: float = 1.0
    # The number of frequencies searched when the effect's frequency was found on these
    # residuals (core.diagnosis.periodic_search); its p-values are multiplied by it. 1: no search.
    searched: int = 1


def screen_effects(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                   candidates: list[BoundEffect] | None = None, folds: int = 0,
                   alpha: float = ADEQUACY_ALPHA, seed: int = 0,
                   tolerances: Tolerances | None = None
                   ) -> tuple[tuple[Candidate, ...], tuple[Candidate, ...]]:
    """Fit and score every candidate effect against the geometric fit ``result``.

    Parameters
    ----------
    model, data, result
        The model, its measurements and its identification.
    candidates : list of BoundEffect, optional
        Default: every screened library effect × joint not already in ``model``.
    folds : int
        Folds (over poses) of the cross-validation; 0 leaves one pose out
        (see :func:`kpi_calib_ros.core.estimation.folds.identifiable_folds`).
    alpha : float
        Family-wise false-alarm level: a candidate is significant when its
        F-test p-value times the number of distinguishable candidates is below.
    tolerances : Tolerances, optional
        The cell's tolerances and effect bounds (default: the library's bounds and the
        default tolerances): a candidate beyond its bounds, undetermined (std above its
        bound), or one that leaves a geometric parameter undetermined (its std with the
        candidate beside it above its tolerance) is not plausible, with that reason.

    Returns
    -------
    ranked : tuple of Candidate
        Distinguishable candidates, significant first, then by validation rms.
    not_distinguishable : tuple of Candidate
        Candidates the geometry absorbs or that change no measurement, with why.
    """
    if candidates is None:
        candidates = candidate_effects(model.robot, exclude=[e.name for e in model.effects],
                                       covariates=data.covariates or (),
                                       temperatures=model.joint_temperatures)
    sys_ = linearized_fit(model, data, result)
    n = len(data)
    pose_folds = identifiable_folds(sys_.jac, np.atleast_2d(data.q), folds, seed)
    r_perp = sys_.r - sys_.basis @ (sys_.basis.T @ sys_.r)
    chi2_base = float(r_perp @ r_perp)
    points = point_rows(data.reflector, model.n_reflectors)  # the rows that are lengths
    rms_base = point_rms(unweighted(r_perp, sys_.w), points)
    cv_base = linear_validation_rms(sys_.jac, sys_.r, sys_.w, pose_folds, points=points)
    dof_base = 3 * n - sys_.basis.shape[1]
    q = np.atleast_2d(data.q)
    # τ with its gradient: a candidate that reads the torque takes it at the deflected
    # configuration (core.measurement.deflection)
    tau = sys_.tau if sys_.tau is not None else payload_torques(model.robot, q, data.covariates,
                                                                gradient=True)
    joint_jac = model.joint_jacobian(sys_.p, q, sys_.tau, sys_.reflector, sys_.rotation,
                                     sys_.covariates)

    fits: list[CandidateFit] = []
    rejected = []
    tolerances = tolerances or Tolerances()
    bounds = tolerances.bounds
    for effect in candidates:
        # An effect nonlinear in its shape parameters is screened at each value of its
        # shape grid (the size parameters linear there); the best fit stands for it.
        tried, why_not = [], None
        unloaded = backlash_unloaded(effect, tau)
        if unloaded:
            why_not = _rejected(effect, 0.0, {}, unloaded)
        for shape in (effect.kind.shape_grid or ((),)) if not unloaded else ():
            cols, disp = effect_columns(model, sys_, effect, q, tau, shape)
            norms = np.linalg.norm(cols, axis=0)
            if disp < NO_EFFECT_M or np.any(norms == 0):
                why_not = why_not or _rejected(effect, 0.0, {}, (
                    f'no effect on these measurements: a typical-size {effect.kind.name} '
                    f'moves no point by more than {disp:.1e} m. To see it: {effect.hint()}.'))
                continue
            unit = cols / norms
            unique = unit - sys_.basis @ (sys_.basis.T @ unit)
            fraction = float(np.linalg.svd(unique, compute_uv=False).min())
            if fraction < DEPENDENCE_TOLERANCE:
                absorbed = absorbed_by(model, result, sys_, unit)
                text = ', '.join(f'{k} ({v:+.2f})' for k, v in absorbed.items())
                why_not = _rejected(effect, fraction, absorbed, (
                    f'not distinguishable with this data: the geometric parameters reproduce '
                    f'its signature (unique part {fraction:.1e}; mainly {text}). To make it '
                    f'distinguishable: {effect.hint()}.'))
                continue
            tried.append(fit_candidate(effect, cols, sys_, r_perp, chi2_base, dof_base,
                                       pose_folds, joint_jac, q, tau, fraction, shape,
                                       points))
        if tried:
            # The best physically plausible shape (a fit constrained to the plausible
            # region); only when none is plausible, the best of all (reported implausible).
            plausible = [f for f in tried if not implausible(effect, f.theta, tau, bounds)]
            best = max(plausible or tried, key=lambda f: f.delta_chi2)
            if len(tried) > 1:
                # The best of several shapes is the best of several tests: its p-value is
                # multiplied by their number (Bonferroni), so the screen's claims keep
                # their level (the plain best-of-grid p-value is too small on clean data).
                best = replace(best, p_value_raw=min(1.0, best.p_value_raw * len(tried)))
            if np.isnan(best.std).any():
                # shape parameters held at a grid value: their std, and the sizes' with them
                # free, from the full Jacobian at the screened values
                best = replace(best, std=effect_std(model, sys_, effect, q, tau, best.theta))
            if effect.searched > 1:
                # A frequency found by a search on these residuals (core.diagnosis.periodic_search):
                # the best of that many tests, counted the same way.
                best = replace(best, p_value_raw=min(1.0, best.p_value_raw * effect.searched))
            fits.append(best)
        elif why_not is not None:
            rejected.append(why_not)

    fits = merge_same_signature(fits)
    notes = torque_effect_notes(fits)
    simpler = nested_alternatives(fits, alpha)
    m = max(len(fits), 1)
    out = []
    for fit in fits:
        p_adj = min(1.0, fit.p_value_raw * m)
        nested = simpler.get(fit.effect.name, '')
        significant = bool(p_adj < alpha) and not nested
        warning = implausible(fit.effect, fit.theta, tau, bounds) \
            or effect_undetermined(fit.effect, fit.scaled_std, bounds)
        if significant and not warning:
            warning = geometry_undetermined(model, sys_, result, fit, q, tau, tolerances)
        merged = fit.merged
        extra = ''.join(f' {t}' for t in (
            warning and f'Warning: {warning}.',
            merged and f'The same signature is explained by {", ".join(merged)} '
                       '(one candidate: the data cannot tell them apart).',
            nested, notes.get(fit.effect.name, ''), _searched(fit.effect)) if t)
        out.append(Candidate(
            effect=fit.effect.kind.name, joint=fit.effect.joint, spec=fit.effect.name,
            parameter_names=fit.effect.parameter_names, units=fit.effect.units,
            distinguishable=True, values=fit.theta,
            std=fit.scaled_std, covariance_scale=fit.covariance_scale,
            rms_after_m=fit.rms_m, validation_rms_after_m=fit.validation_rms_m,
            delta_chi2=fit.delta_chi2, f_statistic=fit.f_statistic, p_value_raw=fit.p_value_raw,
            p_value=p_adj, significant=significant, correlation=fit.correlation,
            driver_correlation=fit.driver_correlation, unique_fraction=fit.unique_fraction,
            absorbed_by={},
            explanation=_explain(fit, significant, p_adj, m, rms_base, cv_base) + extra,
            plausible=not warning, plausibility=warning, also_explained_by=merged,
            note=notes.get(fit.effect.name, ''), searched=fit.effect.searched))
    # A general effect (core.effects.general) is offered when no named one fits: it ranks
    # after the significant, plausible named effects unless it predicts held-out poses
    # PARSIMONY better than the best of them.
    general = {fit.effect.name: fit.effect.kind.general for fit in fits}
    named = min((c.validation_rms_after_m for c in out if c.significant and c.plausible
                 and not general[c.spec]), default=np.inf)
    out.sort(key=lambda c: (not (c.significant and c.plausible),
                            general[c.spec] and not c.validation_rms_after_m
                            < (1 - PARSIMONY) * named,
                            not c.significant, c.validation_rms_after_m, c.p_value_raw))
    return tuple(out), tuple(rejected)


def default_candidates(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                       general: bool = True
                       ) -> tuple[list[BoundEffect], tuple[Periodogram, ...]]:
    """Return the effects the diagnosis and ``auto`` screen against the fit ``result``.

    The library (:func:`~kpi_calib_ros.core.effects.registry.candidate_effects`: the effects
    that read a covariate, the thermal ones, where the measurements carry it) and, with
    ``general``, the general effects: ``link_bending`` of every joint that carries mass and
    the periodic joint error at the peak of each revolute joint's periodogram. Effects
    already in ``model`` are left out. Returns the candidates and the periodograms searched.
    """
    have = {e.name for e in model.effects}
    library = candidate_effects(model.robot, exclude=have, covariates=data.covariates or (),
                                temperatures=model.joint_temperatures)
    q = np.atleast_2d(data.q)
    # A second frequency within the resolution of one the model has on a joint is that
    # one aliased (core.effects.general.aliased_frequency): never a candidate.
    library = [e for e in library if e.joint_index is None
               or not aliased_frequency(e, model.effects, q[:, e.joint_index])]
    if not general:
        return library, ()
    grams = periodograms(model, data, result)
    return (library + general_candidates(model.robot, have) + periodic_candidates(model, grams),
            grams)


def _rejected(effect: BoundEffect, fraction: float, absorbed: dict[str, float],
              why: str) -> Candidate:
    k = len(effect.parameter_names)
    nan = np.full(k, np.nan)
    return Candidate(effect=effect.kind.name, joint=effect.joint, spec=effect.name,
                     parameter_names=effect.parameter_names, units=effect.units,
                     distinguishable=False, values=nan, std=nan, rms_after_m=np.nan,
                     validation_rms_after_m=np.nan, delta_chi2=np.nan, f_statistic=np.nan,
                     p_value_raw=np.nan, p_value=np.nan, significant=False,
                     correlation=np.nan, driver_correlation=np.nan, unique_fraction=fraction,
                     absorbed_by=absorbed, explanation=why)


def _searched(effect: BoundEffect) -> str:
    if effect.searched <= 1:
        return ''
    return (f'Its frequency is the peak of a search over {effect.searched} frequencies '
            f'(cycles per revolution) on these residuals; its p-value counts them '
            f'(× {effect.searched}).')


def _explain(fit: CandidateFit, significant: bool, p_adj: float, m: int, rms_base: float,
             cv_base: float) -> str:
    effect: BoundEffect = fit.effect
    # The std as the candidate table states them: scaled by χ²/dof of the augmented fit
    # when the model is not adequate (at the stated σ they understated it 7.6x on the UR10).
    std = fit.scaled_std
    values = ', '.join(f'{name.rsplit(".", 1)[1]} = {v:.3g} '
                       + (f'± {s:.2g} {u}' if np.isfinite(s) else f'{u} (not determined)')
                       for name, v, s, u in zip(effect.parameter_names, fit.theta,
                                                std, effect.units))
    numbers = (f'rms {rms_base * 1e6:.1f} -> {fit.rms_m * 1e6:.1f} µm, validation rms '
               f'{cv_base * 1e6:.1f} -> {fit.validation_rms_m * 1e6:.1f} µm; {values}; '
               f'p = {p_adj:.3g} (F-test, Bonferroni over {m} candidates)')
    if effect.inputs != effect.kind.inputs:  # a sensor of the cell's own (thermal effects)
        numbers += f'; reads {", ".join(effect.inputs)}'
    if not significant:
        return f'not significant: {numbers}.'
    why = (f'the residuals correlate {fit.correlation:.2f} with the part of its signature the '
           'geometry cannot absorb')
    if np.isfinite(fit.driver_correlation):
        direction = f'the residual along the {effect.joint} rotation direction' \
            if effect.joint_kind != 'prismatic' else f'the residual along the {effect.joint} axis'
        why = (f'{direction} correlates {fit.driver_correlation:.2f} with the '
               f'{effect.signature()}, and {why}')
    return f'{effect.kind.description}: {why}; {numbers}.'

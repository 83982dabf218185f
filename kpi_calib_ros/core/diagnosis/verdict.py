"""The diagnosis of one calibration (:func:`diagnose`): is its model adequate, what is missing.

Three steps, all pure (no files, no plots):

1. :func:`~kpi_calib_ros.core.estimation.residuals.residual_report` -- per-measurement
   residuals, rms, percentiles, the χ² goodness-of-fit test of the weighted
   residual sum against the stated tracker σ, leverage and outlier flags.
2. :func:`~kpi_calib_ros.core.diagnosis.screening.screen_effects` -- for every candidate
   effect × joint: is its signature distinguishable from the geometric parameters with this
   data? If so, fit the augmented model, score it by k-fold cross-validated rms over
   held-out poses and an F-test against the geometric fit, Bonferroni-corrected over the
   candidates so that data the geometric model explains claims no effect at the
   family-wise level ``alpha``.
3. :func:`~kpi_calib_ros.core.diagnosis.model_comparison.compare_models` -- before/after
   numbers when an effect is added.

:func:`diagnose` does the first two and states the verdict.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from kpi_calib_ros.core.diagnosis.periodic_search import Periodogram
from kpi_calib_ros.core.diagnosis.screening import Candidate, default_candidates, screen_effects
from kpi_calib_ros.core.effects.registry import BoundEffect
from kpi_calib_ros.core.estimation.cross_validation import validation_rms
from kpi_calib_ros.core.estimation.estimability import KpiEstimability
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult, point_sigma_squares
from kpi_calib_ros.core.estimation.plausibility import Tolerances
from kpi_calib_ros.core.estimation.precision import JOINT_NOISE_CAUSE
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA, ResidualReport, residual_report
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel

__all__ = ['Diagnosis', 'beyond_bound_candidates', 'beyond_bounds', 'bound_text', 'diagnose',
           'equivalent_joint_sigma', 'not_recommended',
           'with_estimability']


@dataclass(frozen=True)
class Diagnosis:
    """Verdict on a calibration and the ranked candidate effects (best first)."""

    model_adequate: bool
    verdict: str
    residuals: ResidualReport
    rms_m: float
    validation_rms_m: float
    candidates: tuple[Candidate, ...]
    not_distinguishable: tuple[Candidate, ...]
    alpha: float
    folds: int
    # The frequency search of the periodic joint errors (one per revolute joint searched).
    periodograms: tuple[Periodogram, ...] = ()
    # What the verdict says of candidates that fit better than the best but beyond their
    # physical bound (:func:`beyond_bounds`); '' when none does.
    beyond: str = ''

    @property
    def best(self) -> Candidate | None:
        """Top-ranked significant, physically plausible candidate, or None."""
        c = self.candidates[0] if self.candidates else None
        return c if c is not None and c.significant and c.plausible else None


def diagnose(model: MeasurementModel, data: Measurements, result: CalibrationResult,
             candidates: list[BoundEffect] | None = None, folds: int = 0,
             alpha: float = ADEQUACY_ALPHA, seed: int = 0, general: bool = True,
             tolerances: Tolerances | None = None) -> Diagnosis:
    """Residual report, verdict and ranked candidate effects for one calibration.

    The model is adequate when the χ² test passes at ``alpha`` and no candidate
    is significant at the family-wise level ``alpha``. With ``general`` (and the default
    candidates), the general effects join the screen: ``link_bending`` of every joint
    that carries mass and, per revolute joint, the periodic joint error at the peak of
    its periodogram (:mod:`kpi_calib_ros.core.diagnosis.periodic_search`, the search counted in
    its p-value); they rank after the significant, plausible named effects. ``tolerances``:
    the cell's tolerances and effect bounds (:func:`screen_effects`).
    """
    report = residual_report(model, data, result, alpha)
    grams: tuple[Periodogram, ...] = ()
    if candidates is None and general:
        candidates, grams = default_candidates(model, data, result)
    ranked, rejected = screen_effects(model, data, result, candidates, folds, alpha, seed,
                                      tolerances)
    cv = validation_rms(model, data, result, folds, seed)
    best = ranked[0] if ranked and ranked[0].significant and ranked[0].plausible else None
    implausible_only = best is None and any(c.significant for c in ranked)
    adequate = report.adequate and best is None and not implausible_only
    chi = _chi(report)
    beyond = beyond_bounds(ranked, best)
    if adequate:
        verdict = (f'model adequate: {chi}; no candidate effect is significant at the '
                   f'family-wise level {alpha:g}.')
    elif best is not None:
        verdict = (f'model not adequate: {chi}. {_most_likely(best, cv)}.'
                   + ('' if beyond else f' Add it with --effects {best.spec}.'))
    elif implausible_only:
        verdict = (f'model not adequate: {chi}; the significant candidates fit physically '
                   'implausible values (see their warnings): the misfit is something else '
                   '(outliers, the stated σ, an unmodelled effect); none is suggested.')
    else:
        verdict = (f'model not adequate: {chi}, but no candidate effect explains the misfit; '
                   'check the outliers, the stated σ and the plots against time and distance.')
    verdict += beyond
    if not report.adequate and model.joint_sigma is None and best is None:
        # Only where no effect explains the misfit: beside a significant compliance the
        # sentence would send the user after the wrong cause.
        equivalent = equivalent_joint_sigma(model, data, result)
        verdict += (f' The joint readings may be the cause: the residuals equal joint-reading '
                    f'noise of {np.rad2deg(equivalent):.3g}° on every joint. '
                    + JOINT_NOISE_CAUSE[0].upper() + JOINT_NOISE_CAUSE[1:] + '.')
    return Diagnosis(model_adequate=adequate, verdict=verdict, residuals=report,
                     rms_m=report.rms_m, validation_rms_m=cv, candidates=ranked,
                     not_distinguishable=rejected, alpha=alpha, folds=folds,
                     periodograms=grams, beyond=beyond)


BEYOND_BOUND = 'beyond the plausible'
# A candidate beyond its bound is named against the best plausible one when its validation
# rms is below this fraction of the best's: a clear gain, not a tie within the folds' noise.
CLEARLY_BETTER = 0.95


def beyond_bound_candidates(ranked: Sequence[Candidate],
                            best: Candidate | None) -> list[Candidate]:
    """Return the significant candidates that fit better than ``best`` beyond their bound.

    Their fitted values break their physical bound, and they fit the poses better than
    ``best`` (the best plausible candidate; None: any).
    """
    return [c for c in ranked if c.significant and not c.plausible
            and BEYOND_BOUND in c.plausibility
            and (best is None or c.validation_rms_after_m
                 < CLEARLY_BETTER * best.validation_rms_after_m)]


def bound_text(candidates: Sequence[Candidate]) -> str:
    """Return each candidate (at most three) with what its bound refuses.

    Its validation rms, the value beyond its bound and the cell key that states a softer or
    looser arm.
    """
    return '; '.join(
        f'{c.spec} (validation rms {_micro(c.validation_rms_after_m)}: '
        + c.plausibility.removeprefix('physically implausible: ').split(' (the fit')[0]
        + f'; widen identification.bounds.{c.effect}'
        + (f':{c.joint}' if c.joint else '') + ' if the arm is that soft or loose)'
        for c in candidates[:3])


def beyond_bounds(ranked: Sequence[Candidate], best: Candidate | None) -> str:
    """Return the sentence on candidates that fit only beyond their physical bound, or ''.

    A 7-DoF arm with servo compliances (c = -6e-4 rad/(N m), beyond the default bound):
    diagnose said "Add it with --effects joint_play:joint2" (validation rms 1775 µm) and
    ``auto`` added two plays, while the compliance it set aside fitted at 922 µm, its reason
    in diagnosis.json only. The data prefer an explanation the bound refuses: the user must
    hear of it, and of the key that states a softer arm, before taking a stand-in.
    """
    better = beyond_bound_candidates(ranked, best)
    if not better:
        return ''
    said = bound_text(better)
    if best is None:
        return (f' Beyond their physical bound: {said}. If the arm is that soft or loose (a '
                'servo-stiff or cable-driven arm, the physics in the guide), state the bound '
                'in the cell and diagnose again.')
    return (f' Beyond their physical bound, candidates fit these poses better than '
            f'{best.spec}: {said}. {best.spec} may stand in for what they explain: state the '
            'bound in the cell (a servo-stiff or cable-driven arm, the physics in the guide) '
            f'and diagnose again; add it (--effects {best.spec}) only if the arm is as stiff '
            'as the bounds say.')


def not_recommended(diag: Diagnosis, why: str) -> Diagnosis:
    """Return ``diag`` whose best candidate, refitted, is NOT recommended for ``why``.

    Why: it does not predict held-out regions of joint space better, it extrapolates, or
    its fit did not converge. The verdict no longer tells the user to add it. When the χ²
    test accepts the model, the model is adequate: the candidate's significance in the
    screen (a lower misfit of the measured poses) is not a missing effect when adding it
    predicts no better elsewhere, and a clean robot is not called "not adequate" for it.
    """
    best = diag.best
    if best is None:
        return diag
    refused = (f'It is NOT recommended ({why}; see the comparison); keep the model without '
               f'it.')
    if diag.residuals.adequate:
        return replace(diag, model_adequate=True, verdict=(
            f'model adequate: {_chi(diag.residuals)}; the screen\'s most significant '
            f'candidate, {best.spec} (validation rms {_micro(diag.validation_rms_m)} -> '
            f'{_micro(best.validation_rms_after_m)}), lowers the misfit of the measured poses '
            f'only. {refused}{diag.beyond}'))
    return replace(diag, verdict=(f'model not adequate: {_chi(diag.residuals)}. '
                                  f'{_most_likely(best, diag.validation_rms_m)}. {refused}'
                                  f'{diag.beyond}'))


def with_estimability(diag: Diagnosis, estimability: KpiEstimability) -> Diagnosis:
    """Return ``diag`` judged with identify's estimability verdict.

    Where the measurements do not determine the TCP, the residuals cannot show what the
    calibration misses (every parameter vector of the unmeasured directions fits them
    equally well), so the model is not called adequate and the verdict says the TCP is not
    estimable first.
    """
    if estimability.all_estimable:
        return diag
    rep = diag.residuals
    verdict = (f'{estimability.summary()}. No expected TCP error is stated and the model is '
               f'not judged: the residuals describe only the fit of the measured poses '
               f'(χ²/dof = {rep.chi2:.1f}/{rep.dof}, p = {rep.p_value:.3g}), which cannot show '
               f'the error where the data do not reach.')
    return replace(diag, model_adequate=False, verdict=verdict)


def equivalent_joint_sigma(model: MeasurementModel, data: Measurements,
                           result: CalibrationResult) -> float:
    """Joint-reading noise σ_q (rad, the same on every joint) explaining the residuals beyond σ.

    The residual sum of squares beyond the stated tracker σ: Σ‖r_i‖² · 3N/dof = Σ_i (Σ_a σ_a² +
    σ_q² ‖J_q,i‖²) (the fit leaves dof/3N of the noise in the residuals); 0 when σ explains
    them.
    """
    point = (np.ones(len(data), bool) if data.reflector is None
             else np.asarray(data.reflector) < model.n_reflectors)
    q = np.atleast_2d(data.q)[point]
    jq = model.joint_jacobian(result.values, q, None if data.tau is None else data.tau[point],
                              None if data.reflector is None else data.reflector[point],
                              covariates=data.subset(point).covariates)
    residuals = np.asarray(result.residuals)[point]
    n_rows = 3 * len(data)
    excess = (np.sum(residuals ** 2) * n_rows / max(result.dof, 1)
              - len(q) * np.mean(point_sigma_squares(result, data.reflector,
                                                     model.n_reflectors)))
    lever = float(np.sum(jq ** 2))
    return float(np.sqrt(max(excess, 0.0) / lever)) if lever > 0 else float('nan')


def _chi(report: ResidualReport) -> str:
    return (f'χ²/dof = {report.chi2:.1f}/{report.dof} (p = {report.p_value:.3g}) against the '
            f'stated σ')


def _most_likely(best: Candidate, cv: float) -> str:
    return (f'Most likely missing effect: {best.spec} (validation rms {_micro(cv)} -> '
            f'{_micro(best.validation_rms_after_m)})')


def _micro(rms_m: float) -> str:
    return f'{rms_m * 1e6:.1f} µm' if np.isfinite(rms_m) else 'not estimable from this design'

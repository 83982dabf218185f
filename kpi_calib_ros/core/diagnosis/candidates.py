"""Model diagnosis: how well a calibration explains its data, and which effect is missing.

Three steps, all pure (no files, no plots):

1. :func:`~kpi_calib_ros.core.estimation.residuals.residual_report` -- per-measurement
   residuals, rms, percentiles, the χ² goodness-of-fit test of the weighted
   residual sum against the stated tracker σ, leverage and outlier flags.
2. :func:`screen_effects` -- for every candidate effect × joint: is its
   signature distinguishable from the geometric parameters with this data?
   If so, fit the augmented model, score it by k-fold cross-validated rms over
   held-out poses and an F-test against the geometric fit, Bonferroni-corrected
   over the candidates so that data the geometric model explains claims no
   effect at the family-wise level ``alpha``.
3. :func:`compare_models` -- before/after numbers when an effect is added.

The augmented fits are Gauss-Newton steps from the converged geometric
solution: effects of a few tenths of a milliradian move the points by tenths
of a millimetre, so the second-order terms (≈ θ²·1 m ≈ 0.1 µm) are far below
the tracker noise and one linear step is the fit. The effect columns of the
Jacobian are exact (CasADi, from the augmented measurement model).
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, field, replace
from typing import Mapping

import casadi as ca
import numpy as np
import scipy.stats

from kpi_calib_ros.core.diagnosis.misfit import MisfitAnswer
from kpi_calib_ros.core.diagnosis.model_selection import PARSIMONY, region_test, worse_folds
from kpi_calib_ros.core.diagnosis.out_of_sample import OutOfSample
from kpi_calib_ros.core.diagnosis.periodic_search import (
    Periodogram,
    periodic_candidates,
    periodograms,
)
from kpi_calib_ros.core.diagnosis.residual_analysis import ResidualAnalysis
from kpi_calib_ros.core.effects.general import aliased_frequency, general_candidates
from kpi_calib_ros.core.effects.library import BACKLASH_TORQUE_SCALE
from kpi_calib_ros.core.effects.registry import (
    BoundEffect,
    candidate_effects,
    effect_bounds,
    implausible,
)
from kpi_calib_ros.core.estimation.cross_validation import (
    linear_validation_rms,
    region_validation,
    validation_folds,
    validation_rms,
)
from kpi_calib_ros.core.estimation.estimability import KpiEstimability
from kpi_calib_ros.core.estimation.folds import identifiable_folds
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult, point_sigma_squares
from kpi_calib_ros.core.estimation.plausibility import Tolerances
from kpi_calib_ros.core.estimation.precision import (
    JOINT_NOISE_CAUSE,
    ExpectedTcpError,
    chi2_scale,
    fit_prior,
    precision_statement,
)
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.estimation.residuals import (
    ADEQUACY_ALPHA,
    LinearizedFit,
    ResidualReport,
    linearized_fit,
    orthonormal_basis,
    residual_report,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.payload import payload_torques
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import unweighted, weighted_rows

__all__ = ['Candidate', 'CandidateFit', 'CellDiagnosis', 'Diagnosis', 'ModelComparison',
           'ResidualReport',
           'augmented_model', 'backlash_unloaded', 'compare_models', 'default_candidates',
           'diagnose',
           'validation_rms',
           'equivalent_joint_sigma',
           'residual_report', 'screen_effects']
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


@dataclass(frozen=True)
class CandidateFit:
    """The augmented fit of one candidate at one shape, before the candidates are ranked.

    Field names as in :class:`Candidate`; units of the effect's parameters.

    Attributes
    ----------
    effect : BoundEffect
    theta : (k,) ndarray
        Fitted sizes, then the shape parameters held at their grid value.
    std : (k,) ndarray
        Their std from the stated σ (NaN for the held shape parameters).
    rms_m, validation_rms_m : float
        rms (m) of the augmented fit and its cross-validated rms over held-out poses.
    chi2, dof : float, int
        Weighted residual sum of the augmented fit and its degrees of freedom.
    delta_chi2, f_statistic, p_value_raw : float
        χ² reduction over the geometric fit, its F statistic and single-test p-value.
    correlation, driver_correlation, unique_fraction : float
        As in :class:`Candidate`.
    unique : (3N, k) ndarray
        The part of the effect's weighted columns the geometry does not reproduce.
    merged : tuple of str
        Specs of candidates with the same signature merged into this one.
    """

    effect: BoundEffect
    theta: np.ndarray
    std: np.ndarray
    rms_m: float
    chi2: float
    dof: int
    unique: np.ndarray
    validation_rms_m: float
    delta_chi2: float
    f_statistic: float
    p_value_raw: float
    correlation: float
    driver_correlation: float
    unique_fraction: float
    merged: tuple[str, ...] = ()


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

    @property
    def best(self) -> Candidate | None:
        """Top-ranked significant, physically plausible candidate, or None."""
        c = self.candidates[0] if self.candidates else None
        return c if c is not None and c.significant and c.plausible else None


@dataclass(frozen=True)
class ModelComparison:
    """Before/after adding effects: the numbers a person needs to trust the richer model."""

    effects: tuple[str, ...]
    rms_before_m: float
    rms_after_m: float
    validation_rms_before_m: float
    validation_rms_after_m: float
    p_value_before: float
    p_value_after: float
    effect_parameters: tuple[dict, ...]
    tcp_std_before_m: np.ndarray
    tcp_std_after_m: np.ndarray
    working_pose_names: tuple[str, ...] = field(default=())
    # A fit that did not converge, named with its stop: its figures are those of the last
    # iterate, not of a minimum, and the comparison says so.
    warnings: tuple[str, ...] = field(default=())
    # How the after-fit's std were obtained (core.estimation.precision.precision_statement).
    std_basis: str = ''
    # Cross-validated rms over held-out regions of joint space (whole k-means blocks of
    # poses, core.estimation.cross_validation.region_validation) before/after, on the same
    # folds; NaN where not estimable. ``validation_rms_*``: where the poses were measured.
    other_region_rms_before_m: float = float('nan')
    other_region_rms_after_m: float = float('nan')
    region_blocks: int = 0
    # Held-out rms of each region block and each joint's range end, before/after, paired
    # (core.estimation.cross_validation.RegionValidation.held_out_folds_m), m.
    held_out_folds_before_m: tuple[float, ...] = ()
    held_out_folds_after_m: tuple[float, ...] = ()
    held_out_noise_m: tuple[float, ...] = ()  # each fold's rms spread by the noise alone

    @property
    def holds_elsewhere(self) -> bool:
        """Return whether the richer model holds over held-out regions of joint space.

        The test ``auto`` applies
        (:func:`~kpi_calib_ros.core.diagnosis.model_selection.holds_elsewhere`); only then is
        it recommended. Never when a fit did not converge (``warnings``): its cross-validated
        figures linearise a last iterate, not a minimum, as ``auto`` neither screens from nor
        adds such a fit.
        """
        if self.warnings:
            return False
        return region_test(self.other_region_rms_after_m, self.other_region_rms_before_m,
                           self.validation_rms_after_m, self.validation_rms_before_m,
                           folds_after=self.held_out_folds_after_m,
                           folds_before=self.held_out_folds_before_m,
                           noise=self.held_out_noise_m)

    @property
    def worse_folds(self) -> tuple[int, int]:
        """(held-out folds the richer model predicts worse, folds compared)."""
        return worse_folds(self.held_out_folds_after_m, self.held_out_folds_before_m,
                           self.held_out_noise_m)


# ---------------------------------------------------------------- screening
@dataclass(frozen=True)
class CellDiagnosis:
    """Everything :func:`kpi_calib_ros.app.diagnose.diagnose_cell` computes.

    ``after``/``comparison`` only when an effect was added.
    """

    model: MeasurementModel
    data: Measurements
    result: CalibrationResult
    diagnosis: Diagnosis
    added: BoundEffect | None = None
    after_model: MeasurementModel | None = None
    after: CalibrationResult | None = None
    comparison: ModelComparison | None = None
    # Predicted error of new measurements at fresh poses (core.diagnosis.out_of_sample), of the
    # calibration diagnosed and of the one with the added effect.
    out_of_sample: OutOfSample | None = None
    after_out_of_sample: OutOfSample | None = None
    # The measurements given: ``data`` is those identification keeps (``kept``, (M,) bool;
    # None: all), so the diagnosis describes the calibration the user gets; ``excluded``
    # names the others (indices into the given measurements).
    kept: np.ndarray | None = None
    excluded: tuple[int, ...] = ()

    def given_index(self, rows: np.ndarray) -> list[int]:
        """Return indices into the given measurements of rows (bool mask or indices) of ``data``."""
        rows = np.asarray(rows)
        idx = np.flatnonzero(rows) if rows.dtype == bool else rows.astype(int)
        return [int(i) for i in (idx if self.kept is None else np.flatnonzero(self.kept)[idx])]
    # Expected TCP error at the working poses with the misfit (core.estimation.precision).
    expected: ExpectedTcpError | None = None
    # Where the model fails, model-free (core.diagnosis.residual_analysis), and the four answers
    # (core.diagnosis.misfit: where, what is missing, the command, held-out error before/after).
    residual_analysis: ResidualAnalysis | None = None
    answer: MisfitAnswer | None = None
    # Whether the measurements determine the TCP at the working poses, identify's verdict
    # (core.estimation.estimability); when they do not, ``expected`` is None and the
    # verdict says so.
    estimability: KpiEstimability | None = None

    @property
    def tcp_estimable(self) -> bool:
        """Whether the TCP is estimable at every working pose (True when not checked)."""
        return self.estimability is None or self.estimability.all_estimable


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
    rms_base = float(np.sqrt(np.sum(unweighted(r_perp, sys_.w) ** 2) / n))
    cv_base = linear_validation_rms(sys_.jac, sys_.r, sys_.w, pose_folds)
    dof_base = 3 * n - sys_.basis.shape[1]
    q = np.atleast_2d(data.q)
    tau = sys_.tau if sys_.tau is not None else payload_torques(model.robot, q, data.covariates)
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
            cols, disp = _effect_columns(model, sys_, effect, q, tau, shape)
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
                absorbed = _absorbed_by(model, result, sys_, unit)
                text = ', '.join(f'{k} ({v:+.2f})' for k, v in absorbed.items())
                why_not = _rejected(effect, fraction, absorbed, (
                    f'not distinguishable with this data: the geometric parameters reproduce '
                    f'its signature (unique part {fraction:.1e}; mainly {text}). To make it '
                    f'distinguishable: {effect.hint()}.'))
                continue
            tried.append(_fit_candidate(effect, cols, sys_, r_perp, chi2_base, dof_base,
                                        pose_folds, joint_jac, q, tau, fraction, shape))
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
            or _undetermined(fit.effect, fit.std * np.sqrt(chi2_scale(fit.chi2, fit.dof)), bounds)
        if significant and not warning:
            warning = _geometry_undetermined(model, sys_, result, fit, q, tau, tolerances)
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
            std=fit.std * np.sqrt(chi2_scale(fit.chi2, fit.dof)),
            covariance_scale=chi2_scale(fit.chi2, fit.dof),
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


def _undetermined(effect: BoundEffect, std: np.ndarray, bounds: Mapping[str, tuple[float, ...]]
                  ) -> str:
    """Why a screened effect is undetermined (a std above its bound), '' when it is not."""
    loose = [f'{n} std {v:.3g} {u} > its bound {b:.3g}' for n, v, u, b in
             zip(effect.parameter_names, std, effect.units, effect_bounds(effect, bounds))
             if np.isfinite(v) and v > b]
    return ('undetermined: ' + '; '.join(loose) + f' (to determine it: {effect.hint()})'
            if loose else '')


def _geometry_undetermined(model: MeasurementModel, sys_: LinearizedFit,
                           result: CalibrationResult, fit: CandidateFit, q: np.ndarray,
                           tau: np.ndarray, tolerances: Tolerances) -> str:
    """Which identified geometric parameters a candidate leaves undetermined, '' for none.

    With the candidate's columns beside the geometry, the std of each identified geometric
    parameter is that of the fit [J E] (Schur complement, at the candidate's χ²/dof); one above
    its tolerance (m or rad, :class:`~kpi_calib_ros.core.estimation.plausibility.Tolerances`)
    that was within it without the candidate is undetermined by the effect: the data cannot
    tell the effect from that direction of the geometry (link bending turning a column's
    placement by 0.2 rad).
    """
    k = len(fit.effect.parameter_names) - fit.effect.kind.n_shape
    shape = tuple(fit.theta[k:]) if fit.effect.kind.n_shape else ()
    cols, _ = _effect_columns(model, sys_, fit.effect, q, tau, shape)
    basis = orthonormal_basis(cols)
    perp = sys_.jac - basis @ (basis.T @ sys_.jac)
    scale = chi2_scale(fit.chi2, fit.dof)
    with np.errstate(divide='ignore', invalid='ignore'):
        std = np.sqrt(np.abs(np.diag(np.linalg.pinv(perp.T @ perp, hermitian=True))) * scale)
    before = dict(zip(result.estimated, result.std))
    units = dict(zip(model.params.names, model.params.units))
    out = []
    for name, s in zip(result.estimated, std):
        if name not in units or not _is_geometric(name):
            continue
        tol = _tolerance_of(name, units[name], tolerances)
        if s > tol >= before.get(name, 0.0):
            out.append(f'{name} std {s:.3g} {units[name]} > its tolerance {tol:g}')
    return ('it leaves the geometry undetermined: ' + '; '.join(out[:4])
            + (f' and {len(out) - 4} more' if len(out) > 4 else '')
            + ' (the data cannot tell the effect from these directions)') if out else ''


def _is_geometric(name: str) -> bool:
    return name.startswith(('base.', 'reflector.')) or '.placement.' in name \
        or (name.endswith('.offset') and name.count('.') == 1)


def _tolerance_of(name: str, unit: str, tolerances: Tolerances) -> float:
    if name.startswith('reflector.'):
        # an offset (m), or the identified orientation of a tracked body (rad)
        return tolerances.reflector_offset if unit == 'm' else tolerances.rotation
    if name.endswith('.offset'):
        return tolerances.offset
    prefix = 'base_' if name.startswith('base.') else ''
    return getattr(tolerances, prefix + ('translation' if unit == 'm' else 'rotation'))


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
    chi = (f'χ²/dof = {report.chi2:.1f}/{report.dof} (p = {report.p_value:.3g}) against the '
           f'stated σ')
    if adequate:
        verdict = (f'model adequate: {chi}; no candidate effect is significant at the '
                   f'family-wise level {alpha:g}.')
    elif best is not None:
        verdict = (f'model not adequate: {chi}. Most likely missing effect: {best.spec} '
                   f'(validation rms {_micro(cv)} -> {_micro(best.validation_rms_after_m)}'
                   f'). Add it with --effects {best.spec}.')
    elif implausible_only:
        verdict = (f'model not adequate: {chi}; the significant candidates fit physically '
                   'implausible values (see their warnings): the misfit is something else '
                   '(outliers, the stated σ, an unmodelled effect); none is suggested.')
    else:
        verdict = (f'model not adequate: {chi}, but no candidate effect explains the misfit; '
                   'check the outliers, the stated σ and the plots against time and distance.')
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
                     periodograms=grams)


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


# ---------------------------------------------------------------- comparison
def _micro(rms_m: float) -> str:
    return f'{rms_m * 1e6:.1f} µm' if np.isfinite(rms_m) else 'not estimable from this design'


def compare_models(before: tuple[MeasurementModel, CalibrationResult],
                   after: tuple[MeasurementModel, CalibrationResult], data: Measurements,
                   folds: int = 0, seed: int = 0, prior: Prior | None = None,
                   balanced: bool = False) -> ModelComparison:
    """Rms, validation rms, effect parameters and TCP std before/after adding effects.

    ``after``'s model must contain the effects (its extra parameters are the
    effect parameters reported). The validation rms are those of ``folds`` folds of poses
    (where measured) and of folds that hold out whole regions of joint space, both models on
    the folds of ``after`` (which keep the rank of ``before``), every fold refitted with the
    fits' ``prior`` (``balanced``: balanced against the noise by the fits,
    :func:`~kpi_calib_ros.core.estimation.precision.fit_prior`).
    """
    model_b, res_b = before
    model_a, res_a = after
    prior_b, prior_a = fit_prior(prior, res_b, balanced), fit_prior(prior, res_a, balanced)
    same = validation_folds(model_a, data, res_a, prior_a, folds, seed=seed)
    region_b = region_validation(model_b, data, res_b, prior_b, folds, seed=seed,
                                 pose_folds=same)
    region_a = region_validation(model_a, data, res_a, prior_a, folds, seed=seed,
                                 pose_folds=same)
    new = [e for e in model_a.effects if e.name not in {x.name for x in model_b.effects}]
    std = dict(zip(res_a.estimated, res_a.std))
    params = []
    dropped = {d.name: d.reason for d in res_a.dropped}
    for effect in new:
        for name, unit in zip(effect.parameter_names, effect.units):
            entry = {'name': name, 'value': res_a.value(name), 'unit': unit}
            if name in std:
                entry['std'] = float(std[name])
            else:
                entry['dropped'] = dropped.get(name, 'held at its start value (not free)')
            params.append(entry)
    return ModelComparison(
        effects=tuple(e.name for e in new),
        rms_before_m=res_b.rms_m, rms_after_m=res_a.rms_m,
        validation_rms_before_m=region_b.in_region_m,
        validation_rms_after_m=region_a.in_region_m,
        other_region_rms_before_m=region_b.other_region_m,
        other_region_rms_after_m=region_a.other_region_m,
        region_blocks=region_a.blocks,
        held_out_folds_before_m=region_b.held_out_folds_m,
        held_out_folds_after_m=region_a.held_out_folds_m,
        held_out_noise_m=region_a.held_out_noise_m,
        p_value_before=res_b.p_value, p_value_after=res_a.p_value,
        effect_parameters=tuple(params),
        tcp_std_before_m=_tcp_std(res_b),
        tcp_std_after_m=_tcp_std(res_a),
        working_pose_names=res_a.working_pose_names,
        warnings=tuple(unconverged_warning(res, which) for res, which in
                       ((res_b, 'before'), (res_a, 'after')) if not res.converged),
        std_basis=precision_statement(res_a.covariance_scale))


def _tcp_std(result: CalibrationResult) -> np.ndarray:
    """Return the (t, 3) standard deviations of the TCP at the working poses, m.

    (0, 3) for a cell without working poses (its covariance is then an empty array).
    """
    cov = np.reshape(result.tcp_covariance, (-1, 3, 3))
    return np.sqrt(np.diagonal(cov, axis1=1, axis2=2))


def unconverged_warning(result: CalibrationResult, which: str) -> str:
    """Say what a comparison with ``result``, a fit that did not converge, is worth."""
    return (f'the fit {which} did not converge ({result.message}): its figures are those of '
            'the last iterate, not of a minimum, and the comparison may favour the other '
            'side (identification.max_iterations / --max-iterations raises the limit)')


# ------------------------------------------------------------------ helpers
def augmented_model(model: MeasurementModel, effects: tuple) -> MeasurementModel:
    """``model`` with ``effects`` appended (their parameters after the existing ones)."""
    return MeasurementModel(model.robot, model.geometric, model.effects + tuple(effects),
                            model.reflector_axis, model.orientations, model.rotation_scale,
                            model.joint_sigma, model.joint_temperatures)


# Candidate models of a base model, by effect name: the screen builds one per candidate
# (the CasADi expressions and their Jacobians, most of a screen's time), and one base model
# is screened again for every campaign, seed or round.
_CANDIDATE_MODELS: weakref.WeakKeyDictionary[MeasurementModel, dict[str, MeasurementModel]] = \
    weakref.WeakKeyDictionary()


def _candidate_model(model: MeasurementModel, effect: BoundEffect) -> MeasurementModel:
    """Return ``model`` with ``effect`` appended, built once per base model and effect."""
    built = _CANDIDATE_MODELS.setdefault(model, {})
    aug = built.get(effect.name)
    if aug is None or aug.effects[-1] != effect:
        aug = augmented_model(model, (effect,))
        built[effect.name] = aug
    return aug


def _effect_columns(model: MeasurementModel, sys_: LinearizedFit, effect: BoundEffect,
                    q: np.ndarray, tau: np.ndarray,
                    shape: tuple[float, ...] = ()) -> tuple[np.ndarray, float]:
    """Weighted Jacobian columns (3N, k) of the size parameters at size 0, and the largest shift.

    The columns are the effect's size parameters; shape parameters, the last ``len(shape)``, are
    held at ``shape``. The shift is the largest point displacement (m) a typical-size effect
    causes.
    """
    aug = _candidate_model(model, effect)
    k = len(effect.parameter_names) - len(shape)
    p = np.concatenate([sys_.p, np.zeros(k), shape])
    _, jac = aug.jacobian(p, q, tau, sys_.reflector, sys_.rotation, sys_.covariates)
    cols = jac[:, :, len(sys_.p):len(sys_.p) + k]
    disp = float(np.max(np.linalg.norm(cols @ np.asarray(effect.typical[:k]), axis=1)))
    return weighted_rows(cols, sys_.w), disp


def _absorbed_by(model: MeasurementModel, result: CalibrationResult, sys_: LinearizedFit,
                 unit: np.ndarray) -> dict[str, float]:
    norms = np.linalg.norm(sys_.jac, axis=0)
    ok = norms > 0
    coef, *_ = np.linalg.lstsq(sys_.jac[:, ok] / norms[ok], unit[:, 0], rcond=None)
    names = [n for n, keep in zip(result.estimated, ok) if keep]
    top = np.argsort(-np.abs(coef))[:4]
    return {names[t]: float(coef[t]) for t in top if abs(coef[t]) > 1e-3}


def backlash_unloaded(effect: BoundEffect, tau: np.ndarray) -> str:
    """Return why ``joint_backlash`` is no backlash on this data, or ''.

    With the joint's gravity torques ``tau`` (N, n) below its torque scale τ_b
    (:data:`~kpi_calib_ros.core.effects.library.BACKLASH_TORQUE_SCALE`), its b·tanh(τ/τ_b) is
    (b/τ_b)·τ there: a compliance of the joint, never a step. A torque of exactly 0
    everywhere is left to the no-effect test.
    """
    if effect.kind.name != 'joint_backlash' or effect.joint_index is None:
        return ''
    top = float(np.max(np.abs(np.asarray(tau)[:, effect.joint_index]), initial=0.0))
    if top == 0.0 or top >= BACKLASH_TORQUE_SCALE:
        return ''
    return (f'not a backlash with this data: the gravity torque of {effect.joint} stays below '
            f'{top:.2g} N m, under the backlash\'s torque scale τ_b = '
            f'{BACKLASH_TORQUE_SCALE:g} N m, where b·tanh(τ/τ_b) is (b/τ_b)·τ, a compliance '
            f'(joint_compliance:{effect.joint} is its candidate). To see it: '
            f'{effect.hint()}.')


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


def _fit_candidate(effect: BoundEffect, cols: np.ndarray, sys_: LinearizedFit, r_perp: np.ndarray,
                   chi2_base: float, dof_base: int, pose_folds: np.ndarray | None,
                   joint_jac: np.ndarray, q: np.ndarray, tau: np.ndarray,
                   fraction: float, shape: tuple[float, ...] = ()) -> CandidateFit:
    """Augmented least squares [J E] from the geometric solution, its F-test and CV.

    Shape parameters held at ``shape`` (chosen from a grid) count as fitted in the F-test's
    degrees of freedom; their std is NaN.
    """
    n = len(q)
    k = cols.shape[1] + len(shape)
    unique = cols - sys_.basis @ (sys_.basis.T @ cols)
    info = unique.T @ unique  # Schur complement: information on θ with geometry free
    cov = np.linalg.inv(info)
    size = cov @ (unique.T @ r_perp)
    r_aug = r_perp - unique @ size
    theta = np.concatenate([size, shape])
    std = np.concatenate([np.sqrt(np.diag(cov)), np.full(len(shape), np.nan)])
    chi2_aug = float(r_aug @ r_aug)
    delta = chi2_base - chi2_aug
    dof = dof_base - k
    f_stat = (delta / k) / (chi2_aug / dof)
    p_raw = float(scipy.stats.f.sf(f_stat, k, dof))
    cv = linear_validation_rms(np.hstack([sys_.jac, cols]), sys_.r, sys_.w, pose_folds)
    rms = float(np.sqrt(np.sum(unweighted(r_aug, sys_.w) ** 2) / n))
    corr = float(np.sqrt(max(delta, 0.0) / chi2_base)) if chi2_base > 0 else 0.0
    return CandidateFit(
        effect=effect, theta=theta, std=std, rms_m=rms, chi2=chi2_aug, dof=dof, unique=unique,
        validation_rms_m=cv, delta_chi2=delta, f_statistic=f_stat, p_value_raw=p_raw,
        correlation=corr,
        driver_correlation=_driver_correlation(effect, theta, unique, size, r_aug, sys_.w,
                                               joint_jac, q, tau),
        unique_fraction=fraction)


SAME_SIGNATURE = 1e-6  # sin of the largest principal angle between two signatures


def merge_same_signature(fits: list[CandidateFit]) -> list[CandidateFit]:
    """Merge candidates whose signatures span the same subspace.

    A signature is the part of a candidate's Jacobian columns the geometry does not reproduce;
    for one parameter, the same subspace is the same column up to scale. The best-fitting one
    stays, with the others' specs in ``'merged'``: the data cannot tell them apart, so they are
    one candidate, not several.
    """
    bases = [np.linalg.qr(f.unique)[0] for f in fits]
    order = sorted(range(len(fits)), key=lambda i: -fits[i].delta_chi2)
    taken: set[int] = set()
    out = []
    for i in order:
        if i in taken:
            continue
        merged: list[str] = []
        for j in order:
            if j == i or j in taken or bases[j].shape[1] != bases[i].shape[1]:
                continue
            gap = bases[j] - bases[i] @ (bases[i].T @ bases[j])
            if np.linalg.norm(gap, 2) < SAME_SIGNATURE:
                merged.append(fits[j].effect.name)
                taken.add(j)
        taken.add(i)
        out.append(replace(fits[i], merged=tuple(merged)))
    return out


def nested_alternatives(fits: list[CandidateFit], alpha: float = ADEQUACY_ALPHA
                        ) -> dict[str, str]:
    """Test effects that nest simpler ones of the same joint against the best simpler one.

    For an effect that contains simpler ones of the same joint (``EffectType.nests``: joint_play
    is joint_backlash as τ0 -> 0 and joint_compliance as τ0 -> ∞): is it significantly better
    than the best plausible simpler one (F-test of its extra parameters at ``alpha``)? If not,
    the simpler one is the explanation. Returns spec -> why it is not counted significant.
    """
    by_joint: dict[tuple[str | None, str], CandidateFit] = {
        (f.effect.joint, f.effect.kind.name): f for f in fits}
    out = {}
    for fit in fits:
        effect = fit.effect
        rivals = [by_joint[(effect.joint, name)] for name in effect.kind.nests
                  if (effect.joint, name) in by_joint]
        rivals = [r for r in rivals if not implausible(r.effect, r.theta)]
        if not rivals:
            continue
        rival = max(rivals, key=lambda r: r.delta_chi2)
        extra = len(fit.theta) - len(rival.theta)
        f_stat = (fit.delta_chi2 - rival.delta_chi2) / extra / (fit.chi2 / fit.dof)
        p = float(scipy.stats.f.sf(f_stat, extra, fit.dof)) if f_stat > 0 else 1.0
        if p >= alpha:
            out[effect.name] = (f'Not counted: the simpler {rival.effect.name} explains '
                                f'as much (F-test of the extra parameter p = {p:.3g} >= '
                                f'{alpha:g}).')
    return out


def torque_effect_notes(fits: list[CandidateFit]) -> dict[str, str]:
    """Compare backlash and compliance of a joint where both are candidates.

    For a joint with both backlash (a step with the sign of the gravity torque) and compliance
    (in proportion to it) among the candidates: which fits better, by the χ² reduction of each
    (both have one parameter). Returns spec -> note.
    """
    by_joint: dict[str, dict[str, CandidateFit]] = {}
    for f in fits:
        e = f.effect
        if e.kind.name in ('joint_backlash', 'joint_compliance') and e.joint is not None:
            by_joint.setdefault(e.joint, {})[e.kind.name] = f
    notes = {}
    for joint, pair in by_joint.items():
        if len(pair) < 2:
            continue
        b, c = pair['joint_backlash'], pair['joint_compliance']
        better = 'backlash (a sign flip with the torque)' if b.delta_chi2 > c.delta_chi2 \
            else 'compliance (in proportion to the torque)'
        text = (f'On {joint}, {better} fits better: χ² reduction {b.delta_chi2:.1f} for '
                f'backlash vs {c.delta_chi2:.1f} for compliance.')
        notes[b.effect.name] = notes[c.effect.name] = text
    return notes


def _driver_correlation(effect: BoundEffect, theta: np.ndarray, unique: np.ndarray,
                        size: np.ndarray, r_aug: np.ndarray, w: np.ndarray,
                        joint_jac: np.ndarray,
                        q: np.ndarray, tau: np.ndarray) -> float:
    """Correlation of the joint-angle error implied by the residuals with the fitted correction.

    The residual the effect explains (r_aug + Eθ̂, geometry refitted) is
    projected on the direction the point moves when joint j turns, giving an
    implied angle error per pose; it is correlated (weighted by the squared
    lever) with the effect's fitted correction δq_j(q, τ, θ̂).
    """
    if effect.joint_index is None or effect.kind.joint_function is None or effect.inputs:
        return float('nan')  # no correction of its joint's value from (q, τ) alone
    j = effect.joint_index
    explained = unweighted(r_aug + unique @ size, w)
    lever = joint_jac[:, :, j]
    lever2 = np.sum(lever ** 2, axis=1)
    ok = lever2 > 1e-12
    if ok.sum() < 3:
        return float('nan')
    implied = np.sum(lever * explained, axis=1)[ok] / lever2[ok]
    correction = _joint_correction_values(effect, q, tau, theta)[ok, j]
    wt = lever2[ok] / lever2[ok].sum()
    a = implied - wt @ implied
    b = correction - wt @ correction
    denom = np.sqrt((wt @ a ** 2) * (wt @ b ** 2))
    return float(wt @ (a * b) / denom) if denom > 0 else float('nan')


def _joint_correction_values(effect: BoundEffect, q: np.ndarray, tau: np.ndarray,
                             theta: np.ndarray) -> np.ndarray:
    """Numeric joint corrections (N, n) of ``effect`` at parameters ``theta``."""
    n = q.shape[1]
    qs, ts = ca.SX.sym('q', n), ca.SX.sym('tau', n)
    th = ca.SX.sym('theta', len(theta))
    fn = ca.Function('dq', [qs, ts, th], [effect.joint_correction(qs, ts, th)])
    return np.array(fn.map(len(q))(q.T, tau.T, theta)).T


def _searched(effect: BoundEffect) -> str:
    if effect.searched <= 1:
        return ''
    return (f'Its frequency is the peak of a search over {effect.searched} frequencies '
            f'(cycles per revolution) on these residuals; its p-value counts them '
            f'(× {effect.searched}).')


def _explain(fit: CandidateFit, significant: bool, p_adj: float, m: int, rms_base: float,
             cv_base: float) -> str:
    effect: BoundEffect = fit.effect
    values = ', '.join(f'{name.rsplit(".", 1)[1]} = {v:.3g} '
                       + (f'± {s:.2g} {u}' if np.isfinite(s) else f'{u} (best of its grid)')
                       for name, v, s, u in zip(effect.parameter_names, fit.theta,
                                                fit.std, effect.units))
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

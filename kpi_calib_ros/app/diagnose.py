"""Diagnosis: calibrate, test the model, add the most likely missing effect, compare.

``kpi-calib diagnose``, the node's ``~/diagnose`` and the demo call
:func:`diagnose_cell`; :mod:`kpi_calib_ros.io.report` writes what it returns.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from kpi_calib_ros.app.calibration_document import (
    plausibility_gate,
    recording_jumps,
)
from kpi_calib_ros.app.calibration_document import (
    recording_names as bag_recording_names,  # diagnose_cell takes the names themselves
)
from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.app.identify import (
    calibrate_cell,
    cell_prior,
    identify_cell,
    print_progress,
    with_effects,
)
from kpi_calib_ros.app.learned_residual import choose_residual, too_many_rows
from kpi_calib_ros.app.measurements import load_measurements
from kpi_calib_ros.app.placement import registered_start
from kpi_calib_ros.core.diagnosis.cell_diagnosis import CellDiagnosis
from kpi_calib_ros.core.diagnosis.effect_selection import effect_start, extrapolated
from kpi_calib_ros.core.diagnosis.learned_residual import ResidualChoice
from kpi_calib_ros.core.diagnosis.misfit import GENERAL, NAMED, Remedy, answer_misfit
from kpi_calib_ros.core.diagnosis.model_comparison import ModelComparison, compare_models
from kpi_calib_ros.core.diagnosis.model_selection import level_free
from kpi_calib_ros.core.diagnosis.out_of_sample import out_of_sample_error
from kpi_calib_ros.core.diagnosis.residual_analysis import ResidualAnalysis, analyse_calibration
from kpi_calib_ros.core.diagnosis.verdict import (
    Diagnosis,
    diagnose,
    not_recommended,
    with_estimability,
)
from kpi_calib_ros.core.effects.registry import implausible, parse_effect_spec
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.precision import expected_tcp_error
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA, is_adequate
from kpi_calib_ros.core.estimation.robust import robust_sigma
from kpi_calib_ros.core.measurement import weighting
from kpi_calib_ros.core.measurement.covariates import measured_covariates
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import row_torques
from kpi_calib_ros.core.model.parameters import RECORDING_PREFIX
from kpi_calib_ros.io.names import DIAGNOSIS_FILE
from kpi_calib_ros.io.report import diagnosis_text, write_report
from kpi_calib_ros.io.residual_plots import write_learned_residual_plot
from kpi_calib_ros.io.results import writable_folder


def diagnose_cell(cm: CellModel, data: Measurements, folds: int = 0,
                  alpha: float = ADEQUACY_ALPHA, add_best: bool = True,
                  model: str | None = None,
                  progress: Callable[[str], None] | None = None,
                  covariates: Mapping[str, tuple[np.ndarray, str]] | None = None,
                  recording_names: Sequence[str] = ()) -> CellDiagnosis:
    """Calibrate ``cm`` on ``data``, diagnose it and, when an effect is significant,
    add the top one and compare before/after (full nonlinear refit). ``model`` (or the
    cell's ``identification.model``) sets the model level the effects are screened
    against; the default geometric is the full model. Both calibrations carry their
    predicted out-of-sample error (:mod:`kpi_calib_ros.core.diagnosis.out_of_sample`). The points
    diagnosed are those :func:`~kpi_calib_ros.app.identify.calibrate_cell` keeps
    (``kept``, ``excluded`` of the result); ``progress`` gets its exclusion rounds.
    The residuals are also analysed model-free (:func:`with_misfit_answer`), with the
    extra ``covariates`` (name -> ((M,) values of the given measurements, unit); default:
    the temperatures ``data`` carries, :func:`recorded_covariates`). What the recordings
    (``recording_names``, the first included) say before the robot, a probe they disagree on
    or a placement that changed while measured, is ``set_up``, as identify finds it."""
    if covariates is None:
        covariates = recorded_covariates(data)
    # The points identify keeps, with its model level (outliers that are faults excluded,
    # core.estimation.outliers): the diagnosis describes the calibration the user gets.
    cal = calibrate_cell(cm, data, model, progress=progress)
    level = cal.choice.level
    free = None if level == 'geometric' else level_free(cm.model.params, level,
                                                         len(cm.geometric))
    kept, excluded = cal.robust.kept, tuple(e.index for e in cal.robust.excluded)
    names = list(recording_names) or ['first', *cm.model.recordings]
    set_up = tuple(([cal.remount.text()] if cal.remount is not None and cal.remount.disagrees
                    else []) + [j.text() for j in recording_jumps(cm, data, cal, names)])
    given, data = data, data.subset(kept)
    # Without effects auto added, identify's fit is the one on the kept points.
    result = cal.result if cal.cell is None or cal.cell is cm else \
        identify_cell(cm, data, free=free)
    # One estimability verdict for identify and the diagnosis: where the measurements do not
    # determine the TCP, no expected error is stated and no effect is added (the residuals
    # cannot judge what the data leave free).
    est = cal.estimability
    diag = with_estimability(diagnose(cm.model, data, result, folds=folds, alpha=alpha,
                                      tolerances=cm.cell.identification.tolerances), est)
    if excluded and diag.best is None and add_best and est.all_estimable:
        # The excluded points may be an effect's only evidence (the few poses where a
        # joint's torque has the other sign: a backlash's), as auto sees on every point:
        # diagnose called the model adequate where auto added the backlash (z = 12).
        every = explained_outliers(cm, given, kept, level, free, cal.robust.threshold,
                                   folds, alpha)
        if every is not None:
            data, result, diag = every
            diag = with_estimability(diag, est)
    # What the diagnosis describes: the points identify keeps, or every point when the
    # excluded ones are an effect's measurements (the comparison names them, readmitted).
    shown_kept, shown_excluded = (kept, excluded) if len(data) != len(given) else (
        np.ones(len(given), bool), ())
    prior = cell_prior(cm)
    oos = out_of_sample_error(cm.model, data, result, free or list(cm.model.params.names),
                              prior)
    # result: honest precision
    expected = expected_tcp_error(cm.model, data, result) if est.all_estimable else None
    if not add_best or diag.best is None or not est.all_estimable:
        return with_misfit_answer(CellDiagnosis(
            cm.model, data, result, diag, out_of_sample=oos, kept=shown_kept,
            excluded=shown_excluded,
            expected=expected, estimability=est, set_up=set_up), covariates)
    best = parse_effect_spec(diag.best.spec, cm.robot, temperatures=cm.model.joint_temperatures)
    richer = with_effects(cm, (best,))
    richer_free = None if free is None else level_free(richer.model.params, level,
                                                       len(cm.geometric))
    # A shape parameter (joint_play's τ0) starts at its screened grid point; when its free
    # fit fails or leaves the plausible range it is held there, as auto does.
    p0 = effect_start(result.values, best, diag.best.values)
    after = identify_cell(richer, data, p0=p0, free=richer_free)
    shape = best.shape_names
    tau = row_torques(richer.model, data)
    if shape and (not after.converged or implausible(
            best, [after.value(n) for n in best.parameter_names], tau)):
        richer_free = [n for n in (richer_free or richer.model.params.names) if n not in shape]
        after = identify_cell(richer, data, p0=p0, free=richer_free)
    # Points excluded as outliers of the model without the effect that the effect explains
    # (within the exclusion threshold of its fit) are measurements, not faults: both models
    # are refitted and compared with them.
    back = readmitted(richer.model, given, kept, after, cal.robust.threshold)
    compared, without = data, result
    if back:
        rows = kept.copy()
        rows[list(back)] = True
        compared = given.subset(rows)
        without = identify_cell(cm, compared, p0=result.values, free=free)
        after = identify_cell(richer, compared, p0=after.values, free=richer_free)
    comparison = compare_models((cm.model, without), (richer.model, after), compared,
                                folds=folds, prior=prior, balanced=prior is not None)
    comparison = dataclasses.replace(comparison, readmitted=back)
    beyond = extrapolated(best, compared.q, cm.q_work if len(cm.q_work) else None)
    if beyond:
        comparison = dataclasses.replace(comparison, extrapolated=(f'{best.name}: {beyond}',))
    added = added_violations(cm, without, richer, after, compared, richer_free)
    if added:
        comparison = dataclasses.replace(comparison, implausible=added)
    diag = verdict_with_comparison(diag, comparison)
    after_oos = out_of_sample_error(richer.model, compared, after,
                                    richer_free or list(richer.model.params.names), prior)
    return with_misfit_answer(CellDiagnosis(
        cm.model, data, result, diag, best, richer.model, after, comparison, oos, after_oos,
        shown_kept, shown_excluded, expected, estimability=est, set_up=set_up), covariates)


def explained_outliers(cm: CellModel, given: Measurements, kept: np.ndarray, level: str,
                       free: list[str] | None, threshold: float, folds: int, alpha: float
                       ) -> tuple[Measurements, CalibrationResult, Diagnosis] | None:
    """Every point of ``given``, its fit and its diagnosis, when the diagnosis of every
    point finds an effect whose fit (on every point) has each point the outlier rule
    excluded (not ``kept``) within the exclusion threshold, a measurement
    (:func:`readmitted`); None otherwise."""
    every = identify_cell(cm, given, free=free)
    diag = diagnose(cm.model, given, every, folds=folds, alpha=alpha,
                    tolerances=cm.cell.identification.tolerances)
    if diag.best is None:
        return None
    best = parse_effect_spec(diag.best.spec, cm.robot, temperatures=cm.model.joint_temperatures)
    richer = with_effects(cm, (best,))
    richer_free = None if free is None else level_free(richer.model.params, level,
                                                       len(cm.geometric))
    # fitted on every point: the excluded ones may be all that determines the effect (a
    # backlash where the torque has one sign on the kept points is a joint offset)
    after = identify_cell(richer, given, free=richer_free,
                          p0=effect_start(every.values, best, diag.best.values))
    back = readmitted(richer.model, given, kept, after, threshold)
    return (given, every, diag) if len(back) == int(np.count_nonzero(~kept)) else None


def readmitted(model: MeasurementModel, given: Measurements, kept: np.ndarray,
               fit: CalibrationResult, threshold: float) -> tuple[int, ...]:
    """The points of ``given`` not ``kept`` whose distance to the prediction of ``fit`` (the
    model with the effect) is within ``threshold`` σ̂ of that fit: a measured column tilt
    made four points outliers of the model without it, and diagnose fitted the tilt without
    them (gains 0.9565 and 1.088 where identify on every point found 0.9417 and 1.074)."""
    out = np.flatnonzero(~np.asarray(kept, bool))
    if not len(out) or not np.isfinite(threshold):
        return ()
    rows = given.subset(out)
    points = weighting.point_rows(rows.reflector, model.n_reflectors)
    miss = np.linalg.norm(np.atleast_2d(rows.eta) - model.predict(
        fit.values, rows.q, row_torques(model, rows), rows.reflector, rows.rotation,
        rows.covariates), axis=1)
    scale = robust_sigma(np.asarray(fit.residuals, float), fit.dof)
    inside = miss <= threshold * scale  # the exclusion's distance in σ̂
    if points is not None:
        inside &= points
    return tuple(int(i) for i in out[inside])


def added_violations(cm: CellModel, result: CalibrationResult, richer: CellModel,
                     after: CalibrationResult, data: Measurements,
                     free: Sequence[str] | None) -> tuple[str, ...]:
    """What identify's plausibility gate refuses in the fit with the effect (``richer``,
    ``after``) and not in the fit without it: a link bending diagnose recommended on a
    7-DoF arm moved a joint placement 0.133 m, and identify with it was not valid. The
    placement is judged against where identify starts (the registered one)."""
    try:
        start, _ = registered_start(cm, data)
    except DataError:
        start = np.asarray(cm.model.params.nominal, float)
    q = np.atleast_2d(data.q)

    def gate(model: CellModel, fit: CalibrationResult, names: Sequence[str] | None
             ) -> tuple[str, ...]:
        begin = np.concatenate([start, model.model.params.nominal[len(start):]])
        return plausibility_gate(model, fit, begin, q, row_torques(model.model, data),
                                 data.reflector, names, data.covariates)
    before = {v.split(':')[0] for v in gate(cm, result, None)}
    return tuple(v for v in gate(richer, after, free) if v.split(':')[0] not in before)


def verdict_with_comparison(diag: Diagnosis, comparison: ModelComparison) -> Diagnosis:
    """``diag`` whose verdict no longer says to add the screen's best effect when the refit
    with it is NOT recommended (it does not predict held-out regions better, extrapolates
    past the measured ranges, or did not converge): the first line of the real TIAGo's
    diagnosis said "Add it with --effects joint_play:arm_6_joint" of a play whose held-out
    error over other regions rose from 4763 to 5426 µm. With the χ² test passing, the
    model is then adequate (:func:`~kpi_calib_ros.core.diagnosis.verdict.not_recommended`)."""
    if comparison.holds_elsewhere or diag.best is None:
        return diag
    if comparison.warnings:
        why = 'a fit with it did not converge, so the comparison judges a last iterate'
    elif comparison.extrapolated:
        why = '; '.join(comparison.extrapolated)
    elif comparison.implausible:
        why = ('refitted with it, the calibration is not plausible, identify would not '
               'publish it: ' + '; '.join(comparison.implausible))
    else:
        why = ('refitted with it, the calibration does not predict held-out regions of '
               'joint space better beyond noise, or is worse in a held-out fold')
    return not_recommended(diag, why)


def recorded_covariates(data: Measurements) -> dict[str, tuple[np.ndarray, str]]:
    """The covariates the measurements carry for the residual analysis: each temperature
    sensor's reading (``temperature.<frame id>``, °C; ΔT is the same input shifted) and every
    measured input (a tilt, a payload mass, any recorded quantity; measured torques are the
    rows' torques, analysed as such), each with its unit
    (:func:`~kpi_calib_ros.core.measurement.covariates.measured_covariates`)."""
    return measured_covariates(data.covariates)


def with_misfit_answer(cd: CellDiagnosis,
                       covariates: Mapping[str, tuple[np.ndarray, str]] | None = None
                       ) -> CellDiagnosis:
    """``cd`` with the residual analysis of its calibration (each joint, gravity torque,
    tracker distance, time, reflector and ``covariates``, :mod:`~kpi_calib_ros.core.
    residual_analysis`) and the four answers (:func:`~kpi_calib_ros.core.diagnosis.misfit.
    answer_misfit`). Covariates are given per given measurement, the kept ones analysed."""
    keep = np.ones(len(cd.data), bool) if cd.kept is None else cd.kept
    kept_covariates = {name: (np.asarray(values)[keep], unit)
                       for name, (values, unit) in (covariates or {}).items()}
    analysis = analyse_calibration(cd.model, cd.data, cd.result, kept_covariates)
    return with_remedies(dataclasses.replace(
        cd, residual_analysis=analysis, diagnosis=recording_first(cd.diagnosis, analysis)))


JOINT_READINGS = ' The joint readings may be the cause:'


def recording_first(diag: Diagnosis, analysis: ResidualAnalysis) -> Diagnosis:
    """``diag`` whose verdict names a recording where the residual analysis puts the most
    of the misfit on one (its one-hot input first and significant) instead of the
    joint-reading noise it offers when no effect explains the misfit: a station whose
    points were 184 ppm larger (a day 8 K warmer) explained 57 % of the misfit while the
    headline sent the user to state noise.joint_sigma, which would have hidden it."""
    top = analysis.scores[0] if analysis.scores else None
    if (top is None or not top.significant or not top.name.startswith(RECORDING_PREFIX)
            or JOINT_READINGS not in diag.verdict):
        return diag
    head = diag.verdict.split(JOINT_READINGS)[0]
    name = top.name[len(RECORDING_PREFIX):]
    return dataclasses.replace(diag, verdict=(
        f'{head} Recording {name!r} differs from the others: it alone explains '
        f'{top.share:.0%} of the held-out misfit'
        + (f' ({top.region})' if top.region else '') + '; a set-up of its own (a station\'s '
        'scale or a warmer day, a placement that moved while measured, a probe remounted): '
        'validate each recording against a calibration of the others, and identify it '
        'apart if it stays apart.'))


def with_remedies(cd: CellDiagnosis, general: Sequence[Remedy] = ()) -> CellDiagnosis:
    """``cd`` with its four answers given the named effect of its screen and the
    ``general`` remedies (a learned residual, general effects; :func:`~kpi_calib_ros.core.
    misfit.answer_misfit`)."""
    diag = cd.diagnosis
    return dataclasses.replace(cd, answer=answer_misfit(
        cd.residual_analysis, named_remedy(diag, cd.comparison), general,
        chi2_adequate=diag.residuals.adequate, model_adequate=diag.model_adequate,
        tcp_estimable=cd.tcp_estimable))


def learned_remedy(choice: ResidualChoice) -> Remedy | None:
    """The learned residual as a remedy when its cross-validated test chose it: its
    command and the held-out error of the calibrated model without and with it."""
    if not choice.chosen:
        return None
    return Remedy(GENERAL, 'a learned residual (a Gaussian process of the misfit over joint '
                           'space): the misfit is smooth in the joints but no effect of the '
                           'library has its shape',
                  'kpi-calib identify --learned-residual', choice.cv_rms_physical_m,
                  choice.cv_rms_learned_m, f'before: the calibrated model\'s residuals, '
                  'fitted with these poses; after: with the learned residual refitted '
                  f'without each of {choice.folds} pose folds')


def named_remedy(diag: Diagnosis, comparison: ModelComparison | None = None
                 ) -> Remedy | None:
    """The screen's significant named effect as a remedy: its option and the held-out
    error before/after (of the full refit when ``comparison`` has it, else of the screen's
    fit); None when no effect is significant, or when the refit does not predict held-out
    regions of joint space better (``comparison.holds_elsewhere``)."""
    best = diag.best
    if best is None:
        return None
    if comparison is not None and not comparison.holds_elsewhere:
        # Lower where measured but not where the robot works next: not a remedy.
        return None
    if comparison is not None:
        return Remedy(NAMED, f'{best.spec}: {best.explanation}', f'--effects {best.spec}',
                      comparison.validation_rms_before_m, comparison.validation_rms_after_m,
                      'refit with the effect, the diagnosis\'s cross-validation')
    return Remedy(NAMED, f'{best.spec}: {best.explanation}', f'--effects {best.spec}',
                  diag.validation_rms_m, best.validation_rms_after_m,
                  'screening fit, the diagnosis\'s cross-validation')


def diagnose_and_report(cm: CellModel, data: Measurements, out_dir: str | Path, folds: int = 0,
                        alpha: float = ADEQUACY_ALPHA, model: str | None = None,
                        progress: Callable[[str], None] | None = None,
                        recording_names: Sequence[str] = ()
                        ) -> tuple[CellDiagnosis, ResidualChoice | None, str, Path]:
    """Diagnose ``data`` and write the report, the command line's and the node's alike.

    When the model is not adequate and the TCP estimable, the learned residual is one more
    remedy (:func:`kpi_calib_ros.app.learned_residual.choose_residual`): proposed when it
    predicts held-out regions better, its plot drawn.

    Returns
    -------
    cd : CellDiagnosis
        With the learned remedy among its remedies when chosen.
    choice : ResidualChoice or None
        The learned residual's decision; None when not asked or refused.
    refused : str
        Why the learned residual was not tried on these rows ('' when it was or not asked).
    report : Path
        The written ``report.md``.
    """
    cd = diagnose_cell(cm, data, folds=folds, alpha=alpha, model=model, progress=progress,
                       recording_names=recording_names)
    choice, refused = None, ''
    if cd.tcp_estimable and not is_adequate(cd.result.p_value, alpha):
        # Beside the library's answer (or when it has none): would the learned residual
        # predict held-out poses better than the calibrated model? It is one more remedy
        # of the four answers.
        refused = too_many_rows(cm, cd.data)
        choice = None if refused else choose_residual(cm, cd.data, cd.result)
        learned = learned_remedy(choice) if choice is not None else None
        if learned is not None:
            cd = with_remedies(cd, (learned,))
    report = write_report(out_dir, cd)
    if choice is not None:
        write_learned_residual_plot(out_dir, choice.model, choice.chosen)
    return cd, choice, refused, report


def run_diagnose(cell_path: str | Path, bag_path: str | Path, out_dir: str | Path,
                 effects: str = '', folds: int = 0, alpha: float = ADEQUACY_ALPHA,
                 model: str | None = None, **options: Any) -> int:
    """``kpi-calib diagnose``: diagnosis.json, report.md and plots in ``out_dir``
    (checked first); ``model`` overrides the cell's ``identification.model``; ``options``
    as for :func:`load_measurements`. When the model is not adequate, the learned
    residual's decision on the calibrated model is printed too
    (:func:`kpi_calib_ros.app.learned_residual.choose_residual`). The verdict is printed
    first; identify's outlier rounds follow on stderr. Returns 0, or 1 when the TCP is not
    estimable from the measurements (as identify does; no expected error is stated)."""
    writable_folder(out_dir, '--out')
    cm, data, _ = load_measurements(cell_path, bag_path, effects, **options)
    # The exclusion rounds come before the verdict in time, not in importance: kept and
    # printed after it.
    rounds: list[str] = []
    cd, choice, refused, report = diagnose_and_report(cm, data, out_dir, folds=folds,
                                                      alpha=alpha, model=model,
                                                      progress=rounds.append,
                                                      recording_names=bag_recording_names(
                                                          bag_path))
    print(diagnosis_text(cd), flush=True)
    for line in rounds:
        print_progress(line)
    if refused:
        print(refused)
    if choice is not None:
        print(choice.reason + ('; kpi-calib identify --learned-residual writes it beside '
                               'calibration.yaml' if choice.chosen else ''))
    print(f'written: {Path(out_dir) / DIAGNOSIS_FILE}, {report}')
    return 0 if cd.tcp_estimable else 1

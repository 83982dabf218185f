"""The learned residual of a calibration: chosen, stored beside calibration.yaml, and the
TCP predicted with it (the CLI's ``identify --learned-residual`` and the node's
``~/tcp_query``).

See :mod:`kpi_calib_ros.core.diagnosis.learned_residual` for the model and its choice; this module
feeds it the point rows of a calibration, makes learned_residual.yaml and predicts the
TCP at joint values with both parts of its uncertainty.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import scipy.stats

from kpi_calib_ros.app.cell_model import CellModel, build_cell_model
from kpi_calib_ros.core.diagnosis.corrected_tcp import CorrectedTcp, corrected_tcp
from kpi_calib_ros.core.diagnosis.learned_residual import (
    MAX_TRAINING_ROWS,
    LearnedResidual,
    ResidualChoice,
    field_parameter_covariance,
    fit_learned_residual,
    residual_noise_scale,
)
from kpi_calib_ros.core.diagnosis.shared_error import (
    joint_test_points,
    shared_error_test,
    statement_covariance,
)
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA, linearized_fit
from kpi_calib_ros.core.measurement import weighting
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.pose import pose_matrix
from kpi_calib_ros.core.measurement.recordings import to_first_frame
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import row_torques
from kpi_calib_ros.core.model.parameters import BASE_COMPONENTS
from kpi_calib_ros.io.learned_residual_file import (
    StoredResidual,
    read_residual,
    residual_document,
    residual_text,
)
from kpi_calib_ros.io.names import LEARNED_RESIDUAL_FILE


def point_rows(model: MeasurementModel, data: Measurements) -> np.ndarray:
    """(N,) bool: the rows of ``data`` that are points (not rotation rows), every row
    named (:func:`~kpi_calib_ros.core.measurement.weighting.point_rows`)."""
    rows = weighting.point_rows(data.reflector, model.n_reflectors)
    return np.ones(len(data), bool) if rows is None else rows


def too_many_rows(cm: CellModel, data: Measurements) -> str:
    """Why no learned residual is fitted on ``data`` ('' : one is): more point rows than
    :data:`~kpi_calib_ros.core.diagnosis.learned_residual.MAX_TRAINING_ROWS`."""
    rows = int(np.count_nonzero(point_rows(cm.model, data)))
    if rows <= MAX_TRAINING_ROWS:
        return ''
    return (f'learned residual not fitted: {rows} point measurements, more than the '
            f'{MAX_TRAINING_ROWS} a learned residual is fitted on (its cost grows with the '
            'cube of their number); identify --learned-residual on fewer poses')


def choose_residual(cm: CellModel, data: Measurements, result: CalibrationResult,
                    seed: int = 0) -> ResidualChoice:
    """Fit and decide the learned residual on ``result``'s residuals of ``data`` (the
    measurements it was identified from, outliers excluded), its point rows only; with
    several recordings each one's residuals turned into the first's tracker frame."""
    rows = point_rows(cm.model, data)
    # Several recordings: every residual in the first recording's tracker frame, where the
    # field is stored and predicted (core.measurement.recordings).
    residuals = to_first_frame(cm.model, result.values, data, result.residuals)
    return fit_learned_residual(np.atleast_2d(data.q)[rows], residuals[rows],
                                cm.cell.sigma, tuple(cm.robot.joint_names), seed=seed)


def physical_covariance(result: CalibrationResult, residual: LearnedResidual | None,
                        sigma: float | np.ndarray) -> np.ndarray:
    """(k, k) covariance of ``result.estimated``: as reported without a learned residual;
    with one, from the stated σ scaled by the noise the learned residual leaves (the
    misfit it explains no longer inflates it)."""
    if residual is None:
        return np.asarray(result.covariance, float)
    return (np.asarray(result.covariance, float) / result.covariance_scale
            * residual_noise_scale(residual, sigma))


def field_covariance(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                     residual: LearnedResidual, sigma: float | np.ndarray) -> np.ndarray:
    """(k, k) covariance of ``result.estimated`` when the misfit is ``residual``'s field
    (:func:`kpi_calib_ros.core.diagnosis.learned_residual.field_parameter_covariance`),
    from the point rows of ``data``, the measurements ``result`` was identified from."""
    fit = linearized_fit(model, data, result)
    weighted = fit.jac.reshape(len(data), 3, -1)  # W_i J_i
    w = np.asarray(fit.w, float)
    if w.ndim == 3:
        h = np.einsum('nba,nbk->nak', w, weighted)
    else:
        h = np.broadcast_to(w, (len(data), 3))[:, :, None] * weighted
    rows = point_rows(model, data)
    c0 = np.asarray(result.covariance, float) / result.covariance_scale
    return field_parameter_covariance(residual, np.atleast_2d(data.q)[rows], h[rows], c0,
                                      residual_noise_scale(residual, sigma))


def predict_tcp(model: MeasurementModel, values: np.ndarray, estimated: tuple[str, ...],
                covariance: np.ndarray, residual: LearnedResidual | None,
                q: np.ndarray, covariance_outside: np.ndarray | None = None,
                reflector: np.ndarray | None = None,
                covariates: Mapping[str, np.ndarray] | None = None,
                tau: np.ndarray | None = None) -> CorrectedTcp:
    """The TCP (KPI point) at URDF joint values ``q`` (M, n): the physical model at
    ``values`` plus the learned residual, with the covariance of both parts
    (:func:`kpi_calib_ros.core.diagnosis.corrected_tcp.corrected_tcp`). With
    ``reflector`` (M,) the measured points instead, at their ``covariates``. ``tau`` (M, n):
    the joint torques the effects read (a working pose's payload, measured efforts); None:
    the gravity torques with the ``covariates``' payload, else the cell's."""
    q = np.atleast_2d(np.asarray(q, float))
    tcp, jac = model.jacobian(np.asarray(values, float), q, tau, reflector,
                              covariates=covariates)
    idx = model.params.indices(list(estimated))
    return corrected_tcp(tcp, jac[:, :, idx], covariance, q, residual, covariance_outside)


def stored_cell_model(cm: CellModel, stored: StoredResidual) -> CellModel:
    """The cell model ``stored`` corrects: ``cm`` when it has the stored effects, else
    ``cm``'s cell with them (the cell's and those ``identification.model: auto`` added),
    as ``validate`` rebuilds a calibration's model; ConfigError unless its parameters are
    the stored ones (:meth:`StoredResidual.check_model`)."""
    if tuple(e.name for e in cm.model.effects) != stored.effects:
        cm = build_cell_model(cm.cell, effects=stored.effects)
    stored.check_model(cm.model)
    return cm


def predict_stored(model: MeasurementModel, stored: StoredResidual, q: np.ndarray,
                   reflector: np.ndarray | None = None,
                   covariates: Mapping[str, np.ndarray] | None = None,
                   tau: np.ndarray | None = None) -> CorrectedTcp:
    """:func:`predict_tcp` with a learned_residual.yaml read back, ``model`` the one it
    was written for (:func:`stored_cell_model`)."""
    stored.check_model(model)
    return predict_tcp(model, stored.values, stored.estimated, stored.covariance,
                       stored.residual, q, stored.covariance_outside, reflector, covariates,
                       tau)


def validate_learned(cm: CellModel, stored: StoredResidual, data: Measurements,
                     alpha: float = ADEQUACY_ALPHA) -> dict[str, Any]:
    """Does the learned residual predict a new recording within its own uncertainty?

    Every point of ``data`` is predicted by the physical model ``stored`` corrects plus the
    learned δ(q), with the covariance it states (parameters, δ's latent variance and the
    noise it leaves, w · N). Returns a YAML-ready dict (m): the rms with and without δ, the
    share of the points inside their stated 95 % ellipsoid and of the poses inside the
    fitted region, and the points' χ² with two p-values: as if the points were independent
    (``p_value_independent``) and under the joint statement, in which they share the
    parameters' error and the learned field
    (:func:`kpi_calib_ros.core.diagnosis.shared_error.shared_error_test`, on at most
    :data:`~kpi_calib_ros.core.diagnosis.shared_error.MAX_POINTS` points: ``p_value``, the
    independent points the recording is worth, and the range of the share over recordings
    that agree with the statement). ``holds`` when ``p_value`` ≥ ``alpha``. A recording of
    another day, in which the arm changed by more than the training session showed, fails
    it: the learned residual is then to be learned again on the conditions it is used in.
    """
    model = stored_cell_model(cm, stored).model
    rows = point_rows(model, data)
    new = data.subset(rows)
    if len(new) == 0:
        raise DataError('no point measurement to validate the learned residual on')
    tau = row_torques(model, new)  # the rows' own: measured efforts, or their payloads
    tcp = predict_stored(model, stored, new.q, new.reflector, new.covariates, tau)
    assert tcp.correction is not None
    error = np.atleast_2d(new.eta) - tcp.position
    noise = stored.residual.noise_covariance_m2
    cov = tcp.covariance + noise
    m2 = np.einsum('mi,mij,mj->m', error, np.linalg.inv(cov), error)
    chi2, dof = float(np.sum(m2)), 3 * len(new)
    subset = joint_test_points(len(new))
    tested = new.subset(subset)
    _, jac = model.jacobian(stored.values, tested.q,
                            None if tau is None else np.atleast_2d(tau)[subset],
                            tested.reflector, covariates=tested.covariates)
    joint = statement_covariance(jac[:, :, model.params.indices(list(stored.estimated))],
                                 stored.covariance, np.atleast_2d(tested.q), stored.residual,
                                 stored.covariance_outside, noise)
    shared = shared_error_test(error[subset], joint)

    def rms(e: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))
    return {'file': LEARNED_RESIDUAL_FILE, 'points': int(len(new)),
            'rms_m': rms(error), 'rms_physical_m': rms(error + tcp.correction.mean),
            'inside_95_share': float(np.mean(m2 <= scipy.stats.chi2.ppf(0.95, 3))),
            'inside_fitted_region_share': float(np.mean(tcp.correction.inside)),
            'chi2': chi2, 'dof': dof,
            'p_value_independent': float(scipy.stats.chi2.sf(chi2, dof)),
            'tested_points': shared.points, 'effective_points': shared.effective_points,
            'inside_95_share_range': list(shared.share_range),
            'p_value': shared.p_value, 'alpha': alpha, 'holds': bool(shared.p_value >= alpha)}


def learned_validation_text(doc: dict[str, Any]) -> str:
    """A terminal line of :func:`validate_learned`'s figures."""
    verdict = ('its uncertainty holds' if doc['holds'] else
               'its uncertainty does NOT hold on this recording: the arm differs from the '
               'training session by more than that session showed, or too few poses taught '
               'it; learn it again, on more poses, in the conditions it is used in')
    low, high = doc['inside_95_share_range']
    return (f"with the learned residual ({doc['file']}): rms {doc['rms_m'] * 1e3:.3f} mm "
            f"(physical model {doc['rms_physical_m'] * 1e3:.3f} mm); "
            f"{doc['inside_95_share']:.1%} of the points inside their stated 95 % ellipsoid "
            f"(a recording that agrees with the statement: {low:.1%} to {high:.1%}), "
            f"{doc['inside_fitted_region_share']:.0%} inside its fitted region; chi2/dof = "
            f"{doc['chi2']:.1f}/{doc['dof']}; the points share the parameters' error and the "
            f"learned field, {doc['tested_points']} tested are worth "
            f"{doc['effective_points']:.0f} independent ones: p = {doc['p_value']:.3g} "
            f"(as if independent {doc['p_value_independent']:.3g}): {verdict}")


def learned_residual_section(doc: dict[str, Any], cm: CellModel, data: Measurements,
                             result: CalibrationResult, seed: int = 0
                             ) -> tuple[str, str | None]:
    """Choose the learned residual for a calibration.

    Adds ``learned_residual`` to the calibration document ``doc``: the choice with its
    figures and, when chosen, the TCP at every working pose with the correction, its
    covariance and std (parameter part and learned part) and whether the pose lies inside
    the fitted region. Returns the summary text and, when chosen and ``doc`` is valid,
    learned_residual.yaml's text (``section.file`` names it), else None.
    """
    refused = too_many_rows(cm, data)
    if refused:
        doc['learned_residual'] = {'chosen': False, 'reason': refused, 'file': None}
        return refused, None
    choice = choose_residual(cm, data, result, seed)
    section: dict[str, Any] = {**choice.to_dict(), 'file': None}
    lines = [choice.reason]
    content = None
    if choice.chosen:
        cov = physical_covariance(result, choice.model, cm.cell.sigma)
        outside = field_covariance(cm.model, data, result, choice.model, cm.cell.sigma)
        tcp = predict_tcp(cm.model, result.values, result.estimated, cov, choice.model,
                          cm.q_work, outside, tau=cm.tau_work)
        section['tcp'] = tcp_entries(cm.working_pose_names, tcp)
        joints = ', '.join(f'{n} {v:.3g}' for n, v in
                           list(choice.model.relevant_joints().items())[:3])
        lines.append(f'learned residual: amplitude {np.sqrt(choice.model.amplitude_m2) * 1e6:.1f}'
                     f' um, noise left {np.sqrt(choice.model.noise_m2) * 1e6:.1f} um, shortest '
                     f'length scales {joints}')
        for name, entry in section['tcp'].items():
            where = 'inside' if entry['inside_fitted_region'] else 'OUTSIDE'
            lines.append(f"TCP {name} with the learned residual: correction "
                         f"{np.linalg.norm(entry['correction_m']) * 1e6:.1f} um, std "
                         f"{entry['std_m'] * 1e6:.1f} um (parameter part "
                         f"{entry['parameter_std_m'] * 1e6:.1f} um), {where} the fitted region "
                         f"(distance {entry['distance']:.2g} length scales)")
        if doc.get('valid', True):
            content = residual_text(residual_document(
                choice, result, cov, outside, [e.name for e in cm.model.effects]))
            section['file'] = LEARNED_RESIDUAL_FILE
    doc['learned_residual'] = section
    return '\n'.join(lines), content


def tcp_entries(names: tuple[str, ...] | list[str], tcp: CorrectedTcp) -> dict[str, Any]:
    """YAML-ready TCP predictions with the learned residual, by working pose name (m)."""
    out = {}
    corr = tcp.correction
    for i, name in enumerate(names):
        out[name] = {
            'position_m': [float(x) for x in tcp.position[i]],
            'covariance_m2': np.asarray(tcp.covariance[i]).tolist(),
            'std_m': float(tcp.std_m[i]),
            'parameter_std_m': float(np.sqrt(np.trace(tcp.physical_covariance[i]))),
            'correction_m': [float(x) for x in corr.mean[i]] if corr is not None else None,
            'distance': float(corr.distance[i]) if corr is not None else None,
            'inside_fitted_region': bool(corr.inside[i]) if corr is not None else False}
    return out


def learned_section(cm: CellModel, p: np.ndarray, path: Path, data: Measurements,
                    registered: np.ndarray | None = None) -> dict[str, Any]:
    """The learned residual at ``path`` validated on ``data``, or why it was not.

    One written for another calibration than ``p`` (:meth:`~kpi_calib_ros.io.
    learned_residual_file.StoredResidual.other_calibration`) is skipped, said why.
    ``registered``: the values after ``--register`` re-fitted the placement on ``data``. The
    learned field lives in the robot's joint space and moves with the robot: the new points
    are carried into the calibration's tracker frame by the registered base pose relative
    to the calibration's (:func:`carried_residual`) and predicted there.
    """
    stored = read_residual(path, 'learned residual')
    other = stored.other_calibration(cm.model.params.names, p)
    if other:
        return {'file': path.name, 'skipped': f'not validated: {other}'}
    if registered is not None:
        stored, data = carried_residual(cm, stored, p, registered, data)
    return validate_learned(cm, stored, data)


def carried_residual(cm: CellModel, stored: StoredResidual, p: np.ndarray,
                     registered: np.ndarray, data: Measurements
                     ) -> tuple[StoredResidual, Measurements]:
    """``stored`` (written for the calibration ``p``) and ``data`` (measured in a set-up
    registered as ``registered``) in the calibration's own tracker frame.

    The points move rigidly by T_cal T_newᵀ (the base poses in the tracker frame); the
    stored values keep the calibration's base and take the registered rest (a remounted
    probe's offsets). The learned field, its parameters' covariance and its statement are
    then those it was written with, whatever the turn of the new station. Turning the
    field and propagating the calibration's base covariance at the new placement instead
    made the statement grow with the turn (0.38 mm per axis at the calibration's own
    station, 23.5 mm turned by 1 rad), so that "its uncertainty holds" could not fail.
    """
    base = cm.model.params.indices([f'base.{c}' for c in BASE_COMPONENTS])
    move = (pose_matrix(np.asarray(p, float)[base])
            @ np.linalg.inv(pose_matrix(np.asarray(registered, float)[base])))
    values = np.asarray(registered, float).copy()
    values[base] = np.asarray(p, float)[base]
    eta = np.atleast_2d(np.asarray(data.eta, float)) @ move[:3, :3].T + move[:3, 3]
    return dataclasses.replace(stored, values=values), dataclasses.replace(data, eta=eta)


def learned_file(calibration_path: str | Path) -> Path | None:
    """The learned_residual.yaml written beside ``calibration_path``, if there is one."""
    path = Path(calibration_path).parent / LEARNED_RESIDUAL_FILE
    return path if path.is_file() else None


__all__ = ['carried_residual', 'choose_residual', 'field_covariance', 'learned_file',
           'learned_residual_section', 'learned_section', 'learned_validation_text',
           'physical_covariance', 'point_rows', 'predict_stored', 'predict_tcp',
           'stored_cell_model', 'tcp_entries', 'too_many_rows', 'validate_learned']

"""Identification: from recorded or live samples to a calibration, the one path every
front end uses.

The CLI (`kpi-calib identify`), the ROS node and the demo all call these
functions, so a bag replayed into the node and the same bag identified offline
give the same numbers.
"""
from __future__ import annotations

import dataclasses
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.covariates import (
    TemperatureSample,
    temperature_covariates,
    with_covariates,
)
from kpi_calib_ros.core.dh import dh_table
from kpi_calib_ros.core.diagnosis import augmented_model, compare_models
from kpi_calib_ros.core.effect_selection import choose_effects
from kpi_calib_ros.core.effects import BoundEffect, parse_effect_spec, split_specs
from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.estimability import KpiEstimability, result_estimability
from kpi_calib_ros.core.estimation import CalibrationResult, identify
from kpi_calib_ros.core.gravity_compliance import compliance_warnings, mass_warning
from kpi_calib_ros.core.measurement import MeasurementModel, Measurements, with_rotation_rows
from kpi_calib_ros.core.model_selection import ModelChoice, choose_model, level_free
from kpi_calib_ros.core.pairing import PairingResult, pair_measurements, split_frame
from kpi_calib_ros.core.precision import (
    ExpectedTcpError,
    balanced_prior,
    expected_tcp_error,
    honest_precision,
)
from kpi_calib_ros.core.prior import Prior, tolerance_prior
from kpi_calib_ros.core.registration import Registration, register
from kpi_calib_ros.core.robust import (
    LOSS_SCALE,
    ExcludedMeasurement,
    RobustResult,
    gross_outliers,
    robust_identify,
    subset,
)
from kpi_calib_ros.core.streams import JointSample, PointSample
from kpi_calib_ros.io.bag import read_for_pairing, read_temperatures
from kpi_calib_ros.io.cell import CellModel, build_cell_model, load_cell
from kpi_calib_ros.io.measurement_log import stored_pairing
from kpi_calib_ros.io.names import CALIBRATED_URDF_FILE, FAILED_CALIBRATION_FILE
from kpi_calib_ros.io.report import comparison_text, comparison_to_dict
from kpi_calib_ros.io.results import (
    calibration_to_dict,
    summary_text,
    writable_folder,
    write_atomic,
    write_calibration,
)
from kpi_calib_ros.io.urdf_export import calibrated_urdf

# Geometric errors of a robot and a surveyed placement move the predicted points by
# millimetres to a centimetre or two (a base yaw of 4 mrad at 3 m is 12 mm); the
# identification absorbs that itself. A nominal placement that misses the points by
# more (median, m) is a wrong or unknown placement: register it first.
REGISTER_ABOVE_M = 0.05
# The registered nominal points may still miss by the robot's geometric errors; far
# more (rms, m) means the model cannot explain the data (units, joint order, tip frame).
REGISTRATION_MAX_RMS_M = 0.02


def measurements_from_samples(cm: CellModel, joint_samples: Iterable[JointSample],
                              point_samples: Iterable[PointSample],
                              point_sigma: Mapping[tuple[int, str], np.ndarray] | None = None,
                              **pairer_options) -> tuple[Measurements, PairingResult]:
    """Pair tracker points with still joint states, matching joints by name; the points'
    stated σ by (stamp ns, frame id), if any, weigh their rows (:func:`to_measurements`).

    Raises
    ------
    DataError
        When no point could be paired because the joint states lack the
        chain's joints (wrong robot or renamed joints): names both sets.
    """
    joint_samples = list(joint_samples)
    pairer_options.setdefault('reflectors', reflector_names(cm))
    pairing = pair_measurements(joint_samples, point_samples, cm.joint_names,
                                cm.cell.tracker_frame, **pairer_options)
    if len(pairing) == 0 and pairing.rejections.get('missing_joints'):
        seen = sorted({n for s in joint_samples for n in s.names})
        raise DataError(f'the joint states name joints {seen}, but the robot chain needs '
                        f'{cm.joint_names}; record the right robot or fix the URDF joint names')
    return urdf_measurements(cm, to_measurements(cm, pairing, point_sigma)), pairing


def urdf_measurements(cm: CellModel, data: Measurements) -> Measurements:
    """``data`` (paired joint states and points) with its joint values mapped from the
    controller's readings to the URDF chain (``robot.joint_coupling``).

    Every path from joint states to the model (bag, measurement log, live node) goes
    through here, so coupled readings are converted once and only once.
    """
    if not len(data) or cm.joint_coupling.is_identity:
        return data
    return dataclasses.replace(data, q=cm.joint_coupling.to_urdf(data.q))


def reflector_names(cm: CellModel) -> tuple[str, ...]:
    """Reflector names points carry after '#' in their frame id ('' : single reflector)."""
    return cm.cell.reflector_names or ('',)


def to_measurements(cm: CellModel, pairing: PairingResult,
                    point_sigma: Mapping[tuple[int, str], np.ndarray] | None = None
                    ) -> Measurements:
    """(pose, reflector) rows of a pairing, reflector indices in the cell's order
    (controller joint values, as paired); ``point_sigma`` the tracker's stated σ (3,) (m)
    by (stamp ns, frame id) (:attr:`kpi_calib_ros.io.bag.BagContents.point_sigma`): a row
    without one takes the cell's noise.sigma."""
    try:
        ref = pairing.reflector_indices(reflector_names(cm))
    except ValueError as exc:
        raise DataError(f'{exc}: point frame ids are <tracker_frame>#<reflector name> for '
                        "the cell's reflectors: list") from None
    data = Measurements(q=pairing.q, eta=pairing.eta, stamps_ns=pairing.stamps_ns,
                        reflector=ref if cm.cell.reflector_names else None,
                        sigma=stated_sigma(pairing, point_sigma))
    return pose_rows(cm, data, pairing)


def stated_sigma(pairing: PairingResult,
                 point_sigma: Mapping[tuple[int, str], np.ndarray] | None) -> np.ndarray | None:
    """(N, 3) σ (m) of the pairing's rows, matched by stamp and reflector (the frame id's
    part after '#'; the tracker frame is the pairing's), NaN where none was stated; None
    when no row has one."""
    if not point_sigma:
        return None
    by_row = {(stamp, split_frame(frame)[1]): s for (stamp, frame), s in point_sigma.items()}
    names = pairing.reflectors or ('',) * len(pairing)
    rows = np.array([by_row.get((int(t), name), np.full(3, np.nan))
                     for t, name in zip(pairing.stamps_ns, names)], dtype=float).reshape(-1, 3)
    return rows if np.isfinite(rows).any() else None


def pose_rows(cm: CellModel, data: Measurements,
              pairing: PairingResult | None) -> Measurements:
    """``data`` with the rotation row of every tracked 6-DoF pose of ``pairing`` (see
    :func:`kpi_calib_ros.core.measurement.with_rotation_rows`); None: no pairing, as is."""
    if pairing is None or pairing.rotations is None:
        return data
    try:
        return with_rotation_rows(cm.model, data, pairing.rotations)
    except ValueError as exc:
        names = reflector_names(cm)
        raise DataError(f'{exc}; a PoseStamped was recorded for a reflector of the cell '
                        f'{list(names)} that has no orientation: give the tracked body\'s '
                        'orientation in the cell (reflectors[i].orientation: {rpy: [r, p, y]}) '
                        'or record its position as a PointStamped') from None


def measurements_from_bag(cm: CellModel, path: str | Path,
                          joint_topic: str | None = None,
                          point_topic: str | None = None,
                          pose_topic: str | None = None,
                          **pairer_options) -> tuple[Measurements, PairingResult]:
    """Measurements from a recording (paired here) or from the node's measurement log
    (paired when stored), reading only the joint states pairing needs. Topics default
    to the cell's ``topics:``; tracked 6-DoF poses on the pose topic add rotation rows."""
    cell = cm.cell
    contents = read_for_pairing(path, joint_topic or cell.joint_topic,
                                point_topic or cell.point_topic,
                                window_ns=pairer_options.get('window_ns'),
                                pose_topic=pose_topic or cell.pose_topic)
    if contents.measurement_log:
        pairing = stored_pairing(zip(contents.joints, contents.points), list(cm.joint_names),
                                 cm.cell.tracker_frame)
        data = urdf_measurements(cm, to_measurements(cm, pairing, contents.point_sigma))
    else:
        data, pairing = measurements_from_samples(cm, contents.joints, contents.points,
                                                  point_sigma=contents.point_sigma,
                                                  **pairer_options)
    return with_temperature(cm, data, path), pairing


def with_temperature(cm: CellModel, data: Measurements, path: str | Path) -> Measurements:
    """``data`` with the temperatures of the cell's ``temperature:`` topic in the bag
    ``path`` paired to every row by its stamp (:mod:`kpi_calib_ros.core.covariates`); rows
    without a temperature are refused with a warning. ``data`` unchanged without the
    section.

    Raises
    ------
    DataError
        The section is there but the bag has no temperature on its topic, or a listed
        sensor never published.
    """
    settings = cm.cell.temperature
    if settings is None or len(data) == 0:
        return data
    kept, refused = paired_temperature(cm, data, read_temperatures(path, settings.topic),
                                       str(path))
    if refused:
        warnings.warn(refused_text(cm, len(data), refused), stacklevel=2)
    return kept


def paired_temperature(cm: CellModel, data: Measurements, samples: Sequence[TemperatureSample],
                       where: str = 'the recording'
                       ) -> tuple[Measurements, list[tuple[int, str]]]:
    """``data`` with the temperature readings ``samples`` paired to its rows by stamp, per
    the cell's ``temperature:`` section, rows without one removed; [(row, reason)] of those.

    Raises
    ------
    DataError
        No reading at all, no stamps, or a listed sensor never published.
    """
    settings = cm.cell.temperature
    assert settings is not None
    if not samples:
        raise DataError(f"{where}: no sensor_msgs/Temperature on '{settings.topic}' "
                        '(temperature.topic in the cell file); record it, or remove the '
                        'temperature: section')
    if data.stamps_ns is None:
        raise DataError('the measurements carry no stamps to pair temperatures with')
    try:
        cov = temperature_covariates(data.stamps_ns, samples, settings.sensors,
                                     settings.reference_c, settings.max_gap_ns)
    except ValueError as exc:
        raise DataError(f'temperature.sensors: {exc}') from None
    return with_covariates(data, cov)


def refused_text(cm: CellModel, total: int, refused: list[tuple[int, str]]) -> str:
    """One line on the rows refused for want of a temperature."""
    gap = cm.cell.temperature.max_gap_s if cm.cell.temperature else float('nan')
    return (f'{len(refused)} of {total} measurement rows refused: {refused[0][1]} '
            f'(temperature.max_gap = {gap:g} s)')


def places_the_points(cm: CellModel, data: Measurements, p: np.ndarray) -> bool:
    """Do parameters ``p`` predict ``data`` within :data:`REGISTER_ABOVE_M` (median miss)?
    If not, the placement is registered from the points before fitting."""
    tau = cm.robot.gravity_torques(data.q) if cm.model.uses_torque else None
    miss = np.linalg.norm(np.atleast_2d(data.eta)
                          - cm.model.predict(p, data.q, tau, data.reflector, data.rotation,
                                           data.covariates),
                          axis=1)
    return float(np.median(miss)) <= REGISTER_ABOVE_M


def registered_start(cm: CellModel, data: Measurements) -> tuple[np.ndarray, Registration | None]:
    """Start parameters for identification, with the placement registered when needed.

    The cell's nominal values, except when ``tracker.base_in_tracker`` or a reflector
    offset is left out of the cell, or the nominal prediction misses the measured points
    by more than :data:`REGISTER_ABOVE_M` (median): then the base pose in the tracker
    frame and every reflector offset on the tip are registered from the points
    (:func:`kpi_calib_ros.core.registration.register`) and replace the nominal ones.
    Returns the start vector and the registration (None if not run).

    Raises
    ------
    DataError
        The registered nominal points still miss by more than :data:`REGISTRATION_MAX_RMS_M`
        rms: the message gives the distances and the likely causes (units, joint
        order, tip frame).
    """
    params = cm.model.params
    p0 = np.array(params.nominal, dtype=float)
    if not cm.needs_registration and len(data) and places_the_points(cm, data, p0):
        return p0, None
    if data.reflector is not None:  # rotation rows (tracked poses) carry no point
        data = data.subset(np.asarray(data.reflector) < cm.model.n_reflectors)
    tips = np.array([cm.robot.pin_tip_pose(row) for row in np.atleast_2d(data.q)])
    reg = register(data.eta, tips, max_rms=REGISTRATION_MAX_RMS_M, reflector=data.reflector)
    offsets = (reg.reflector_offsets if reg.reflector_offsets is not None
               else reg.reflector_offset.reshape(1, 3))
    values = {f'base.{c}': float(v) for c, v in
              zip(('x', 'y', 'z', 'roll', 'pitch', 'yaw'), reg.base_in_tracker)}
    prefixes = [f'reflector.{n}' for n in cm.cell.reflector_names] or ['reflector']
    for prefix, offset in zip(prefixes, offsets):
        values.update({f'{prefix}.{c}': float(v) for c, v in zip('xyz', offset)})
    return params.with_values(values), reg


def registration_text(reg: Registration | None, cm: CellModel) -> str:
    """One readable line on the placement the identification started from."""
    if reg is None:
        return 'placement: the cell\'s tracker.base_in_tracker and reflector.offset'
    why = ('left out of the cell' if cm.needs_registration
           else f'the nominal missed the points by more than {REGISTER_ABOVE_M} m')
    return (f'placement registered from the points ({why}): base_in_tracker '
            f'{np.round(reg.base_in_tracker, 5).tolist()}, reflector offset '
            f'{np.round(reg.reflector_offset, 5).tolist()} m, registered miss '
            f'{reg.rms_m * 1e3:.3g} mm rms'
            + (f'; measurements {list(reg.trimmed)} missed by far more and were left out of '
               'the registration' if reg.trimmed else ''))


def cell_prior(cm: CellModel) -> Prior | None:
    """The tolerance prior of the cell's ``identification.prior`` (None when not set)."""
    tol = cm.cell.identification.prior
    if tol is None:
        return None
    return tolerance_prior(cm.model.params, *tol, n_geometric=len(cm.geometric))


def tolerance_text(cm: CellModel, scale: float = 1.0) -> str:
    """One line on the cell's tolerance prior and its balance against the data ('' when
    the cell has none)."""
    tol = cm.cell.identification.prior
    if tol is None:
        return ''
    text = ('prior: nominal tolerances (translation, rotation, offset std) '
            f'{list(tol)} (identification.prior)')
    if scale != 1.0:
        text += (f'; weighed against the data at the noise they show, {np.sqrt(scale):.3g} x '
                 f'the stated sigma (chi2/dof {scale:.3g} at the balance): with the stated '
                 'sigma the data would outweigh the tolerances that much more')
    return text


def identify_cell(cm: CellModel, data: Measurements, p0: np.ndarray | None = None,
                  free: list[str] | None = None, prior: Prior | None = None
                  ) -> CalibrationResult:
    """Identify the cell's parameters from paired measurements (σ and poses from the cell).

    Without ``p0`` the start is :func:`registered_start`: an unknown or far-off
    placement is registered from the data first. Covariances come from the stated σ when
    the χ² test accepts the model, else they are scaled by χ²/dof
    (``result.covariance_scale``, see :mod:`kpi_calib_ros.core.precision`). ``prior``
    defaults to the cell's :func:`cell_prior`, weighed against the noise the data show
    (:func:`kpi_calib_ros.core.precision.balanced_prior`).
    """
    if len(data) == 0:
        raise DataError('no accepted measurement to identify from')
    if p0 is None:
        p0 = registered_start(cm, data)[0]
    tolerance = cell_prior(cm) if prior is None else None
    result = _fit_function(cm, p0, prior or tolerance, balance=tolerance is not None)(
        data, free or list(cm.model.params.names))
    # A model that fails χ² must not report the stated σ's precision (core.precision).
    return honest_precision(result)


@dataclass(frozen=True)
class CellCalibration:
    """A calibration with its model choice, robust statistics and KPI estimability.

    ``valid`` is what may be published as the calibration: converged and the TCP estimable
    at every working pose; ``problems`` says why not.
    """

    result: CalibrationResult
    robust: RobustResult
    choice: ModelChoice
    estimability: KpiEstimability
    free: tuple[str, ...]
    registration: Registration | None = None
    # The cell's tolerance prior was tightened by this factor: the data weighed at the
    # noise they show, √prior_scale × the stated σ (core.precision.balanced_prior).
    prior_scale: float = 1.0
    # The cell model the result belongs to: the given one with the effects ``auto`` added
    # (core.effect_selection); documents and the calibrated URDF are written with it.
    cell: CellModel | None = None
    # Expected TCP error at the working poses with the misfit included (core.precision).
    expected: ExpectedTcpError | None = None

    @property
    def problems(self) -> tuple[str, ...]:
        out = []
        if not self.result.converged:
            out.append(f'identification did not converge: {self.result.message}')
        if not self.estimability.all_estimable:
            out.append(self.estimability.summary())
        return tuple(out)

    @property
    def valid(self) -> bool:
        return not self.problems


def _fit_function(cm: CellModel, start: np.ndarray | None = None,
                  prior: Prior | None = None, balance: bool = False,
                  scales: list[float] | None = None):
    """``fit(data, free, p0=None, point_weights=None)``: identify with the cell's settings
    and ``prior``, from ``start`` (e.g. the registered placement) when no ``p0`` is given.
    ``balance``: ``prior`` is a tolerance prior, tightened for every fit by the noise
    scale its data show (:func:`kpi_calib_ros.core.precision.balanced_prior`), the scale
    appended to ``scales``."""
    def fit(d: Measurements, free: list[str], p0: np.ndarray | None = None,
            point_weights: np.ndarray | None = None) -> CalibrationResult:
        def with_prior(pr: Prior | None) -> CalibrationResult:
            return identify(cm.model, d, cm.cell.sigma, cm.q_work, list(cm.working_pose_names),
                            p0=start if p0 is None else p0, free=free,
                            identifiability_method=cm.cell.identification_method,
                            priority=list(cm.cell.identification_priority) or None,
                            point_weights=point_weights, prior=pr,
                            max_iterations=cm.cell.identification.max_iterations)
        if not balance or prior is None:
            return with_prior(prior)
        _, scale, result = balanced_prior(with_prior, prior)
        if scales is not None:
            scales.append(scale)
        return result
    return fit


def choose_level(cm: CellModel, data: Measurements, model: str | None = None,
                 start: np.ndarray | None = None, prior: Prior | None = None,
                 fit: Callable[..., CalibrationResult] | None = None) -> ModelChoice:
    """The model level to identify: ``model`` or the cell's ``identification.model``;
    ``auto`` is decided by the predicted out-of-sample error on ``data`` (fits from
    ``start``, or by ``fit``; :func:`kpi_calib_ros.core.model_selection.choose_model`)."""
    requested = model or cm.cell.identification.model
    if requested == 'auto':
        return choose_model(cm.model, data, fit or _fit_function(cm, start, prior), 'auto',
                            len(cm.geometric), cm.cell.identification.cv_folds, prior=prior)
    return ModelChoice(requested, requested, {}, {}, 0, f'{requested} as configured '
                       '(identification.model / --model; auto compares the levels)')


def calibrate_cell(cm: CellModel, data: Measurements, model: str | None = None,
                   prior: Prior | None = None, start: np.ndarray | None = None,
                   allowed: Sequence[str] | None = None,
                   progress: Callable[[str], None] | None = None) -> CellCalibration:
    """The identification the CLI and the node publish: model size (``model`` or the
    cell's ``identification.model``), outlier exclusion and loss, KPI estimability;
    ``prior`` (e.g. a previous calibration's) replaces the cell's tolerance prior.
    ``start`` replaces the registered start; ``allowed`` restricts the free parameters
    of the model level (a previous calibration's gauge, see :mod:`app.reidentify`);
    ``progress`` is called with a line per outlier-exclusion round."""
    if len(data) == 0:
        raise DataError('no accepted measurement to identify from')
    settings = cm.cell.identification
    n_geo = len(cm.geometric)
    # An unknown or far-off placement is registered from the points first (the median
    # decides whether it is needed, so a few gross points do not trigger it).
    registration = None
    if start is None:
        start, registration = registered_start(cm, data)
    tolerance = cell_prior(cm) if prior is None else None
    prior = prior or tolerance
    # Model choice on the data without gross points (a 10 m point would decide it alone).
    screened = subset(data, ~gross_outliers(cm.model, data, start)[0]) \
        if settings.outliers.exclude else data
    # Every fit weighs the cell's tolerances against the noise its data show
    # (core.precision.balanced_prior); ``scales`` keeps the last balance.
    scales = [1.0]
    balance = tolerance is not None
    fit = _fit_function(cm, start, prior, balance=balance, scales=scales)
    choice = choose_level(cm, screened, model, start, prior, fit)
    if choice.requested == 'auto' and allowed is None:
        cm, start, choice = add_chosen_effects(cm, screened, choice, start, prior, balance)
        fit = _fit_function(cm, start, prior, balance=balance, scales=scales)
    free = [n for n in level_free(cm.model.params, choice.level, n_geo)
            if n not in choice.held]
    if allowed is not None:
        free = [n for n in free if n in set(allowed)]

    def robust_fit(free: list[str]) -> RobustResult:
        return robust_identify(cm.model, data, cm.cell.sigma,
                               lambda d, **kw: fit(d, free, **kw), settings.loss,
                               settings.outliers, start=start, progress=progress)
    robust = robust_fit(free)
    shapes = [n for e in cm.model.effects
              if isinstance(e, BoundEffect) and e.name in choice.effects
              for n in e.shape_names if n in free]
    if not robust.result.converged and shapes:
        # The effects auto added converged in its trials; when the final fit (other
        # points kept) does not with their shapes free, they are held at the values the
        # selection found, as the trials do.
        free = [n for n in free if n not in shapes]
        robust = robust_fit(free)
        choice = dataclasses.replace(choice, held=tuple(choice.held) + tuple(shapes), reason=(
            f'{choice.reason}; the final fit did not converge with '
            f'{", ".join(shapes)} free: held at the selected values'))
    kept = subset(data, robust.kept)
    est = result_estimability(cm.model, kept.q, cm.cell.sigma, robust.result.values,
                              cm.q_work, cm.working_pose_names, free, prior=prior,
                              reflector=kept.reflector, rotation=kept.rotation)
    # A model that fails χ² must not report the stated σ's precision (core.precision).
    result = honest_precision(robust.result)
    return CellCalibration(result, robust, choice, est, tuple(free),
                           registration, scales[-1], cm,
                           expected_tcp_error(cm.model, kept, result))


def add_chosen_effects(cm: CellModel, data: Measurements, choice: ModelChoice,
                       start: np.ndarray, prior: Prior | None, balance: bool = False
                       ) -> tuple[CellModel, np.ndarray, ModelChoice]:
    """``auto``'s second step: the physical effects the diagnosis finds significant and
    plausible on ``data`` that predict new measurements better
    (:func:`kpi_calib_ros.core.effect_selection.choose_effects`), added to ``cm``'s model at
    the chosen level. Returns the cell model with them, the start vector extended with
    their nominal values (0) and the choice with the effects and the record."""
    n_geo = len(cm.geometric)

    def fit_for(model: MeasurementModel):
        extra = np.zeros(len(model.params.names) - len(start))
        return _fit_function(dataclasses.replace(cm, model=model),
                             np.concatenate([start, extra]), prior, balance=balance)
    chosen = choose_effects(cm.model, data, fit_for, choice.level, n_geo, prior)
    if not chosen.effects:
        return cm, start, dataclasses.replace(
            choice, reason=f'{choice.reason}; {chosen.reason}',
            effect_selection=chosen.to_dict())
    richer = dataclasses.replace(cm, model=chosen.model)
    # The effects start from their selected values: a shape parameter (joint_play's τ0)
    # is nonlinear, and at zero size its column vanishes.
    start = np.concatenate([start, [chosen.values[n] for n in
                                    chosen.model.params.names[len(start):]]])
    return richer, start, dataclasses.replace(
        choice, reason=f'{choice.reason}; {chosen.reason}',
        effects=tuple(e.name for e in chosen.effects), effect_selection=chosen.to_dict(),
        held=chosen.held)


def calibration_document(cm: CellModel, result: CalibrationResult,
                         pairing: PairingResult | None = None) -> dict:
    """The calibration.yaml document: the result plus the DH/Hayati view of its axes.
    Its training joint ranges and poses are URDF joint values (``robot.joint_coupling``
    applied to the readings), as validate reads new joint states."""
    if (pairing is not None and len(pairing) and not cm.joint_coupling.is_identity
            and tuple(pairing.joint_names) == tuple(cm.joint_names)):
        pairing = dataclasses.replace(pairing, q=cm.joint_coupling.to_urdf(pairing.q))
    doc = calibration_to_dict(result, pairing)
    std = dict(zip(result.estimated, result.std))
    estimated = [n for n in result.names if n in std]
    values = dict(zip(result.names, result.values))
    notes = compliance_warnings(estimated, [values[n] for n in estimated],
                                [std[n] for n in estimated])
    missing_masses = mass_warning(cm.robot, cm.model.effects)
    if missing_masses:
        notes.insert(0, missing_masses)
    if notes:
        doc['warnings'] = notes
    doc['effects'] = [e.name for e in cm.model.effects]  # validate rebuilds this model
    doc['dh_hayati'] = dh_table(cm.robot, cm.geometric, cm.geometric.nominal,
                                result.values[:len(cm.geometric)])
    return doc


def add_robust_sections(doc: dict[str, Any], cal: CellCalibration) -> dict[str, Any]:
    """Add validity, model choice, robust statistics and KPI estimability to a calibration
    document (see the README's calibration.yaml fields); TCP std of a pose whose TCP is
    not estimable becomes null with ``determined: false``."""
    rob = cal.robust
    doc['valid'] = cal.valid
    doc['invalid_reasons'] = list(cal.problems)
    doc['model'] = {**cal.choice.to_dict(), 'free_parameters': len(cal.free)}
    doc['robust'] = {
        'sigma_stated_m': rob.sigma_stated, 'sigma_robust_m': rob.sigma_robust,
        'sigma_ratio': rob.sigma_ratio, 'loss': rob.loss,
        'loss_scale': ('c·σ̂ with c = %.3f' % LOSS_SCALE) if rob.loss != 'linear' else None,
        'outlier_threshold_sigma': rob.threshold,
        'excluded': [{'index': e.index, 'stamp_ns': e.stamp_ns, 'distance_m': e.distance_m,
                      'distance_sigma': e.distance_sigma, 'reason': e.reason}
                     for e in rob.excluded],
        'outliers': list(rob.outliers),
        # Over the threshold but kept: the model misfits their pose (core.outliers).
        'misfit': list(rob.misfit),
        'used_indices': [int(i) for i in np.flatnonzero(rob.kept)],
        'warnings': list(rob.warnings)}
    doc['tcp_estimable'] = cal.estimability.all_estimable
    doc['tcp_estimability'] = cal.estimability.to_dict()
    for entry, ok in zip(doc['tcp'], cal.estimability.estimable):
        entry['determined'] = bool(ok)
        if not ok:
            entry.update(covariance=None, std=None, trace_m2=None)
    if cal.expected is not None:
        # tcp_std_m: the parameter part; expected_tcp_error_m: with the model's misfit.
        expected = cal.expected.to_dict()
        for name, ok in zip(cal.expected.working_pose_names, cal.estimability.estimable):
            if not ok:
                expected['tcp_std_m'][name] = expected['expected_tcp_error_m'][name] = None
        doc['precision'].update(expected)
    return doc


def _um(metres: float | None) -> str:
    return 'not estimable' if metres is None else f'{metres * 1e6:.1f} µm'


def robust_summary(doc: dict[str, Any]) -> str:
    """Summary lines of the sections :func:`add_robust_sections` adds."""
    rob, model = doc['robust'], doc['model']
    def per_level(values: dict, missing: str) -> str:
        return ', '.join(f'{k} {missing if v is None else f"{v * 1e6:.1f} µm"}'
                         for k, v in values.items())
    lines = [f"model: {model['level']} ({model['free_parameters']} free parameters; "
             f"{model['reason']})"]
    if model.get('predicted_rms_m'):
        lines.append('predicted out-of-sample rms per level (measured configurations): '
                     + per_level(model['predicted_rms_m'], 'n/a'))
    if model.get('cv_rms_m'):
        lines.append(f"cross-validated rms per level ({model['folds']}-fold, folds that keep "
                     'every parameter determined): '
                     + per_level(model['cv_rms_m'], 'not estimable from this design'))
    lines.append(f"noise σ: stated {rob['sigma_stated_m'] * 1e6:.3g} µm, robust estimate from "
                 f"the residuals {rob['sigma_robust_m'] * 1e6:.3g} µm "
                 f"(ratio {rob['sigma_ratio']:.3g}); loss {rob['loss']}")
    lines += [ExcludedMeasurement(**e).text() for e in rob['excluded']]
    lines += [f'WARNING: {w}' for w in rob['warnings']]
    precision = doc.get('precision', {})
    for name, error in precision.get('expected_tcp_error_m', {}).items():
        std = precision['tcp_std_m'][name]
        if std is not None:
            lines.append(f'TCP {name}: expected error {_um(error)} (with the misfit), '
                         f'parameter part tcp_std {_um(std)} (sqrt(trace))')
    if precision.get('expected_tcp_error_m'):
        lines.append(f"expected TCP error: {precision['expected_tcp_error_basis']}")
    if doc['tcp_estimable'] and doc['tcp']:
        lines.append('TCP estimable at every working pose')
    if not doc['valid']:
        lines.append('CALIBRATION NOT VALID: ' + ' | '.join(doc['invalid_reasons']))
    return '\n'.join(lines)


def write_calibration_checked(out_dir: str | Path, doc: dict[str, Any]) -> Path:
    """calibration.yaml for a valid calibration; a failed one goes to
    calibration.failed.yaml and never replaces the last good calibration.yaml."""
    if doc.get('valid', True):
        return write_calibration(out_dir, doc)
    import yaml
    return write_atomic(Path(out_dir) / FAILED_CALIBRATION_FILE,
                        yaml.safe_dump(doc, sort_keys=False))


def calibrated_robot_description(cm: CellModel, result: CalibrationResult) -> str:
    """The calibrated URDF of ``result`` (identified joint errors folded into the joint
    origins, see :mod:`kpi_calib_ros.io.urdf_export`); the CLI and the node write this."""
    return calibrated_urdf(cm.cell.urdf_xml, cm.robot, dict(zip(result.names, result.values)))


def write_results(cm: CellModel, result: CalibrationResult, doc: dict[str, Any],
                  out_dir: str | Path) -> tuple[Path, Path | None, str]:
    """Write a valid calibration as calibration.yaml and the calibrated URDF beside it
    (atomically); an invalid one (``doc['valid']`` false) only as calibration.failed.yaml,
    leaving the last good files as they were.

    Returns the calibration document's path, the URDF's path (None when invalid) and the
    URDF text ('' when invalid).
    """
    path = write_calibration_checked(out_dir, doc)
    if not doc.get('valid', True):
        return path, None, ''
    urdf = calibrated_robot_description(cm, result)
    urdf_path = write_atomic(Path(out_dir) / CALIBRATED_URDF_FILE, urdf)
    return path, urdf_path, urdf


def with_iteration_limit(cm: CellModel, max_iterations: int) -> CellModel:
    """``cm`` with ``identification.max_iterations`` replaced (``--max-iterations``)."""
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) \
            or max_iterations < 1:
        raise ConfigError('--max-iterations', f'must be a positive integer, got '
                          f'{max_iterations!r}')
    settings = dataclasses.replace(cm.cell.identification, max_iterations=max_iterations)
    return dataclasses.replace(cm, cell=dataclasses.replace(cm.cell, identification=settings))


def geometric_only(cm: CellModel) -> CellModel:
    """``cm`` with the geometric model only (no effects)."""
    return dataclasses.replace(cm, model=MeasurementModel(
        cm.robot, cm.geometric, (), cm.cell.reflector_axis, cm.model.orientations,
        cm.model.rotation_scale, cm.model.joint_sigma))


def with_effects(cm: CellModel, effects: tuple) -> CellModel:
    """``cm`` with ``effects`` (specs or bound effects) appended to its model."""
    bound = tuple(parse_effect_spec(e, cm.robot) if isinstance(e, str) else e for e in effects)
    return dataclasses.replace(cm, model=augmented_model(cm.model, bound))


def add_effect_comparison(doc: dict[str, Any], cm: CellModel, data: Measurements,
                          result: CalibrationResult, folds: int = 0) -> str:
    """Compare ``result`` (model with effects) with the geometric model on the same data.

    Adds ``effects_comparison`` to the calibration document ``doc`` and returns
    the readable summary.
    """
    base = geometric_only(cm)
    before = identify_cell(base, data)
    cmp = compare_models((base.model, before), (cm.model, result), data, folds=folds)
    doc['effects_comparison'] = comparison_to_dict(cmp)
    return comparison_text(cmp)


def load_measurements(cell_path: str | Path, bag_path: str | Path, effects: str = '',
                      joint_topic: str | None = None, point_topic: str | None = None,
                      allow_code_effects: bool = False, pose_topic: str | None = None
                      ) -> tuple[CellModel, Measurements, PairingResult]:
    """Cell model (with the extra ``effects`` specs, comma-separated) and the paired
    measurements of a bag; rejections are reported on stderr.

    ``joint_topic`` / ``point_topic`` / ``pose_topic`` (``--joint-topic`` /
    ``--point-topic`` / ``--pose-topic``) override the cell's ``topics:``;
    ``allow_code_effects`` lets effects name Python code.
    """
    cell = load_cell(cell_path, allow_code_effects=allow_code_effects)
    cm = build_cell_model(cell, effects=tuple(split_specs(effects)))
    data, pairing = measurements_from_bag(cm, bag_path, joint_topic, point_topic, pose_topic)
    print_rejections(pairing)
    return cm, data, pairing


def print_rejections(pairing: PairingResult) -> None:
    """Every rejection reason on stderr with its count and the first one's detail (which
    names what was received and the fix)."""
    first: dict[str, str] = {}
    for r in pairing.rejected:
        first.setdefault(r.reason, r.detail)
    for reason, count in sorted(pairing.rejections.items()):
        detail = f' (first: {first[reason]})' if reason in first else ''
        print(f'rejected {count} sample(s): {reason}{detail}', file=sys.stderr)


def print_progress(line: str) -> None:
    """A progress line of a long identification, on stderr (stdout is the summary)."""
    print(line, file=sys.stderr, flush=True)


def run_identify(cell_path: str | Path, bag_path: str | Path, out_dir: str | Path,
                 effects: str = '', model: str | None = None,
                 max_iterations: int | None = None, **options: Any) -> int:
    """``kpi-calib identify``: calibration.yaml and the calibrated URDF
    (:data:`~kpi_calib_ros.io.names.CALIBRATED_URDF_FILE`) in ``out_dir`` (checked first),
    a summary on stdout; ``options`` as for :func:`load_measurements`.

    ``model`` overrides the cell's ``identification.model``, ``max_iterations`` its
    ``identification.max_iterations``; the cell's
    ``identification.prior`` (tolerances) is used when set. With a previous calibration as
    prior (``--prior``) the CLI runs :func:`kpi_calib_ros.app.reidentify.run_reidentify`
    instead. Returns 0 for a valid calibration; 1 when it did not converge or the TCP is
    not estimable (then the document goes to calibration.failed.yaml, and an existing
    calibration.yaml is left as it was).
    """
    writable_folder(out_dir, '--out')
    cm, data, pairing = load_measurements(cell_path, bag_path, effects, **options)
    if max_iterations is not None:
        cm = with_iteration_limit(cm, max_iterations)
    cal = calibrate_cell(cm, data, model, progress=print_progress)
    cm = cal.cell or cm  # with the effects auto added
    how = tolerance_text(cm, cal.prior_scale)
    doc = add_robust_sections(calibration_document(cm, cal.result, pairing), cal)
    if how:
        doc['prior'] = {'source': 'identification.prior', 'description': how,
                        'noise_scale': cal.prior_scale}
    comparison = ''
    if cm.model.effects and cal.valid:
        comparison = add_effect_comparison(doc, cm, subset(data, cal.robust.kept), cal.result)
    path, urdf_path, _ = write_results(cm, cal.result, doc, out_dir)
    print(summary_text(doc))
    print(registration_text(cal.registration, cm))
    print(robust_summary(doc))
    if how:
        print(how)
    if comparison:
        print(comparison)
    print(f'written: {path}')
    if urdf_path is not None:
        print(f'calibrated robot description (URDF): {urdf_path}')
    return 0 if cal.valid else 1

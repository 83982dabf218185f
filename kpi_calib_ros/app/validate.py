"""Validate: does a calibration predict a new recording within its own predicted errors?

A recording made with the tracker (or the probe) set up again is validated with
``register`` (:data:`REGISTER`): the base pose, and with ``'base+reflector'`` the
reflector offsets too (``'reflector'``: the offsets alone, the probe remounted and the
tracker where it was), are re-fitted on the new recording alone; the rms after that
re-registration is the figure to compare, and χ² loses the dof the fit took. A later
recording from a set-up a calibration of several recordings holds is placed as that
recording (``recording``, :func:`recording_calibration`), no dof taken. A learned
residual is carried into the registered or named set-up (it moves with the robot).

``kpi-calib validate`` and the node's ``~/validate`` call :func:`validate_calibration`;
the numerics are :mod:`kpi_calib_ros.core.diagnosis.validation`.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from kpi_calib_ros.app.calibration_document import require_valid
from kpi_calib_ros.app.cell_model import CellModel, build_cell_model
from kpi_calib_ros.app.learned_residual import learned_file, learned_section, point_rows
from kpi_calib_ros.app.measurements import (
    measurements_from_bag,
    print_rejections,
    with_recordings,
)
from kpi_calib_ros.app.validation_text import (
    PREDICTION_OVERSTATED,
    registration_valid,
    validation_text,
)
from kpi_calib_ros.core.diagnosis.validation import (
    Validation,
    against_nominal_on_new,
    nominal_validation,
    set_up_moved,
    validate,
)
from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.estimation.folds import pose_index
from kpi_calib_ros.core.estimation.plausibility import reflector_shift, registration_violations
from kpi_calib_ros.core.estimation.residuals import (
    SIGMA_OVERSTATED,
    noise_verdict,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.payload import outside_payloads, reads_load, row_masses
from kpi_calib_ros.core.measurement.pose import orientation_names
from kpi_calib_ros.core.measurement.recordings import (
    Recording,
    as_first,
    combine,
    row_covariates,
)
from kpi_calib_ros.core.model.parameters import BASE_COMPONENTS, reflector_prefixes
from kpi_calib_ros.io.calibration_file import calibration_recordings, read_calibration_document
from kpi_calib_ros.io.cell import load_cell
from kpi_calib_ros.io.names import VALIDATION_FILE
from kpi_calib_ros.io.report_plots import write_validation_plots
from kpi_calib_ros.io.results import writable_folder, write_atomic

# What ``validate --register`` re-fits on the new recording: the base pose, the base pose
# and the reflector offsets, or the reflector offsets alone (the probe remounted, the
# tracker where it was); a remounted tracked body whose orientation the cell identifies
# is turned by its remount too, so its orientation is re-fitted with its offset.
REGISTER = ('base', 'base+reflector', 'reflector')


def registered_names(cm: CellModel, register: str | None,
                     data: Measurements | None = None) -> list[str]:
    """Names of the parameters ``register`` (one of :data:`REGISTER`, or None) re-fits.

    With ``data``, only the reflectors (markers) its rows measure: a bag of one marker of a
    cell that declares four re-fitted all four, three of them undetermined, and failed.
    """
    if register is None:
        return []
    if register not in REGISTER:
        raise ConfigError('register', f'must be one of {list(REGISTER)}, not {register!r}')
    names = [] if register == 'reflector' else [f'base.{c}' for c in BASE_COMPONENTS]
    if register in ('base+reflector', 'reflector'):
        params = set(cm.model.params.names)
        n_ref = cm.model.n_reflectors
        present = (None if data is None else set(range(n_ref)) if data.reflector is None
                   else {int(r) - n_ref if r >= n_ref else int(r)
                         for r in np.unique(np.asarray(data.reflector))})
        for k, prefix in enumerate(reflector_prefixes(cm.model.params)):
            if present is not None and k not in present:
                continue
            names += [f'{prefix}.{c}' for c in 'xyz']
            names += [n for n in orientation_names(prefix) if n in params]
    return names


def read_calibration(path: str | Path) -> dict[str, Any]:
    """The calibration.yaml document, checked for what validation needs
    (:func:`~kpi_calib_ros.io.calibration_file.read_calibration_document`)."""
    return read_calibration_document(path, 'calibration',
                                     required=('parameter_covariance', 'noise_sigma_m'))


def calibrated_model(cell: Any, doc: dict[str, Any]) -> tuple[CellModel, np.ndarray]:
    """The cell model with the calibration's effects and recordings (each further one's
    placement, :mod:`kpi_calib_ros.core.measurement.recordings`) and its parameter vector.
    A new recording's rows carry no recording covariate: they are placed by ``base.*``."""
    cm = build_cell_model(cell, effects=tuple(doc.get('effects') or ()))
    cm = with_recordings(cm, calibration_recordings(doc, 'calibration'))
    return cm, parameter_vector(cm, doc)


def recording_calibration(cm: CellModel, doc: dict[str, Any], name: str) -> dict[str, Any]:
    """``doc`` seen from its recording ``name`` (``recordings:``): a new recording made from
    that set-up, its rows without a recording covariate, is placed by that recording's base
    pose (and, remounted, its reflector offsets) with their covariance with the robot, not by
    the first recording's. The parameters, ``parameter_covariance`` and
    ``dropped_parameters`` renamed by :func:`~kpi_calib_ros.core.measurement.recordings.
    as_first`; ``doc`` itself for the first recording. ``cm`` is :func:`calibrated_model`'s.

    Raises
    ------
    ConfigError
        ``--recording``: ``name`` is none of the calibration's recordings (the message names
        them).
    """
    known = [r.name for r in calibration_recordings(doc, 'calibration')]
    if name not in known:
        raise ConfigError('--recording', f'the calibration has no recording {name!r}; '
                          + (f'its recordings: {known}' if known else
                             'it was identified from one recording (no recordings: '
                             'section): validate without --recording')
                          + '; a set-up not in the calibration is validated with --register')
    swap = as_first(cm.model.params, name)
    if not swap:
        return doc

    def renamed(entries: Any) -> list[dict[str, Any]]:
        return [dict(e, name=swap.get(str(e['name']), e['name'])) for e in entries]
    out = dict(doc, parameters=renamed(doc['parameters']))
    cov = doc['parameter_covariance']
    out['parameter_covariance'] = dict(cov, names=[swap.get(n, n) for n in cov['names']])
    if doc.get('dropped_parameters'):
        out['dropped_parameters'] = renamed(doc['dropped_parameters'])
    return out


def parameter_vector(cm: CellModel, doc: dict[str, Any]) -> np.ndarray:
    """The calibration's values of ``cm``'s parameters, by name."""
    values = {str(e['name']): float(e['value']) for e in doc['parameters']}
    missing = [n for n in cm.model.params.names if n not in values]
    if missing:
        raise ConfigError('calibration.parameters', f'lacks {missing[:5]} of this cell\'s '
                          'model: the calibration belongs to another cell, robot or effects')
    return np.array([values[n] for n in cm.model.params.names])


def calibration_noise_scale(doc: dict[str, Any]) -> float:
    """χ²/dof the calibration's noise showed (its model not adequate), else 1: new points
    scatter about its predictions by σ·√scale, the noise it showed.

    ``precision.noise_scale`` where the covariance was scaled for another reason (a stopped
    sequential campaign's, to the upper confidence limit of σ: read as noise it widened
    every new point and a bag 1.3× noisier than stated held), else
    ``precision.covariance_scale`` (identify scales the covariance by the noise it showed).
    """
    precision = doc.get('precision') or {}
    key = 'noise_scale' if 'noise_scale' in precision else 'covariance_scale'
    scale = float(precision.get(key, 1.0))
    if not np.isfinite(scale) or scale <= 0.0:
        raise ConfigError(f'calibration.precision.{key}',
                          f'must be a positive number, not {scale}; identify again')
    return scale


def training_poses(cm: CellModel, doc: dict[str, Any]) -> np.ndarray | None:
    """The calibration's training poses in ``cm``'s chain order, or None when it does not
    list them (written before ``training_configurations``) or lacks one of the joints."""
    conf = doc.get('training_configurations') or {}
    names = list(conf.get('joints') or ())
    chain = cm.robot.joint_names
    if not names or any(n not in names for n in chain):
        return None
    q = np.array(conf.get('q') or (), dtype=float).reshape(-1, len(names))
    return q[:, [names.index(n) for n in chain]]


def validate_calibration(cm: CellModel, p: np.ndarray, doc: dict[str, Any],
                         data: Measurements, register: str | None = None) -> Validation:
    """Test the calibration ``doc`` (values ``p``) on new measurements ``data``, after
    re-fitting the placement ``register`` (:data:`REGISTER`) on them when given."""
    registered = registered_names(cm, register, data)
    cov = doc['parameter_covariance']
    estimated = cm.model.params.indices(list(cov['names']))
    ranges = doc.get('training_joint_ranges') or {}
    lower = np.array([ranges.get(n, [-np.inf, np.inf])[0] for n in cm.robot.joint_names])
    upper = np.array([ranges.get(n, [-np.inf, np.inf])[1] for n in cm.robot.joint_names])
    scale = calibration_noise_scale(doc)
    sigma = np.array(doc['noise_sigma_m'], dtype=float) * np.sqrt(scale)
    training_q = training_poses(cm, doc)
    return validate(cm.model, p, estimated, np.array(cov['matrix'], dtype=float).reshape(
        len(estimated), len(estimated)), sigma, data, lower, upper,
        training_q=training_q, noise_scale=scale,
        registered=cm.model.params.indices(registered) if registered else None,
        free=free_parameters(cm, doc))


def free_parameters(cm: CellModel, doc: dict[str, Any]) -> np.ndarray | None:
    """Indices of the calibration's free parameters: those it identified and those it held
    for identifiability (``dropped_parameters``, a choice of gauge); None when it held none
    (one gauge only: its covariance is gauge-free as it is)."""
    held = [str(d['name']) for d in doc.get('dropped_parameters') or ()
            if str(d['name']) in cm.model.params.names]
    if not held:
        return None
    return cm.model.params.indices(list(doc['parameter_covariance']['names']) + held)


def validation_to_dict(v: Validation, data: Measurements, training_rms_m: float | None,
                       cm: CellModel | None = None, noise_scale: float = 1.0,
                       calibrated: np.ndarray | None = None) -> dict[str, Any]:
    """JSON-ready verdict, figures and per-point residuals.

    The rms figures (m) are over point rows; with ``cm``, ``rms_per_reflector_m`` gives
    each reflector's and ``rotation_rms_rad`` each tracked body's orientation residual
    (rad). The χ² test and the per-row list take every row; ``scale`` is the
    calibration's :func:`calibration_noise_scale` (the predicted std includes it)."""
    ref = (np.zeros(len(v.residuals), dtype=int) if data.reflector is None
           else np.asarray(data.reflector, dtype=int))
    n_points = cm.model.n_reflectors if cm is not None else int(ref.max(initial=0)) + 1
    points = ref < n_points
    inside = ~v.outside
    determined = (np.ones(len(v.residuals), dtype=bool) if v.determined is None
                  else v.determined)
    extra: dict[str, Any] = {}
    if v.registration is not None and cm is not None:
        names = [cm.model.params.names[i] for i in v.registration.index]
        std = (v.registration.std if len(v.registration.std) == len(names)
               else np.full(len(names), np.inf))
        violations = registration_violations(
            cm.model, names, std, cm.cell.identification.tolerances, data.q, None if
            calibrated is None else reflector_shift(cm.model, names, v.registration.p,
                                                    calibrated))
        extra['registration'] = {
            'parameters': names, 'dof': v.registration.dof,
            'values': {n: float(v.registration.p[i])
                       for n, i in zip(names, v.registration.index)},
            # None: the new poses do not determine it at all.
            'std': {n: _num(float(x)) for n, x in zip(names, std)},
            'valid': not violations,
            **({'violations': [x.text() for x in violations]} if violations else {})}
    moved = set_up_moved(v, data, points)
    if moved is not None:
        extra['set_up_moved'] = moved
    if cm is not None:
        names = list(cm.cell.reflector_names) or ['reflector']
        extra['rms_per_reflector_m'] = {n: _num(v.rms_where(ref == k))
                                        for k, n in enumerate(names)}
        scale = cm.model.rotation_scale
        if cm.model.orientations and scale is not None:
            extra['rotation_rms_rad'] = {
                names[k]: _num(float(np.sqrt(np.mean(np.sum(
                    (v.residuals[ref == n_points + k] / scale) ** 2, axis=1))))
                    if np.any(ref == n_points + k) else float('nan'))
                for k in sorted(cm.model.orientations)}
    return {
        # None when no test could be made (no dof left): not 'does not hold'.
        'holds': v.holds if v.tested else None,
        'tested': v.tested,
        'verdict': verdict(v),
        **({} if v.tested else {'not_tested_reason': not_tested_reason(v)}),
        'measurements': int(len(v.residuals)),
        'rms_m': _num(v.rms_where(points)),
        'rms_inside_training_range_m': _num(v.rms_where(inside & points)),
        'rms_outside_training_range_m': _num(v.rms_where(v.outside & points)),
        'rms_repeated_from_training_m': _num(v.rms_where(v.repeated & points)),
        'rms_new_inside_training_range_m': _num(v.rms_where(inside & ~v.repeated & points)),
        **extra,
        # Points, as the rms beside them (a tracked body's rotation row is no point).
        'outside_training_range': int(np.count_nonzero(v.outside & points)),
        'repeated_from_training': int(np.count_nonzero(v.repeated & points)),
        'identical_to_training': int(np.count_nonzero(v.identical & points))
        if v.identical is not None else 0,
        'noise_scale': noise_scale,
        'training_rms_m': training_rms_m,
        **_with_reason('predicted_std_median_m', float(np.median(v.predicted_std[determined]))
                       if determined.any() else float('nan'), NOT_DETERMINED),
        # Points whose prediction the training poses do not determine (any gauge would give
        # another number): no predicted std, no part in chi2.
        'not_determined_by_training': int(np.count_nonzero(~determined)),
        'chi2': v.chi2, 'dof': v.dof, 'p_value': _num(v.p_value), 'alpha': v.alpha,
        # The lower tail at the same level: 'sigma overstated'
        # (core.estimation.residuals.noise_verdict).
        **dict(zip(('noise_verdict', 'lower_tail_p'), _numbers(validation_noise_verdict(v)))),
        'residual_to_noise_ratio': _num(v.noise_ratio),
        'points': [{'stamp_ns': int(s) if data.stamps_ns is not None else None,
                    'reflector': int(data.reflector[i]) if data.reflector is not None else 0,
                    'residual_m': [float(x) for x in v.residuals[i]],
                    'mahalanobis': _num(v.mahalanobis[i]),
                    'determined_by_training': bool(determined[i]),
                    'outside_training_range': bool(v.outside[i]),
                    'repeated_from_training': bool(v.repeated[i])}
                   for i, s in enumerate(data.stamps_ns if data.stamps_ns is not None
                                         else np.zeros(len(v.residuals)))],
    }


def validation_noise_verdict(v: Validation) -> tuple[str, float]:
    """The lower tail of the validation's χ² (:func:`noise_verdict`), told apart:
    :data:`SIGMA_OVERSTATED` only when the residuals are smaller than the stated noise
    (``v.noise_ratio`` < 1); a χ² far below its dof with residuals at or above the noise
    says the parameters' predicted part is too large, :data:`PREDICTION_OVERSTATED`."""
    verdict_, lower = noise_verdict(v.chi2, v.dof, v.alpha)
    if verdict_ == SIGMA_OVERSTATED and not v.noise_ratio < 1.0:
        return PREDICTION_OVERSTATED, lower
    return verdict_, lower


def passed(doc: Mapping[str, Any]) -> bool:
    """Whether the validation document passes: the calibration holds, the placement it
    re-registered on the new recording (if any) is determined, it predicts the new points
    no worse than the nominal robot registered on them (``against_nominal``), and its
    learned residual, when it has one, holds too (it is part of the calibration as used:
    one that made fresh poses worse, 83 % inside their 95 % ellipsoids, passed with exit 0)."""
    learned = doc.get('learned_residual') or {}
    return (doc.get('holds') is True and registration_valid(doc)
            and learned.get('holds') is not False
            and not (doc.get('against_nominal') or {}).get('worse_than_nominal', False)
            and not (doc.get('against_nominal_as_used') or {}).get('worse_than_nominal',
                                                                   False))


def against_nominal_as_used(cm: CellModel, doc: dict[str, Any], data: Measurements,
                            v: Validation, register: str | None) -> dict[str, Any] | None:
    """The calibration as used (its own placement, nothing re-registered) against the
    nominal robot with the placement identify registered for it (``against_nominal.nominal.
    placement`` of calibration.yaml): what each gives a user who does not touch the set-up.
    A joint-offset calibration of one grid predicted a second recording of the same set-up
    at 0.699 mm where that nominal robot gave 0.288 mm, while the comparison with both
    placements re-registered on the new points called it better (0.063 against 0.075 mm).
    None: re-registered, or no nominal placement stored."""
    stored = ((doc.get('against_nominal') or {}).get('nominal') or {}).get('placement')
    if register is not None or v.registration is not None or not stored \
            or any(n not in cm.model.params.names for n in stored):
        return None
    index = cm.model.params.indices(list(stored))
    p = np.array(cm.model.params.nominal, dtype=float)
    p[index] = [float(x) for x in stored.values()]
    scale = calibration_noise_scale(doc)
    nominal = nominal_validation(cm.model, p, index, np.array(
        doc['noise_sigma_m'], float) * np.sqrt(scale), data, scale, refit=False)
    if nominal is None:
        return None
    versus = against_nominal_on_new(v, nominal, point_rows(cm.model, data),
                                    pose_index(data.q)[1])
    if not np.isfinite([versus.rms_m, versus.nominal_rms_m]).all():
        return None
    return versus.to_dict()


def against_nominal_robot(cm: CellModel, placed: np.ndarray, doc: dict[str, Any],
                          data: Measurements, v: Validation, register: str | None
                          ) -> dict[str, Any] | None:
    """The calibrated robot against the nominal one on the new points ``data``, each placed
    (base pose, reflector offsets) on them: robots compared, not placements
    (:func:`~kpi_calib_ros.core.diagnosis.validation.against_nominal_on_new`). ``v``: the
    validation with ``register``, reused when it registered both. None: nothing to compare."""
    index = cm.model.params.indices(registered_names(cm, 'base+reflector', data))
    scale = calibration_noise_scale(doc)
    nominal = nominal_validation(cm.model, placed, index, np.array(
        doc['noise_sigma_m'], float) * np.sqrt(scale), data, scale)
    try:
        same = v if register == 'base+reflector' else validate_calibration(
            cm, placed, doc, data, 'base+reflector')
    except (DataError, np.linalg.LinAlgError):
        return None
    versus = (None if nominal is None else against_nominal_on_new(
        same, nominal, point_rows(cm.model, data), pose_index(data.q)[1]))
    if versus is None or not np.isfinite([versus.rms_m, versus.nominal_rms_m]).all():
        return None
    return versus.to_dict()


def verdict(v: Validation) -> str:
    """The validation's verdict: holds, does not hold, or cannot test."""
    if not v.tested:
        return 'cannot test'
    return 'calibration holds' if v.holds else 'calibration does not hold'


def not_tested_reason(v: Validation) -> str:
    """Why ``v`` could make no test (its degrees of freedom)."""
    taken = v.registration.dof if v.registration is not None else 0
    if v.determined is not None and not v.determined.any():
        return ('no point determined by the training poses: the calibration predicts none '
                'of them (measure poses like them and identify again)')
    return (f'no degrees of freedom left: {3 * len(v.residuals)} residual components, '
            f'{taken} taken by the re-registration; measure more points (at least '
            f'{taken // 3 + 1}) or re-register less')


def _num(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


NOT_DETERMINED = ('not determined by the training poses: the calibration does not predict '
                  'these points (measure poses like them and identify again)')


def _with_reason(key: str, x: float, reason: str) -> dict[str, Any]:
    """{key: x} as a JSON number, or {key: None, key_reason: reason} when not finite."""
    return {key: float(x)} if np.isfinite(x) else {key: None, f'{key}_reason': reason}


def _numbers(values: tuple[str, float]) -> tuple[str, float | None]:
    return values[0], _num(values[1])


def new_row_conditions(doc: dict[str, Any], data: Measurements, recording: str | None,
                       stated: Mapping[str, float] | None = None
                       ) -> tuple[Measurements, dict[str, float]]:
    """The new rows with the conditions they were measured under, and those conditions.

    ``stated`` (``validate --covariate``) holds on every new row; a later bag of the
    calibration's recording ``recording`` (``--recording``) was measured under that
    recording's conditions (its ``covariates``, e.g. its payload) where ``stated`` says
    nothing; a covariate the bag carries row by row is kept where neither states one. Rows
    that carry covariates carry every recording's one-hot too, at 0: they are placed by
    ``base.*``.

    Raises
    ------
    ConfigError
        The calibration's recordings each stated a condition (``payload.mass``: one
        calibration over several loads) that the new rows carry from nowhere: predicted
        with the cell's one value they would be judged against a load nobody measured.
    """
    recordings = calibration_recordings(doc, 'calibration')
    own = next((r.covariates for r in recordings if r.name == recording), {})
    conditions = {**own, **dict(stated or {})}
    carried = set(data.covariates or {})
    needed = sorted({n for r in recordings for n in r.covariates} - carried - set(conditions))
    if needed:
        values = {n: sorted({r.covariates[n] for r in recordings}) for n in needed}
        raise ConfigError('--covariate', f'the calibration\'s recordings were each measured '
                          f'under their own {", ".join(needed)} ({values}); the new rows '
                          'state none: give it, e.g. --covariate '
                          f'{needed[0]}=VALUE, or --recording NAME for a later bag of one '
                          'of its recordings')
    if conditions:
        try:
            data = combine([data], [Recording('new', covariates=conditions)])
        except ValueError as exc:
            raise ConfigError('--covariate', str(exc).replace("recording 'new'", 'the bag')
                              .replace("the recording's covariates", '--covariate')) from None
    if recordings and data.covariates:
        # placed by base.* (the first's, or the named one's renamed so): no recording's own
        zeros = row_covariates([r.name for r in recordings], np.zeros(len(data), int))
        data = dataclasses.replace(data, covariates={**zeros, **data.covariates})
    return data, conditions


def validate_report(cm: CellModel, doc: dict[str, Any], data: Measurements,
                    out_dir: str | Path, register: str | None = None,
                    learned: Path | None = None,
                    recording: str | None = None,
                    conditions: Mapping[str, float] | None = None) -> dict[str, Any]:
    """Validate ``doc`` on ``data`` (re-fitting ``register`` first, :data:`REGISTER`) and
    write validation.json and the plot to ``out_dir``; returns the validation document.

    ``learned``: the calibration's learned_residual.yaml, when it has one; its predictions
    are validated too (``learned_residual`` in the document,
    :func:`~kpi_calib_ros.app.learned_residual.validate_learned`). ``recording``: ``data``
    was measured from that set-up of the calibration's ``recordings:``, placed as it is
    there (:func:`recording_calibration`); a learned residual is carried into it.
    ``conditions``: what the new rows were measured under (:func:`new_row_conditions`)."""
    if len(data) == 0:
        raise DataError('no new measurement to validate the calibration on')
    data, conditions = new_row_conditions(doc, data, recording, conditions)
    p = parameter_vector(cm, doc)
    seen = doc if recording is None else recording_calibration(cm, doc, recording)
    placed = parameter_vector(cm, seen)
    v = validate_calibration(cm, placed, seen, data, register)
    out = validation_to_dict(v, data, doc.get('rms_m'), cm, calibration_noise_scale(doc),
                             placed)
    versus = against_nominal_robot(cm, placed, seen, data, v, register)
    if versus is not None:
        out['against_nominal'] = versus
    as_used = against_nominal_as_used(cm, seen, data, v, register) if recording is None \
        else None
    if as_used is not None:
        out['against_nominal_as_used'] = as_used
    if recording is not None:
        out['recording'] = recording
    if conditions:
        out['conditions'] = dict(conditions)
    loads = payloads_outside(cm, doc, data)
    if loads:
        out['payloads_outside_training'] = loads
    if learned is not None and not registration_valid(out):
        out['learned_residual'] = {
            'file': learned.name, 'skipped': 'not carried into the new set-up: its '
            're-registered placement is undetermined (registration.violations)'}
    elif learned is not None:
        moved = seen is not doc or v.registration is not None
        out['learned_residual'] = learned_section(
            cm, p, learned, data,
            None if not moved else placed if v.registration is None else v.registration.p)
    write_atomic(Path(out_dir) / VALIDATION_FILE, json.dumps(out, indent=1, allow_nan=False))
    write_validation_plots(out_dir, cm.robot, np.atleast_2d(data.q), v.residuals, v.outside,
                           v.repeated)
    return out


def payloads_outside(cm: CellModel, doc: dict[str, Any], data: Measurements
                     ) -> dict[str, Any] | None:
    """The new rows whose payload lies outside those the calibration measured
    (``training_payload_kg``), or None: there its prediction of the deflection under load is
    an extrapolation (or, with no effect of the gravity torque, absent)."""
    measured = doc.get('training_payload_kg')
    if not measured or not len(data):
        return None
    mass = row_masses(data.covariates, len(data), cm.robot.payload.mass)
    outside = [outside_payloads(float(m), (float(measured[0]), float(measured[1])))
               for m in mass]
    if not any(outside):
        return None
    return {'points': int(sum(outside)), 'new_kg': [float(mass.min()), float(mass.max())],
            'training_kg': [float(measured[0]), float(measured[1])],
            'reads_load': reads_load(cm.model)}


def run_validate(cell_path: str | Path, calibration_path: str | Path, bag_path: str | Path,
                 out_dir: str | Path, register: str | None = None,
                 allow_code_effects: bool = False, joint_topic: str | None = None,
                 point_topic: str | None = None, pose_topic: str | None = None,
                 recording: str | None = None,
                 conditions: Mapping[str, float] | None = None) -> int:
    """``kpi-calib validate``: validation.json and a plot in ``out_dir``; ``register``
    (:data:`REGISTER`) re-fits the placement on the new recording first; ``recording``
    (``--recording``): the new recording was made from that set-up of the calibration,
    placed as the calibration placed it (:func:`recording_calibration`); ``conditions``
    (``--covariate NAME=VALUE``): what every new row was measured under, e.g. its payload
    (:func:`new_row_conditions`).

    ``allow_code_effects``: the cell's (and the calibration's) effects may name Python
    code, as for identify. ``joint_topic`` / ``point_topic`` / ``pose_topic``: the bag's
    topics when they are not the cell's (``--joint-topic`` …, as for identify).

    Returns 0 when the calibration holds, 1 when it does not or cannot be tested (no
    degrees of freedom left after the re-registration), when the placement ``register``
    re-fitted is undetermined by the new poses, or when it predicts the new points worse
    than the nominal robot registered on them (:func:`passed`). A calibration whose ``valid:`` is
    false (calibration.failed.yaml) is refused (ConfigError): whether it holds is no
    question for a calibration that was never published.
    """
    writable_folder(out_dir, '--out')
    doc = read_calibration(calibration_path)
    require_valid(doc, '--calibration', calibration_path, 'calibration to validate')
    cm, _ = calibrated_model(load_cell(cell_path, allow_code_effects=allow_code_effects), doc)
    if recording is not None:
        recording_calibration(cm, doc, recording)  # an unknown name before the bag is read
    data, pairing = measurements_from_bag(cm, bag_path, joint_topic, point_topic, pose_topic)
    print_rejections(pairing)
    out = validate_report(cm, doc, data, out_dir, register, learned_file(calibration_path),
                          recording, conditions)
    print(validation_text(out))
    print(f"written: {Path(out_dir) / VALIDATION_FILE}, "
          f"{Path(out_dir) / 'validation_residuals.png'}")
    return 0 if passed(out) else 1

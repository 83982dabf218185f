"""The calibration document of an identification: :class:`CellCalibration` (a calibration
with its model choice, robust statistics and KPI estimability), calibration.yaml's content
made of it (the result, the DH/Hayati view, warnings, validity), its summary lines and
the calibrated URDF; :mod:`kpi_calib_ros.app.finish` writes them.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.core.acquisition.outcomes import PairingResult
from kpi_calib_ros.core.diagnosis.effect_selection import RANGE_TOLERANCE
from kpi_calib_ros.core.diagnosis.model_selection import ModelChoice, NominalComparison
from kpi_calib_ros.core.diagnosis.placement_jump import PlacementJump, placement_jumps
from kpi_calib_ros.core.diagnosis.remount import RemountTest
from kpi_calib_ros.core.effects.gravity_compliance import compliance_warnings, mass_warning
from kpi_calib_ros.core.effects.registry import BoundEffect, effect_bounds
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.estimability import KpiEstimability
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.plausibility import gate
from kpi_calib_ros.core.estimation.precision import ExpectedTcpError
from kpi_calib_ros.core.estimation.prior import PLACEMENT_PREFIXES
from kpi_calib_ros.core.estimation.registration import Registration
from kpi_calib_ros.core.estimation.robust import LOSS_SCALE, ExcludedMeasurement, RobustResult
from kpi_calib_ros.core.measurement.data import Measurements, row_sigma
from kpi_calib_ros.core.measurement.payload import gravity_input, outside_payloads, reads_load
from kpi_calib_ros.core.measurement.recordings import Recording, contributions, row_recording
from kpi_calib_ros.core.measurement.weighting import point_rows
from kpi_calib_ros.core.model.dh import dh_table
from kpi_calib_ros.core.model.parameters import reflector_prefixes
from kpi_calib_ros.io.recordings_manifest import RecordingSource
from kpi_calib_ros.io.results import calibration_to_dict
from kpi_calib_ros.io.urdf_export import calibrated_urdf


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
    # noise they show, √prior_scale × the stated σ (core.estimation.precision.balanced_prior).
    prior_scale: float = 1.0
    # The cell model the result belongs to: the given one with the effects ``auto`` added
    # (core.diagnosis.effect_selection); documents and the calibrated URDF are written with it.
    cell: CellModel | None = None
    # Expected TCP error at the working poses with the misfit included (core.estimation.precision).
    expected: ExpectedTcpError | None = None
    # Identified quantities the plausibility gate refuses (core.estimation.plausibility):
    # each names the quantity, why, and the fix.
    implausible: tuple[str, ...] = ()
    # Cross-validated rms against the nominal robot with the placement registered
    # (core.diagnosis.model_selection.against_nominal); None: the calibration is that fit.
    nominal: NominalComparison | None = None
    # Whether recordings sharing the probe disagree on it (core.diagnosis.remount); None:
    # one recording, or every one after the first remounted.
    remount: RemountTest | None = None
    # The lightest and heaviest payload (kg) of the measured rows kept (core.measurement.
    # payload.payload_range); None: not recorded (working poses are not checked against it).
    payload_range_kg: tuple[float, float] | None = None

    @property
    def problems(self) -> tuple[str, ...]:
        out = []
        if not self.result.converged:
            out.append(f'identification did not converge: {self.result.message}')
        if not self.estimability.all_estimable:
            out.append(self.estimability.summary())
        out += [f'not plausible: {text}' for text in self.implausible]
        if self.nominal is not None and not self.nominal.better:
            out.append('worse than no calibration: ' + self.nominal.text())
        if self.nominal is not None:
            out += [f'worse than no calibration on one set-up: {r.text()}'
                    for r in self.nominal.harmed]
            if self.nominal.undetermined_where_it_works:
                out.append('worse than no calibration where the robot works: '
                           + self.nominal.working_text())
        if self.remount is not None and self.remount.disagrees:
            out.append(self.remount.text())
        return tuple(out)

    @property
    def valid(self) -> bool:
        return not self.problems


def with_recording_names(cal: CellCalibration,
                         recordings: str | Path | Sequence[Recording | RecordingSource]
                         ) -> CellCalibration:
    """``cal`` with the names of its ``recordings`` (every recording, first included; or
    their sources; one bag's path: none) in the per-recording comparison with the nominal
    robot; ``cal`` itself with one recording."""
    if cal.nominal is None or not cal.nominal.recordings or isinstance(recordings, (str, Path)):
        return cal
    return dataclasses.replace(cal, nominal=cal.nominal.named([
        r.recording.name if isinstance(r, RecordingSource) else r.name for r in recordings]))


def plausibility_gate(cm: CellModel, result: CalibrationResult, start: np.ndarray,
                      q: np.ndarray, tau: np.ndarray | None = None,
                      reflector: np.ndarray | None = None,
                      free: Sequence[str] | None = None,
                      covariates: Mapping[str, np.ndarray] | None = None) -> tuple[str, ...]:
    """The plausibility gate of ``result`` with the cell's ``identification.tolerances`` and
    ``identification.bounds`` (:func:`kpi_calib_ros.core.estimation.plausibility.gate`): the
    base pose against ``start`` (the cell's or registered placement), the reflector offsets
    against the cell's (or, left out, whether the measured rows determine them), the joint
    corrections against the URDF, the effects against their bounds, at the measured joint
    values ``q`` (N, n), gravity torques ``tau`` and reflector indices ``reflector`` (N,);
    an effect parameter in ``free`` the fit left out is undetermined; ``covariates`` the rows'
    (their recording: each further recording's placement is judged against its own
    registration in ``start``). Returns one line per violation."""
    n_geo = len(cm.geometric)
    params = cm.model.params
    # The placement against where the fit started (the cell's, the registered or the
    # previous cycle's); every joint correction against the URDF, whatever the start (a
    # cycle started from the previous calibration drifted from it unjudged).
    reference = np.array(params.nominal[:n_geo], dtype=float)
    placed = [i for i, n in enumerate(params.names[:n_geo]) if n.startswith(PLACEMENT_PREFIXES)]
    reference[placed] = np.asarray(start, float)[placed]
    stated = cm.cell.reflector_offset_given
    if stated:
        for prefix, offset in zip(reflector_prefixes(params), cm.cell.offsets):
            reference[params.indices([f'{prefix}.{c}' for c in 'xyz'])] = offset
    if tau is None and cm.model.uses_torque and len(q):
        tau = cm.robot.gravity_torques(np.atleast_2d(q))
    # A tracked body's orientation the cell states and identifies from there.
    guessed = [f'reflector.{cm.cell.reflector_names[k]}' for k in cm.cell.stated_orientations
               if k < len(cm.cell.reflector_names)]
    return tuple(v.text() for v in gate(cm.model, result, reference,
                                        cm.cell.identification.tolerances, stated,
                                        q, tau, n_geo, reflector, free, covariates, guessed))


def calibration_document(cm: CellModel, result: CalibrationResult,
                         pairing: PairingResult | None = None) -> dict:
    """The calibration.yaml document: the result plus the DH/Hayati view of its axes.
    Its training joint ranges and poses are URDF joint values (``robot.joint_coupling``
    applied to the readings), as validate reads new joint states."""
    if (pairing is not None and len(pairing) and not cm.joint_coupling.is_identity
            and tuple(pairing.joint_names) == tuple(cm.joint_names)):
        pairing = dataclasses.replace(pairing, q=cm.joint_coupling.to_urdf(pairing.q),
                                      joint_names=tuple(cm.robot.joint_names))
    doc = calibration_to_dict(result, pairing)
    std = dict(zip(result.estimated, result.std))
    estimated = [n for n in result.names if n in std]
    values = dict(zip(result.names, result.values))
    # the cell's bound (identification.bounds) widens the stiffness range it warns outside
    bounds = cm.cell.identification.tolerances.bounds
    softest = {e.parameter_names[0]: effect_bounds(e, bounds)[0]
               for e in cm.model.effects if isinstance(e, BoundEffect)
               and e.kind.name == 'joint_compliance'}
    notes = compliance_warnings(estimated, [values[n] for n in estimated],
                                [std[n] for n in estimated], softest)
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
    if cal.cell is not None:
        doc['model']['reads_load'] = reads_load(cal.cell.model)
    if cal.nominal is not None:
        doc['against_nominal'] = cal.nominal.to_dict()
        if cal.nominal.elsewhere_worse:
            doc['against_nominal']['scope_warning'] = cal.nominal.scope_text()
    if cal.remount is not None:
        doc['shared_probe'] = cal.remount.to_dict()
    doc['robust'] = {
        'sigma_stated_m': rob.sigma_stated, 'sigma_robust_m': rob.sigma_robust,
        'sigma_ratio': rob.sigma_ratio, 'loss': rob.loss,
        'loss_scale': ('c·σ̂ with c = %.3f' % LOSS_SCALE) if rob.loss != 'linear' else None,
        'outlier_threshold_sigma': rob.threshold,
        'excluded': [{'index': e.index, 'stamp_ns': e.stamp_ns, 'distance_m': e.distance_m,
                      'distance_sigma': e.distance_sigma, 'reason': e.reason}
                     for e in rob.excluded],
        'outliers': list(rob.outliers),
        # Over the threshold but kept: the model misfits their pose (core.estimation.outliers).
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
        outside = working_poses_outside(doc, cal)
        if outside:
            doc['precision']['working_poses_outside_training'] = outside
        narrow = narrow_joints(doc, cal)
        if narrow:
            doc['precision']['narrowly_measured_joints'] = narrow
    if cal.payload_range_kg is not None:
        doc['training_payload_kg'] = [float(m) for m in cal.payload_range_kg]
        loads = working_payloads_outside(cal)
        if loads:
            doc['precision']['working_payloads_outside_training'] = loads
    return doc


def working_payloads_outside(cal: CellCalibration) -> dict[str, float]:
    """{working pose: payload kg} of the working poses whose payload (their own, else the
    cell's) lies outside the payloads measured (``cal.payload_range_kg``): calibrated at 0 kg,
    a 7-DoF arm's TCP at 2.5 kg missed by 7.8 mm where 1.6 mm was stated."""
    cm, measured = cal.cell, cal.payload_range_kg
    if cm is None or measured is None or not len(cm.q_work):
        return {}
    cell_mass = cm.robot.payload.mass
    masses = [cell_mass if w.payload is None else w.payload[0]
              for w in cm.cell.working_poses][:len(cm.working_pose_names)]
    return {name: float(m) for name, m in zip(cm.working_pose_names, masses)
            if outside_payloads(float(m), measured)}


# A joint measured over less than this share of its limits' span (a continuous joint: of a
# turn) leaves what only its motion shows (its axis direction, its scale) to the few values
# measured: the calibration holds near them.
NARROW_SHARE = 0.1


def narrow_joints(doc: dict[str, Any], cal: CellCalibration) -> dict[str, dict[str, Any]]:
    """{joint: {measured, limits, tcp_std_at_limits_m}} of the joints measured over less than
    :data:`NARROW_SHARE` of their span whose motion to a limit, from a working pose, grows the
    stated TCP std (sqrt(trace), the identified parameters' covariance) at least twofold:
    the calibration holds near the values measured, and elsewhere extrapolates what only that
    joint's motion shows (a PR2 torso lift measured over 2 mm of 310 mm published its placement
    tilt 0.016 ± 0.007 rad as valid, true 0.0005; 3.4 mm off at the other end of the lift)."""
    ranges, cm, result = doc.get('training_joint_ranges'), cal.cell, cal.result
    if not ranges or cm is None or not len(cm.q_work) or not len(result.estimated):
        return {}
    model = cm.model
    idx = model.params.indices(list(result.estimated))
    out: dict[str, dict[str, Any]] = {}

    def stds(q: np.ndarray) -> np.ndarray:
        tau = gravity_input(cm.robot, q) if model.uses_torque else None
        _, jac = model.jacobian(np.asarray(result.values, float), q, tau)
        j = jac[:, :, idx]
        return np.sqrt(np.einsum('nak,kl,nal->n', j, result.covariance, j))
    here = float(np.max(stds(np.atleast_2d(cm.q_work))))
    for i, joint in enumerate(cm.robot.joints):
        if joint.name not in ranges:
            continue
        lo, hi = (-np.pi, np.pi) if joint.kind == 'continuous' else (joint.lower, joint.upper)
        measured = ranges[joint.name]
        if not hi > lo or measured[1] - measured[0] >= NARROW_SHARE * (hi - lo):
            continue
        ends = np.repeat(np.atleast_2d(cm.q_work), 2, axis=0)
        ends[0::2, i], ends[1::2, i] = lo, hi
        there = float(np.max(stds(ends)))
        if there >= 2 * here:
            out[joint.name] = {'measured': [float(v) for v in measured],
                               'limits': [float(lo), float(hi)],
                               'unit': 'm' if joint.kind == 'prismatic' else 'rad',
                               'tcp_std_at_limits_m': there, 'tcp_std_m': here}
    return out


def working_poses_outside(doc: dict[str, Any], cal: CellCalibration
                          ) -> dict[str, dict[str, float]]:
    """{working pose: {joint: value}} of the joints each working pose sets outside the
    calibration's ``training_joint_ranges`` (beyond 1e-3 rad or m): there its expected TCP
    error is an extrapolation no held-out fold checks (on the real UR10, 300 poses of one
    region stated 405 µm at a working pose whose neighbourhood it missed by 1990 µm)."""
    ranges, cm = doc.get('training_joint_ranges'), cal.cell
    if not ranges or cm is None or not len(cm.q_work):
        return {}
    names = cm.robot.joint_names
    out: dict[str, dict[str, float]] = {}
    for pose, q in zip(cm.working_pose_names, np.atleast_2d(cm.q_work)):
        beyond = {n: float(v) for n, v in zip(names, q) if n in ranges
                  and not ranges[n][0] - RANGE_TOLERANCE <= v <= ranges[n][1] + RANGE_TOLERANCE}
        if beyond:
            out[pose] = beyond
    return out


def require_valid(doc: dict[str, Any], key: str, path: str | Path, use: str) -> None:
    """Refuse a calibration document that says ``valid: false`` (calibration.failed.yaml:
    not converged, the TCP not estimable, a change detected) for ``use``.

    Raises
    ------
    ConfigError
        Naming ``key`` (the option that gave ``path``), the file, its reasons and the fix.
    """
    if doc.get('valid', True) is True:  # files older than the key were all valid
        return
    reasons = ' | '.join(str(r) for r in doc.get('invalid_reasons') or ()) or 'no reason given'
    raise ConfigError(key, f'{path} is not a valid calibration (valid: false: {reasons}); a '
                      f'failed identification is no {use}: give the last valid '
                      'calibration.yaml')


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
    if model.get('other_region_rms_m'):
        lines.append(f"cross-validated rms per level over held-out regions of joint space "
                     f"({model['region_blocks']} regions): "
                     + per_level(model['other_region_rms_m'], 'not estimable from this design'))
    if doc.get('against_nominal'):
        lines.append(doc['against_nominal']['text'])
        if doc['against_nominal'].get('scope_warning'):
            lines.append('WARNING: ' + doc['against_nominal']['scope_warning'])
    lines.append(f"noise σ: stated {rob['sigma_stated_m'] * 1e6:.3g} µm, robust estimate from "
                 f"the residuals {rob['sigma_robust_m'] * 1e6:.3g} µm "
                 f"(ratio {rob['sigma_ratio']:.3g}); loss {rob['loss']}")
    lines += [(f"recording {e['recording']!r}: " if 'recording' in e else '')
              + ExcludedMeasurement(**{k: v for k, v in e.items() if k != 'recording'}).text()
              for e in rob['excluded']]
    lines += [f'WARNING: {w}' for w in rob['warnings']]
    lines += [f'WARNING: auto, {b}; state the bound in the cell if the arm is that soft or '
              'loose, and identify again'
              for b in (model.get('effect_selection') or {}).get('beyond_bounds', ())]
    precision = doc.get('precision', {})
    for name, error in precision.get('expected_tcp_error_m', {}).items():
        std = precision['tcp_std_m'][name]
        if std is not None:
            lines.append(f'TCP {name}: expected error {_um(error)} (with the misfit), '
                         f'parameter part tcp_std {_um(std)} (sqrt(trace))')
    if precision.get('expected_tcp_error_m'):
        lines.append(f"expected TCP error: {precision['expected_tcp_error_basis']}")
    for name, joints in precision.get('working_poses_outside_training', {}).items():
        lines.append(f'WARNING: working pose {name} sets '
                     + ', '.join(f'{j} = {v:.3g}' for j, v in joints.items())
                     + ' outside the measured joint ranges (training_joint_ranges): its '
                     'expected TCP error is an extrapolation no held-out fold checks; measure '
                     'poses around it (kpi-calib design plans them)')
    for joint, n in precision.get('narrowly_measured_joints', {}).items():
        lines.append(f'WARNING: joint {joint} was measured from {n["measured"][0]:.4g} to '
                     f'{n["measured"][1]:.4g} {n["unit"]} only, of {n["limits"][0]:.4g} to '
                     f'{n["limits"][1]:.4g} {n["unit"]}: the calibration holds near those values; '
                     'moved to its limits from a working pose, the stated TCP std grows from '
                     f'{_um(n["tcp_std_m"])} to {_um(n["tcp_std_at_limits_m"])} (what only its '
                     'motion shows, its axis direction and scale, is extrapolated, also in the '
                     'written URDF); measure poses over its range (kpi-calib design)')
    loaded = bool(doc.get('model', {}).get('reads_load'))
    for name, mass in precision.get('working_payloads_outside_training', {}).items():
        lo, hi = doc['training_payload_kg']
        lines.append(f'WARNING: working pose {name} carries {mass:.3g} kg, outside the payloads '
                     f'measured ({lo:.3g} to {hi:.3g} kg, training_payload_kg): '
                     + ('its deflection under that load is extrapolated from the measured '
                        'loads and no measured pose checks it' if loaded else
                        'no effect of the model reads the load, so the joints\' deflection '
                        'under it is in no prediction and no expected TCP error')
                     + '; measure poses with that payload (payload.mass per row) and '
                     'diagnose again')
    if doc['tcp_estimable'] and doc['tcp']:
        lines.append('TCP estimable at every working pose')
    if not doc['valid']:
        lines.append('CALIBRATION NOT VALID: ' + ' | '.join(doc['invalid_reasons']))
    return '\n'.join(lines)


def calibrated_robot_description(cm: CellModel, result: CalibrationResult) -> str:
    """The calibrated URDF of ``result`` (identified joint errors folded into the joint
    origins, see :mod:`kpi_calib_ros.io.urdf_export`); the CLI and the node write this."""
    return calibrated_urdf(cm.cell.urdf_xml, cm.robot, dict(zip(result.names, result.values)))


def urdf_omission(cm: CellModel, result: CalibrationResult, data: Measurements) -> str:
    """What the calibrated URDF leaves out, in words ('' when nothing): a URDF holds the
    geometry only, so the effects of the model (a compliance's sag, a periodic error, a
    measured tilt) are not in it; the figure is how far they move the point at the
    measured rows (``data``, with their torques and covariates), the calibration's values
    against the same values with every effect parameter at its nominal value."""
    effects = [e.name for e in cm.model.effects]
    if not effects or len(data) == 0:
        return ''
    values = np.asarray(result.values, float)
    geometric = values.copy()
    extra = np.arange(len(cm.geometric), len(values))
    geometric[extra] = np.asarray(cm.model.params.nominal, float)[extra]
    points = point_rows(data.reflector, cm.model.n_reflectors)
    rows = data if points is None else data.subset(points)
    moved = np.linalg.norm(
        cm.model.predict(values, rows.q, rows.tau, rows.reflector, covariates=rows.covariates)
        - cm.model.predict(geometric, rows.q, rows.tau, rows.reflector,
                           covariates=rows.covariates), axis=1)
    return (f'the calibrated URDF holds the geometry only: the effects {", ".join(effects)} '
            f'move the point by up to {moved.max() * 1e6:.1f} µm (rms '
            f'{np.sqrt(np.mean(moved ** 2)) * 1e6:.1f} µm) at the measured poses and are not '
            'in it; predict the TCP with calibration.yaml (the node\'s TCP query, validate)')


def recordings_section(cm: CellModel, data: Measurements, cal: CellCalibration,
                       recordings: Sequence[Recording], bags: Sequence[str]
                       ) -> list[dict[str, Any]]:
    """calibration.yaml's ``recordings:``: per recording (``data`` every row the calibration
    ``cal`` was given) its bag, whether its probe was remounted, its constant covariates, the
    rows the outlier test excluded from it (``excluded``), what its kept rows contributed
    (:func:`kpi_calib_ros.core.measurement.recordings.contributions`): poses, rms, its
    placement with std, and the TCP variance without its rows over the one with them; and
    its own figures against the nominal robot (``against_nominal``,
    :mod:`kpi_calib_ros.core.diagnosis.recording_verdict`)."""
    result, nominal = cal.result, cal.nominal
    names = [r.name for r in recordings]
    index = row_recording(data, names)
    excluded = np.bincount(index[~np.asarray(cal.robust.kept, bool)], minlength=len(names))
    data = data.subset(cal.robust.kept)
    found = contributions(cm.model, data, result.values, result.estimated, result.std,
                          result.sigma, cm.q_work, names)
    verdicts = (nominal.recordings if nominal is not None
                and len(nominal.recordings) == len(names) else ())
    out = []
    for i, (rec, bag, c) in enumerate(zip(recordings, bags, found)):
        ratio = c.tcp_variance_ratio
        entry: dict[str, Any] = {
            'name': rec.name, 'bag': str(bag), 'reflector_remounted': rec.reflector_remounted,
            'covariates': {k: float(v) for k, v in rec.covariates.items()},
            'poses': c.poses, 'points': c.points, 'excluded': int(excluded[i]),
            'rms_m': _finite(c.rms_m),
            'placement': {n: {'value': float(v), 'std': _finite(c.placement_std[n])}
                          for n, v in c.placement.items()},
            'tcp_variance_ratio_without': (None if ratio is None or not np.isfinite(ratio)
                                           else float(ratio))}
        if ratio is not None and not np.isfinite(ratio):
            entry['tcp_variance_ratio_without_reason'] = (
                'without this recording the identified robot is not determined')
        if verdicts:
            entry['against_nominal'] = verdicts[i].to_dict()
        out.append(entry)
    return out


def name_excluded(doc: dict[str, Any], data: Measurements,
                  recordings: Sequence[Recording]) -> None:
    """Name each excluded row's recording in ``doc['robust']['excluded']`` (its index is
    into every recording's rows in order, ``data``)."""
    index = row_recording(data, [r.name for r in recordings])
    for entry in doc.get('robust', {}).get('excluded', []):
        entry['recording'] = recordings[int(index[entry['index']])].name


def recordings_text(section: Sequence[Mapping[str, Any]]) -> str:
    """One line per recording of :func:`recordings_section`."""
    lines = []
    for entry in section:
        base = [v['value'] for n, v in entry['placement'].items() if '.reflector' not in n
                and not n.startswith('reflector')]
        ratio = entry['tcp_variance_ratio_without']
        versus = entry.get('against_nominal')
        lines.append(
            f"recording {entry['name']}: {entry['poses']} poses"
            + (f" ({entry['points']} points)" if entry.get('points', entry['poses'])
               != entry['poses'] else '') + ', rms '
            + ('n/a' if entry['rms_m'] is None else f"{entry['rms_m'] * 1e3:.3f} mm")
            + f", base in tracker {np.round(base, 4).tolist()}"
            + (' (reflector remounted)' if entry['reflector_remounted'] else '')
            + ('; TCP variance without it: '
               + ('not determined' if ratio is None and 'tcp_variance_ratio_without_reason'
                  in entry else 'n/a' if ratio is None else f'{ratio:.3g} x'))
            + ('' if not versus else
               f"; held-out rms {_um(versus['in_region_rms_m'])} against the nominal robot's "
               f"{_um(versus['nominal_in_region_rms_m'])}"
               + (' (WORSE than nominal beyond the noise)' if versus['worse_than_nominal']
                  else '')))
    return '\n'.join(lines)


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def recording_jumps(cm: CellModel, data: Measurements, cal: CellCalibration,
                    names: Sequence[str]) -> list[PlacementJump]:
    """The recordings (``names``, the first that of rows without a recording covariate) whose
    placement changed while they were measured, judged on the calibration's kept rows
    (:mod:`kpi_calib_ros.core.diagnosis.placement_jump`); [] without stamps."""
    kept = data.subset(cal.robust.kept)
    result = cal.result
    if kept.stamps_ns is None or len(kept) != len(result.residuals):
        return []
    points = point_rows(kept.reflector, cm.model.n_reflectors)
    rows = np.arange(len(kept)) if points is None else np.flatnonzero(points)
    sigma = (result.point_sigma if result.point_sigma is not None
             else row_sigma(result.sigma, None, len(kept)))
    index = row_recording(kept, names)[rows]
    residuals = np.asarray(result.residuals)[rows]
    return placement_jumps(residuals, np.asarray(kept.eta)[rows] - residuals,
                           np.asarray(sigma)[rows], np.asarray(kept.stamps_ns)[rows],
                           [(name, np.flatnonzero(index == i)) for i, name in enumerate(names)])


def add_placement_jumps(doc: dict[str, Any], cm: CellModel, data: Measurements,
                        cal: CellCalibration, names: Sequence[str]) -> list[str]:
    """calibration.yaml's ``placement_jumps`` (:func:`recording_jumps`) in ``doc``, and the
    WARNING line of each for the summary."""
    jumps = recording_jumps(cm, data, cal, names)
    doc['placement_jumps'] = [j.to_dict() for j in jumps]
    return [f'WARNING: {j.text()}' for j in jumps]


def recording_names(bags: str | Path | Sequence[RecordingSource]) -> list[str]:
    """The recordings' names, the first included: one bag's file stem, or each source's."""
    if isinstance(bags, (str, Path)):
        return [Path(bags).stem]
    return [s.recording.name for s in bags]

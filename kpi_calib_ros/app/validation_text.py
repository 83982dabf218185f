"""The validation's verdict in words, for a terminal and the node's answer.

:func:`validation_text` summarises ``validation.json``
(:func:`~kpi_calib_ros.app.validate.validate_report`): the χ² verdict, the rms inside and
outside the training ranges, the registration's gate, the calibrated robot against the
nominal one, and the warnings.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from kpi_calib_ros.app.learned_residual import learned_validation_text
from kpi_calib_ros.core.estimation.residuals import SIGMA_OVERSTATED, sigma_overstated_text
from kpi_calib_ros.core.measurement.replicates import SAME_POSE_TOLERANCE

# χ² far below its dof while the residuals are not below the stated noise: the calibration's
# prediction (the noise it showed, σ·√covariance_scale, and its parameters' part), not σ, is
# wider than the new points.
PREDICTION_OVERSTATED = 'predicted error overstated'


def registration_valid(doc: Mapping[str, Any]) -> bool:
    """Whether the validation document's re-registered placement (if any) passed the gate
    (:func:`~kpi_calib_ros.core.estimation.plausibility.registration_violations`)."""
    return bool((doc.get('registration') or {}).get('valid', True))


def prediction_overstated_text(doc: dict[str, Any]) -> str:
    """The warning of :data:`PREDICTION_OVERSTATED` from the validation document."""
    scale = float(doc.get('noise_scale', 1.0))
    return (f"{PREDICTION_OVERSTATED}: chi2/dof = {doc['chi2']:.3g}/{doc['dof']} is far below "
            f"its dof while the residuals are {doc['residual_to_noise_ratio']:.3g} x the "
            'stated noise: the calibration predicts them wider'
            + (f", with the noise it showed ({np.sqrt(scale):.3g} x the stated sigma, its "
               'model not adequate)' if scale != 1.0 else '')
            + (f" and its parameters' error (predicted std median "
               f"{doc['predicted_std_median_m'] * 1e3:.3g} mm per axis)"
               if doc.get('predicted_std_median_m') is not None else '')
            + ', and the test cannot fail; noise.sigma is not the cause (the residuals are '
            'not below it): a better model or more poses like these narrow the prediction')


def nominal_verdict(versus: Mapping[str, Any]) -> str:
    """The calibrated robot against the nominal one (``against_nominal``), in words: worse,
    better, or neither beyond the paired test's level."""
    z = versus['z'] if versus['z'] is not None else float('nan')
    if versus['worse_than_nominal']:
        return 'WORSE THAN NO CALIBRATION'
    if z < -versus['z_needed']:
        return 'better than no calibration'
    return 'neither better nor worse than no calibration'


def validation_text(doc: dict[str, Any]) -> str:
    """Readable summary for a terminal."""
    def mm(x: float | None) -> str:
        return 'n/a' if x is None else f'{x * 1e3:.3f} mm'
    lines = [f"{doc['verdict']}: chi2/dof = {doc['chi2']:.1f}/{doc['dof']}, "
             + (f"p = {doc['p_value']:.3g} (level {doc['alpha']})" if doc.get('tested', True)
                else doc['not_tested_reason']),
             f"new measurements: {doc['measurements']}, rms {mm(doc['rms_m'])} "
             f"(training rms {mm(doc['training_rms_m'])}, predicted std per axis "
             + (f"{mm(doc['predicted_std_median_m'])} median" if doc['predicted_std_median_m']
                is not None else 'none: ' + doc['predicted_std_median_m_reason'])
             + (f", with the noise the calibration showed, {np.sqrt(doc['noise_scale']):.3g} x "
                'the stated sigma' if doc.get('noise_scale', 1.0) != 1.0 else '') + ')',
             *([f"placed as recording {doc['recording']} of the calibration (its base pose "
                'and, remounted, its reflector offsets, with their covariance)']
               if doc.get('recording') else []),
             *(['conditions of the new rows: ' + ', '.join(
                 f'{k} = {v:g}' for k, v in doc['conditions'].items())]
               if doc.get('conditions') else []),
             *(['re-registered on the new recording: '
                + ', '.join(doc['registration']['parameters'])
                + f" ({doc['registration']['dof']} dof); the rms above is after it"]
               if doc.get('registration') else []),
             *(['NOT VALID: the re-registered placement fails the gate, a guess to use for '
                'nothing: ' + '; '.join(doc['registration']['violations'])]
               if not registration_valid(doc) else []),
             f"inside the training joint ranges: rms {mm(doc['rms_inside_training_range_m'])}; "
             f"outside ({doc['outside_training_range']} points): "
             f"{mm(doc['rms_outside_training_range_m'])}"]
    versus = doc.get('against_nominal')
    if versus:
        worse = versus['worse_than_nominal']
        z = versus['z'] if versus['z'] is not None else float('nan')
        label = nominal_verdict(versus)
        if label.startswith('neither'):
            label += ' beyond the scatter of these poses'
        lines.append(
            f"{label}: with the placement (base pose, reflector offsets) registered on these "
            f"points, the calibrated robot predicts them at {mm(versus['rms_m'])} rms, the "
            f"nominal robot at {mm(versus['nominal_rms_m'])} (corrected for the "
            f"{versus['dof']} dof the placement took; paired over {versus['poses']} poses, "
            f"z = {z:.2f}, worse beyond {versus['z_needed']:.2f})" + (
                '; here the calibration does harm: do not use it for poses like these '
                '(identify again with poses that cover them)' if worse else ''))
    used = doc.get('against_nominal_as_used')
    if used:
        z = used['z'] if used['z'] is not None else float('nan')
        label = nominal_verdict(used)
        lines.append(
            f"{label} as used: with the placement as calibrated (nothing re-registered), the "
            f"calibrated robot predicts these points at {mm(used['rms_m'])} rms, the nominal "
            f"robot with the placement identify registered for it at "
            f"{mm(used['nominal_rms_m'])} (paired over {used['poses']} poses, z = {z:.2f}, "
            f"worse beyond {used['z_needed']:.2f})" + (
                '; as it stands, the calibration does harm here: identify again with poses '
                'that cover these, or re-register (--register base) if the set-up moved'
                if used['worse_than_nominal'] else ''))
    moved = doc.get('set_up_moved')
    if moved:
        lines.append(f"the new points match the calibration after a rigid move of "
                     f"{moved['translation_m']:.3g} m and {np.degrees(moved['rotation_rad']):.3g}"
                     f" deg (rms {mm(moved['rms_before_m'])} -> {mm(moved['rms_after_m'])}): "
                     'the tracker or the robot was set up again since the calibration; '
                     'validate with --register base (--recording NAME for a later bag of one '
                     'of its set-ups)')
    loads = doc.get('payloads_outside_training')
    if loads:
        lines.append(f"WARNING: {loads['points']} points carry a payload outside those the "
                     f"calibration measured ({loads['new_kg'][0]:.3g} to {loads['new_kg'][1]:.3g} "
                     f"kg against {loads['training_kg'][0]:.3g} to {loads['training_kg'][1]:.3g}"
                     ' kg, training_payload_kg): '
                     + ('its deflection under that load is extrapolated' if loads['reads_load']
                        else 'no effect of the calibration reads the load, so the deflection '
                        'under it is in no prediction')
                     + '; a miss there is the load before the calibration')
    if doc.get('not_determined_by_training'):
        lines.append(f"not determined by the training poses: {doc['not_determined_by_training']} "
                     'points (their prediction depends on the parameters the calibration held '
                     'for identifiability; no predicted std, not in chi2): measure poses like '
                     'them and identify again')
    if doc.get('noise_verdict') == SIGMA_OVERSTATED:
        lines.append('WARNING: ' + sigma_overstated_text(doc['chi2'], doc['dof'],
                                                         doc['lower_tail_p'], doc['alpha'],
                                                         doc['residual_to_noise_ratio']))
    elif doc.get('noise_verdict') == PREDICTION_OVERSTATED:
        lines.append('WARNING: ' + prediction_overstated_text(doc))
    learned = doc.get('learned_residual')
    if learned is not None:
        lines.append(f"learned residual ({learned['file']}) {learned['skipped']}"
                     if 'skipped' in learned else learned_validation_text(learned))
        if learned.get('holds') is False:
            lines.append(f"WARNING: with its learned residual the calibration does NOT hold "
                         f"on these points (rms {learned['rms_m'] * 1e3:.3f} mm against "
                         f"{learned['rms_physical_m'] * 1e3:.3f} mm without it): predict "
                         f"without {learned['file']}, or learn it again on more poses")
    if 2 * doc.get('identical_to_training', 0) >= doc['measurements']:
        lines.append(f"WARNING: {doc['identical_to_training']} of {doc['measurements']} points "
                     'have the joint readings of a training pose bit for bit: these are the '
                     "calibration's own training measurements, and how well it fits them "
                     'says nothing of how it predicts; validate on a recording it was not '
                     'identified from')
    if doc.get('repeated_from_training'):
        training = doc.get('training_rms_m')
        lines.append(f"inside: poses repeated from training ({doc['repeated_from_training']} "
                     f"points, every joint within {SAME_POSE_TOLERANCE:g} rad or m): rms "
                     f"{mm(doc['rms_repeated_from_training_m'])} (the calibration's misfit at "
                     'poses it was fitted to'
                     + (f', its training rms {mm(training)},' if training is not None else '')
                     + ' plus the repeatability between the campaigns: no floor, a better '
                     'model lowers the misfit part); new poses: '
                     f"{mm(doc['rms_new_inside_training_range_m'])}")
    return '\n'.join(lines)


__all__ = ['PREDICTION_OVERSTATED', 'nominal_verdict', 'prediction_overstated_text',
           'registration_valid', 'validation_text']

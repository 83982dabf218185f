"""The one-line answers of the node's services, from plain results (no rclpy)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from kpi_calib_ros.app.validation_text import nominal_verdict
from kpi_calib_ros.core.estimation.precision import precision_statement


def design_answer(design: Any, not_estimable: str, topic: str, path: Path) -> str:
    """~/design: the poses, their criterion and predicted TCP precision, where they went."""
    tcp_um = np.sqrt((design.tcp_std ** 2).sum(axis=1)).max() * 1e6
    return (f'{len(design.configurations)} poses ({design.criterion}), predicted TCP '
            f'sqrt(trace) <= {tcp_um:.1f} µm; {design.status}; '
            + (f'{not_estimable}; ' if not_estimable else '') + 'published on '
            f'{topic}, written to {path}')


def identify_answer(measurements: int, cal: Any, prior: str, notes: Sequence[str],
                    data_dir: Path, learned: str = '') -> str:
    """~/identify: the fit, its TCP precision (and expected error with the misfit of a
    model χ² rejects, core.estimation.precision.expected_tcp_error), exclusions and prior;
    ``learned``: the learned residual's summary lines (the choice with its figures), joined by
    '; '."""
    result = cal.result
    tcp_um = np.sqrt(np.trace(result.tcp_covariance, axis1=1, axis2=2)).max() * 1e6
    expected = ('' if cal.expected is None else
                f', expected TCP error <= '
                f'{np.max(cal.expected.expected_tcp_error_m) * 1e6:.1f} µm with the misfit')
    precision = precision_statement(result.covariance_scale, result.joint_sigma)
    return (
        f'identified from {measurements} measurements: {result.message}; rms '
        f'{result.rms_m * 1e6:.1f} µm, p = {result.p_value:.3g}, TCP sqrt(trace) <= '
        f'{tcp_um:.1f} µm ({precision}){expected}; {len(cal.robust.excluded)} excluded; '
        + (f'prior {prior}; ' if prior else '') + ''.join(f'{n}; ' for n in notes)
        + ''.join(f'{line}; ' for line in learned.splitlines())
        + f'written to {data_dir}')


def validate_answer(doc: dict[str, Any]) -> str:
    """~/validate: the verdict on the new measurements (the validation document)."""
    return (f"{doc['verdict']} on {doc['measurements']} new measurements: "
            f"rms {doc['rms_m'] * 1e6:.1f} µm"
            + (f" placed as station {doc['recording']} of the calibration"
               if doc.get('recording') else '')
            + (' after re-registering ' + '/'.join(doc['registration']['parameters'])
               if doc.get('registration') else '')
            + ('; NOT VALID, the re-registered placement fails the gate: '
               + '; '.join(doc['registration']['violations'])
               if doc.get('registration') and not doc['registration'].get('valid', True)
               else '')
            + nominal_answer(doc.get('against_nominal'))
            + f", chi2/dof {doc['chi2']:.1f}/{doc['dof']}, "
            + (f"p = {doc['p_value']:.3g}; " if doc.get('tested', True)
               else f"{doc['not_tested_reason']}; ")
            + f"{doc['outside_training_range']} outside the training ranges"
            + (f"; {doc['repeated_from_training']} at training poses "
               f"measured again, rms "
               f"{doc['rms_repeated_from_training_m'] * 1e6:.1f} µm"
               if doc['repeated_from_training'] else '')
            + learned_answer(doc.get('learned_residual')))


def nominal_answer(versus: dict[str, Any] | None) -> str:
    """~/validate: the calibrated robot against the nominal one on the new points, both
    placed on them (``against_nominal``; '' without)."""
    if not versus:
        return ''
    z = versus['z'] if versus['z'] is not None else float('nan')
    head = nominal_verdict(versus) + (', it does harm here' if versus['worse_than_nominal']
                                      else '')
    return (f"; {head}: the calibrated robot {versus['rms_m'] * 1e6:.1f} µm, the nominal "
            f"robot {versus['nominal_rms_m'] * 1e6:.1f} µm, both placed on these points "
            f"(paired z {z:.2f})")


def learned_answer(learned: dict[str, Any] | None) -> str:
    """~/validate: the learned residual's part of the answer ('' without one)."""
    if learned is None:
        return ''
    if 'skipped' in learned:
        return f"; learned residual {learned['skipped']}"
    return (f"; with the learned residual rms {learned['rms_m'] * 1e6:.1f} µm, "
            f"{learned['inside_95_share']:.1%} in the stated 95 % ellipsoid, p = "
            f"{learned['p_value']:.3g} ({learned['tested_points']} points worth "
            f"{learned['effective_points']:.0f} independent ones): its uncertainty "
            + ('holds' if learned['holds'] else 'does not hold, learn it again'))


def campaign_progress(status: Any, planned: int) -> str:
    """A sequential campaign's measurements, largest TCP std against its target, and
    whether it stopped or how many poses are planned."""
    return (f'{status.measurements} measurements, largest TCP std '
            f'{status.statistic * 1e6:.2f} µm (target '
            f'{status.target_std * 1e6:.2f} µm), '
            + (f'stopped: {status.stop_reason}' if status.stopped
               else f'{planned} poses planned'))


__all__ = ['campaign_progress', 'design_answer', 'identify_answer', 'validate_answer']

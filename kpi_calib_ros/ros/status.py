"""The node's health as /diagnostics reports it: a pure function of plain data.

No rclpy here: :func:`node_status` takes the run state, the campaign's counts and what
the subscriptions lost, and returns (level, message, key values); the node converts
that into a ``diagnostic_msgs/DiagnosticArray``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from kpi_calib_ros.core.campaigns.settings import MODEL_INADEQUATE
from kpi_calib_ros.core.estimation.residuals import is_adequate
from kpi_calib_ros.ros.run_state import RunState


@dataclass(frozen=True)
class StreamHealth:
    """Messages lost before the node read them (joint states; points, tracked poses and
    their σ together) and the largest publication-to-callback lag of joint states (ns)."""

    lost_joint_states: int = 0
    lost_points: int = 0
    max_lag_ns_joint_states: int = 0


def node_status(run: RunState, counts: Mapping[str, int], streams: StreamHealth, *,
                job: str = '', model_ready: bool = True, model_error: str = '',
                identifications: int = 0, log_file: str = '', tcp_query: str = '',
                station: str = '') -> tuple[str, str, dict[str, Any]]:
    """(level, message, key values) of the node.

    Parameters
    ----------
    run : RunState
        The current run's results and sequential campaign.
    counts : mapping
        :meth:`kpi_calib_ros.ros.measurement_store.MeasurementStore.counts` (``accepted``,
        ``rejected``, ``rejected.<reason>``, ...).
    streams : StreamHealth
    job : str
        The running job ('' when idle).
    model_ready : bool
        The robot model is known.
    model_error : str
        Why the robot description was rejected ('' if it was not).
    identifications : int
        Calibrations published since the node started.
    log_file : str
        The measurement log being written.
    station : str
        The tracker station the arriving measurements belong to ('' : not given).
    tcp_query : str
        What ``~/tcp_query`` last answered with, and why not with the learned residual
        when there is one (:attr:`kpi_calib_ros.ros.tcp_query.TcpQuery.source`; '' before
        the first answer).

    Returns
    -------
    level : str
        'OK', 'WARN' or 'ERROR'.
    message : str
        The first reason for the level.
    values : dict
        Key values in a stable order.
    """
    values: dict[str, Any] = {'state': job or (
        'waiting for robot description' if not model_ready else 'idle')}
    values.update(counts)
    values.update({'identified_with': run.identified_with,
                   'identifications': identifications,
                   'lost.joint_states': streams.lost_joint_states,
                   'lost.points': streams.lost_points,
                   'max_lag_ms.joint_states': round(streams.max_lag_ns_joint_states * 1e-6, 1),
                   'log_file': log_file})
    if station:
        values['station'] = station
    lost = values['lost.joint_states'] + values['lost.points']
    result, n, rejected = run.result, values['accepted'], values['rejected']
    if result is not None:
        values.update({'rms_um': round(result.rms_m * 1e6, 3),
                       'p_value': float(result.p_value), 'converged': result.converged})
    restored = run.restored if result is None else None
    if restored is not None:
        # The calibration of an earlier run, read back at start (no fit of this run).
        values['calibration'] = restored.summary()
        if restored.rms_m is not None:
            values['rms_um'] = round(restored.rms_m * 1e6, 3)
        if restored.p_value is not None:
            values['p_value'] = restored.p_value
    if run.robust is not None:
        values.update({'sigma_robust_um': round(run.robust.sigma_robust * 1e6, 3),
                       'excluded_measurements': len(run.robust.excluded)})
    if run.learned_residual:
        values['learned_residual'] = run.learned_residual
    if tcp_query:
        values['tcp_query'] = tcp_query
    if run.diagnosis is not None:
        best = next((c['spec'] for c in run.diagnosis['candidates'] if c['significant']),
                    'none')
        values.update({'model_adequate': run.diagnosis['model_adequate'],
                       'suggested_effect': best})
    seq, state = run.sequential_status, run.sequential_state
    if state is not None:
        # The campaign's own target (the one its status and stop rule use).
        values.update({'campaign': 'sequential',
                       'campaign.measurements': seq.measurements if seq else 0,
                       'campaign.tcp_std_um': round(seq.statistic * 1e6, 3) if seq
                       else float('inf'),
                       'campaign.target_um': round(state.settings.target_std * 1e6, 3),
                       'campaign.max_measurements': state.settings.max_measurements,
                       'campaign.excluded': len(seq.excluded) if seq else 0,
                       'campaign.resumed': run.resumed or run.resume_pending,
                       'campaign.stop_reason': (
                           'resuming' if run.resume_pending else run.sequential_stopped
                           or (seq.stop_reason if seq else '') or 'running')})
    error = model_error or run.result_error
    if error or values['rejected.not_stored']:
        return 'ERROR', error or 'accepted measurements could not be stored', values
    if seq is not None and seq.stop_reason == MODEL_INADEQUATE:
        return 'WARN', f'sequential campaign stopped: {MODEL_INADEQUATE}', values
    if run.robust is not None and run.robust.warnings:
        return 'WARN', run.robust.warnings[0], values
    p_value = result.p_value if result is not None else (
        restored.p_value if restored is not None else None)
    if p_value is not None and not is_adequate(p_value):
        return 'WARN', f'model inadequate (p = {p_value:.2g})', values
    if lost:
        return 'WARN', (f"{values['lost.joint_states']} joint states and "
                        f"{values['lost.points']} points lost before the node read them "
                        '(queue overflow: the node fell behind)'), values
    if rejected:
        return 'WARN', f'{n} accepted, {rejected} rejected', values
    if not model_ready:
        return 'OK', 'waiting for robot description', values
    if restored is not None:
        return 'OK', f"{n} accepted, calibration {values['calibration']}", values
    return 'OK', f'{n} accepted' + ('' if result is None else
                                    f', rms {result.rms_m * 1e6:.1f} µm'), values


__all__ = ['StreamHealth', 'node_status']

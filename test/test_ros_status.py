"""The node's /diagnostics status and its run state, with plain data (no rclpy): the level
follows the first problem in order of gravity, the values say what the node holds, and a
sequential campaign's questions (running, step due) are answered from the state alone."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

from kpi_calib_ros.core.campaigns.settings import MODEL_INADEQUATE, CampaignSettings
from kpi_calib_ros.io.campaign_io import CampaignState
from kpi_calib_ros.ros.run_state import RunState
from kpi_calib_ros.ros.status import StreamHealth, node_status


def counts(accepted: int = 0, rejected: int = 0, not_stored: int = 0) -> dict[str, int]:
    return {'accepted': accepted, 'restored': 0, 'rejected': rejected + not_stored,
            'rejected.not_stored': not_stored}


def fit(rms_m: float = 2.5e-5, p_value: float = 0.4) -> SimpleNamespace:
    return SimpleNamespace(rms_m=rms_m, p_value=p_value, converged=True)


def campaign_status(stop_reason: str = '', measurements: int = 12) -> SimpleNamespace:
    return SimpleNamespace(stop_reason=stop_reason, measurements=measurements,
                           statistic=8e-6, excluded=[{}], stopped=bool(stop_reason))


def state(stop_reason: str = 'running') -> CampaignState:
    return CampaignState(CampaignSettings(target_std=1e-5, max_measurements=60), 7,
                         status={'stop_reason': stop_reason})


def test_a_fresh_node_waits_for_the_robot_description():
    level, message, values = node_status(RunState(), counts(), StreamHealth(),
                                         model_ready=False, log_file='/d/measurements_1.mcap')
    assert (level, message) == ('OK', 'waiting for robot description')
    assert values['state'] == 'waiting for robot description'
    assert values['log_file'] == '/d/measurements_1.mcap' and values['identified_with'] == 0
    assert 'rms_um' not in values and 'campaign' not in values


def test_an_identified_run_reports_its_fit_and_the_running_job():
    run = RunState(result=fit(), identified_with=30,
                   robust=SimpleNamespace(sigma_robust=2.1e-5, excluded=[1], warnings=[]))
    level, message, values = node_status(run, counts(30), StreamHealth(
        max_lag_ns_joint_states=1_234_567), job='identifying', identifications=2)
    assert (level, message) == ('OK', '30 accepted, rms 25.0 µm')
    assert values['state'] == 'identifying' and values['identifications'] == 2
    assert values['rms_um'] == 25.0 and values['p_value'] == 0.4 and values['converged']
    assert values['sigma_robust_um'] == 21.0 and values['excluded_measurements'] == 1
    assert values['max_lag_ms.joint_states'] == 1.2
    # The order of the values is stable: the campaign's counts come right after the state.
    assert list(values)[:3] == ['state', 'accepted', 'restored']


def restored(p_value: float) -> SimpleNamespace:
    """A calibration.yaml read back at start (app.stored_calibration.StoredCalibration)."""
    return SimpleNamespace(rms_m=2.5e-5, p_value=p_value,
                           summary=lambda: 'restored from /d/calibration.yaml, identified '
                                           'at 17 ns')


def test_a_restored_calibration_is_reported_until_a_fit_replaces_it():
    level, message, values = node_status(RunState(restored=restored(0.4), identified_with=30),
                                         counts(30), StreamHealth())
    assert (level, message) == ('OK', '30 accepted, calibration restored from '
                                '/d/calibration.yaml, identified at 17 ns')
    assert values['rms_um'] == 25.0 and values['p_value'] == 0.4
    assert 'converged' not in values and values['identifications'] == 0
    # Restored, a model that was not adequate warns as it did when it was identified.
    level, message, _ = node_status(RunState(restored=restored(1e-9)), counts(30),
                                    StreamHealth())
    assert (level, message) == ('WARN', 'model inadequate (p = 1e-09)')
    # A fit of this run is the calibration: the restored one is no longer reported.
    _, message, values = node_status(RunState(result=fit(), restored=restored(0.4)),
                                     counts(30), StreamHealth())
    assert message == '30 accepted, rms 25.0 µm' and 'calibration' not in values


@pytest.mark.parametrize('run, c, streams, model_error, expected', [
    (RunState(result_error='identification failed: disk full', result=fit(p_value=1e-9)),
     counts(5, rejected=2), StreamHealth(lost_points=1), '',
     ('ERROR', 'identification failed: disk full')),
    (RunState(), counts(5, not_stored=1), StreamHealth(), '',
     ('ERROR', 'accepted measurements could not be stored')),
    (RunState(), counts(), StreamHealth(), 'robot description rejected: no joints',
     ('ERROR', 'robot description rejected: no joints')),
    (RunState(sequential_status=campaign_status(MODEL_INADEQUATE), sequential_state=state(),
              result=fit(p_value=1e-9)), counts(12), StreamHealth(), '',
     ('WARN', f'sequential campaign stopped: {MODEL_INADEQUATE}')),
    (RunState(robust=SimpleNamespace(sigma_robust=6e-5, excluded=[], warnings=['sigma 3x']),
              result=fit(p_value=1e-9)), counts(9), StreamHealth(lost_joint_states=4), '',
     ('WARN', 'sigma 3x')),
    (RunState(result=fit(p_value=1e-9)), counts(9, rejected=1), StreamHealth(), '',
     ('WARN', 'model inadequate (p = 1e-09)')),
    (RunState(), counts(9, rejected=1), StreamHealth(lost_joint_states=4, lost_points=1), '',
     ('WARN', '4 joint states and 1 points lost before the node read them (queue overflow: '
              'the node fell behind)')),
    (RunState(), counts(9, rejected=3), StreamHealth(), '', ('WARN', '9 accepted, 3 rejected')),
])
def test_the_level_is_the_gravest_problem(run, c, streams, model_error, expected):
    level, message, _ = node_status(run, c, streams, model_error=model_error)
    assert (level, message) == expected


def test_a_sequential_campaign_reports_its_own_target_and_stop():
    run = RunState(sequential_state=state(), sequential_status=campaign_status())
    values = node_status(run, counts(12), StreamHealth())[2]
    assert values['campaign'] == 'sequential' and values['campaign.measurements'] == 12
    assert values['campaign.tcp_std_um'] == 8.0 and values['campaign.target_um'] == 10.0
    assert values['campaign.max_measurements'] == 60 and values['campaign.excluded'] == 1
    assert values['campaign.stop_reason'] == 'running' and not values['campaign.resumed']
    resuming = node_status(RunState(sequential_state=state(), resume_pending=True),
                           counts(), StreamHealth())[2]
    assert resuming['campaign.stop_reason'] == 'resuming' and resuming['campaign.resumed']
    assert resuming['campaign.tcp_std_um'] == float('inf')


def test_run_state_answers_whether_a_campaign_runs_and_a_step_is_due():
    assert not RunState().sequential_running() and not RunState().sequential_due(50)
    running = RunState(sequential=SimpleNamespace(), sequential_initial=10,
                       sequential_stamps={1, 2, 3})
    assert running.sequential_running()
    assert not running.sequential_due(9)       # the initial design is not measured yet
    assert running.sequential_due(10)
    done = RunState(sequential=SimpleNamespace(), sequential_initial=2,
                    sequential_stamps={1, 2, 3}, sequential_status=campaign_status('target met'))
    assert not done.sequential_running() and not done.sequential_due(10)
    assert not done.campaign_inadequate()
    assert RunState(sequential_status=campaign_status(MODEL_INADEQUATE)).campaign_inadequate()
    # Found at start and not yet resumed: running if its file says so, never due.
    pending = RunState(sequential_state=state(), resume_pending=True)
    assert pending.sequential_running() and not pending.sequential_due(100)
    assert not RunState(sequential_state=state('target met'),
                        resume_pending=True).sequential_running()


"""kpi_calib_node over several tracker stations, end to end (the node a separate process,
real rclpy and Fast DDS): the cell controller names the station with the ``station``
parameter; every accepted measurement keeps its station in the measurement log, so it
survives a restart; ``~/identify`` identifies every station together, each with its own
placement, and the calibration says what each contributed; ``~/validate`` places later
measurements from a station it holds as it placed that station."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

from kpi_calib_ros.app.measurements import with_recordings
from kpi_calib_ros.app.validate import calibrated_model
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.measurement import recordings as rec
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.measurement_log import DEFAULT_STATION, MeasurementLog, log_station
from kpi_calib_ros.ros.measurement_store import MeasurementStore

N_POSES = 30
# The far station: the tracker 3.2 m and 0.7 rad away from the near one, ground tilted.
MOVE = np.array([2.5, -2.0, 0.15, 0.03, -0.02, 0.7])
STATIONS = [rec.Recording('near'), rec.Recording('far')]


def _station(cm, p_robot, move, n, rng, sigma):
    single = p_robot.copy()
    single[:6] += move
    q = random_configurations(cm.model, single, n, rng)
    return simulate_measurements(cm.model, single, q, sigma, rng)


def _truth(cm, p_robot):
    """The true vector of the two-station model."""
    model = rec.placed_model(cm.model, STATIONS)
    truth = np.concatenate([p_robot, np.zeros(len(model.params) - len(p_robot))])
    truth[model.params.indices(rec.base_names('far'))] = p_robot[:6] + MOVE
    return truth


def _set_station(client, name: str) -> None:
    params = AsyncParameterClient(client.node, 'kpi_calib_node')
    assert params.wait_for_services(timeout_sec=10)
    future = params.set_parameters([Parameter('station', value=name)])
    client.executor.spin_until_future_complete(future, timeout_sec=10)
    result = future.result().results[0]
    assert result.successful, result.reason


@pytest.mark.slow
def test_two_stations_metres_apart_are_identified_together_across_a_restart(cm, client,
                                                                           spawn, tmp_path):
    rng = np.random.default_rng(5)
    sigma = float(np.max(cm.cell.sigma))
    p_robot = true_parameters(cm.model.params, rng)
    near = _station(cm, p_robot, np.zeros(6), N_POSES, rng, sigma)
    far = _station(cm, p_robot, MOVE, N_POSES, rng, sigma)
    data_dir = tmp_path / 'data'
    frame = cm.cell.tracker_frame
    node = spawn(data_dir, 'node_1.log', 'auto_identify:=false', 'station:=near')
    try:
        client.publish_measurements(near.q, cm.joint_names, near.eta, frame, N_POSES)
        _set_station(client, 'far')  # the tracker was moved
        client.publish_measurements(far.q, cm.joint_names, far.eta, frame, 2 * N_POSES,
                                    start_ns=1_700_000_100_000_000_000)
        assert node.stop() == 0, node.output()
        # A restart without the parameter continues the last station; the log keeps each.
        client.received.clear()
        node = spawn(data_dir, 'node_2.log', 'auto_identify:=false')
        client.spin_until(lambda: client.count('accepted') == 2 * N_POSES
                          and client.diagnostics().get('station') == 'far'
                          and client.count('stations') == 2
                          and client.diagnostics().get('state') == 'idle', 60,
                          'the robot model and the restored measurements of both stations, '
                          'the last one current')
        answer = client.call('identify', timeout=180)
        assert answer.success, answer.message
        print(answer.message)
        assert 'recording near: 30 poses' in answer.message, answer.message
        assert 'recording far: 30 poses' in answer.message, answer.message
        client.spin_until(lambda: client.received['calibration'], 10, 'the calibration')
        doc = client.received['calibration'][-1]
        # Later poses from the far station (the current one): ~/validate places them with
        # the far station's stored placement, no re-registration (validate_register '').
        later = _station(cm, p_robot, MOVE, 10, np.random.default_rng(6), sigma)
        client.publish_measurements(later.q, cm.joint_names, later.eta, frame,
                                    2 * N_POSES + 10, start_ns=1_700_000_200_000_000_000)
        answer = client.call('validate', timeout=60)
        print(answer.message)
        assert answer.success, answer.message
        assert answer.message.startswith('calibration holds on 10 new measurements')
        assert 'placed as station far of the calibration' in answer.message
        assert '; better than no calibration: the calibrated robot' in answer.message
        # The calibration of both stations is served again after a restart.
        assert node.stop() == 0, node.output()
        client.received.clear()
        node = spawn(data_dir, 'node_3.log', 'auto_identify:=false')
        client.spin_until(lambda: client.diagnostics().get('calibration', '').startswith(
            'restored from'), 60, 'the restored calibration')
        client.spin_until(lambda: client.received['calibration'], 10, 'the calibration')
        assert client.received['calibration'][-1] == doc
    finally:
        code = node.stop()
    assert code == 0, node.output()
    assert "station 'far'" in node.output()
    logs = sorted(data_dir.glob('measurements_*.mcap'))
    assert [log_station(p)[0] for p in logs] == ['near', 'far', 'far', 'far']
    assert [r['name'] for r in doc['recordings']] == ['near', 'far']
    assert [r['poses'] for r in doc['recordings']] == [N_POSES, N_POSES]

    # Every identified parameter within 3σ of the equivalent truth (the true robot in the
    # kept parameters: a noise-free fit to 300 fresh poses of each station).
    placed = with_recordings(cm, STATIONS)
    names = [p['name'] for p in doc['parameters']]
    assert names == list(placed.model.params.names)
    values = np.array([p['value'] for p in doc['parameters']])
    estimated = [p['name'] for p in doc['parameters'] if p['estimated']]
    std = np.array([p['std'] for p in doc['parameters'] if p['estimated']])
    assert set(rec.base_names('far')) <= set(estimated)
    dense = rec.combine([_station(cm, p_robot, np.zeros(6), 300, rng, 1e-300),
                         _station(cm, p_robot, MOVE, 300, rng, 1e-300)], STATIONS)
    truth = _truth(cm, p_robot)
    dense = dataclasses.replace(dense, eta=placed.model.predict(truth, dense.q,
                                                                covariates=dense.covariates))
    equivalent = identify(placed.model, dense, sigma, cm.q_work, p0=values, free=estimated)
    assert equivalent.rms_m < 1e-9
    idx = placed.model.params.indices(estimated)
    z = (values[idx] - equivalent.values[idx]) / std
    worst = int(np.argmax(np.abs(z)))
    far_base = placed.model.params.indices(rec.base_names('far'))
    print(f'worst |error|/sigma {abs(z[worst]):.2f} ({estimated[worst]}) of {len(z)}; far '
          f'station base error {np.abs(values[far_base] - truth[far_base]).max():.2e}')
    assert np.all(np.abs(z) < 3), estimated[worst]


def test_an_old_log_without_station_loads_as_one_station_and_a_new_station_starts_a_file(
        cm, tmp_path):
    """A log written before stations were stored (no station in its metadata) is one
    station; a station measured before keeps whether its probe was remounted."""
    from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
    old = tmp_path / 'old'
    with MeasurementLog(old, station='') as log:  # as before: no station named
        log.append(JointSample(1, tuple(cm.joint_names), np.zeros(len(cm.joint_names))),
                   PointSample(1, cm.cell.tracker_frame, np.ones(3)))
    assert log_station(old / 'measurements_1.mcap') == (DEFAULT_STATION, False)
    store = MeasurementStore(old)
    try:
        recordings, index = store.stations(np.array([1]))
        assert recordings == [rec.Recording(DEFAULT_STATION)] and index.tolist() == [0]
        assert store.set_station('b', True)
        assert log_station(store.log.path) == ('b', True)
        assert store.station_conflict(DEFAULT_STATION, True).startswith(
            f"station '{DEFAULT_STATION}' was measured with station_reflector_remounted false")
        with pytest.raises(ValueError, match='must start with a letter'):
            store.set_station('2nd station')
    finally:
        store.close()


@pytest.mark.slow
def test_identify_names_the_rows_rejected_on_arrival(cm, client, spawn, tmp_path):
    """A second station's bag simulated with the first one's stamps: its points are
    rejected as duplicate stamps (a bag replayed twice is not counted twice), and
    ~/identify, which answered success with one station and said nothing, names them."""
    rng = np.random.default_rng(7)
    sigma = float(np.max(cm.cell.sigma))
    p_robot = true_parameters(cm.model.params, rng)
    near = _station(cm, p_robot, np.zeros(6), N_POSES, rng, sigma)
    far = _station(cm, p_robot, MOVE, N_POSES, rng, sigma)
    frame = cm.cell.tracker_frame
    node = spawn(tmp_path / 'data', 'node.log', 'auto_identify:=false', 'station:=near')
    try:
        client.publish_measurements(near.q, cm.joint_names, near.eta, frame, N_POSES)
        _set_station(client, 'far')
        client.publish_measurements(far.q, cm.joint_names, far.eta, frame, N_POSES)
        client.spin_until(lambda: client.count('rejected.duplicate_stamp') == N_POSES, 60,
                          'the far station\'s points rejected as duplicates')
        answer = client.call('identify', timeout=180)
        assert answer.success, answer.message
        assert (f'rejected on arrival, not in this fit: {N_POSES} duplicate_stamp'
                in answer.message), answer.message
    finally:
        assert node.stop() == 0, node.output()


def _remounted(client) -> bool:
    params = AsyncParameterClient(client.node, 'kpi_calib_node')
    assert params.wait_for_services(timeout_sec=10)
    future = params.get_parameters(['station_reflector_remounted'])
    client.executor.spin_until_future_complete(future, timeout_sec=10)
    return bool(future.result().values[0].bool_value)


@pytest.mark.slow
def test_a_station_set_alone_takes_its_own_remount_not_the_last_ones(cm, client, spawn,
                                                                     tmp_path):
    """station_reflector_remounted is a parameter and kept its value: a new station set
    alone after a remounted one was logged as remounted too (its probe got offsets of its
    own, silently; then a warning). Now a station set alone takes its own remount: a new
    one is not remounted, one measured before keeps the remount it was measured with, and
    the parameter follows."""
    rng = np.random.default_rng(3)
    near = _station(cm, true_parameters(cm.model.params, rng), np.zeros(6), 5, rng,
                    float(np.max(cm.cell.sigma)))
    node = spawn(tmp_path / 'data', 'node.log', 'auto_identify:=false', 'station:=b',
                 'station_reflector_remounted:=true')
    try:
        client.spin_until(lambda: client.diagnostics().get('station') == 'b', 30, 'station b')
        client.publish_measurements(near.q, cm.joint_names, near.eta, cm.cell.tracker_frame, 5)
        _set_station(client, 'd')
        client.spin_until(lambda: client.diagnostics().get('station') == 'd', 30, 'station d')
        assert not _remounted(client)
        logs = sorted((tmp_path / 'data').glob('measurements_*.mcap'))
        assert [log_station(p) for p in logs] == [('b', True), ('d', False)]
        _set_station(client, 'b')  # measured remounted: it stays so
        client.spin_until(lambda: client.diagnostics().get('station') == 'b', 30, 'back to b')
        assert _remounted(client)
        assert 'takes station_reflector_remounted' not in node.output()
    finally:
        assert node.stop() == 0, node.output()


def _identify_near_then_far(client, cm, near, far) -> None:
    """Measure ``near`` from station near (the node started there), set station far,
    measure ``far``, and ~/identify both stations together."""
    frame = cm.cell.tracker_frame
    client.publish_measurements(near.q, cm.joint_names, near.eta, frame, len(near))
    _set_station(client, 'far')
    client.publish_measurements(far.q, cm.joint_names, far.eta, frame, len(near) + len(far),
                                start_ns=1_700_000_100_000_000_000)
    answer = client.call('identify', timeout=180)
    assert answer.success, answer.message


@pytest.mark.slow
def test_the_design_for_a_station_the_calibration_holds_predicts_its_identification(
        cm, client, spawn, tmp_path):
    """Two stations identified together, the far one from a few poses: ~/design plans the
    far station from where the calibration places it, with the calibration as prior (as
    ``kpi-calib design --prior`` does with that station's cell file). The TCP std it
    predicts at the far station is the one the identification of everything measured and
    its poses gives there (offline, 4.544 / 4.369 / 4.813 µm both). Before, ~/design planned
    where the cell file places the robot (the near station) as if nothing had been
    measured, and predicted 8.7 / 9.7 / 9.4 µm."""
    import yaml
    rng = np.random.default_rng(21)
    sigma = float(np.max(cm.cell.sigma))
    p_robot = true_parameters(cm.model.params, rng)
    near = _station(cm, p_robot, np.zeros(6), N_POSES, rng, sigma)
    far = _station(cm, p_robot, MOVE, 12, rng, sigma)
    frame = cm.cell.tracker_frame
    data_dir = tmp_path / 'data'
    node = spawn(data_dir, 'node.log', 'auto_identify:=false', 'station:=near',
                 'num_measurements:=20')
    try:
        _identify_near_then_far(client, cm, near, far)
        answer = client.call('design', timeout=300)
        print(answer.message)
        assert answer.success, answer.message
        assert "designed for station 'far' with the calibration of stations near, far" \
            in answer.message
        design = yaml.safe_load((data_dir / 'design.yaml').read_text())
        assert design['prior']['station'] == 'far'
        q = np.array(design['configurations'])
        predicted = np.array(design['working_poses'][0]['tcp_std_m'])
        single = p_robot.copy()
        single[:6] += MOVE
        measured = simulate_measurements(cm.model, single, q, sigma, rng)
        client.publish_measurements(q, cm.joint_names, measured.eta, frame,
                                    N_POSES + 12 + len(q),
                                    start_ns=1_700_000_200_000_000_000)
        answer = client.call('identify', timeout=180)
        assert answer.success, answer.message
        client.spin_until(lambda: len(client.received['calibration']) == 2, 10,
                          'the second calibration')
        doc = client.received['calibration'][-1]
        # The TCP covariance of that identification in the far station's tracker frame
        # (the design's), from its parameter covariance: J C Jᵀ, dense.
        placed, values = calibrated_model(cm.cell, doc)
        names = doc['parameter_covariance']['names']
        cov = np.array(doc['parameter_covariance']['matrix'], float)
        _, jac = placed.model.jacobian(values, placed.q_work, covariates={
            'recording.far': np.ones(len(placed.q_work))})
        jac = jac.reshape(-1, len(values))[:3, placed.model.params.indices(names)]
        reported = np.sqrt(np.diag(jac @ cov @ jac.T))
        print(f'TCP std at the far station predicted {np.round(predicted * 1e6, 3)} µm, '
              f'identified {np.round(reported * 1e6, 3)} µm')
        np.testing.assert_allclose(predicted, reported, rtol=0.01)
    finally:
        assert node.stop() == 0, node.output()


@pytest.mark.slow
def test_a_sequential_campaign_runs_at_a_later_station_from_where_it_stands(cm, client, spawn,
                                                                           tmp_path):
    """A sequential campaign at a station the published calibration of several stations
    holds plans from where that calibration places it and identifies that station's
    measurements only, until the target is met; killed mid-campaign, the restarted node
    resumes it at that station with the same plan. Before, any step with measurements from
    two stations failed ("a sequential campaign plans from one station"), so after a
    station change the campaign could not run without archiving the first station."""
    import signal

    import yaml
    from std_msgs.msg import String

    from kpi_calib_ros.app.campaign import campaign_context, new_campaign
    from kpi_calib_ros.app.design import design_free, design_point
    from kpi_calib_ros.core.campaigns.settings import TARGET_MET, CampaignSettings
    from kpi_calib_ros.ros import job_work

    from ros_helpers import LATCHED, NS
    target = 9e-6
    rng = np.random.default_rng(23)
    sigma = float(np.max(cm.cell.sigma))
    p_robot = true_parameters(cm.model.params, rng)
    near = _station(cm, p_robot, np.zeros(6), N_POSES, rng, sigma)
    far = _station(cm, p_robot, MOVE, 8, rng, sigma)
    single = p_robot.copy()
    single[:6] += MOVE
    frame = cm.cell.tracker_frame
    client.node.create_subscription(String, f'{NS}/campaign_status',
                                    client._recorder('campaign_status'), LATCHED)
    node = spawn(tmp_path / 'data', 'node.log', 'auto_identify:=false', 'station:=near',
                 'campaign:=sequential', f'target_tcp_std:={target}', 'max_measurements:=80')
    try:
        _identify_near_then_far(client, cm, near, far)
        calibration = client.received['calibration'][-1]
        answer = client.call('design', timeout=300)
        print(answer.message)
        assert answer.success, answer.message
        assert "station 'far' placed where the published calibration" in answer.message
        client.spin_until(lambda: client.received['measurement_poses'], 10, 'the initial design')
        initial = np.array([p.positions for p in client.received['measurement_poses'][-1].points])
        # The same campaign offline, planned where the calibration places the far station,
        # with that calibration as prior: an initial design of a few poses, not the 11 a
        # campaign that knows nothing needs.
        placed, _, cp = job_work.station_campaign(cm, yaml.safe_dump(calibration), 'far')
        p, free = design_point(placed, cp), design_free(placed, cp.allowed)
        cell, ctx = campaign_context(placed, 0, prior=cp.prior, p=p, free=free)
        offline = new_campaign(placed, cell, ctx, CampaignSettings(
            target_std=target, max_measurements=80), 0, prior=cp.prior, start=p, free=free)
        np.testing.assert_allclose(ctx.candidates.configurations[offline.initial_design()],
                                   initial, atol=1e-12)
        alone, alone_ctx = campaign_context(placed, 0)
        without = new_campaign(placed, alone, alone_ctx, CampaignSettings(
            target_std=target, max_measurements=80), 0)
        print(f'initial design {len(initial)} poses with the prior, '
              f'{len(without.initial_design())} without')
        assert len(initial) < len(without.initial_design())
        measured = 8
        stamp = 1_700_000_200_000_000_000
        plan = initial
        plans_seen = len(client.received['measurement_poses'])
        resumed = False
        while True:
            eta = simulate_measurements(cm.model, single, plan, sigma, rng).eta
            client.publish_measurements(plan, cm.joint_names, eta, frame,
                                        N_POSES + measured + len(plan), start_ns=stamp)
            measured += len(plan)
            stamp += 100_000_000_000

            def reported(count: int = measured) -> bool:
                return any(yaml.safe_load(m.data).get('measurements') == count
                           for m in client.received['campaign_status'])
            client.spin_until(reported, 90, f'the campaign status after {measured}')
            status = next(d for d in (yaml.safe_load(m.data) for m in
                                      client.received['campaign_status'])
                          if d.get('measurements') == measured)
            if status['stop_reason'] != 'running':
                break
            assert measured < 80, 'the campaign did not stop'
            client.spin_until(lambda seen=plans_seen: len(client.received['measurement_poses'])
                              > seen, 10, 'the updated plan')
            plans_seen = len(client.received['measurement_poses'])
            plan = np.array(client.received['measurement_poses'][-1].points[0].positions)[None]
            if not resumed:  # killed mid-campaign: the restart resumes it at the far station
                resumed = True
                assert node.stop(signal.SIGKILL) == -signal.SIGKILL
                client.received['measurement_poses'].clear()
                client.received['diagnostics'].clear()
                node = spawn(tmp_path / 'data', 'node_2.log', 'auto_identify:=false',
                             'campaign:=sequential', f'target_tcp_std:={target}',
                             'max_measurements:=80')
                client.spin_until(lambda: client.diagnostics().get('campaign.resumed')
                                  == 'True', 90, 'the campaign resumed')
                client.spin_until(lambda: client.received['measurement_poses'], 30,
                                  'the plan after the restart')
                again = client.received['measurement_poses'][-1].points[0].positions
                np.testing.assert_allclose(again, plan[0], atol=1e-9)
                plans_seen = len(client.received['measurement_poses'])
        print(f"stopped after {measured} far measurements: {status['stop_reason']}, TCP std "
              f"{status['statistic_m'] * 1e6:.2f} µm")
        assert status['stop_reason'] == TARGET_MET and status['statistic_m'] <= target
        assert resumed, 'the campaign stopped before the kill: nothing resumed'
        # The campaign counted the far station's measurements only, not the near 30.
        assert status['measurements'] == measured
    finally:
        assert node.stop() == 0, node.output()

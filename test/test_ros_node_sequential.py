"""kpi_calib_node in a sequential campaign, end to end (node process, real rclpy, Fast DDS).

A simulated robot client plays the cell controller: it calls ~/design, drives to every
pose the node publishes on ~/measurement_poses (the initial design, then always the
first pose of the updated plan), publishes still joint states around each stop and the
tracker point of a simulated true robot. The campaign must stop by itself with the
target met, and its figures must equal the same campaign run offline on the same data.
"""
from __future__ import annotations

import signal

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import Point, PointStamped
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Header, String

from kpi_calib_ros.app.campaign import campaign_context, new_campaign
from kpi_calib_ros.core.campaigns.settings import MODEL_INADEQUATE, TARGET_MET, CampaignSettings
from kpi_calib_ros.core.simulation import true_parameters
from kpi_calib_ros.ros import conversions as cv

from ros_helpers import KR15_URDF, LATCHED, NS, Client, Spawner

pytestmark = pytest.mark.slow
# Below what the initial design reaches at the stated σ (about 17 µm for its 12 poses), so the
# node must plan and the client drive to further poses; at 15 µm a low noise draw let the
# initial design alone meet it and the loop was never exercised.
TARGET = 12e-6
SECOND = 1_000_000_000


def measure(client: Client, names: list[str], q: np.ndarray, point: np.ndarray,
            stamp: int) -> None:
    """The robot still at ``q`` from stamp - 0.4 s to stamp + 0.4 s (50 Hz), the tracker
    point at ``stamp``."""
    for dt in range(-400_000_000, 400_000_001, 20_000_000):
        client.joints.publish(JointState(header=Header(stamp=cv.time_msg(stamp + dt)),
                                         name=names, position=[float(v) for v in q]))
    x, y, z = (float(v) for v in point)
    client.points.publish(PointStamped(header=Header(stamp=cv.time_msg(stamp),
                                                     frame_id='laser_tracker'),
                                       point=Point(x=x, y=y, z=z)))


def assert_offline_campaign_agrees(cm, initial, measured_q, measured_eta, status) -> None:
    """The campaign run offline on the node's measurements has the node's initial design,
    plans every next pose the node planned (1e-9) and stops at its statistic."""
    cell, ctx = campaign_context(cm, 0)
    offline = new_campaign(cm, cell, ctx, CampaignSettings(target_std=TARGET,
                                                           max_measurements=80), 0)
    first = ctx.candidates.configurations[offline.initial_design()]
    assert np.allclose(first, initial, atol=1e-12)
    q_all, eta_all = np.array(measured_q), np.array(measured_eta)
    result = offline.add(q_all[:len(initial)], eta_all[:len(initial)])
    for i in range(len(initial), len(q_all)):
        assert np.allclose(result.next_configurations[0], q_all[i], atol=1e-9), (
            f'measurement {i}: the node planned another pose than the campaign offline')
        result = offline.add(q_all[i:i + 1], eta_all[i:i + 1])
    assert result.stop_reason == TARGET_MET
    assert result.statistic == pytest.approx(status['statistic_m'], rel=1e-6)


def test_sequential_campaign_stops_by_itself_at_the_target(ros_domain, tmp_path, cm):
    rng = np.random.default_rng(31)
    p_true = true_parameters(cm.model.params, rng)
    sigma = float(cm.cell.sigma[0])
    spawn = Spawner(tmp_path)
    client = Client(ros_domain)
    client.node.create_subscription(String, f'{NS}/campaign_status',
                                    client._recorder('campaign_status'), LATCHED)
    client.description.publish(String(data=KR15_URDF))
    measured_q: list[np.ndarray] = []
    measured_eta: list[np.ndarray] = []
    try:
        node = spawn(tmp_path / 'data', 'node.log', 'campaign:=sequential',
                     f'target_tcp_std:={TARGET}', 'max_measurements:=80')
        client.spin_until(lambda: client.diagnostics().get('state') == 'idle', 60,
                          'the robot model')
        answer = client.call('design')
        assert answer.success, answer.message
        client.spin_until(lambda: client.received['measurement_poses'], 10, 'the initial design')
        plan = client.received['measurement_poses'][-1]
        names = list(plan.joint_names)
        initial = np.array([p.positions for p in plan.points])
        stamp = client.node.get_clock().now().nanoseconds

        def go(q: np.ndarray) -> None:
            nonlocal stamp
            stamp += 2 * SECOND
            eta = cm.model.predict(p_true, q[None, :])[0] + rng.normal(scale=sigma, size=3)
            measure(client, names, q, eta, stamp)
            measured_q.append(q)
            measured_eta.append(eta)

        for q in initial:
            go(q)
        plans_seen = len(client.received['measurement_poses'])
        while True:
            n = len(measured_q)

            def reported(count: int = n) -> bool:
                docs = [yaml.safe_load(m.data) for m in client.received['campaign_status']]
                return any(d.get('measurements') == count and 'statistic_m' in d for d in docs)
            client.spin_until(reported, 60, f'the campaign status after {n} measurements')
            status = next(d for d in (yaml.safe_load(m.data) for m in
                                      client.received['campaign_status'])
                          if d.get('measurements') == n and 'statistic_m' in d)
            if status['stop_reason'] != 'running':
                break
            client.spin_until(lambda seen=plans_seen: len(client.received['measurement_poses'])
                              > seen, 10, 'the updated plan')
            plans_seen = len(client.received['measurement_poses'])
            go(np.array(client.received['measurement_poses'][-1].points[0].positions))
            assert len(measured_q) < 80, 'the campaign did not stop'
        print(f'stopped after {status["measurements"]} measurements: '
              f'{status["stop_reason"]}, TCP std {status["statistic_m"] * 1e6:.2f} µm')
        assert status['stop_reason'] == TARGET_MET
        assert status['statistic_m'] <= TARGET
        assert status['measurements'] == len(measured_q) > len(initial)
        client.spin_until(lambda: client.diagnostics().get('campaign.stop_reason') == TARGET_MET,
                          10, 'diagnostics of the stopped campaign')
        # The finished campaign is calibrated as an automatic identification would.
        client.spin_until(lambda: any(d['measurements'] == len(measured_q)
                                      for d in client.received['calibration']),
                          60, 'the calibration of the finished campaign')
        node.stop()
    finally:
        spawn.kill_all()
        client.close()
    # The same campaign offline on the same measurements: same initial design, same plan,
    # same figures (the node only converts and calls the core).
    assert_offline_campaign_agrees(cm, initial, measured_q, measured_eta, status)


def test_campaign_survives_a_fault_a_kill_and_a_parameter_change(ros_domain, tmp_path, cm):
    """One 1 mm fault among the initial design's points, ``kill -9`` of the node after
    ~/design and right after the 13th measurement, restarts on the same data_dir, a refused
    change of the target:
    the campaign resumes (same plan as the same campaign offline, to 1e-9), excludes and
    names the fault, stops 'target met', never 'model inadequate'; no calibration is
    published before it stops, and the one it publishes states the stop statistic."""
    rng = np.random.default_rng(31)
    p_true = true_parameters(cm.model.params, rng)
    sigma = float(cm.cell.sigma[0])
    fault, kill_at = 3, 13
    spawn = Spawner(tmp_path)
    client = Client(ros_domain)
    client.node.create_subscription(String, f'{NS}/campaign_status',
                                    client._recorder('campaign_status'), LATCHED)
    client.description.publish(String(data=KR15_URDF))
    measured_q: list[np.ndarray] = []
    measured_eta: list[np.ndarray] = []
    data = tmp_path / 'data'
    args = ('campaign:=sequential', f'target_tcp_std:={TARGET}', 'max_measurements:=80')

    def statuses() -> list[dict]:
        return [yaml.safe_load(m.data) for m in client.received['campaign_status']]
    try:
        node = spawn(data, 'node.log', *args)
        client.spin_until(lambda: client.diagnostics().get('state') == 'idle', 60,
                          'the robot model')
        answer = client.call('design')
        assert answer.success, answer.message
        client.spin_until(lambda: client.received['measurement_poses'], 10, 'the initial design')
        plan = client.received['measurement_poses'][-1]
        names = list(plan.joint_names)
        initial = np.array([p.positions for p in plan.points])
        # Killed before any measurement: the restarted node publishes the same initial
        # design again and identifies nothing.
        assert node.stop(signal.SIGKILL) == -signal.SIGKILL
        for topic in ('measurement_poses', 'diagnostics'):
            client.received[topic].clear()  # what the killed node said
        node = spawn(data, 'node1.log', *args)
        client.spin_until(lambda: client.received['measurement_poses'], 90,
                          'the initial design after the restart')
        again = client.received['measurement_poses'][-1]
        np.testing.assert_allclose([p.positions for p in again.points], initial, atol=1e-12)
        client.spin_until(lambda: client.diagnostics().get('campaign.resumed') == 'True', 10,
                          'campaign.resumed')
        stamp = client.node.get_clock().now().nanoseconds

        stamps: list[int] = []

        def go(q: np.ndarray, offset: float = 0.0) -> None:
            nonlocal stamp
            stamp += 2 * SECOND
            eta = cm.model.predict(p_true, q[None, :])[0] + rng.normal(scale=sigma, size=3)
            eta[0] += offset
            measure(client, names, q, eta, stamp)
            measured_q.append(q)
            measured_eta.append(eta)
            stamps.append(stamp)

        def settle(count: int) -> None:
            """Wait until a restarted node has accepted ``count`` measurements, sending
            them again while it has not: its discovery of this client may take a while
            (a stamp it already stored is rejected as a duplicate)."""
            for _ in range(18):
                try:
                    client.spin_until(lambda: client.count('accepted') >= count, 5,
                                      f'{count} accepted measurements')
                    return
                except AssertionError:
                    for args_ in zip(measured_q, measured_eta, stamps):
                        measure(client, names, *args_)
            raise AssertionError(f'the restarted node never accepted {count} measurements')

        for i, q in enumerate(initial):
            go(q, 1e-3 if i == fault else 0.0)
        settle(len(initial))
        plans_seen = len(client.received['measurement_poses'])
        refused = None
        while True:
            n = len(measured_q)
            if n == kill_at and refused is None:
                # Killed as soon as the measurement is sent: whether it was stored or not,
                # the restarted node takes it once (the same stamp again is a duplicate).
                assert node.stop(signal.SIGKILL) == -signal.SIGKILL
                assert not client.received['calibration'], 'published before the stop'
                before = np.array([p.positions for p in
                                   client.received['measurement_poses'][-1].points])
                for topic in ('measurement_poses', 'campaign_status', 'diagnostics'):
                    client.received[topic].clear()  # what the killed node said
                node = spawn(data, 'node2.log', *args)
                client.spin_until(lambda: client.diagnostics().get('campaign.resumed') == 'True'
                                  and client.diagnostics().get('state') == 'idle', 90,
                                  'the resumed campaign')
                # The resumed campaign publishes the plan the killed one had published.
                # 30 s: the latched plan reaches a loaded machine's subscription late (10 s
                # timed out once in a full `make test` with both workers busy).
                client.spin_until(lambda: client.received['measurement_poses'], 30,
                                  'the plan of the resumed campaign')
                resumed = client.received['measurement_poses'][0]
                np.testing.assert_allclose([p.positions for p in resumed.points], before,
                                           atol=1e-9)
                settle(kill_at)
                request = SetParameters.Request(parameters=[Parameter(
                    'target_tcp_std', value=2 * TARGET).to_parameter_msg()])
                # Discovery may still list the killed nodes' services: a request sent only
                # to them is lost, so it is sent again until the new node answers.
                set_parameters = client.node.create_client(SetParameters,
                                                           f'{NS}/set_parameters')
                assert set_parameters.wait_for_service(timeout_sec=10)
                for _ in range(6):
                    future = set_parameters.call_async(request)
                    client.executor.spin_until_future_complete(future, timeout_sec=5)
                    if future.done():
                        break
                assert future.done(), 'set_parameters did not answer'
                refused = future.result().results[0]
                plans_seen = 0

            def reported(count: int = n) -> bool:
                return any(d.get('measurements') == count and 'statistic_m' in d
                           for d in statuses())
            client.spin_until(reported, 90, f'the campaign status after {n} measurements')
            status = next(d for d in statuses()
                          if d.get('measurements') == n and 'statistic_m' in d)
            if status['stop_reason'] != 'running':
                break
            assert not client.received['calibration'], 'published before the stop'
            client.spin_until(lambda seen=plans_seen: len(client.received['measurement_poses'])
                              > seen, 10, 'the updated plan')
            plans_seen = len(client.received['measurement_poses'])
            go(np.array(client.received['measurement_poses'][-1].points[0].positions))
            assert len(measured_q) < 80, 'the campaign did not stop'
        print(f'stopped after {status["measurements"]} measurements: '
              f'{status["stop_reason"]}, TCP std {status["statistic_m"] * 1e6:.2f} µm, '
              f'excluded {status.get("excluded")}')
        assert refused is not None and not refused.successful
        assert 'target_tcp_std' in refused.reason and 'campaign is running' in refused.reason
        assert all(d.get('stop_reason') != MODEL_INADEQUATE for d in statuses())
        assert status['stop_reason'] == TARGET_MET and status['statistic_m'] <= TARGET
        assert status['resumed'] is True
        assert [e['measurement'] for e in status['excluded']] == [fault]
        client.spin_until(lambda: client.diagnostics().get('campaign.stop_reason') == TARGET_MET,
                          10, 'diagnostics of the stopped campaign')
        diagnostics = client.diagnostics()
        assert float(diagnostics['campaign.target_um']) == pytest.approx(TARGET * 1e6)
        # The campaign's calibration: it states the stop statistic, at the σ it stopped on.
        client.spin_until(lambda: client.received['calibration'], 60, 'the calibration')
        calibration = client.received['calibration'][-1]
        std = np.array([t['std'] for t in calibration['tcp']])
        print(f'calibration TCP std per axis {np.round(std * 1e6, 2).tolist()} µm')
        assert std.max() == pytest.approx(status['statistic_m'], rel=1e-6)
        assert calibration['campaign']['target_met'] is True
        assert [e['index'] for e in calibration['robust']['excluded']] == [fault]
        assert len(list((data / 'calibrations').glob('*.yaml'))) == 1
        node.stop()
    finally:
        spawn.kill_all()
        client.close()
    # The same campaign offline: the node's plan after the restart is the one an
    # uninterrupted campaign makes.
    assert_offline_campaign_agrees(cm, initial, measured_q, measured_eta, status)

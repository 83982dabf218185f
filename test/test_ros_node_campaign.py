"""kpi_calib_node on a replayed campaign, end to end (real rclpy and Fast DDS).

One scenario is set up once for the module, because starting nodes and replaying is
the expensive part: a simulated 30-pose bag is replayed into the node, the node is
killed (SIGKILL) mid-replay, restarted on the same data folder, and the whole bag is
replayed again; the restarted node identifies by itself once it has all 30. Each
test then checks one behaviour of that run. The tests that
send more input or call services come last, in file order; the clean stop is the
last test.
"""
from __future__ import annotations

import json
import signal
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import Point, PointStamped
from sensor_msgs.msg import JointState
from std_msgs.msg import Header, String

from kpi_calib_ros import cli
from kpi_calib_ros.app.simulate import simulate_campaign
from kpi_calib_ros.io.bag import read_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.measurement_log import MeasurementLog
from kpi_calib_ros.ros import conversions as cv

from ros_helpers import KR15_URDF, Client, NodeProcess, Spawner, finish

pytestmark = pytest.mark.slow
N_POSES = 30


@pytest.fixture(scope='module')
def offline(tmp_path_factory) -> dict[str, Any]:
    """A simulated 30-pose bag and what `kpi-calib identify` and `kpi-calib diagnose`
    make of it offline."""
    folder = tmp_path_factory.mktemp('campaign')
    bag = folder / 'run.mcap'
    simulate_campaign(DEFAULT_CELL, N_POSES, bag, seed=21)
    assert cli.main(['identify', '--cell', str(DEFAULT_CELL), '--bag', str(bag),
                     '--out', str(folder / 'offline')]) == 0
    assert cli.main(['diagnose', '--cell', str(DEFAULT_CELL), '--bag', str(bag),
                     '--out', str(folder / 'diagnosis')]) == 0
    calibration = yaml.safe_load((folder / 'offline' / 'calibration.yaml').read_text())
    diagnosis = json.loads((folder / 'diagnosis' / 'diagnosis.json').read_text())
    joints, points = read_bag(bag)
    return {'bag': bag, 'calibration': calibration, 'diagnosis': diagnosis, 'joints': joints,
            'points': points}


@dataclass
class Run:
    """What the module's scenario left: the restarted node, still running, and what was
    seen on the way."""

    client: Client
    node: NodeProcess
    data_dir: Path
    reported_before_kill: int     # accepted, as /diagnostics last said before the kill
    logged_before_kill: list      # (joint, point) on disk after the kill
    restored: int                 # the restarted node's 'restored' count
    calibration: dict[str, Any]   # the first ~/calibration from all N_POSES measurements
    diagnostics: dict[str, str]   # /diagnostics once that calibration is reported


@pytest.fixture(scope='module')
def run(offline, ros_domain, tmp_path_factory):
    folder = tmp_path_factory.mktemp('node')
    data_dir = folder / 'data'
    spawn = Spawner(folder)
    client = Client(ros_domain)
    client.description.publish(String(data=KR15_URDF))  # as robot_state_publisher does
    try:
        first = spawn(data_dir, 'node_1.log')
        replay = spawn.replay(offline['bag'])
        try:
            client.spin_until(lambda: client.count('accepted') >= 8, 60,
                              '8 accepted measurements')
            reported = client.count('accepted')
            first_log = client.diagnostics()['log_file']
            first.process.kill()                        # SIGKILL: no chance to clean up
            assert first.stop() == -signal.SIGKILL
        finally:
            replay.kill()
            replay.wait()
        logged = MeasurementLog.load_all(data_dir)
        print(f'killed after {reported} reported accepted, {len(logged)} on disk')

        client.received.clear()
        # Identification only once every point is in: an identification running in its
        # worker thread while 1000 joint states/s arrive can starve pairing of the GIL
        # long enough to lose joint states (a load effect this scenario is not about).
        second = spawn(data_dir, 'node_2.log', f'min_measurements:={N_POSES}')
        # The restarted node logs to a new file: that tells its reports from late ones.
        client.spin_until(lambda: client.diagnostics().get('log_file', first_log) != first_log,
                          30, 'the restarted node')
        restored = client.count('restored')
        print(finish(spawn.replay(offline['bag']), client).strip())
        client.spin_until(lambda: any(d['measurements'] == N_POSES
                                      for d in client.received['calibration']),
                          60, f'a calibration from {N_POSES} measurements')
        doc = next(d for d in client.received['calibration'] if d['measurements'] == N_POSES)
        client.spin_until(lambda: client.count('identified_with') == N_POSES, 10, 'diagnostics')
        yield Run(client, second, data_dir, reported, logged, restored, doc,
                  client.diagnostics())
        second.stop()
    finally:
        spawn.kill_all()
        client.close()


def parameter_values(doc: dict[str, Any]) -> np.ndarray:
    return np.array([p['value'] for p in doc['parameters']])


# ---------------------------------------------------------------- kill and restart
def test_every_measurement_reported_before_a_kill_is_on_disk(run, offline):
    point_stamps = {p.stamp_ns for p in offline['points']}
    assert len(run.logged_before_kill) >= run.reported_before_kill >= 8
    assert {p.stamp_ns for _, p in run.logged_before_kill} <= point_stamps


def test_a_restarted_node_restores_what_was_logged(run):
    assert run.restored == len(run.logged_before_kill)


def test_measurements_received_again_are_counted_as_duplicates_not_accepted(run):
    values = run.diagnostics
    assert int(values['accepted']) == N_POSES
    assert int(values['rejected.duplicate_stamp']) == len(run.logged_before_kill)
    assert int(values['rejected']) == len(run.logged_before_kill)


# ---------------------------------------------------------------- results equal offline
def test_the_node_calibration_equals_offline_identify(run, offline):
    doc, expected = run.calibration, offline['calibration']
    assert list(doc) == list(expected)
    assert doc['measurements'] == expected['measurements'] == N_POSES
    assert [p['name'] for p in doc['parameters']] == [p['name'] for p in expected['parameters']]
    difference = np.abs(parameter_values(doc) - parameter_values(expected)).max()
    print(f'max |node - offline| parameter difference: {difference:.2e}; rms node '
          f'{doc["rms_m"] * 1e6:.3f} µm, offline {expected["rms_m"] * 1e6:.3f} µm')
    np.testing.assert_allclose(parameter_values(doc), parameter_values(expected),
                               rtol=1e-9, atol=1e-12)
    assert doc['rms_m'] == pytest.approx(expected['rms_m'], rel=1e-9)
    assert doc['model_adequacy']['p_value'] == pytest.approx(
        expected['model_adequacy']['p_value'], rel=1e-6, abs=1e-9)


def test_the_published_tcp_equals_offline_identify(run, offline):
    run.client.spin_until(lambda: run.client.received['tcp'], 10, 'tcp')
    tcp = run.client.received['tcp'][-1]
    expected = offline['calibration']['tcp'][0]
    assert tcp.header.frame_id == 'laser_tracker'
    p = tcp.pose.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], expected['position'], rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.reshape(tcp.pose.covariance, (6, 6))[:3, :3],
                               expected['covariance'], rtol=1e-6, atol=1e-18)


def test_results_on_disk_equal_what_was_published(run):
    client = run.client
    assert yaml.safe_load((run.data_dir / 'calibration.yaml').read_text()) == run.calibration
    client.spin_until(lambda: client.received['robot_description_calibrated'], 10, 'urdf')
    urdf = client.received['robot_description_calibrated'][-1].data
    assert (run.data_dir / 'robot_description_calibrated.urdf').read_text() == urdf
    assert {j.get('name') for j in ET.fromstring(urdf).iter('joint')} == \
        {j.get('name') for j in ET.fromstring(KR15_URDF).iter('joint')}


def test_markers_show_one_residual_per_measurement_and_the_tcp_ellipsoid(run):
    client = run.client
    client.spin_until(lambda: any(m.ns == 'residuals' for a in client.received['markers']
                                  for m in a.markers), 10, 'residual markers')
    markers = client.received['markers'][-1].markers
    assert sum(m.ns == 'residuals' for m in markers) == N_POSES
    assert sum(m.ns == 'tcp_ellipsoids' for m in markers) == 1


# ---------------------------------------------------------------- malformed input
def joint_state(stamp: int, names: list[str], positions: list[float]) -> JointState:
    return JointState(header=Header(stamp=cv.time_msg(stamp)), name=names, position=positions)


def point(stamp: int, frame: str = 'laser_tracker',
          xyz: tuple[float, float, float] = (1.0, 0.5, 0.2)) -> PointStamped:
    x, y, z = xyz
    return PointStamped(header=Header(stamp=cv.time_msg(stamp), frame_id=frame),
                        point=Point(x=x, y=y, z=z))


def nan_point(client: Client, stamp: int, names: list[str]) -> None:
    client.points.publish(point(stamp, xyz=(float('nan'), 0.0, 0.0)))


def point_in_another_frame(client: Client, stamp: int, names: list[str]) -> None:
    client.points.publish(point(stamp, frame='world'))


def nan_joint_position(client: Client, stamp: int, names: list[str]) -> None:
    client.joints.publish(joint_state(stamp, names, [0.0, float('nan'), 0, 0, 0, 0]))


def fewer_positions_than_names(client: Client, stamp: int, names: list[str]) -> None:
    client.joints.publish(joint_state(stamp, names, [0.0, 0.1]))


def another_robots_joints_around_a_point(client: Client, stamp: int, names: list[str]) -> None:
    for dt in (-100_000_000, 100_000_000, 300_000_000):
        client.joints.publish(joint_state(stamp + dt, ['axis_a', 'axis_b'], [0.0, 0.0]))
    client.points.publish(point(stamp))


# Stamps past the recording and increasing from case to case, as a live stream's would.
@pytest.mark.parametrize('case, send, reason, ignored', [
    (1, nan_point, 'non_finite_point', 0),
    (2, point_in_another_frame, 'wrong_frame', 0),
    (3, nan_joint_position, 'non_finite_joint_state', 0),
    (4, fewer_positions_than_names, 'non_finite_joint_state', 0),
    (5, another_robots_joints_around_a_point, 'missing_joints', 3),
])
def test_a_malformed_message_is_rejected_and_counted_by_its_reason(run, offline, case, send,
                                                                   reason, ignored):
    client = run.client
    before = client.diagnostics()
    stamp = offline['joints'][-1].stamp_ns + case * 60_000_000_000
    send(client, stamp, list(offline['joints'][0].names))

    def counted() -> bool:
        return int(client.diagnostics()[f'rejected.{reason}']) == int(
            before[f'rejected.{reason}']) + 1
    client.spin_until(counted, 20, f'a {reason} rejection')
    after = client.diagnostics()
    print(f'{send.__name__}: rejected.{reason} {before[f"rejected.{reason}"]} -> '
          f'{after[f"rejected.{reason}"]}')
    assert int(after['rejected']) == int(before['rejected']) + 1  # this reason alone
    assert after['accepted'] == before['accepted']
    assert int(after['ignored_joint_samples']) - int(before['ignored_joint_samples']) == ignored
    assert client.received['diagnostics'][-1][0] == DiagnosticStatus.WARN
    assert run.node.process.poll() is None, run.node.output()


# ---------------------------------------------------------------- services
def test_identify_service_uses_every_accepted_measurement(run):
    answer = run.client.call('identify')
    print('identify:', answer.message)
    assert answer.success and f'from {N_POSES} measurements' in answer.message


def test_diagnose_service_equals_offline_diagnose(run, offline):
    client = run.client
    answer = client.call('diagnose')
    print('diagnose:', answer.message)
    assert answer.success, answer.message
    client.spin_until(lambda: client.received['diagnosis'], 10, 'diagnosis')
    diagnosis = json.loads(client.received['diagnosis'][-1].data)
    expected = offline['diagnosis']
    assert diagnosis['verdict'] == expected['verdict']
    assert diagnosis['model_adequate'] == expected['model_adequate']
    assert diagnosis['rms_m'] == pytest.approx(expected['rms_m'], rel=1e-9)
    assert [c['spec'] for c in diagnosis['candidates']] == \
        [c['spec'] for c in expected['candidates']]
    assert (run.data_dir / 'diagnosis' / 'report.md').is_file()
    client.spin_until(lambda: 'model_adequate' in client.diagnostics(), 10, 'diagnostics')
    assert client.diagnostics()['model_adequate'] == str(expected['model_adequate'])


# ---------------------------------------------------------------- stop (last)
def test_a_clean_stop_leaves_every_measurement_in_the_log_once(run, offline):
    code = run.node.stop()
    assert code == 0, run.node.output()
    stamps = [p.stamp_ns for _, p in MeasurementLog.load_all(run.data_dir)]
    assert sorted(stamps) == sorted(p.stamp_ns for p in offline['points'])
    assert len(stamps) == N_POSES

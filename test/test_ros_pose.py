"""kpi_calib_node with a tracked 6-DoF body (real rclpy and Fast DDS, the node as a
separate process): PoseStamped on the pose topic is paired, logged, restored after a
restart and identified with its rotation rows, as `kpi-calib identify` does offline."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import String

from kpi_calib_ros import cli
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.acquisition.streams import PointSample, synthesize_streams
from kpi_calib_ros.core.measurement.pose import noisy_rotations, quaternion_from_rotation
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document
from kpi_calib_ros.io.ros_messages import joint_state_msg, pose_stamped_msg

from ros_helpers import KR15_URDF, Client, Spawner, finish

pytestmark = pytest.mark.slow
N_POSES = 24


def _pose_cell(folder):
    doc = copy.deepcopy(read_cell_document(DEFAULT_CELL))
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    del doc['reflector']['offset']
    doc['reflectors'] = [{'name': 'probe', 'offset': [0.0, 0.02, 0.03],
                          'orientation': {'rpy': [0.1, -0.2, 0.3]}}]
    doc['noise']['sigma_rotation'] = 1e-4
    path = folder / 'pose_cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path, doc


def _publish_paced(client, stream, joints_pub, poses_pub):
    """Publish in stamp order, at most 100 messages ahead of what the node reports
    received, so no queue can overflow."""
    sent_joints = sent_poses = 0
    for sample in stream:
        if isinstance(sample, PointSample):
            poses_pub.publish(pose_stamped_msg(sample))
            sent_poses += 1
        else:
            joints_pub.publish(joint_state_msg(sample))
            sent_joints += 1
        sent = sent_joints + sent_poses
        if sent % 100 == 0:
            client.spin_until(lambda sent=sent: client.count('received.joint_states')
                              + client.count('received.points') >= sent - 100, 30,
                              'the node to catch up')
    client.spin_until(lambda: client.count('received.joint_states') == sent_joints
                      and client.count('received.points') == sent_poses, 30,
                      'every message to arrive')


def test_the_node_identifies_tracked_poses_as_offline_and_restores_them(ros_domain,
                                                                         tmp_path):
    cell, doc = _pose_cell(tmp_path)
    cm = build_cell_model(cell_from_dict(doc, tmp_path))
    rng = np.random.default_rng(41)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, cm.model.params.nominal, N_POSES, rng)
    eta = (cm.model.predict(p_true, q, reflector=np.zeros(N_POSES, int))
           + rng.normal(size=(N_POSES, 3)) * cm.cell.sigma)
    rotations = noisy_rotations(cm.model.body_rotations(p_true, q, 0), 1e-4, rng)
    joints, points = synthesize_streams(q, cm.joint_names, eta, 'laser_tracker', rate_hz=20.0,
                                        move_time_s=0.5, hold_time_s=1.0)
    poses = [PointSample(p.stamp_ns, 'laser_tracker#probe', p.xyz, quaternion_from_rotation(r))
             for p, r in zip(points, rotations)]
    stream = sorted(joints + poses, key=lambda s: (s.stamp_ns, isinstance(s, PointSample)))

    data_dir = tmp_path / 'data'
    spawn = Spawner(tmp_path)
    client = Client(ros_domain)
    client.description.publish(String(data=KR15_URDF))
    poses_pub = client.node.create_publisher(PoseStamped, '/laser_tracker/pose', 100)
    try:
        node = spawn(data_dir, 'node.log', f'cell_file:={cell}', 'auto_identify:=false')
        client.spin_until(lambda: client.diagnostics().get('state') == 'idle', 60,
                          'the node to load the cell')
        _publish_paced(client, stream, client.joints, poses_pub)
        client.spin_until(lambda: client.count('accepted') == N_POSES, 30,
                          f'{N_POSES} accepted tracked poses')
        answer = client.call('identify', timeout=120)
        assert answer.success, answer.message
        client.spin_until(lambda: client.received['calibration'], 30, 'the calibration')
        live = client.received['calibration'][-1]
        assert live['measurements'] == 2 * N_POSES  # a point and a rotation row per pose
        log = sorted(data_dir.glob('measurements_*.mcap'))[0]
        node.stop()

        # Offline, from the node's own log (PoseStamped records): the same numbers.
        assert cli.main(['identify', '--cell', str(cell), '--bag', str(log),
                         '--out', str(tmp_path / 'offline')]) == 0
        offline = yaml.safe_load((tmp_path / 'offline' / 'calibration.yaml').read_text())
        values = np.array([p['value'] for p in live['parameters']])
        expected = np.array([p['value'] for p in offline['parameters']])
        assert np.allclose(values, expected, rtol=1e-9, atol=1e-12)
        tcp_live = np.array(live['tcp'][0]['position'])
        assert np.allclose(tcp_live, offline['tcp'][0]['position'], rtol=0, atol=1e-12)
        truth = cm.model.predict(p_true, cm.q_work)[0]
        cov = np.array(live['tcp'][0]['covariance'])
        error = tcp_live - truth
        assert error @ np.linalg.solve(cov, error) < 14.2  # 3σ of χ²₃

        # A restarted node restores every tracked pose from its log, rotations included.
        client.received.clear()
        again = spawn(data_dir, 'node_2.log', f'cell_file:={cell}', 'auto_identify:=false')
        # The restarted node logs to a new file: that tells its reports from late ones.
        client.spin_until(lambda: client.diagnostics().get('log_file', str(log)) != str(log)
                          and client.diagnostics().get('state') == 'idle', 60,
                          'the restarted node')
        assert client.count('restored') == N_POSES
        answer = client.call('identify', timeout=120)
        assert answer.success, answer.message
        client.spin_until(lambda: client.received['calibration'], 30, 'the calibration')
        restored = np.array([p['value'] for p in client.received['calibration'][-1]
                             ['parameters']])
        assert np.allclose(restored, values, rtol=1e-9, atol=1e-12)
        again.stop()
    finally:
        spawn.kill_all()
        client.close()


def test_a_replayed_pose_bag_gives_the_node_what_identify_gets_offline(ros_domain, tmp_path):
    cell, _ = _pose_cell(tmp_path)
    bag = tmp_path / 'run.mcap'
    assert cli.main(['simulate', '--cell', str(cell), '--n', '20', '--out', str(bag),
                     '--seed', '5']) == 0
    assert cli.main(['identify', '--cell', str(cell), '--bag', str(bag),
                     '--out', str(tmp_path / 'offline')]) == 0
    offline = yaml.safe_load((tmp_path / 'offline' / 'calibration.yaml').read_text())
    spawn = Spawner(tmp_path)
    client = Client(ros_domain)
    client.description.publish(String(data=KR15_URDF))
    try:
        node = spawn(tmp_path / 'data', 'node.log', f'cell_file:={cell}', 'auto_identify:=false')
        client.spin_until(lambda: client.diagnostics().get('state') == 'idle', 60,
                          'the node to load the cell')
        output = finish(spawn.replay(bag), client)
        assert 'and 20 tracker points' in output and 'LOST' not in output
        client.spin_until(lambda: client.count('accepted') == 20, 30, '20 accepted poses')
        answer = client.call('identify', timeout=120)
        assert answer.success, answer.message
        client.spin_until(lambda: client.received['calibration'], 30, 'the calibration')
        live = client.received['calibration'][-1]
        assert live['measurements'] == offline['measurements'] == 40
        assert np.allclose([p['value'] for p in live['parameters']],
                           [p['value'] for p in offline['parameters']], rtol=1e-9, atol=1e-12)
        node.stop()
    finally:
        spawn.kill_all()
        client.close()

"""The tracker's stated σ of each point, live: the node subscribes to '<point topic>/sigma',
pairs each σ with its point whichever comes first, and identifies exactly as
`kpi-calib identify` does on a bag of the same data (in process with a private context,
and end to end with `kpi-calib replay` into the node as a process)."""
from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
import yaml
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from kpi_calib_ros import cli
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.bag_writing import BagStream
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.names import DEFAULT_POINT_TOPIC, point_sigma_topic
from kpi_calib_ros.io.ros_messages import joint_state_msg, point_stamped_msg, vector3_stamped_msg
from kpi_calib_ros.ros import job_work
from kpi_calib_ros.ros.node import CalibrationNode

from ros_helpers import KR15_URDF, SpinThread, finish, run_job

POSES = 40
SIGMA_TOPIC = point_sigma_topic(DEFAULT_POINT_TOPIC)


def campaign(cm, seed: int = 8):
    """Streams of POSES poses whose points carry noise of their own σ (5-60 µm per point
    and axis, drawn per point), and those σ (N, 3) (m)."""
    rng = np.random.default_rng(seed)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, p_true, POSES, rng)
    sigma = rng.uniform(5e-6, 60e-6, (POSES, 3))
    eta = cm.model.predict(p_true, q) + rng.normal(size=(POSES, 3)) * sigma
    joints, points = synthesize_streams(q, cm.joint_names, eta, cm.cell.tracker_frame,
                                        move_time_s=0.5, hold_time_s=1.0)
    return joints, points, sigma


def write_campaign_bag(joints, points, sigma, path):
    """A recording of the streams, with each point's σ on the σ topic when ``sigma`` is
    given (as ``kpi-calib import-csv`` writes it)."""
    with BagStream(path, sigma_topic=SIGMA_TOPIC if sigma is not None else None) as bag:
        stream = sorted([(j.stamp_ns, 0, j) for j in joints]
                        + [(p.stamp_ns, 1, k) for k, p in enumerate(points)],
                        key=lambda item: item[:2])
        for _, kind, item in stream:
            if kind == 0:
                bag.write_joint(item)
            else:
                bag.write_point(points[item])
                if sigma is not None:
                    bag.write_point_sigma(points[item], sigma[item])
    return path


def offline_values(cm, joints, points, sigma, path):
    """The parameters `kpi-calib identify` finds in a bag of these streams (with the σ
    topic when ``sigma`` is given)."""
    data, pairing = measurements_from_bag(cm, write_campaign_bag(joints, points, sigma, path))
    out = path.with_suffix('')
    out.mkdir()
    cal = job_work.identify_work(cm, data, pairing, out).calibration
    assert cal is not None and cal.valid, cal and cal.problems
    return cal.result.values


def identify_cli(bag, out):
    """The parameter values of `kpi-calib identify` on ``bag``."""
    assert cli.main(['identify', '--cell', str(DEFAULT_CELL), '--bag', str(bag),
                     '--out', str(out)]) == 0
    return parameter_values(yaml.safe_load((out / 'calibration.yaml').read_text()))


def parameter_values(doc):
    return np.array([p['value'] for p in doc['parameters']])


@pytest.mark.slow
def test_live_sigma_identifies_as_the_bag_with_sigma(tmp_path, ros_domain, cm):
    """40 points, each with its own σ on the σ topic: half published before their point,
    half after it. The node stores every σ with its measurement and its identification
    equals the offline one of a bag of the same data with σ to 1e-9; without σ the offline
    parameters differ by far more."""
    joints, points, sigma = campaign(cm)
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    node = source = spinner = None
    executor = SingleThreadedExecutor(context=context)
    try:
        node = CalibrationNode(context=context, parameter_overrides=[
            Parameter('robot_description', value=KR15_URDF),
            Parameter('data_dir', value=str(tmp_path / 'live')),
            Parameter('auto_identify', value=False)])
        source = rclpy.create_node('tracker_and_robot', context=context)
        qos = QoSProfile(depth=len(joints) + 2 * len(points),
                         reliability=ReliabilityPolicy.RELIABLE)
        pub_joints = source.create_publisher(JointState, '/joint_states', qos)
        pub_points = source.create_publisher(PointStamped, DEFAULT_POINT_TOPIC, qos)
        pub_sigma = source.create_publisher(Vector3Stamped, SIGMA_TOPIC, qos)
        executor.add_node(node)
        executor.add_node(source)

        def spin_until(condition, what: str, timeout: float = 60.0) -> None:
            deadline = time.monotonic() + timeout
            while not condition():
                assert time.monotonic() < deadline, f'timed out waiting for {what}'
                executor.spin_once(timeout_sec=0.05)
        spin_until(lambda: pub_sigma.get_subscription_count() and pub_points
                   .get_subscription_count() and pub_joints.get_subscription_count(),
                   'the node to subscribe')
        stream = sorted([(j.stamp_ns, 0, j) for j in joints]
                        + [(p.stamp_ns, 1, k) for k, p in enumerate(points)],
                        key=lambda item: item[:2])
        for n, (_, kind, item) in enumerate(stream):
            if kind == 0:
                pub_joints.publish(joint_state_msg(item))
                continue
            p = points[item]
            sigma_msg = vector3_stamped_msg(p.stamp_ns, p.frame_id, sigma[item])
            if item % 2 == 0:
                pub_sigma.publish(sigma_msg)
            pub_points.publish(point_stamped_msg(p))
            if item % 2:
                pub_sigma.publish(sigma_msg)
            if n % 50 == 0:
                executor.spin_once(timeout_sec=0)
        spin_until(lambda: node.store.counts()['stated_sigma'] == POSES
                   and len(node.store) == POSES, 'every point with its sigma')
        counts = node.store.counts()
        assert counts['rejected'] == 0 and counts['received.sigma'] == POSES, counts

        spinner = SpinThread(executor)
        spinner.start()
        ok, message = run_job(node, executor, 'identifying', node._identify, 120)
        assert ok, message
        live = node._run.result.values
    finally:
        if spinner is not None:
            spinner.stop()
        else:
            executor.shutdown()
        for made in (source, node):
            if made is not None:
                made.destroy_node()
        rclpy.shutdown(context=context)

    with_sigma = offline_values(cm, joints, points, sigma, tmp_path / 'sigma.mcap')
    without = offline_values(cm, joints, points, None, tmp_path / 'plain.mcap')
    np.testing.assert_allclose(live, with_sigma, rtol=0, atol=1e-9)
    assert np.max(np.abs(without - with_sigma)) > 1e-6, np.max(np.abs(without - with_sigma))


@pytest.mark.slow
def test_kpi_calib_replay_carries_the_sigma_to_the_node_process(client, spawn, tmp_path, cm):
    """End to end: `kpi-calib replay` of a bag with σ into the node as a process; the node
    stores every σ and its ~/calibration equals `kpi-calib identify` of the bag to 1e-9,
    not that of the bag without σ."""
    joints, points, sigma = campaign(cm, seed=9)
    bag = write_campaign_bag(joints, points, sigma, tmp_path / 'sigma.mcap')
    with_sigma = identify_cli(bag, tmp_path / 'offline_sigma')
    without = identify_cli(write_campaign_bag(joints, points, None, tmp_path / 'plain.mcap'),
                           tmp_path / 'offline_plain')
    node = spawn(tmp_path / 'data', 'node.log', 'auto_identify:=false')
    try:
        client.spin_until(lambda: client.diagnostics().get('state') == 'idle', 30,
                          'the robot model')
        output = finish(spawn.replay(bag, 1000.0), client, timeout=120)
        assert f'with the stated sigma of {POSES} points on {SIGMA_TOPIC}' in output, output
        client.spin_until(lambda: client.count('accepted') == POSES
                          and client.count('stated_sigma') == POSES, 20, 'every point with σ')
        assert client.count('received.sigma') == POSES and client.count('rejected') == 0
        response = client.call('identify', timeout=120)
        assert response.success, response.message
        client.spin_until(lambda: client.received['calibration'], 10, '~/calibration')
        live = parameter_values(client.received['calibration'][-1])
    finally:
        assert node.stop() == 0, node.output()
    np.testing.assert_allclose(live, with_sigma, rtol=0, atol=1e-9)
    assert np.max(np.abs(without - with_sigma)) > 1e-6

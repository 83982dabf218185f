"""kpi_calib_node ~/validate, in process (private context): the last calibration is
tested on the measurements accepted since it was identified, as `kpi-calib validate`."""
from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import String

from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.ros_messages import joint_state_msg, point_stamped_msg

from ros_helpers import SpinThread, idle_node, run_job


@pytest.fixture
def node(tmp_path, ros_domain):
    with idle_node(tmp_path, ros_domain) as made:
        yield made


def _feed(node, joints, points):
    stream = sorted([(s.stamp_ns, 0, s) for s in joints] + [(p.stamp_ns, 1, p) for p in points],
                    key=lambda item: item[:2])
    for _, kind, sample in stream:
        if kind:
            node._on_point(point_stamped_msg(sample), {})
        else:
            node._on_joint_state(joint_state_msg(sample), {})



@pytest.mark.slow
def test_validate_service_tests_the_calibration_on_the_new_measurements(node, tmp_path, cm):
    rng = np.random.default_rng(21)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, p_true, 45, rng)
    q[42:] = q[:3]  # three training poses measured again among the ten new ones
    eta = simulate_measurements(cm.model, p_true, q, cm.cell.sigma, rng).eta
    joints, points = synthesize_streams(q, cm.joint_names, eta, cm.cell.tracker_frame)
    cut = points[35].stamp_ns - 1_000_000_000  # between the holds of poses 34 and 35
    received, got = [], threading.Event()
    node.create_subscription(String, '~/validation',
                             lambda m: (received.append(m.data), got.set()),
                             QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    spinner = SpinThread(executor)
    spinner.start()
    try:
        ok, message = run_job(node, executor, 'validating', node._validate, 120)
        assert not ok and 'no calibration' in message
        _feed(node, [j for j in joints if j.stamp_ns < cut], points[:35])
        ok, message = run_job(node, executor, 'identifying', node._identify, 120)
        assert ok, message
        ok, message = run_job(node, executor, 'validating', node._validate, 120)
        assert not ok and 'since the last identification' in message
        _feed(node, [j for j in joints if j.stamp_ns >= cut], points[35:])
        ok, message = run_job(node, executor, 'validating', node._validate, 120)
        assert ok and message.startswith('calibration holds on 10 new measurements'), message
        assert '; 3 at training poses measured again' in message, message
        assert got.wait(timeout=30), 'no message on ~/validation'
    finally:
        spinner.stop()
    doc = json.loads((tmp_path / 'validation' / 'validation.json').read_text())
    assert doc['holds'] and doc['measurements'] == 10 and doc['repeated_from_training'] == 3
    assert received and json.loads(received[-1]) == doc


@pytest.mark.slow
def test_validate_service_re_registers_a_tracker_set_up_again(node, tmp_path, cm):
    """With ``validate_register: base`` the node scores new measurements from a moved
    tracker after re-fitting the base pose on them (as ``validate --register``): the
    calibration holds with 3N − 6 dof; without it the same points do not hold."""
    import pinocchio as pin
    rng = np.random.default_rng(22)
    p_true = true_parameters(cm.model.params, rng)
    p_moved = p_true.copy()
    base = cm.model.params.indices([f'base.{c}' for c in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')])
    moved = pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.0, 1.3), np.array([0.8, -0.5, 0.1])) * pin.SE3(
        pin.rpy.rpyToMatrix(*p_true[base[3:]]), p_true[base[:3]])
    p_moved[base[:3]], p_moved[base[3:]] = moved.translation, pin.rpy.matrixToRpy(moved.rotation)
    q = np.vstack([random_configurations(cm.model, p_true, 35, rng),
                   random_configurations(cm.model, p_moved, 12, rng)])
    eta = np.vstack([simulate_measurements(cm.model, p_true, q[:35], cm.cell.sigma, rng).eta,
                     simulate_measurements(cm.model, p_moved, q[35:], cm.cell.sigma, rng).eta])
    joints, points = synthesize_streams(q, cm.joint_names, eta, cm.cell.tracker_frame)
    cut = points[35].stamp_ns - 1_000_000_000
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    spinner = SpinThread(executor)
    spinner.start()
    try:
        _feed(node, [j for j in joints if j.stamp_ns < cut], points[:35])
        ok, message = run_job(node, executor, 'identifying', node._identify, 120)
        assert ok, message
        _feed(node, [j for j in joints if j.stamp_ns >= cut], points[35:])
        ok, message = run_job(node, executor, 'validating', node._validate, 120)
        assert not ok and 're-registering' not in message, message
        result = node.set_parameters([Parameter('validate_register', value='bad')])
        assert not result[0].successful and 'validate_register' in result[0].reason
        assert node.set_parameters([Parameter('validate_register', value='base')])[0].successful
        ok, message = run_job(node, executor, 'validating', node._validate, 120)
        assert ok and 'after re-registering base.x/base.y/base.z/' in message, message
        assert 'chi2/dof' in message and f'/{3 * 12 - 6},' in message, message
    finally:
        spinner.stop()
    doc = json.loads((tmp_path / 'validation' / 'validation.json').read_text())
    assert doc['holds'] and doc['registration']['dof'] == 6 and doc['rms_m'] < 1e-4

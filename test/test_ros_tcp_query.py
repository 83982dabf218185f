"""kpi_calib_node ~/tcp_query -> ~/tcp_corrected, in process (private context, real rclpy):
joint positions in any order are answered with the TCP and covariance the stored learned
residual predicts, the query's stamp echoed; a changed learned_residual.yaml is read again;
one written for a model with an effect ``auto`` added is answered with that model by a
node that has only the cell's (as after a restart)."""
from __future__ import annotations

import threading

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState

from kpi_calib_ros.app.identify import with_effects
from kpi_calib_ros.app.learned_residual import field_covariance, physical_covariance, predict_stored
from kpi_calib_ros.core.diagnosis.learned_residual import fit_learned_residual
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.precision import honest_precision
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    smooth_joint_map,
    true_parameters,
)
from kpi_calib_ros.io.learned_residual_file import read_residual, residual_document, write_residual
from kpi_calib_ros.io.ros_messages import time_msg
from kpi_calib_ros.ros.conversions import UNKNOWN_ORIENTATION_VARIANCE

from ros_helpers import SpinThread, idle_node


@pytest.fixture
def node(tmp_path, ros_domain):
    with idle_node(tmp_path, ros_domain) as made:
        yield made


def learned(cm, tmp_path, seed: int, amplitude: float) -> None:
    """learned_residual.yaml in ``tmp_path`` for a robot with a smooth unknown map, fitted
    with ``cm``'s model (its effects stored with it)."""
    rng = np.random.default_rng(seed)
    p = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, p, 80, rng)
    eta = simulate_measurements(cm.model, p, q, cm.cell.sigma, rng).eta
    eta = eta + smooth_joint_map(q, (1, 2), amplitude, rng.uniform(0, 6, 6))
    data = Measurements(q=q, eta=eta)
    result = honest_precision(identify(cm.model, data, cm.cell.sigma, cm.q_work))
    choice = fit_learned_residual(q, result.residuals, cm.cell.sigma, tuple(cm.joint_names))
    cov = physical_covariance(result, choice.model, cm.cell.sigma)
    outside = field_covariance(cm.model, data, result, choice.model, cm.cell.sigma)
    write_residual(tmp_path, residual_document(choice, result, cov, outside,
                                               [e.name for e in cm.model.effects]))


def ask(node, msg: JointState) -> PoseWithCovarianceStamped:
    """``node``'s answer on ~/tcp_corrected to the query ``msg``."""
    received: list[PoseWithCovarianceStamped] = []
    got = threading.Event()
    probe = rclpy.create_node('tcp_probe', context=node.context)
    probe.create_subscription(PoseWithCovarianceStamped, '/kpi_calib_node/tcp_corrected',
                              lambda m: (received.append(m), got.set()), 10)
    query = probe.create_publisher(JointState, '/kpi_calib_node/tcp_query', 10)
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    executor.add_node(probe)
    spinner = SpinThread(executor)
    spinner.start()
    try:
        for _ in range(100):  # until discovery: the query is re-sent, never slept on
            query.publish(msg)
            if got.wait(timeout=0.2):
                break
        assert received, 'no answer on ~/tcp_corrected'
    finally:
        spinner.stop()
        probe.destroy_node()
    return received[0]


def query(cm, q: np.ndarray) -> JointState:
    """A query of joints ``q`` (chain order): by name, in another order, a gripper too."""
    order = [5, 2, 0, 4, 1, 3]
    msg = JointState(name=[cm.joint_names[i] for i in order] + ['gripper'],
                     position=[float(q[i]) for i in order] + [0.01])
    msg.header.stamp = time_msg(1_234_567_890_123)
    return msg


def test_tcp_query_is_answered_with_the_learned_residual(node, tmp_path):
    cm = node._cm
    learned(cm, tmp_path, 5, 1e-4)
    q = np.array([0.3, -0.4, 0.5, 0.2, 0.6, -0.1])
    answer = ask(node, query(cm, q))
    expected = predict_stored(cm.model, read_residual(tmp_path / 'learned_residual.yaml'), q)
    assert answer.header.stamp.sec == 1234 and answer.header.stamp.nanosec == 567_890_123
    assert answer.header.frame_id == cm.cell.tracker_frame
    position = answer.pose.pose.position
    np.testing.assert_allclose([position.x, position.y, position.z], expected.position[0],
                               rtol=0, atol=1e-12)
    cov = np.array(answer.pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(cov[:3, :3], expected.covariance[0], rtol=1e-12, atol=0)
    assert np.all(cov[3:, 3:] == np.eye(3) * UNKNOWN_ORIENTATION_VARIANCE)
    # The learned correction is in the answer: it differs from the physical model alone.
    assert np.linalg.norm(expected.correction.mean[0]) > 1e-6
    # A new learned_residual.yaml is read again on the next query.
    before = node.tcp_query.stored().residual.amplitude_m2
    learned(cm, tmp_path, 6, 2e-4)
    new = read_residual(tmp_path / 'learned_residual.yaml').residual.amplitude_m2
    assert new != before
    assert node.tcp_query.stored().residual.amplitude_m2 == new


def test_a_learned_residual_of_a_model_auto_augmented_is_answered_after_a_restart(node,
                                                                                   tmp_path):
    """The node has only the cell's model and no calibration (as after a restart);
    learned_residual.yaml was written for the model with joint_2's compliance, as
    ``identification.model: auto`` adds it: the answer is that model's prediction."""
    rich = with_effects(node._cm, ('joint_compliance:joint_2',))
    learned(rich, tmp_path, 5, 1e-4)
    assert node._run.result is None and node._run.cell is None
    q = np.array([0.3, -0.4, 0.5, 0.2, 0.6, -0.1])
    answer = ask(node, query(node._cm, q))
    expected = predict_stored(rich.model, read_residual(tmp_path / 'learned_residual.yaml'), q)
    position = answer.pose.pose.position
    np.testing.assert_allclose([position.x, position.y, position.z], expected.position[0],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.array(answer.pose.covariance).reshape(6, 6)[:3, :3],
                               expected.covariance[0], rtol=1e-12, atol=0)


class _Log:
    """A logger that keeps what it is given."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def warning(self, text: str) -> None:
        self.lines.append(text)


@pytest.mark.parametrize('value', [100.0, 1e300, float('nan')])
def test_a_query_beyond_the_joint_limits_is_dropped_naming_the_joint(node, monkeypatch, value):
    cm = node._cm
    log, published = _Log(), []
    monkeypatch.setattr(node.tcp_query, '_logger', log)
    monkeypatch.setattr(node.tcp_query.publisher, 'publish', published.append)
    q = np.array([0.3, value, 0.5, 0.2, 0.6, -0.1])
    node.tcp_query.answer(query(cm, q))
    assert published == [] and node.tcp_query.warnings['joint_range'] == 1
    joint = cm.robot.joints[1]
    if np.isfinite(value):
        assert log.lines == [f'TCP query dropped: joint {joint.name} at {value:.6g} rad is '
                             f'outside its URDF limits [{joint.lower:.6g}, {joint.upper:.6g}] '
                             'rad (tolerance 0.01 rad)']
    else:
        assert log.lines == [f'TCP query dropped: joint {joint.name} position is not finite']
    # Within the tolerance of a limit: not a range problem (the query goes on, here to the
    # missing calibration).
    q[1] = joint.upper + 0.005
    node.tcp_query.answer(query(cm, q))
    assert node.tcp_query.warnings['joint_range'] == 1
    assert log.lines[-1] == 'TCP query dropped: no calibration yet (call ~/identify)'


def test_each_kind_of_tcp_query_warning_has_its_own_throttle(node, monkeypatch):
    cm = node._cm
    log = _Log()
    monkeypatch.setattr(node.tcp_query, '_logger', log)
    far = np.array([0.3, 100.0, 0.5, 0.2, 0.6, -0.1])
    for _ in range(3):  # one problem repeated: logged once in 5 s, counted every time
        node.tcp_query.answer(query(cm, far))
    missing = JointState(name=list(cm.joint_names[:5]), position=[0.0] * 5)
    node.tcp_query.answer(missing)  # another problem at once: logged, not hidden
    node.tcp_query.answer(query(cm, np.array([0.3, -0.4, 0.5, 0.2, 0.6, -0.1])))
    assert node.tcp_query.warnings == {'joint_range': 3, 'missing_joints': 1,
                                       'no_calibration': 1}
    assert len(log.lines) == 3
    assert log.lines[0].startswith(f'TCP query dropped: joint {cm.joint_names[1]} at 100 rad '
                                   'is outside its URDF limits')
    assert log.lines[1].startswith(f"TCP query dropped: joints ['{cm.joint_names[5]}'] "
                                   'missing')
    assert log.lines[2] == 'TCP query dropped: no calibration yet (call ~/identify)'


def test_a_continuous_joint_is_checked_for_absurd_magnitudes_only(node):
    import dataclasses
    from types import SimpleNamespace

    from kpi_calib_ros.ros.tcp_query import CONTINUOUS_MAX_RAD, joint_range_problem
    joints = [dataclasses.replace(j, kind='continuous', lower=-np.inf, upper=np.inf)
              if i == 5 else j for i, j in enumerate(node._cm.robot.joints)]
    cm = SimpleNamespace(robot=SimpleNamespace(joints=joints))
    q = np.array([0.3, -0.4, 0.5, 0.2, 0.6, 40.0])
    assert joint_range_problem(cm, q) == ''  # six turns of a continuous wrist
    q[5] = 1e6
    assert joint_range_problem(cm, q) == (
        f'joint {joints[5].name} (continuous) at 1e+06 rad is beyond ±{CONTINUOUS_MAX_RAD:.4g} '
        'rad (16 turns): a unit or driver fault')

"""Message conversions: exact round trips, the same samples as the bag path, faithful markers."""
from __future__ import annotations

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PointStamped
from mcap.reader import make_reader
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from visualization_msgs.msg import Marker

from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample, synthesize_streams
from kpi_calib_ros.core.collision.capsules import Capsule
from kpi_calib_ros.io.bag import read_bag, write_bag
from kpi_calib_ros.ros import conversions as cv

NAMES = ('joint_1', 'joint_2', 'joint_3')


def matrix_of(q) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q if np.linalg.det(q) > 0 else -q


def test_joint_state_round_trip_is_exact():
    sample = JointSample(1_700_000_000_123_456_789, NAMES, [0.1, -2.5, 3.0], [0.0, 1e-3, -2.0])
    back = cv.joint_sample_from_msg(cv.joint_state_msg(sample))
    assert back.stamp_ns == sample.stamp_ns and back.names == sample.names
    np.testing.assert_array_equal(back.positions, sample.positions)
    np.testing.assert_array_equal(back.velocities, sample.velocities)
    no_velocity = cv.joint_sample_from_msg(cv.joint_state_msg(
        JointSample(5, NAMES, [1, 2, 3], None)))
    assert no_velocity.velocities is None


def test_malformed_joint_state_is_kept_for_the_pairer_to_count():
    msg = JointState(name=list(NAMES), position=[0.1, 0.2], velocity=[0.0])
    sample = cv.joint_sample_from_msg(msg)
    assert sample.names == NAMES
    assert np.isnan(sample.positions).all() and sample.velocities is None


def test_point_round_trip_is_exact():
    point = PointSample(42_000_000_007, 'laser_tracker', [1.25, -0.5, 1e-9])
    back = cv.point_sample_from_msg(cv.point_stamped_msg(point))
    assert (back.stamp_ns, back.frame_id) == (point.stamp_ns, point.frame_id)
    np.testing.assert_array_equal(back.xyz, point.xyz)
    nan = cv.point_sample_from_msg(PointStamped())
    assert nan.stamp_ns == 0 and nan.frame_id == ''


def test_live_conversion_equals_the_bag_reader(tmp_path):
    """Messages deserialised by rclpy from a bag's CDR bytes convert to exactly the samples
    read_bag gives: the node and `kpi-calib identify` see the same data."""
    rng = np.random.default_rng(5)
    joints, points = synthesize_streams(rng.uniform(-1, 1, (2, 3)), NAMES,
                                        rng.uniform(-1, 1, (2, 3)), 'laser_tracker',
                                        joint_noise_rad=1e-5, rng=rng)
    joints.append(JointSample(joints[-1].stamp_ns + 1, ('gripper',) + NAMES, [0, 1, 2, 3], None))
    path = write_bag(tmp_path / 'run.mcap', joints, points)
    expected_joints, expected_points = read_bag(path)
    live_joints, live_points = [], []
    with open(path, 'rb') as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            if channel.topic == '/joint_states':
                live_joints.append(cv.joint_sample_from_msg(
                    deserialize_message(message.data, JointState)))
            else:
                live_points.append(cv.point_sample_from_msg(
                    deserialize_message(message.data, PointStamped)))
    assert len(live_joints) == len(expected_joints) and len(live_points) == len(expected_points)
    for a, e in zip(live_joints, expected_joints):
        assert (a.stamp_ns, a.names) == (e.stamp_ns, e.names)
        np.testing.assert_array_equal(a.positions, e.positions)
        assert (a.velocities is None) == (e.velocities is None)
        if e.velocities is not None:
            np.testing.assert_array_equal(a.velocities, e.velocities)
    for a, e in zip(live_points, expected_points):
        assert (a.stamp_ns, a.frame_id) == (e.stamp_ns, e.frame_id)
        np.testing.assert_array_equal(a.xyz, e.xyz)


def test_design_trajectory_keeps_order_and_values():
    q = np.random.default_rng(2).uniform(-2, 2, (5, 3))
    msg = cv.joint_trajectory_msg(NAMES, q)
    assert msg.joint_names == list(NAMES) and len(msg.points) == 5
    times = [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in msg.points]
    assert np.all(np.diff(times) > 0) and times[0] > 0
    names, back = cv.configurations_from_trajectory(msg)
    assert names == list(NAMES)
    np.testing.assert_array_equal(back, q)
    with pytest.raises(ValueError, match='configurations'):
        cv.joint_trajectory_msg(NAMES, q[:, :2])


def test_tcp_pose_carries_the_position_covariance_and_unknown_orientation():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(2, 3, 3)) * 1e-5
    cov = a @ a.transpose(0, 2, 1)
    tcp = rng.normal(size=(2, 3))
    msgs = cv.tcp_pose_msgs(tcp, cov, 'laser_tracker', 1_000_000_001)
    assert len(msgs) == 2
    for msg, point, c in zip(msgs, tcp, cov):
        assert msg.header.frame_id == 'laser_tracker'
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1, 1)
        p = msg.pose.pose.position
        np.testing.assert_array_equal([p.x, p.y, p.z], point)
        full = np.array(msg.pose.covariance).reshape(6, 6)
        np.testing.assert_array_equal(full[:3, :3], c)
        assert np.all(full[:3, 3:] == 0)
        assert np.all(np.diag(full)[3:] >= 1e6 * np.diag(full)[:3].max())


def test_diagnostics_level_and_values():
    msg = cv.diagnostic_array_msg(7, 'kpi_calib_node', 'WARN', 'model inadequate',
                                  {'accepted': 3, 'rms_um': 20.5})
    assert msg.status[0].level == DiagnosticStatus.WARN
    assert cv.diagnostic_values(msg) == {'accepted': '3', 'rms_um': '20.5'}
    with pytest.raises(ValueError, match='level'):
        cv.diagnostic_array_msg(0, 'x', 'BAD', '', {})


def test_quaternion_reproduces_the_rotation():
    rng = np.random.default_rng(4)
    rotations = [random_rotation(rng) for _ in range(200)]
    rotations += [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]),
                  np.diag([-1.0, -1.0, 1.0]), np.eye(3)]
    for r in rotations:
        np.testing.assert_allclose(matrix_of(cv.quaternion_from_matrix(r)), r, atol=1e-12)


def test_ellipsoid_marker_reproduces_the_covariance():
    rng = np.random.default_rng(6)
    r = random_rotation(rng)
    cov = r @ np.diag([4e-10, 1e-10, 9e-12]) @ r.T
    marker = cv.ellipsoid_marker(np.array([1.0, 2.0, 3.0]), cov, 'laser_tracker', 0, 0,
                                 n_sigma=3.0, exaggeration=1000.0)
    axes = np.array([marker.scale.x, marker.scale.y, marker.scale.z]) / (2 * 3.0 * 1000.0)
    rotation = matrix_of(marker.pose.orientation)
    np.testing.assert_allclose(rotation @ np.diag(axes ** 2) @ rotation.T, cov, atol=1e-20)
    assert marker.pose.position.z == 3.0


def test_markers_for_capsules_tcp_design_and_residuals():
    link = Capsule('link_2', 'link_2', (0.0, 0.0, 0.0), (0.3, 0.4, 0.0), 0.1)
    floor_bar = Capsule('car_roof', 'base', (1.0, -1.0, 0.5), (1.0, 1.0, 0.5), 0.25)
    measured = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    residuals = np.array([[1e-5, 0.0, 0.0], [0.0, -2e-5, 0.0]])
    msg = cv.marker_array_msg(0, 'laser_tracker', 'base_link',
                              design_points=np.zeros((4, 3)), tcp=np.zeros((1, 3)),
                              tcp_covariance=np.eye(3)[None] * 1e-10,
                              capsules=[link, floor_bar], measured=measured,
                              residuals=residuals)
    assert msg.markers[0].action == Marker.DELETEALL
    by_ns: dict[str, list[Marker]] = {}
    for m in msg.markers[1:]:
        by_ns.setdefault(m.ns, []).append(m)
    assert len(by_ns['design_poses'][0].points) == 4
    assert len(by_ns['tcp_ellipsoids']) == 1
    capsules = by_ns['capsules']
    assert len(capsules) == 6 and len({(m.ns, m.id) for m in msg.markers[1:]}) == \
        len(msg.markers) - 1
    cylinder = next(m for m in capsules if m.type == Marker.CYLINDER
                    and m.header.frame_id == 'link_2')
    axis = matrix_of(cylinder.pose.orientation)[:, 2]
    np.testing.assert_allclose(axis, [0.6, 0.8, 0.0], atol=1e-12)
    assert cylinder.scale.z == pytest.approx(0.5) and cylinder.scale.x == pytest.approx(0.2)
    assert {m.header.frame_id for m in capsules} == {'link_2', 'base_link'}
    for arrow, eta, r in zip(by_ns['residuals'], measured, residuals):
        start, end = (np.array([p.x, p.y, p.z]) for p in arrow.points)
        np.testing.assert_allclose(start, eta - r, atol=1e-15)
        np.testing.assert_allclose(end - start, 1000.0 * r, atol=1e-12)

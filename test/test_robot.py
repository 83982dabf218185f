"""Robot model: chain extraction from arbitrary URDFs, against Pinocchio."""
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.model.kinematics import nominal_fk_function
from kpi_calib_ros.core.model.parameters import geometric_parameters
from kpi_calib_ros.core.model.robot import Payload, RobotModel


def test_chain_skips_fixed_joints_and_side_branches(odd_arm_urdf):
    robot = RobotModel(odd_arm_urdf, 'mount', 'flange')
    assert robot.joint_names == ['swing', 'lift', 'telescope', 'wrist', 'tilt']
    kinds = [j.kind for j in robot.joints]
    assert kinds == ['revolute', 'revolute', 'prismatic', 'continuous', 'revolute']
    assert np.allclose(robot.joints[1].axis, [0, 0.6, 0.8])
    assert robot.joints[3].lower == -np.inf


def test_symbolic_nominal_fk_equals_pinocchio(odd_arm_urdf):
    robot = RobotModel(odd_arm_urdf, 'mount', 'flange')
    params = geometric_parameters(robot, np.zeros(6), np.zeros(3))
    fk = nominal_fk_function(robot, params)
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(50):
        q = rng.uniform([-2.5, -1.5, 0, -6, -2], [2.5, 1.5, 0.3, 6, 2])
        ours = np.array(fk(params.nominal, q))
        worst = max(worst, np.abs(ours - robot.pin_tip_pose(q)).max())
    assert worst < 1e-12


def test_gravity_torque_counts_payload(odd_arm_urdf):
    bare = RobotModel(odd_arm_urdf, 'mount', 'flange')
    loaded = RobotModel(odd_arm_urdf, 'mount', 'flange', Payload(2.0, (0.0, 0.0, 0.1)))
    q = np.array([0.3, 0.4, 0.1, 0.5, 0.7])
    extra = loaded.gravity_torques(q) - bare.gravity_torques(q)
    # The payload's torque about the tilt axis is m g times its lever arm: check by
    # finite differences of the payload's potential energy along that joint.
    def potential(qq):
        fk_tip = loaded.pin_tip_pose(qq)
        com_world = fk_tip[:3, :3] @ np.array([0, 0, 0.1]) + fk_tip[:3, 3]
        return 2.0 * 9.81 * com_world @ _up_in_mount(loaded)
    eps = 1e-6
    for j in range(5):
        dq = np.zeros(5)
        dq[j] = eps
        expected = (potential(q + dq) - potential(q - dq)) / (2 * eps)
        assert extra[j] == pytest.approx(expected, abs=1e-5)


def _up_in_mount(robot):
    data = robot.pin_model.createData()
    pin.framesForwardKinematics(robot.pin_model, data, pin.neutral(robot.pin_model))
    o_mount = data.oMf[robot.pin_model.getFrameId('mount')]
    return o_mount.rotation.T @ np.array([0, 0, 1.0])


@pytest.mark.parametrize('base,tip,key', [
    ('nope', 'flange', 'robot.base_frame'),
    ('mount', 'nope', 'robot.tip_frame'),
    ('flange', 'mount', 'robot.tip_frame'),
])
def test_bad_frames_name_the_key(odd_arm_urdf, base, tip, key):
    with pytest.raises(ConfigError, match=key):
        RobotModel(odd_arm_urdf, base, tip)


def test_malformed_urdf_is_a_config_error():
    with pytest.raises(ConfigError, match='robot.urdf'):
        RobotModel('<robot name="x"><joint name="j"/></robot>', 'a', 'b')


def test_a_urdf_with_more_links_than_any_robot_is_refused_before_parsing(odd_arm_urdf):
    """20 000 fixed links took Pinocchio 7.9 s (200 000: no answer in 300 s); a bound far
    above any robot (MAX_URDF_ELEMENTS) refuses them with the count, and a robot with
    a few hundred extra fixed links still loads."""
    from kpi_calib_ros.core.model.robot import MAX_URDF_ELEMENTS

    def with_fixed_links(n: int) -> str:
        extra = ''.join(f'<link name="extra_{i}"/><joint name="fix_{i}" type="fixed">'
                        f'<parent link="mount"/><child link="extra_{i}"/></joint>'
                        for i in range(n))
        return odd_arm_urdf.replace('</robot>', extra + '</robot>')
    assert RobotModel(with_fixed_links(300), 'mount', 'flange').n_joints == \
        RobotModel(odd_arm_urdf, 'mount', 'flange').n_joints
    n = MAX_URDF_ELEMENTS // 2 + 1  # n links and n joints: just over the bound
    with pytest.raises(ConfigError, match=r'robot.urdf: \d+ <link>/<joint>') as info:
        RobotModel(with_fixed_links(n), 'mount', 'flange')
    found = int(str(info.value).split()[1])
    assert found >= 2 * n and str(MAX_URDF_ELEMENTS) in str(info.value)


def test_a_link_named_like_a_joint_is_the_tip():
    """The stock SO-100 names a joint and a link ``gripper``: Pinocchio holds two frames of
    that name and refused ``tip_frame: gripper`` with an uncaught "Several frames match".
    The link is the frame; the chain's FK equals Pinocchio's at the link."""
    from kpi_calib_ros.io.resources import resolve_uri
    path = resolve_uri('package://example-robot-data/robots/so_arm_description/urdf/so100.urdf')
    xml = Path(path).read_text()
    pinned = pin.buildModelFromXML(xml)
    assert len([f for f in pinned.frames if f.name == 'gripper']) == 2
    robot = RobotModel(xml, 'base', 'gripper')
    params = geometric_parameters(robot, np.zeros(6), np.zeros(3))
    fk = nominal_fk_function(robot, params)
    data = pinned.createData()
    link = pinned.getFrameId('gripper', pin.BODY)
    base = pinned.getFrameId('base', pin.BODY)
    rng = np.random.default_rng(2)
    for _ in range(10):
        q = rng.uniform(pinned.lowerPositionLimit, pinned.upperPositionLimit)
        pin.framesForwardKinematics(pinned, data, q)
        expected = (data.oMf[base].inverse() * data.oMf[link]).homogeneous
        chain = [pinned.getJointId(n) for n in robot.joint_names]
        qc = np.array([q[pinned.joints[j].idx_q] for j in chain])
        assert np.abs(np.array(fk(params.nominal, qc)) - expected).max() < 1e-12

"""Calibrated URDF: Pinocchio FK of the exported file equals the calibrated model's FK."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from kpi_calib_ros.core.kinematics import nominal_fk_function, rpy_matrix
from kpi_calib_ros.core.parameters import geometric_parameters
from kpi_calib_ros.core.robot import RobotModel
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.urdf_export import calibrated_urdf, rpy_from_matrix

KR15 = (DEFAULT_CELL.parent.parent / 'robots' / 'kr15_class.urdf').read_text()


def random_errors(robot: RobotModel, rng: np.random.Generator, scale: float) -> dict[str, float]:
    values = {}
    for joint in robot.joints:
        for c in ('tx', 'ty', 'tz'):
            values[f'{joint.name}.placement.{c}'] = rng.normal(0, scale * 1e-2)
        for c in ('rx', 'ry', 'rz'):
            values[f'{joint.name}.placement.{c}'] = rng.normal(0, scale)
        values[f'{joint.name}.offset'] = rng.normal(0, scale)
    return values


def random_q(robot: RobotModel, rng: np.random.Generator, n: int) -> np.ndarray:
    lower = np.where(np.isfinite(robot.lower), robot.lower, -np.pi)
    upper = np.where(np.isfinite(robot.upper), robot.upper, np.pi)
    return rng.uniform(lower, upper, (n, robot.n_joints))


@pytest.mark.parametrize('which', ['odd_arm', 'kr15'])
@pytest.mark.parametrize('scale', [1e-3, 0.3])
def test_exported_urdf_fk_equals_calibrated_model_fk(which, scale, odd_arm_urdf):
    urdf, base, tip = ((odd_arm_urdf, 'base', 'flange') if which == 'odd_arm'
                       else (KR15, 'base_link', 'tool0'))
    rng = np.random.default_rng(4)
    robot = RobotModel(urdf, base, tip)
    params = geometric_parameters(robot, np.zeros(6), np.zeros(3))
    errors = random_errors(robot, rng, scale)
    # Cell-level parameters are accepted and ignored: they are not part of a robot URDF.
    values = {**errors, 'base.x': 1.0, 'reflector.z': 0.03}
    p = params.with_values(errors)
    fk = nominal_fk_function(robot, params)

    exported = RobotModel(calibrated_urdf(urdf, robot, values), base, tip)
    worst = 0.0
    for q in random_q(robot, rng, 25):
        expected = np.array(fk(p, q))
        actual = exported.pin_tip_pose(q)
        worst = max(worst, np.abs(actual - expected).max())
    print(f'{which} errors ~{scale}: max |T_exported - T_calibrated| = {worst:.2e}')
    assert worst < 1e-9
    # ... and the calibration changed something measurable.
    assert np.abs(exported.pin_tip_pose(q) - robot.pin_tip_pose(q)).max() > 1e-5


def test_only_chain_joint_origins_change(odd_arm_urdf):
    robot = RobotModel(odd_arm_urdf, 'base', 'flange')
    out = calibrated_urdf(odd_arm_urdf, robot, random_errors(robot, np.random.default_rng(1), 1e-3))
    before = {e.get('name'): e for e in ET.fromstring(odd_arm_urdf).iter('joint')}
    after = {e.get('name'): e for e in ET.fromstring(out).iter('joint')}
    assert before.keys() == after.keys()
    for name, element in after.items():
        changed = ET.tostring(element) != ET.tostring(before[name])
        assert changed == (name in robot.joint_names), name
        # Type, axis and limits are kept: only the origin moves.
        assert element.get('type') == before[name].get('type')
        for tag in ('axis', 'limit', 'parent', 'child'):
            old, new = before[name].find(tag), element.find(tag)
            assert (old is None) == (new is None)
            if old is not None:
                assert old.attrib == new.attrib
    assert [k.get('name') for k in ET.fromstring(out).iter('link')] == \
        [k.get('name') for k in ET.fromstring(odd_arm_urdf).iter('link')]


def test_zero_errors_reproduce_the_original(odd_arm_urdf):
    robot = RobotModel(odd_arm_urdf, 'base', 'flange')
    exported = RobotModel(calibrated_urdf(odd_arm_urdf, robot, {}), 'base', 'flange')
    for q in random_q(robot, np.random.default_rng(2), 10):
        np.testing.assert_allclose(exported.pin_tip_pose(q), robot.pin_tip_pose(q), atol=1e-12)


def test_rpy_round_trip_is_exact_next_to_gimbal_lock():
    rng = np.random.default_rng(3)
    worst = 0.0
    for pitch in [np.pi / 2, -np.pi / 2, 1.5707963, np.pi / 2 - 1e-12, 0.3, -2.0]:
        for _ in range(20):
            rpy = [rng.uniform(-np.pi, np.pi), pitch, rng.uniform(-np.pi, np.pi)]
            rotation = np.array(rpy_matrix(*rpy))
            again = np.array(rpy_matrix(*rpy_from_matrix(rotation)))
            worst = max(worst, np.abs(again - rotation).max())
    assert worst < 1e-14


def test_bad_parameters_are_named(odd_arm_urdf):
    robot = RobotModel(odd_arm_urdf, 'base', 'flange')
    with pytest.raises(ValueError, match='gripper'):
        calibrated_urdf(odd_arm_urdf, robot, {'gripper.offset': 0.01})
    with pytest.raises(ValueError, match='swing.placement.tx'):
        calibrated_urdf(odd_arm_urdf, robot, {'swing.placement.tx': float('nan')})

"""Truths about the robot library: kinematics by hand, reach, gravity, bodies, files."""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin
import pytest

from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.model import robot_library as rl

KUKA = {'kr15_class': rl.kr15_class, 'kr300_class': rl.kr300_class,
        'kr500_class': rl.kr500_class}
KUKA_JOINTS = [f'joint_{i}' for i in range(1, 7)]
UR_JOINTS = ['shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint',
             'wrist_1_joint', 'wrist_2_joint', 'wrist_3_joint']
# Data-sheet class weights (kg) of the whole arm, base included.
CLASS_MASS = {'kr15_class': 230.0, 'kr300_class': 1100.0, 'kr500_class': 2400.0,
              'ur_class': 20.0}


def _model(xml: str) -> tuple[pin.Model, pin.Data]:
    model = pin.buildModelFromXML(xml)
    return model, model.createData()


def _random_q(model: pin.Model, rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform(model.lowerPositionLimit, model.upperPositionLimit, (n, model.nq))


def _tool0(model: pin.Model, data: pin.Data, q: np.ndarray) -> pin.SE3:
    pin.framesForwardKinematics(model, data, q)
    return data.oMf[model.getFrameId('tool0')]


def _kuka_wrist_centre(g: rl.Industrial6RGeometry, q: np.ndarray) -> np.ndarray:
    """Wrist centre by hand: planar arm (x forward, z up) turned by -q1 about z."""
    theta = q[1] + q[2]
    x = g.a1 + g.a2 * math.sin(q[1]) + g.d4 * math.cos(theta) - g.a3 * math.sin(theta)
    z = g.d1 + g.a2 * math.cos(q[1]) - g.d4 * math.sin(theta) - g.a3 * math.cos(theta)
    return np.array([x * math.cos(q[0]), -x * math.sin(q[0]), z])


def _dh(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
                     [0, sa, ca, d], [0, 0, 0, 1]])


def test_shipped_files_equal_generator_output():
    generated = rl.shipped_urdfs()
    assert sorted(generated) == sorted(rl.SHIPPED_ROBOTS)
    for name, text in generated.items():
        assert rl.shipped_urdf_path(name).read_text(encoding='utf-8') == text, (
            f'{name}.urdf drifted; run kpi-calib robots')


def test_written_shipped_files_are_the_generated_text(tmp_path):
    from kpi_calib_ros.io.shipped_robots import write_shipped
    paths = write_shipped(tmp_path / 'robots')
    assert sorted(p.stem for p in paths) == sorted(rl.SHIPPED_ROBOTS)
    generated = rl.shipped_urdfs()
    assert all(p.read_text(encoding='utf-8') == generated[p.stem] for p in paths)


def test_shipped_urdf_path_rejects_unknown_name():
    assert rl.shipped_urdf_path('kr15_class.urdf') == rl.shipped_urdf_path('kr15_class')
    with pytest.raises(ConfigError, match='robot.name'):
        rl.shipped_urdf_path('kr1000_titan')


def test_robots_command_regenerates_into_directory(tmp_path):
    from kpi_calib_ros.cli import main
    assert main(['robots', '--out', str(tmp_path)]) == 0
    for name in rl.SHIPPED_ROBOTS:
        assert (tmp_path / f'{name}.urdf').read_text() == rl.shipped_urdf_path(name).read_text()


@pytest.mark.parametrize('name', rl.SHIPPED_ROBOTS)
def test_shipped_urdf_loads_with_specified_names(name):
    model, _ = _model(rl.shipped_urdf_path(name).read_text())
    assert model.nq == 6
    expected = UR_JOINTS if name == 'ur_class' else KUKA_JOINTS
    assert list(model.names)[1:] == expected
    for frame in ('base_link', 'tool0'):
        assert model.existFrame(frame)
    total = sum(inertia.mass for inertia in model.inertias)
    assert abs(total - CLASS_MASS[name]) < 0.15 * CLASS_MASS[name]
    # q = 0 is the reference pose and must be admissible.
    assert np.all(model.lowerPositionLimit < 0) and np.all(model.upperPositionLimit > 0)


@pytest.mark.parametrize('name', list(KUKA))
def test_kuka_zero_pose_matches_geometry(name):
    g = KUKA[name]()
    model, data = _model(rl.shipped_urdf_path(name).read_text())
    tool0 = _tool0(model, data, np.zeros(6))
    expected = [g.a1 + g.d4 + g.d6, 0.0, g.d1 + g.a2 - g.a3]
    np.testing.assert_allclose(tool0.translation, expected, atol=1e-9)
    # Flange normal (tool0 z) points forward, tool0 x points down.
    np.testing.assert_allclose(tool0.rotation[:, 2], [1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(tool0.rotation[:, 0], [0, 0, -1], atol=1e-9)
    # Joint axes in the world at q = 0: the ROS-Industrial KUKA axes A1..A6.
    jac = pin.computeJointJacobians(model, data, np.zeros(6))
    axes = [(0, 0, -1), (0, 1, 0), (0, 1, 0), (-1, 0, 0), (0, 1, 0), (-1, 0, 0)]
    np.testing.assert_allclose(jac[3:, :].T, axes, atol=1e-12)


@pytest.mark.parametrize('name', list(KUKA))
def test_kuka_wrist_centre_matches_hand_kinematics(name):
    g = KUKA[name]()
    model, data = _model(rl.shipped_urdf_path(name).read_text())
    for q in _random_q(model, np.random.default_rng(7), 50):
        pin.forwardKinematics(model, data, q)
        np.testing.assert_allclose(data.oMi[5].translation, _kuka_wrist_centre(g, q), atol=1e-9)
        tool0 = _tool0(model, data, q)
        np.testing.assert_allclose(tool0.translation - data.oMi[5].translation,
                                   g.d6 * tool0.rotation[:, 2], atol=1e-9)


def test_kuka_controller_offset_maps_home_to_zero():
    home_a = np.radians([0.0, -90.0, 90.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(home_a + np.array(rl.KUKA_CONTROLLER_OFFSET), 0.0, atol=1e-15)
    # Data-sheet A2 range -155/+35 deg of the KR 16-2 becomes -65/+125 deg.
    g = rl.kr15_class()
    np.testing.assert_allclose(np.degrees([g.lower[1], g.upper[1]]), [-65.0, 125.0])


def _distance_from_joint2_axis(model, data, q) -> float:
    tool0 = _tool0(model, data, q).translation
    joint2 = data.oMi[2]
    axis = joint2.rotation[:, 1]  # joint_2 turns about its local +y
    rel = tool0 - joint2.translation
    return float(np.linalg.norm(rel - rel.dot(axis) * axis))


@pytest.mark.parametrize('name', list(KUKA))
def test_kuka_reach_from_joint2_axis(name):
    g = KUKA[name]()
    model, data = _model(rl.shipped_urdf_path(name).read_text())
    bound = g.a2 + math.hypot(g.a3, g.d4) + g.d6
    # Straight up with forearm and flange in line with the upper arm reaches the bound.
    phi = math.atan2(g.a3, g.d4)
    stretched = np.array([0.0, 0.0, -math.pi / 2 - phi, 0.0, phi, 0.0])
    assert np.all(stretched >= model.lowerPositionLimit)
    assert np.all(stretched <= model.upperPositionLimit)
    assert _distance_from_joint2_axis(model, data, stretched) == pytest.approx(bound, abs=1e-9)
    distances = [_distance_from_joint2_axis(model, data, q)
                 for q in _random_q(model, np.random.default_rng(3), 5000)]
    assert max(distances) <= bound + 1e-9
    assert max(distances) > 0.97 * bound


@pytest.mark.parametrize('name, low, high', [('kr15_class', 300.0, 2000.0),
                                             ('kr300_class', 2000.0, 15000.0),
                                             ('kr500_class', 5000.0, 30000.0)])
def test_kuka_gravity_torque_at_stretched_pose(name, low, high):
    model, data = _model(rl.shipped_urdf_path(name).read_text())
    # Arm stretched forward, as far down as joint 2 allows up to horizontal.
    q2 = min(math.pi / 2, model.upperPositionLimit[1])
    tau = pin.computeGeneralizedGravity(model, data, np.array([0, q2, -q2, 0, 0, 0]))
    assert low < abs(tau[1]) < high
    # Holding the arm forward costs torque against gravity about +y: negative.
    assert tau[1] < 0
    assert abs(tau[2]) < abs(tau[1])


@pytest.mark.parametrize('name', rl.SHIPPED_ROBOTS)
def test_effort_limits_hold_the_arm_anywhere(name):
    model, data = _model(rl.shipped_urdf_path(name).read_text())
    for q in _random_q(model, np.random.default_rng(11), 500):
        tau = pin.computeGeneralizedGravity(model, data, q)
        assert np.all(np.abs(tau) < model.effortLimit)


@pytest.mark.parametrize('name', rl.SHIPPED_ROBOTS)
def test_link_inertias_are_physical(name):
    model, _ = _model(rl.shipped_urdf_path(name).read_text())
    for inertia in model.inertias[1:]:
        eig = np.linalg.eigvalsh(inertia.inertia)
        assert inertia.mass > 0 and eig.min() > 0
        assert eig[0] + eig[1] >= eig[2] - 1e-12  # triangle inequality of a real body


def test_ur_class_matches_public_dh_table():
    d = [0.1625, 0, 0, 0.1333, 0.0997, 0.0996]
    a = [0, -0.425, -0.3922, 0, 0, 0]
    alpha = [math.pi / 2, 0, 0, math.pi / 2, -math.pi / 2, 0]
    model, data = _model(rl.shipped_urdf_path('ur_class').read_text())
    tool0 = _tool0(model, data, np.zeros(6))
    np.testing.assert_allclose(tool0.translation, [0.8172, 0.2329, 0.0628], atol=1e-9)
    base = np.diag([-1.0, -1.0, 1.0, 1.0])  # ur_description: base_link = DH base turned by pi
    for q in _random_q(model, np.random.default_rng(5), 50):
        pose = base.copy()
        for i in range(6):
            pose = pose @ _dh(q[i], d[i], a[i], alpha[i])
        np.testing.assert_allclose(_tool0(model, data, q).homogeneous, pose, atol=1e-9)


def test_ur_limits():
    model, _ = _model(rl.shipped_urdf_path('ur_class').read_text())
    bounds = [2 * math.pi, 2 * math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi]
    np.testing.assert_allclose(model.upperPositionLimit, bounds, atol=1e-9)
    np.testing.assert_allclose(model.lowerPositionLimit, np.negative(bounds), atol=1e-9)


def _inside(geom_model, geom_data, point: np.ndarray, tol: float = 1e-9) -> bool:
    """Is a world point inside any collision box or cylinder?"""
    for obj, placement in zip(geom_model.geometryObjects, geom_data.oMg):
        local = placement.actInv(point)
        shape = obj.geometry
        if type(shape).__name__ == 'Box':
            if np.all(np.abs(local) <= shape.halfSide + tol):
                return True
        elif (abs(local[2]) <= shape.halfLength + tol
              and math.hypot(local[0], local[1]) <= shape.radius + tol):
            return True
    return False


def _collision(xml: str):
    model, data = _model(xml)
    geom_model = pin.buildGeomFromUrdfString(model, xml, pin.COLLISION)
    return model, data, geom_model, geom_model.createData()


@pytest.mark.parametrize('name', rl.SHIPPED_ROBOTS)
def test_every_link_has_primitive_bodies_around_its_joints(name):
    xml = rl.shipped_urdf_path(name).read_text()
    assert '<mesh' not in xml
    root = ET.fromstring(xml)
    for link in root.iter('link'):
        if link.get('name') == 'tool0':
            continue
        for tag in ('inertial', 'visual', 'collision'):
            assert link.find(tag) is not None, f'{link.get("name")} lacks <{tag}>'
        shapes = {child.tag for c in link.iter('collision') for child in c.find('geometry')}
        assert shapes <= {'box', 'cylinder'}
    model, data, geom_model, geom_data = _collision(xml)
    with_bodies = {model.frames[o.parentFrame].name for o in geom_model.geometryObjects}
    assert with_bodies == {link.get('name') for link in root.iter('link')} - {'tool0'}
    for q in _random_q(model, np.random.default_rng(2), 20):
        pin.framesForwardKinematics(model, data, q)
        pin.updateGeometryPlacements(model, data, geom_model, geom_data)
        for joint in range(1, model.njoints):
            assert _inside(geom_model, geom_data, data.oMi[joint].translation), model.names[joint]


@pytest.mark.parametrize('name', list(KUKA))
def test_kuka_bodies_enclose_the_kinematic_skeleton(name):
    model, data, geom_model, geom_data = _collision(rl.shipped_urdf_path(name).read_text())
    for q in [np.zeros(6), *_random_q(model, np.random.default_rng(4), 10)]:
        tool0 = _tool0(model, data, q).translation
        pin.updateGeometryPlacements(model, data, geom_model, geom_data)
        chain = [np.zeros(3)] + [data.oMi[j].translation for j in range(1, 7)] + [tool0]
        for start, end in zip(chain[:-1], chain[1:]):
            for s in np.linspace(0.0, 1.0, 25):
                assert _inside(geom_model, geom_data, start + s * (end - start))


def test_notional_manipulators_grid():
    robots = rl.notional_manipulators()
    assert len(robots) == 90 and len({g.name for g in robots}) == 90
    assert sorted({g.a2 for g in robots}) == pytest.approx(np.arange(0.65, 1.1001, 0.05))
    assert sorted({g.d4 for g in robots}) == pytest.approx(np.arange(0.60, 1.0001, 0.05))
    reference = rl.kr15_class()
    for g in robots:
        assert (g.d1, g.a1, g.a3, g.d6) == (reference.d1, reference.a1, reference.a3, reference.d6)


def test_all_notional_urdfs_load_with_the_named_lengths():
    for g in rl.notional_manipulators():
        model, data = _model(rl.industrial_6r_urdf(g.name, g))
        assert model.nq == 6 and list(model.names)[1:] == KUKA_JOINTS
        _, a2_mm, _, d4_mm = g.name.split('_')[1:]
        # Lengths read back from the loaded model, not from the dataclass.
        a2 = np.linalg.norm(model.jointPlacements[3].translation)
        d4 = model.jointPlacements[4].translation[0]
        assert a2 == pytest.approx(int(a2_mm) / 1000, abs=1e-12)
        assert d4 == pytest.approx(int(d4_mm) / 1000, abs=1e-12)


def test_geometry_validation_names_the_field():
    with pytest.raises(ConfigError, match='geometry.a2'):
        rl.Industrial6RGeometry(**{**rl.kr15_class().__dict__, 'a2': -0.1})
    bad_lower = (0.1,) + rl.kr15_class().lower[1:]
    with pytest.raises(ConfigError, match=r'geometry.lower\[0\]'):
        rl.Industrial6RGeometry(**{**rl.kr15_class().__dict__, 'lower': bad_lower})

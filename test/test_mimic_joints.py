"""Robot descriptions with mimic joints, as the URDF states them (multiplier and offset).

The description: the UR5 of example-robot-data set on a two-stage lifting column
(:func:`~kpi_calib_ros.core.model.robot_library.with_lifting_column`, built here from the
installed file at test time), each stage ``0.5 · lift − 0.1`` with the drive ``lift`` off
the chain, as construction robots ship it. Truths asserted: the chain's forward kinematics
equals Pinocchio's own mimic expansion (``buildModelFromXML(mimic=True)``) of the actuated
joints; a stage's limits narrow its drive's; joint states with or without the mimic joints
pair to the same rows, and a stage that does not follow its drive is a rejected row;
``joint_coupling`` takes an offset and names a mimic joint it cannot take; ``kpi-calib
identify`` on a simulated recording recovers the robot within 3σ, and its calibrated URDF
keeps the mimic tags (calibrated offsets) and reproduces the calibration's forward
kinematics to 1e-9 m in Pinocchio; ``kpi-calib design`` returns poses of the actuated joints
inside every limit. The Panda's mimic finger loads whether or not the chain holds it.
"""
from __future__ import annotations

import pickle
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.measurements import measurements_from_samples
from kpi_calib_ros.app.validate import calibrated_model
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.acquisition.streams import JointSample, synthesize_streams
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.model.kinematics import nominal_fk_function
from kpi_calib_ros.core.model.parameters import geometric_parameters
from kpi_calib_ros.core.model.robot import RobotModel
from kpi_calib_ros.core.simulation import equivalent_parameters
from kpi_calib_ros.io.cell import load_cell
from kpi_calib_ros.io.cell_sections import coupling_from_mapping
from kpi_calib_ros.io.names import CALIBRATED_URDF_FILE
from kpi_calib_ros.io.resources import resolve_uri
from kpi_calib_ros.io.urdf_export import calibrated_urdf

from mimic_column import ARM, SIGMA, STAGES, column_urdf, write_cell

PANDA = 'package://example-robot-data/robots/panda_description/urdf/panda.urdf'


@pytest.fixture(scope='module')
def cell_path(tmp_path_factory) -> Path:
    return write_cell(tmp_path_factory.mktemp('column'))


def pinocchio_mimic_fk(urdf: str, base: str, tip: str, names: tuple[str, ...],
                       x: np.ndarray) -> np.ndarray:
    """Tip in base (4, 4) by Pinocchio's own mimic joints, from actuated values ``x``."""
    model = pin.buildModelFromXML(urdf, mimic=True)
    data = model.createData()
    q = pin.neutral(model)
    for name, value in zip(names, x):
        q[model.joints[model.getJointId(name)].idx_q] = value
    pin.framesForwardKinematics(model, data, q)
    return np.array((data.oMf[model.getFrameId(base)].inverse()
                     * data.oMf[model.getFrameId(tip)]).homogeneous)


def test_actuated_joints_limits_and_kinematics_of_a_mimic_column():
    urdf = column_urdf()
    robot = RobotModel(urdf, 'column_base', 'tool0')
    assert robot.joint_names == [*STAGES, *ARM]
    assert robot.actuated_names == ('lift', *ARM)
    assert [j.mimic.master for j in robot.joints[:2]] == ['lift', 'lift']
    # The drive's own range is [0, 0.8] m; a stage's [-0.1, 0.25] m allows only [0, 0.7].
    assert robot.actuated_lower[0] == 0.0
    assert robot.actuated_upper[0] == pytest.approx(0.7, abs=1e-15)
    rng = np.random.default_rng(0)
    q = robot.sample_configurations(rng, 20)
    np.testing.assert_allclose(q[:, 0], q[:, 1], rtol=0, atol=0)
    assert robot.within_limits(q).all() and robot.mimic_residual(q).max() < 1e-15
    x = robot.actuated_values(q)
    np.testing.assert_allclose(q[:, 0], 0.5 * x[:, 0] - 0.1, rtol=0, atol=1e-15)
    fk = nominal_fk_function(robot, geometric_parameters(robot, np.zeros(6), np.zeros(3)))
    p = np.r_[np.zeros(6), np.zeros(7 * robot.n_joints), np.zeros(3)]
    worst = 0.0
    for qi, xi in zip(q, x):
        expected = pinocchio_mimic_fk(urdf, 'column_base', 'tool0', robot.actuated_names, xi)
        worst = max(worst, np.abs(np.array(fk(p, qi)) - expected).max(),
                    np.abs(robot.pin_tip_pose(qi) - expected).max())
    assert worst < 1e-12
    # The node's jobs hand the model to a worker process: it pickles, the drive included.
    again = pickle.loads(pickle.dumps(robot))
    assert np.abs(again.pin_tip_pose(q[0]) - robot.pin_tip_pose(q[0])).max() == 0.0


def _leader_after(extra: str = '', j2_master: str = 'j4') -> str:
    """Four revolute joints in a row; j2 = -j4 + 0.1, its leader later on the chain."""
    def joint(name, parent, child, mimic=''):
        return (f'<joint name="{name}" type="revolute"><parent link="{parent}"/>'
                f'<child link="{child}"/><origin xyz="0 0.05 0.3"/><axis xyz="0 1 0"/>'
                f'<limit lower="-1.5" upper="1.5" effort="1" velocity="1"/>{mimic}</joint>')
    links = ''.join(f'<link name="{n}"/>' for n in ('base', 'l1', 'l2', 'l3', 'tip'))
    return (f'<robot name="leader_after">{links}' + joint('j1', 'base', 'l1')
            + joint('j2', 'l1', 'l2', f'<mimic joint="{j2_master}" multiplier="-1" '
                    'offset="0.1"/>')
            + joint('j3', 'l2', 'l3') + joint('j4', 'l3', 'tip') + extra + '</robot>')


def test_the_independent_joints_keep_their_chain_order_whatever_their_mimics():
    """j2 mimics j4, later on the chain: the independent joints are j1, j3, j4 in that
    order (before, j4 took j2's place and an unnamed working pose [j1, j3, j4] was read
    with j3 and j4 swapped: a column arm's TCP 384.7 mm off, no error)."""
    urdf = _leader_after()
    robot = RobotModel(urdf, 'base', 'tip')
    assert robot.actuated_names == ('j1', 'j3', 'j4')
    x = np.array([0.2, -0.7, 0.5])
    q = robot.chain_values(x)
    np.testing.assert_allclose(q, [0.2, -0.4, -0.7, 0.5], rtol=0, atol=1e-15)
    # Pinocchio's mimic=True cannot load a leader after its mimic: plain Pinocchio with
    # the relation applied by hand (the URDF's j2 = -j4 + 0.1).
    model = pin.buildModelFromXML(urdf)
    data = model.createData()
    values = {'j1': 0.2, 'j2': -0.5 + 0.1, 'j3': -0.7, 'j4': 0.5}
    full = pin.neutral(model)
    for name, value in values.items():
        full[model.joints[model.getJointId(name)].idx_q] = value
    pin.framesForwardKinematics(model, data, full)
    expected = (data.oMf[model.getFrameId('base')].inverse()
                * data.oMf[model.getFrameId('tip')]).homogeneous
    assert np.abs(robot.pin_tip_pose(q) - expected).max() < 1e-12


def _heavy_chain() -> str:
    """Four horizontal-axis revolute joints with masses; j3 = -j2 + 0.1 (j2 drives it)."""
    def joint(name, parent, child, mimic=''):
        return (f'<joint name="{name}" type="revolute"><parent link="{parent}"/>'
                f'<child link="{child}"/><origin xyz="0.3 0 0.05"/><axis xyz="0 1 0"/>'
                f'<limit lower="-1.5" upper="1.5" effort="1" velocity="1"/>{mimic}</joint>')

    def link(name, mass):
        return (f'<link name="{name}"><inertial><origin xyz="0.15 0 0"/><mass value="{mass}"/>'
                '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/>'
                '</inertial></link>')
    links = ''.join(link(n, m) for n, m in (('base', 5.0), ('l1', 4.0), ('l2', 3.0),
                                             ('l3', 2.0), ('tip', 1.0)))
    return (f'<robot name="heavy">{links}' + joint('j1', 'base', 'l1')
            + joint('j2', 'l1', 'l2') + joint('j3', 'l2', 'l3', '<mimic joint="j2" '
                                                'multiplier="-1" offset="0.1"/>')
            + joint('j4', 'l3', 'tip') + '</robot>')


def test_a_drive_carries_the_gravity_load_of_the_joints_that_mimic_it():
    """The gravity force of a chain joint other chain joints mimic is that of its actuated
    coordinate (the drive's virtual work, Pinocchio's mimic=True model): it was the joint's
    own torque alone, so a compliance on a drive read a lift's 470 N where it carries
    607 N. A mimic joint and the others keep their own."""
    urdf = _heavy_chain()
    robot = RobotModel(urdf, 'base', 'tip')
    assert robot.actuated_names == ('j1', 'j2', 'j4')
    reduced = pin.buildModelFromXML(urdf, mimic=True)
    plain = pin.buildModelFromXML(urdf)
    rng = np.random.default_rng(3)
    for x in rng.uniform(-1.0, 1.0, (5, 3)):
        q = robot.chain_values(x)
        tau = robot.gravity_torques(q)
        values = pin.neutral(reduced)
        for name, v in zip(robot.actuated_names, x):
            values[reduced.joints[reduced.getJointId(name)].idx_q] = v
        g = pin.computeGeneralizedGravity(reduced, reduced.createData(), values)
        own = pin.computeGeneralizedGravity(plain, plain.createData(), q)
        for name in robot.actuated_names:
            assert tau[robot.joint_names.index(name)] == pytest.approx(
                g[reduced.joints[reduced.getJointId(name)].idx_v], rel=1e-10, abs=1e-10)
        assert tau[2] == pytest.approx(own[2], rel=1e-12)  # the mimic joint: its own
        assert abs(tau[1] - own[1]) > 1.0  # the drive carries j3's load too


def test_a_mimic_of_a_mimic_off_the_chain_is_refused():
    """j2 mimics aux, off the chain, which mimics j3: refused as on the chain (before, aux
    was taken as independent and j2 read 0.1 where the URDF makes it -0.7)."""
    aux = ('<link name="aux_link"/><joint name="aux" type="revolute"><parent link="l1"/>'
           '<child link="aux_link"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" '
           'effort="1" velocity="1"/><mimic joint="j3"/></joint>')
    with pytest.raises(ConfigError, match="'j2' mimics 'aux', which mimics another joint"):
        RobotModel(_leader_after(aux, 'aux'), 'base', 'tip')


@pytest.mark.parametrize('tip, mimic_in_chain', [('panda_hand', False),
                                                 ('panda_rightfinger', True)])
def test_panda_finger_mimic_loads(tip, mimic_in_chain):
    """The Panda's right finger mimics the left one: off the chain it changes nothing; on
    the chain (tip on the right finger) its master, off the chain, is actuated."""
    urdf = resolve_uri(PANDA).read_text()
    robot = RobotModel(urdf, 'panda_link0', tip)
    assert robot.has_mimic == mimic_in_chain
    arm = [f'panda_joint{i}' for i in range(1, 8)]
    if not mimic_in_chain:
        assert robot.actuated_names == tuple(robot.joint_names) == tuple(arm)
        return
    assert robot.joint_names == [*arm, 'panda_finger_joint2']
    assert robot.actuated_names == (*arm, 'panda_finger_joint1')
    rng = np.random.default_rng(1)
    for q in robot.sample_configurations(rng, 5):
        x = robot.actuated_values(q)
        expected = pinocchio_mimic_fk(urdf, 'panda_link0', tip, robot.actuated_names, x)
        assert np.abs(robot.pin_tip_pose(q) - expected).max() < 1e-12
        assert 0.0 <= q[-1] <= 0.04


def _streams(cm, n: int, seed: int):
    """Joint samples with the actuated joints only, and the points, of ``n`` poses."""
    rng = np.random.default_rng(seed)
    q = cm.robot.sample_configurations(rng, n)
    eta = cm.model.predict(cm.model.params.nominal, q)
    x = cm.joint_coupling.to_controller(q)
    joints, points = synthesize_streams(x, cm.joint_names, eta, cm.cell.tracker_frame, rng=rng)
    return q, joints, points


def _with_stages(cm, joints, error: float = 0.0, every: int = 1):
    """The samples carrying the stages' readings too (``error`` m added to stage 2 on
    every ``every``-th sample's pose)."""
    out = []
    for k, s in enumerate(joints):
        chain = cm.joint_coupling.to_urdf(np.asarray(s.positions))
        stages = chain[:2].copy()
        if k % every == 0:
            stages[1] += error
        out.append(JointSample(s.stamp_ns, (*STAGES, *s.names), np.r_[stages, s.positions],
                               None if s.velocities is None else np.r_[0.0, 0.0, s.velocities]))
    return out


def test_joint_states_with_and_without_the_mimic_joints(cell_path, caplog):
    cm = build_cell_model(load_cell(cell_path))
    assert cm.joint_names == ['lift', *ARM]
    q, joints, points = _streams(cm, 12, seed=4)
    plain, _ = measurements_from_samples(cm, joints, points)
    with_stages, pairing = measurements_from_samples(cm, _with_stages(cm, joints), points)
    assert len(plain) == len(with_stages) == 12 and not pairing.rejections
    np.testing.assert_array_equal(with_stages.q, plain.q)
    np.testing.assert_allclose(plain.q, q, rtol=0, atol=1e-12)  # chain values, stages too
    # A stage 1 mm off its relation in every joint state: every row rejected, and why; the
    # log says it once (a swapped stage column logged a line per joint state, a thousand
    # lines for one recording), the rejections count every point.
    caplog.clear()
    with caplog.at_level('WARNING'):
        off, pairing = measurements_from_samples(cm, _with_stages(cm, joints, 1e-3), points)
    assert len(off) == 0 and pairing.rejections == {'mimic_mismatch': 12}
    assert "mimic joint 'stage_2' reads" in pairing.rejected[0].detail
    logged = [r for r in caplog.records if 'mimic joint' in r.getMessage()]
    assert len(logged) == 1 and 'further mismatches are counted' in logged[0].getMessage()


def test_joint_coupling_takes_an_offset_and_names_a_mimic_joint(cell_path):
    names = [f'joint_{i}' for i in range(1, 7)]
    coupling = coupling_from_mapping({'joint_3': {'joint_3': 1.0, 'joint_2': 1.0,
                                                  'offset': 0.1}}, names)
    x = np.random.default_rng(2).uniform(-1, 1, (5, 6))
    q = coupling.to_urdf(x)
    np.testing.assert_allclose(q[:, 2], x[:, 2] + x[:, 1] + 0.1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(coupling.to_controller(q), x, rtol=0, atol=1e-15)
    # A stage's value is the URDF's relation: the cell cannot restate it.
    doc = yaml.safe_load(cell_path.read_text())
    doc['robot']['joint_coupling'] = {'stage_1': {'lift': 0.5}}
    bad = cell_path.parent / 'coupled_stage.yaml'
    bad.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError) as err:
        build_cell_model(load_cell(bad))
    assert err.value.key == 'robot.joint_coupling.stage_1'
    assert "mimic joint" in str(err.value) and "couple its master 'lift'" in str(err.value)
    # The master (off the chain) is coupled like any actuated joint, offset and all.
    doc['robot']['joint_coupling'] = {'lift': {'lift': 1.0, 'offset': 0.05}}
    good = cell_path.parent / 'coupled_lift.yaml'
    good.write_text(yaml.safe_dump(doc))
    cm = build_cell_model(load_cell(good))
    reading = np.r_[0.2, np.zeros(6)]
    chain = cm.joint_coupling.to_urdf(reading)
    np.testing.assert_allclose(chain[:2], 0.5 * (0.2 + 0.05) - 0.1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(cm.joint_coupling.to_controller(chain), reading, atol=1e-15)


def test_calibrated_urdf_keeps_the_mimic_tags_with_calibrated_offsets():
    urdf = column_urdf()
    robot = RobotModel(urdf, 'column_base', 'tool0')
    params = geometric_parameters(robot, np.zeros(6), np.zeros(3))
    rng = np.random.default_rng(6)
    errors = {n: rng.normal(0, 1e-3) for n in params.names
              if '.placement.' in n or n.endswith('.offset')}
    out = calibrated_urdf(urdf, robot, errors)
    tags = {e.get('name'): e.find('mimic') for e in ET.fromstring(out).findall('joint')}
    for stage in STAGES:
        assert tags[stage].get('joint') == 'lift' and float(tags[stage].get('multiplier')) == 0.5
        assert float(tags[stage].get('offset')) == -0.1 + errors[f'{stage}.offset']
    fk = nominal_fk_function(robot, params)
    p = params.with_values(errors)
    again = RobotModel(out, 'column_base', 'tool0')  # read back as the tool reads it
    worst = 0.0
    for x in robot.actuated_values(robot.sample_configurations(rng, 20)):
        expected = np.array(fk(p, robot.chain_values(x)))
        written = pinocchio_mimic_fk(out, 'column_base', 'tool0', robot.actuated_names, x)
        worst = max(worst, np.abs(written - expected).max(),
                    np.abs(again.pin_tip_pose(again.chain_values(x)) - expected).max())
    assert worst < 1e-9


@pytest.mark.slow
def test_identify_recovers_the_column_robot_and_writes_its_urdf(cell_path, tmp_path):
    bag, out = tmp_path / 'column.mcap', tmp_path / 'cal'
    assert main(['simulate', '--cell', str(cell_path), '--n', '60', '--out', str(bag),
                 '--seed', '3']) == 0
    assert main(['identify', '--cell', str(cell_path), '--bag', str(bag),
                 '--out', str(out)]) == 0
    doc = yaml.safe_load((out / 'calibration.yaml').read_text())
    cm, values = calibrated_model(load_cell(cell_path), doc)
    truth = yaml.safe_load(bag.with_suffix('.truth.yaml').read_text())['parameters']
    p_true = cm.model.params.with_values(truth)
    names = list(doc['parameter_covariance']['names'])
    idx = cm.model.params.indices(names)
    std = np.sqrt(np.diag(np.array(doc['parameter_covariance']['matrix'], float).reshape(
        len(names), len(names))))
    start = values.copy()
    start[idx] = p_true[idx]
    dense = cm.robot.sample_configurations(np.random.default_rng(5), 600)
    p_equiv, representation = equivalent_parameters(cm.model, p_true, tuple(names), start,
                                                    dense)
    z = (values[idx] - p_equiv[idx]) / std
    print(f'identified {len(idx)}, within 3σ {np.mean(np.abs(z) < 3):.3f}, max |z| '
          f'{np.abs(z).max():.2f}, representation error {representation * 1e6:.2f} µm')
    assert np.mean(np.abs(z) < 3) >= 0.95 and representation < SIGMA / 2
    # The calibrated URDF keeps the column's mimic joints and reproduces the calibration.
    written = (out / CALIBRATED_URDF_FILE).read_text()
    tags = {e.get('name'): e.find('mimic') for e in ET.fromstring(written).findall('joint')}
    assert all(tags[s] is not None and tags[s].get('joint') == 'lift' for s in STAGES)
    fk = nominal_fk_function(cm.robot, cm.model.params)
    worst = 0.0
    for x in cm.robot.actuated_values(dense[:30]):
        expected = np.array(fk(values, cm.robot.chain_values(x)))
        got = pinocchio_mimic_fk(written, 'column_base', 'tool0', cm.robot.actuated_names, x)
        worst = max(worst, np.abs(got - expected).max())
    print(f'calibrated URDF against the calibration: {worst:.2e} m')
    assert worst < 1e-9


@pytest.mark.slow
def test_design_gives_actuated_poses_inside_every_limit(tmp_path):
    cell = write_cell(tmp_path, design={'candidates': 600, 'max_iterations': 40},
                      obstacles=[{'name': 'floor', 'type': 'halfspace',
                                  'normal': [0, 0, 1], 'offset': -0.005}])
    out = tmp_path / 'design.yaml'
    assert main(['design', '--cell', str(cell), '--n', '16', '--out', str(out)]) == 0
    design = yaml.safe_load(out.read_text())
    assert design['joint_names'] == ['lift', *ARM]
    cm = build_cell_model(load_cell(cell))
    x = np.array(design['configurations'], float)
    assert x.shape == (16, 7)
    assert np.all((x >= cm.robot.actuated_lower) & (x <= cm.robot.actuated_upper))
    q = cm.joint_coupling.to_urdf(x)
    assert cm.robot.within_limits(q).all() and cm.robot.mimic_residual(q).max() < 1e-12
    assert design['verification']['ok']


def test_a_leader_its_mimics_leave_one_value_is_a_named_error():
    """The stock PR2's right parallel link mimics the left finger with limits that leave the
    finger the single value 0: a clear error naming the joint, where sampling poses
    crashed with numpy's 'high - low < 0'."""
    urdf = resolve_uri('package://example-robot-data/robots/pr2_description/urdf/pr2.urdf')
    with pytest.raises(ConfigError, match=r"\['r_gripper_l_finger_joint'\].*single value 0"):
        RobotModel(urdf.read_text(), 'base_footprint', 'r_gripper_r_parallel_link')


def test_the_drives_reading_noise_moves_its_mimic_joints_with_it(tmp_path):
    """noise.joint_sigma of the drive ``lift`` (off the chain; before refused as an unknown
    joint, and a number was taken as independent noise on each stage): each point's stated
    covariance σ²I + J_q S Sᵀ J_qᵀ matches Monte Carlo of the drive's reading error carried
    to both stages by the URDF relation: the whitened residuals' mean square is 3."""
    cm = build_cell_model(load_cell(write_cell(tmp_path, noise={
        'sigma': SIGMA, 'joint_sigma': {'lift': 2e-3}})))
    with pytest.raises(ConfigError, match="'stage_1' mimics 'lift'"):
        build_cell_model(load_cell(write_cell(tmp_path, noise={
            'sigma': SIGMA, 'joint_sigma': {'stage_1': 2e-3}})))
    robot, model = cm.robot, cm.model
    rng = np.random.default_rng(3)
    p = model.params.nominal
    for x in robot.actuated_values(robot.sample_configurations(rng, 3)):
        draws = 4000
        read = np.tile(x, (draws, 1))
        read[:, 0] += rng.normal(0.0, 2e-3, draws)       # the drive's reading error
        q_read = robot.chain_values(read)
        eta = model.predict(p, robot.chain_values(x)[None])[0] + rng.normal(0, SIGMA, (draws, 3))
        r = eta - model.predict(p, q_read)
        w = model.whitening(p, q_read, np.full(3, SIGMA))
        mean_square = float(np.mean(np.sum(np.einsum('nab,nb->na', w, r) ** 2, axis=1)))
        # the mean of χ²₃ over 4000 draws: 3 ± 0.05 (1σ)
        assert abs(mean_square - 3.0) < 0.2, mean_square

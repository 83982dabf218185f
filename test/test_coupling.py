"""Coupled controller joints (robot.joint_coupling), the calibrated URDF from the CLI, and
cell files as users write them (YAML 1.1 floats)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import identify_cell
from kpi_calib_ros.app.measurements import measurements_from_samples
from kpi_calib_ros.app.simulate import simulate_campaign
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.bag import read_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.cell_sections import coupling_from_mapping
from kpi_calib_ros.io.names import CALIBRATED_URDF_FILE

NAMES = [f'joint_{i}' for i in range(1, 7)]
FANUC = {'joint_3': {'joint_3': 1.0, 'joint_2': 1.0}}  # URDF joint_3 = J3 + J2


def _cell_copy(tmp_path: Path, **robot_keys) -> Path:
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['robot'].update(robot_keys)
    path = tmp_path / f'cell_{len(robot_keys)}.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def test_coupling_maps_and_inverts():
    c = coupling_from_mapping(FANUC, NAMES)
    q = np.random.default_rng(0).uniform(-1, 1, (5, 6))
    u = c.to_urdf(q)
    np.testing.assert_allclose(u[:, 2], q[:, 2] + q[:, 1], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(u[:, [0, 1, 3, 4, 5]], q[:, [0, 1, 3, 4, 5]])
    np.testing.assert_allclose(c.to_controller(u), q, rtol=0, atol=1e-15)
    assert coupling_from_mapping({}, NAMES).is_identity


@pytest.mark.parametrize('raw, key', [
    ({'joint_9': {'joint_3': 1.0}}, 'robot.joint_coupling.joint_9'),
    ({'joint_3': {'elbow': 1.0}}, 'robot.joint_coupling.joint_3.elbow'),
    ({'joint_3': {'joint_2': 'one'}}, 'robot.joint_coupling.joint_3.joint_2'),
    ({'joint_3': {'joint_2': 1.0}}, 'robot.joint_coupling'),  # joint_3 = joint_2: singular
])
def test_coupling_is_validated(raw, key):
    with pytest.raises(ConfigError) as err:
        coupling_from_mapping(raw, NAMES)
    assert err.value.key == key


def test_working_poses_in_controller_values(tmp_path):
    plain = build_cell_model(load_cell(_cell_copy(tmp_path)))
    ctrl = build_cell_model(load_cell(_cell_copy(tmp_path, joint_coupling=FANUC)))
    urdf = build_cell_model(load_cell(_cell_copy(tmp_path, joint_coupling=FANUC,
                                                 working_poses_in='urdf')))
    np.testing.assert_array_equal(urdf.q_work, plain.q_work)
    expected = plain.q_work.copy()
    expected[:, 2] += expected[:, 1]   # the cell's values read as the controller's
    np.testing.assert_allclose(ctrl.q_work, expected, rtol=0, atol=1e-15)
    with pytest.raises(ConfigError, match='working_poses_in'):
        load_cell(_cell_copy(tmp_path, working_poses_in='pendant'))


def _coupled_pair(tmp_path: Path, poses=None):
    plain_path = _cell_copy(tmp_path)
    coupled_path = _cell_copy(tmp_path, joint_coupling=FANUC, working_poses_in='urdf')
    plain = build_cell_model(load_cell(plain_path))
    coupled = build_cell_model(load_cell(coupled_path))
    bags = tmp_path / 'plain.mcap', tmp_path / 'coupled.mcap'
    for path, bag in zip((plain_path, coupled_path), bags):  # same truth, same draws
        simulate_campaign(path, 40, bag, seed=5, poses=poses)
    (j_plain, p_plain), (j_coupled, p_coupled) = read_bag(bags[0]), read_bag(bags[1])
    # The recorded readings differ (J3 = joint_3 - joint_2), as the controller reports them.
    a, b = np.array(j_plain[-1].positions), np.array(j_coupled[-1].positions)
    np.testing.assert_allclose(b[2], a[2] - a[1], rtol=0, atol=1e-12)
    assert abs(a[1]) > 0.01
    # Fed as published to the uncoupled model, the coupled readings are far off: some read
    # beyond joint 3's limits and are refused, the others misplace the arm.
    wrong, wrong_pairing = measurements_from_samples(plain, j_coupled, p_coupled)
    right, _ = measurements_from_samples(coupled, j_coupled, p_coupled)
    ref, _ = measurements_from_samples(plain, j_plain, p_plain)
    kept = np.isin(ref.stamps_ns, wrong.stamps_ns)
    assert len(wrong) + wrong_pairing.rejections.get('outside_joint_limits', 0) == len(ref)
    assert np.abs(wrong.q - ref.q[kept]).max() > 0.01
    np.testing.assert_allclose(right.q, ref.q, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(right.eta, ref.eta)
    r_ref, r_cpl = identify_cell(plain, ref), identify_cell(coupled, right)
    assert r_ref.converged and r_cpl.converged
    return ref, r_ref, r_cpl


@pytest.mark.slow
def test_coupled_publication_gives_the_uncoupled_calibration(tmp_path):
    """A FANUC-like controller publishes J3 against the horizontal; with
    robot.joint_coupling the calibration is the uncoupled one to 1e-9 (relative).

    Readings on an encoder grid (2⁻²⁰ rad) map back to the URDF values exactly, as
    real quantised readings do, so the same parameters are selected and estimated."""
    ref, _, _ = _coupled_pair(tmp_path)
    grid = np.round(ref.q * 2.0 ** 20) / 2.0 ** 20
    _, r_ref, r_cpl = _coupled_pair(tmp_path, poses=(NAMES, grid))
    assert r_ref.estimated == r_cpl.estimated
    scale = np.maximum(np.abs(r_ref.values), 1e-12)
    assert (np.abs(r_cpl.values - r_ref.values) / scale).max() <= 1e-9
    np.testing.assert_allclose(r_cpl.std, r_ref.std, rtol=1e-9, atol=0)
    np.testing.assert_allclose(r_cpl.tcp, r_ref.tcp, rtol=1e-9, atol=0)
    np.testing.assert_allclose(r_cpl.tcp_covariance, r_ref.tcp_covariance, rtol=1e-9, atol=0)


@pytest.mark.slow
def test_coupled_publication_off_grid_gives_the_same_tcp(tmp_path):
    """Off the encoder grid the readings come back within one ulp; the identifiable
    subset may then be a different but equivalent choice (same span), so the
    gauge-free results are compared: TCP, its covariance and χ²."""
    _, r_ref, r_cpl = _coupled_pair(tmp_path)
    np.testing.assert_allclose(r_cpl.tcp, r_ref.tcp, rtol=1e-9, atol=0)
    np.testing.assert_allclose(r_cpl.tcp_covariance, r_ref.tcp_covariance, rtol=1e-8, atol=0)
    assert abs(r_cpl.chi2 / r_ref.chi2 - 1) < 1e-9
    assert len(r_cpl.estimated) == len(r_ref.estimated)


def test_design_poses_leave_in_controller_values(tmp_path):
    from kpi_calib_ros.app.design import controller_design
    from kpi_calib_ros.core.design.optimum import DesignResult
    cm = build_cell_model(load_cell(_cell_copy(tmp_path, joint_coupling=FANUC)))
    q = np.random.default_rng(1).uniform(-1, 1, (4, 6))
    fake = DesignResult.__new__(DesignResult)
    object.__setattr__(fake, 'configurations', q)
    for f in dataclasses.fields(DesignResult):
        if f.name != 'configurations':
            object.__setattr__(fake, f.name, None)
    out = controller_design(cm, fake)
    np.testing.assert_allclose(cm.joint_coupling.to_urdf(out.configurations), q, atol=1e-15)
    assert np.abs(out.configurations[:, 2] - (q[:, 2] - q[:, 1])).max() < 1e-15


def test_cli_writes_the_node_calibrated_urdf(tmp_path, capsys):
    """kpi-calib identify writes the calibrated URDF beside calibration.yaml, and it is
    the node's byte for byte on the same data."""
    from kpi_calib_ros.app.measurements import load_measurements
    from kpi_calib_ros.ros.job_work import identify_work
    bag = tmp_path / 'run.mcap'
    simulate_campaign(DEFAULT_CELL, 30, bag, seed=3)
    out_cli, out_node = tmp_path / 'cli', tmp_path / 'node'
    out_cli.mkdir()
    out_node.mkdir()
    assert main(['identify', '--cell', str(DEFAULT_CELL), '--bag', str(bag),
                 '--out', str(out_cli)]) == 0
    text = capsys.readouterr().out
    cli_urdf = out_cli / CALIBRATED_URDF_FILE
    assert f'calibrated robot description (URDF): {cli_urdf}' in text
    cm, data, pairing = load_measurements(DEFAULT_CELL, bag)
    urdf = identify_work(cm, data, pairing, out_node).urdf
    assert cli_urdf.read_text() == urdf == (out_node / CALIBRATED_URDF_FILE).read_text()
    assert (out_cli / 'calibration.yaml').read_text() == (out_node / 'calibration.yaml').read_text()


def test_yaml_1_1_floats_are_numbers(tmp_path):
    """PyYAML reads 2e-06 as a string; the cell loader reads it as YAML 1.2 does."""
    path = _cell_copy(tmp_path)
    text = path.read_text()
    doc = yaml.safe_load(text)
    doc['noise'] = {'sigma': 'SIGMA'}
    path.write_text(yaml.safe_dump(doc).replace('SIGMA', '2e-06'))
    assert isinstance(yaml.safe_load(path.read_text())['noise']['sigma'], str)
    np.testing.assert_array_equal(load_cell(path).sigma, [2e-6] * 3)


def test_a_number_written_as_text_names_the_cause(tmp_path):
    path = _cell_copy(tmp_path)
    doc = yaml.safe_load(path.read_text())
    doc['noise'] = {'sigma': 'SIGMA'}
    path.write_text(yaml.safe_dump(doc).replace('SIGMA', '"2e-06"'))  # quoted: text
    with pytest.raises(ConfigError, match=r'write 2\.0e-06'):
        load_cell(path)


@pytest.mark.slow
def test_validate_compares_urdf_values_with_the_training_poses_of_a_coupled_robot(tmp_path):
    """The training ranges and poses of calibration.yaml are URDF joint values, as validate
    reads new joint states: the training recording validated against its own calibration
    has every pose inside the ranges and repeated (controller values would put joint_3
    outside for poses where J3 and joint_3 differ)."""
    cell = _cell_copy(tmp_path, joint_coupling=FANUC, working_poses_in='urdf')
    bag = tmp_path / 'coupled.mcap'
    simulate_campaign(cell, 30, bag, seed=5)
    assert main(['identify', '--cell', str(cell), '--bag', str(bag),
                 '--out', str(tmp_path / 'cal')]) == 0
    cal = yaml.safe_load((tmp_path / 'cal' / 'calibration.yaml').read_text())
    cm = build_cell_model(load_cell(cell))
    data, _ = measurements_from_samples(cm, *read_bag(bag))
    lo, hi = np.array([cal['training_joint_ranges'][n] for n in NAMES]).T
    np.testing.assert_allclose(lo, data.q.min(axis=0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(hi, data.q.max(axis=0), rtol=0, atol=1e-12)
    main(['validate', '--cell', str(cell), '--calibration',
          str(tmp_path / 'cal' / 'calibration.yaml'), '--bag', str(bag),
          '--out', str(tmp_path / 'val')])
    out = yaml.safe_load((tmp_path / 'val' / 'validation.json').read_text())
    assert out['outside_training_range'] == 0
    assert out['repeated_from_training'] == out['measurements'] == 30


def test_a_reading_beyond_the_limits_is_judged_on_the_urdf_joint_values(tmp_path):
    """The joint-limit check of a recorded pose is on the URDF joint values the coupling
    gives: a FANUC-like J3 reading (joint_3 − joint_2) far from joint_3's own range is a
    pose, and a URDF joint beyond its limit is a rejected row that names the joint, the
    value and its range."""
    coupled = build_cell_model(load_cell(_cell_copy(tmp_path, joint_coupling=FANUC,
                                                    working_poses_in='urdf')))
    robot = coupled.robot
    q = np.repeat(coupled.q_work[:1], 3, axis=0)
    q[0, 1], q[0, 2] = robot.upper[1] - 0.05, robot.lower[2] + 0.05  # J3 below joint_3's range
    q[1, 2] = robot.lower[2] - 0.3
    joints, points = synthesize_streams(coupled.joint_coupling.to_controller(q),
                                        coupled.joint_names, np.zeros((3, 3)),
                                        coupled.cell.tracker_frame)
    assert coupled.joint_coupling.to_controller(q)[0, 2] < robot.lower[2] - 0.5
    data, pairing = measurements_from_samples(coupled, joints, points)
    assert len(data) == 2 and pairing.rejections == {'outside_joint_limits': 1}
    assert pairing.rejected[0].detail.startswith(
        f'joint joint_3 at {robot.lower[2] - 0.3:.6g} rad is outside its URDF limits')

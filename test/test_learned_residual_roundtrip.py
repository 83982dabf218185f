"""``identify --learned-residual`` → ``validate``, through the command line, on campaigns of
real size: validate reads every learned_residual.yaml identify writes, with and without
``--register`` (which carries it into the registered set-up).

Three stock arms of example-robot-data (UR5 200 poses, Panda 300, UR10 200) with a
second-harmonic error of their second joint that the geometric model lacks (so the learned
residual is chosen and written), validated on a new recording of the same robot; and 1000
poses of the real UR10 of ../shared/data/ipa_ur10 Series A (imported as import-csv does),
validated on 100 others. Above MAX_TRAINING_ROWS identify fits no learned residual and says
why."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.learned_residual import too_many_rows
from kpi_calib_ros.app.simulate import simulate_campaign, truth_cell_model
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.diagnosis.learned_residual import MAX_TRAINING_ROWS
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.io.arm_cell import arm_cell_document
from kpi_calib_ros.io.cell import load_cell
from kpi_calib_ros.io.learned_residual_file import read_residual
from kpi_calib_ros.io.results import read_truth

from real_data import UR10_DATA

HERE = Path(__file__).parent / 'data'
ROBOTS = 'package://example-robot-data/robots/'
UR_POSE = [0.0, -1.2, 1.7, -2.07, -1.57, 0.0]
# id: (URDF, base, tip, the joint of the hidden error, working pose, training poses)
ARMS = {
    'ur5': ('ur_description/urdf/ur5_robot.urdf', 'base_link', 'tool0', 'shoulder_lift_joint',
            UR_POSE, 200),
    'panda': ('panda_description/urdf/panda.urdf', 'panda_link0', 'panda_hand', 'panda_joint2',
              [0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.8], 300),
    'ur10': ('ur_description/urdf/ur10_robot.urdf', 'base_link', 'tool0',
             'shoulder_lift_joint', UR_POSE, 200),
}
NEW_POSES = 50


def round_trip(cell: Path, train: Path, new: Path, out: Path, capsys) -> None:
    """identify --learned-residual writes the file; validate reads it (exit 0 or 1, never
    2), and with --register carries it into the registered set-up."""
    capsys.readouterr()
    assert main(['identify', '--cell', str(cell), '--bag', str(train), '--out', str(out / 'cal'),
                 '--learned-residual']) == 0, capsys.readouterr()
    text = capsys.readouterr().out
    assert 'learned residual chosen' in text, text
    path = out / 'cal' / 'learned_residual.yaml'
    written = yaml.safe_load(path.read_text())['physical']
    for field in ('covariance', 'covariance_outside'):
        matrix = np.array(written[field])
        np.testing.assert_array_equal(matrix, matrix.T)
    stored = read_residual(path)
    args = ['validate', '--cell', str(cell), '--calibration', str(out / 'cal' / 'calibration.yaml'),
            '--bag', str(new)]
    assert main(args + ['--out', str(out / 'val')]) in (0, 1)
    captured = capsys.readouterr()
    assert 'with the learned residual (learned_residual.yaml): rms' in captured.out, captured
    assert main(args + ['--out', str(out / 'val_reg'), '--register', 'base']) in (0, 1)
    captured = capsys.readouterr()
    assert 'with the learned residual (learned_residual.yaml): rms' in captured.out, captured
    print(f'{len(stored.residual.q)} training rows, {len(stored.estimated)} parameters: read back')


def stock_campaign(arm: str, folder: Path) -> tuple[Path, Path, Path]:
    """A stock arm's cell with a second-harmonic error of its second joint the geometric
    model lacks; its training bag (simulated, seed 1) and NEW_POSES new poses of the same
    robot. Returns (cell, train, new)."""
    path, base, tip, joint, pose, n = ARMS[arm]
    doc = arm_cell_document(ROBOTS + path, base, tip, 2e-5)
    doc['working_poses'] = [pose]
    doc['identification'] = {'model': 'geometric'}
    doc['simulation'] = {'hidden_effects': {f'cyclic_joint_error_h2:{joint}':
                                            {'a': 4e-4, 'b': 2e-4}}}
    cell = folder / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    train, new = folder / 'train.mcap', folder / 'new.mcap'
    assert main(['simulate', '--cell', str(cell), '--n', str(n), '--out', str(train),
                 '--seed', '1']) == 0
    cm, _ = truth_cell_model(load_cell(cell))
    truth = read_truth(train)['parameters']
    simulate_campaign(cell, NEW_POSES, new, 2, cm=cm,
                      p_true=np.array([truth[name] for name in cm.model.params.names]))
    return cell, train, new


@pytest.mark.slow
@pytest.mark.parametrize('arm', ARMS)
def test_validate_reads_what_identify_writes_on_a_stock_arm(arm, tmp_path, capsys):
    round_trip(*stock_campaign(arm, tmp_path), tmp_path, capsys)


@pytest.mark.slow
def test_validate_reads_what_identify_writes_on_the_real_ur10(tmp_path, capsys):
    """1000 poses of Series A (a posture: a point and a probe rotation), 100 others to
    validate on."""
    lines = (UR10_DATA / 'Series_A' / 'measurements_grid.csv').read_bytes().split(b'\r\n')
    rows = [line for line in lines[1:] if line]
    pick = np.random.default_rng(0).permutation(len(rows))
    for name, chosen in (('train', pick[:1000]), ('new', pick[1000:1100])):
        table = tmp_path / f'{name}.csv'
        table.write_bytes(b'\r\n'.join([lines[0], *[rows[i] for i in sorted(chosen)]]) + b'\r\n')
        assert main(['import-csv', str(table), '--mapping', str(HERE / 'ipa_ur10_mapping.yaml'),
                     '--out', str(tmp_path / f'{name}.mcap')]) == 0
    round_trip(HERE / 'ipa_ur10_cell.yaml', tmp_path / 'train.mcap', tmp_path / 'new.mcap',
               tmp_path, capsys)


def test_above_the_training_bound_no_learned_residual_is_fitted(cm):
    """identify fits none above MAX_TRAINING_ROWS point rows (so the reader's bound covers
    every file it writes), and says why."""
    q = np.zeros((MAX_TRAINING_ROWS + 1, 6))
    eta = np.zeros((MAX_TRAINING_ROWS + 1, 3))
    assert too_many_rows(cm, Measurements(q=q[:-1], eta=eta[:-1])) == ''
    assert too_many_rows(cm, Measurements(q=q, eta=eta)) == (
        f'learned residual not fitted: {MAX_TRAINING_ROWS + 1} point measurements, more than '
        f'the {MAX_TRAINING_ROWS} a learned residual is fitted on (its cost grows with the '
        'cube of their number); identify --learned-residual on fewer poses')


def test_the_learned_statement_after_registration_does_not_depend_on_the_turn_of_the_station(
        tmp_path, capsys):
    """The same 50 poses, the same noise, measured from the calibration's station and from
    stations moved rigidly (shifted, turned by 0.1 and 1 rad about the vertical, tilted by
    36 mrad): validated after ``--register base``, the learned residual's statement is the
    same (χ², p-value, the independent points the recording is worth). Before, the
    calibration's base covariance was propagated at the registered placement and the
    statement grew with the turn (a column robot: 34 independent points from its own
    station, 1 to 3 turned, and "its uncertainty holds" could not fail)."""
    from kpi_calib_ros.app.measurements import measurements_from_bag
    from kpi_calib_ros.app.validate import calibrated_model, validate_report
    from kpi_calib_ros.core.model.kinematics import rpy_matrix
    cell, train, new = stock_campaign('ur5', tmp_path)
    assert main(['identify', '--cell', str(cell), '--bag', str(train), '--out',
                 str(tmp_path / 'cal'), '--learned-residual']) == 0
    calibration = yaml.safe_load((tmp_path / 'cal' / 'calibration.yaml').read_text())
    placed, _ = calibrated_model(load_cell(cell), calibration)
    data, _ = measurements_from_bag(placed, new)
    seen = {}
    for name, (rpy, shift) in {'same': ((0, 0, 0), (0, 0, 0)),
                               'shifted': ((0, 0, 0), (1.5, -0.7, 0.2)),
                               'turned 0.1': ((0, 0, 0.1), (0, 0, 0)),
                               'turned 1': ((0, 0, 1.0), (0.3, 0.2, 0)),
                               'tilted': ((0.036, 0, 0), (0, 0, 0))}.items():
        turn = np.array(rpy_matrix(*rpy), float)
        moved = dataclasses.replace(data, eta=data.eta @ turn.T + np.array(shift))
        out = validate_report(placed, calibration, moved, tmp_path / name, 'base',
                              tmp_path / 'cal' / 'learned_residual.yaml')
        learned = out['learned_residual']
        seen[name] = (learned['chi2'], learned['p_value'], learned['effective_points'])
        print(name, seen[name])
    for name, figures in seen.items():
        np.testing.assert_allclose(figures, seen['same'], rtol=1e-4, err_msg=name)

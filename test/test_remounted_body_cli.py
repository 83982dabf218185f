"""A tracked 6-DoF body (a probe whose orientation the cell identifies) remounted between
recordings, through the command line on bags the tool's own writer makes: identified with
its own turn, and the calibration read back by ``validate --recording``, ``validate
--register reflector`` and ``--prior``."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.simulate import simulate_campaign
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.simulation import true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell, read_cell_document

SIGMA = 2e-5            # m per axis, the default cell's
SIGMA_ROTATION = 1e-4   # rad
BODY_RPY = [0.1, -0.2, 0.3]
ORIENTATION = [f'reflector.probe.r{c}' for c in 'xyz']
OFFSET = [f'reflector.probe.{c}' for c in 'xyz']
BASE = [f'base.{c}' for c in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')]
# Each set-up: the base moved against the tracker (m, rad), the probe offset moved (m), the
# body turned by exp(omega) on its remount (rad).
SET_UPS = {'a': (np.zeros(6), np.zeros(3), np.zeros(3)),
           'b': (np.array([-1.2, 1.5, 0.1, 0.02, -0.03, 0.6]), np.array([0.004, -0.003, 0.01]),
                 np.array([0.05, -0.03, 0.08])),
           'a_remounted': (np.zeros(6), np.array([-0.006, 0.002, 0.004]),
                           np.array([-0.04, 0.06, 0.02]))}


def _cell_document() -> dict:
    doc = copy.deepcopy(read_cell_document(DEFAULT_CELL))
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    del doc['reflector']
    doc['reflectors'] = [{'name': 'probe', 'offset': [0.0, 0.02, 0.03],
                          'orientation': {'rpy': BODY_RPY, 'identify': True}}]
    doc['noise']['sigma_rotation'] = SIGMA_ROTATION
    doc.setdefault('identification', {})['model'] = 'geometric'
    return doc


def _measure(folder: Path, name: str, bag: str, n: int, seed: int, robot: np.ndarray) -> None:
    """Measure ``robot`` (the true vector of set-up a's cell) ``n`` times from set-up
    ``name`` into ``folder/bag``; that set-up's cell (the tracker moved, the probe remounted
    and turned) is ``folder/cell_<name>.yaml``."""
    moved, remount, omega = SET_UPS[name]
    doc = _cell_document()
    doc['tracker']['base_in_tracker'] = (np.array(doc['tracker']['base_in_tracker'])
                                         + moved).tolist()
    body = doc['reflectors'][0]
    body['offset'] = (np.array(body['offset']) + remount).tolist()
    turned = Rotation.from_euler('xyz', BODY_RPY) * Rotation.from_rotvec(omega)
    body['orientation']['rpy'] = turned.as_euler('xyz').tolist()
    path = folder / f'cell_{name}.yaml'
    path.write_text(yaml.safe_dump(doc))
    cm = build_cell_model(load_cell(path))
    truth = robot.copy()
    names = cm.model.params.names
    truth[cm.model.params.indices(BASE)] += moved
    truth[cm.model.params.indices(OFFSET)] += remount
    assert list(names) == list(build_cell_model(load_cell(folder / 'cell.yaml')).model.params.names)
    simulate_campaign(path, n, folder / bag, seed, cm=cm, p_true=truth)


def _independent_residuals(folder: Path, cal: Path, bag: str, prefix: str
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Point residuals (N, 3) (m) and body rotation residuals (N, 3) (rad, the rotation
    vector of R_predᵀ R_measured) of ``bag``'s poses under calibration ``cal``, recomputed
    with Pinocchio from the calibrated URDF and the placement parameters ``prefix`` + base /
    reflector.probe names (URDF roll-pitch-yaw; the body: the cell's orientation times
    exp of its turn). The bag is read by the tool's reader, which its own tests check."""
    import pinocchio as pin

    from kpi_calib_ros.app.measurements import measurements_from_bag
    doc = yaml.safe_load((cal / 'calibration.yaml').read_text())
    value = {p['name']: p['value'] for p in doc['parameters']}
    cm = build_cell_model(load_cell(folder / 'cell.yaml'))
    data = measurements_from_bag(cm, folder / bag)[0]
    model = pin.buildModelFromXML((cal / 'robot_description_calibrated.urdf').read_text())
    pdata = model.createData()
    tip = model.getFrameId('tool0')
    base_turn = Rotation.from_euler('xyz', [value[f'{prefix}base.{c}']
                                            for c in ('roll', 'pitch', 'yaw')]).as_matrix()
    base_shift = np.array([value[f'{prefix}base.{c}'] for c in 'xyz'])
    offset = np.array([value[f'{prefix}reflector.probe.{c}'] for c in 'xyz'])
    body = (Rotation.from_euler('xyz', BODY_RPY) * Rotation.from_rotvec(
        [value[f'{prefix}reflector.probe.r{c}'] for c in 'xyz'])).as_matrix()
    ref = np.asarray(data.reflector, int)
    points, turns = [], []
    for row in range(len(data)):
        config = pin.neutral(model)
        for name, angle in zip(cm.robot.joint_names, data.q[row]):
            config[model.joints[model.getJointId(name)].idx_q] = angle
        pin.framesForwardKinematics(model, pdata, config)
        flange = pdata.oMf[tip]
        if ref[row] == 0:
            point = base_turn @ (flange.rotation @ offset + flange.translation) + base_shift
            points.append(data.eta[row] - point)
        else:
            predicted = base_turn @ flange.rotation @ body
            turns.append(Rotation.from_matrix(predicted.T @ data.rotation[row]).as_rotvec())
    return np.array(points), np.array(turns)


@pytest.fixture(scope='module')
def campaign(tmp_path_factory):
    folder = tmp_path_factory.mktemp('remounted_body')
    (folder / 'cell.yaml').write_text(yaml.safe_dump(_cell_document()))
    cm = build_cell_model(load_cell(folder / 'cell.yaml'))
    robot = true_parameters(cm.model.params, np.random.default_rng(21))
    robot[cm.model.params.indices(ORIENTATION)] = 0.0   # the stated orientation is a's
    for i, (name, bag, n) in enumerate((('a', 'a.mcap', 40), ('b', 'b.mcap', 40),
                                        ('b', 'b_later.mcap', 30),
                                        ('a_remounted', 'a_remounted.mcap', 30))):
        _measure(folder, name, bag, n, 100 + i, robot)
    return folder


@pytest.mark.slow
def test_a_remounted_tracked_body_is_identified_and_read_back_by_validate_and_prior(
        campaign, capsys):
    """Set-ups a and b (b: the tracker moved metres, the probe remounted and turned by
    (0.05, −0.03, 0.08) rad) identified together with ``--remounted b``: valid, b's body has
    its own turn in calibration.yaml. Read back: a later bag from b placed with
    ``--recording b`` holds at the noise, points and rotations; the probe remounted again at
    station a (turned another way) holds after ``--register reflector`` re-fits its offset and
    its orientation, and not without; the file is a ``--prior``."""
    folder = campaign
    cal = folder / 'cal'
    assert main(['identify', '--cell', str(folder / 'cell.yaml'), '--bag',
                 str(folder / 'a.mcap'), '--bag', str(folder / 'b.mcap'), '--remounted', 'b',
                 '--out', str(cal)]) == 0, capsys.readouterr()
    doc = yaml.safe_load((cal / 'calibration.yaml').read_text())
    assert doc['valid'] is True
    values = {p['name']: p for p in doc['parameters']}
    for c in 'xyz':
        assert f'recording.b.reflector.probe.r{c}' in values
    args = ['validate', '--cell', str(folder / 'cell.yaml'), '--calibration',
            str(cal / 'calibration.yaml')]
    capsys.readouterr()
    # a later bag from b, placed as b was
    assert main(args + ['--bag', str(folder / 'b_later.mcap'), '--out', str(folder / 'v_b'),
                        '--recording', 'b']) == 0, capsys.readouterr()
    out = json.loads((folder / 'v_b' / 'validation.json').read_text())
    with capsys.disabled():
        print(f"--recording b: chi2/dof {out['chi2']:.1f}/{out['dof']}, p "
              f"{out['p_value']:.3g}, rms {out['rms_m'] * 1e6:.1f} µm")
    assert out['holds'] is True and out['recording'] == 'b'
    assert out['rms_m'] < 2 * np.sqrt(3) * SIGMA
    # the same residuals recomputed without the tool's model: Pinocchio's tool0 of the
    # calibrated URDF, placed by b's base pose, b's probe offset and b's body turn
    points, turns = _independent_residuals(folder, cal, 'b_later.mcap', 'recording.b.')
    written = np.array([p['residual_m'] for p in out['points'] if p['reflector'] == 0])
    assert np.max(np.abs(points - written)) < 1e-9
    angle_rms = np.sqrt(np.mean(np.sum(turns ** 2, axis=1)))
    assert abs(angle_rms - out['rotation_rms_rad']['probe']) < 1e-9
    assert angle_rms < 2 * np.sqrt(3) * SIGMA_ROTATION
    # the probe remounted at a's station, its body turned another way
    bag = ['--bag', str(folder / 'a_remounted.mcap')]
    assert main(args + bag + ['--out', str(folder / 'v_r'), '--register', 'reflector']) == 0, \
        capsys.readouterr()
    registered = json.loads((folder / 'v_r' / 'validation.json').read_text())
    with capsys.disabled():
        print(f"--register reflector: chi2/dof {registered['chi2']:.1f}/{registered['dof']}, "
              f"rms {registered['rms_m'] * 1e6:.1f} µm, re-fitted "
              f"{registered['registration']['parameters']}")
    assert registered['holds'] is True
    assert set(ORIENTATION) <= set(registered['registration']['parameters'])
    turn = np.array([registered['registration']['values'][n] for n in ORIENTATION])
    stored = np.array([values[n]['value'] for n in ORIENTATION])
    # the remount's turn, composed on the stated orientation the calibration identified
    found = Rotation.from_rotvec(stored).inv() * Rotation.from_rotvec(turn)
    assert np.linalg.norm(found.as_rotvec() - SET_UPS['a_remounted'][2]) < 2e-3
    assert main(args + bag + ['--out', str(folder / 'v_nr')]) == 1
    assert json.loads((folder / 'v_nr' / 'validation.json').read_text())['holds'] is False
    # as a restarted node reads it back: the same TCP and parameters, the calibrated URDF's
    # tool where the calibration puts it
    from kpi_calib_ros.app.stored_calibration import read_stored_calibration
    stored = read_stored_calibration(build_cell_model(load_cell(folder / 'cell.yaml')),
                                     cal / 'calibration.yaml')
    assert list(stored.estimated) == doc['parameter_covariance']['names']
    assert np.allclose(stored.tcp, [t['position'] for t in doc['tcp']], atol=1e-12)
    # as a prior of a new identification of a's station
    capsys.readouterr()
    assert main(['identify', '--cell', str(folder / 'cell.yaml'), '--bag',
                 str(folder / 'a.mcap'), '--prior', str(cal / 'calibration.yaml'), '--out',
                 str(folder / 'again')]) == 0, capsys.readouterr()
    assert 'Traceback' not in capsys.readouterr().err

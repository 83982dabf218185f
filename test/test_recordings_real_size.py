"""Several recordings of the real UR10 (../shared/data/ipa_ur10) through the command line, at
a size real campaigns have: 2000 poses of Series A and half of Series D (316 poses, months
later, the tracker set up again and the probe remounted) identified together; the other half
of D held out.

Every file the tool writes is read back by the tool (validate, ``--prior``), and its figures
equal an evaluation that shares no code with it: the CSV tables read with the csv module,
forward kinematics by Pinocchio from the written URDF, the placements of calibration.yaml.
Full size (all 11 911 poses of A): bench/recordings_real_size.py.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import scipy.optimize
import yaml
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from kpi_calib_ros.cli import main

from real_data import UR10_DATA

DATA = UR10_DATA
HERE = Path(__file__).resolve().parent / 'data'
CELL = HERE / 'ipa_ur10_cell.yaml'
MAPPING = HERE / 'ipa_ur10_mapping.yaml'
JOINTS = ['shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint', 'wrist_1_joint',
          'wrist_2_joint', 'wrist_3_joint']
BASE = [f'base.{c}' for c in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')]
PROBE = [f'reflector.tmac.{c}' for c in 'xyz']
A_POSES = 2000
# The cell's probe axes in tool0 and its rotation rows' scale σ/σ_rot (m/rad).
BODY = Rotation.from_euler('xyz', [0.0, 0.0, -1.5707963]).as_matrix()
ROTATION_SCALE = 2.0e-5 / 1.0e-3


def _rows(source: Path, target: Path, keep: np.ndarray) -> Path:
    """The header and the rows ``keep`` (indices, in file order) of ``source``, bytes as
    they are."""
    lines = source.read_bytes().split(b'\r\n')
    body = [line for line in lines[1:] if line]
    target.write_bytes(b'\r\n'.join([lines[0], *[body[i] for i in np.sort(keep)]]) + b'\r\n')
    return target


def _table(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint values (rad), probe origins (m) and orientations of a table, read without the
    tool."""
    with open(path, newline='') as f:
        rows = list(csv.DictReader(f, delimiter=';'))

    def column(*names: str) -> np.ndarray:
        return np.array([[float(r[n].replace(',', '.')) for n in names] for r in rows])
    angles = column('measurement_rx', 'measurement_ry', 'measurement_rz')
    return (column(*JOINTS), column('measurement_x', 'measurement_y', 'measurement_z') * 1e-3,
            Rotation.from_euler('XYZ', angles, degrees=True).as_matrix())


def _flange(urdf: str, q: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """tool0's rotation and position in the base frame of ``urdf`` at each row of ``q``."""
    model = pin.buildModelFromXML(urdf)
    data = model.createData()
    tip = model.getFrameId('tool0')
    out = []
    for row in q:
        config = pin.neutral(model)
        for value, name in zip(row, JOINTS):
            joint = model.joints[model.getJointId(name)]
            config[joint.idx_q:joint.idx_q + joint.nq] = (
                [np.cos(value), np.sin(value)] if joint.nq == 2 else [value])
        pin.framesForwardKinematics(model, data, config)
        out.append((data.oMf[tip].rotation.copy(), data.oMf[tip].translation.copy()))
    return out


def _misses(value: dict, flange: list, points: np.ndarray, rotations: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Point residuals (N, 3) (m) and rotation residuals (N, 3) (scaled, m) with the base
    pose and probe offset of ``value`` (URDF roll-pitch-yaw)."""
    turn = Rotation.from_euler('xyz', [value[n] for n in BASE[3:]]).as_matrix()
    shift = np.array([value[n] for n in BASE[:3]])
    offset = np.array([value[n] for n in PROBE])
    predicted = np.array([turn @ (r @ offset + t) + shift for r, t in flange])
    turned = [turn @ r @ BODY for r, _ in flange]
    angle = np.array([Rotation.from_matrix(p.T @ m).as_rotvec()
                      for m, p in zip(rotations, turned)])
    return points - predicted, angle * ROTATION_SCALE


def _registered_rms(folder: Path, table: Path, names: list[str]) -> float:
    """Rms (m) of the points of ``table`` after ``names`` are re-fitted by least squares
    over its point and rotation rows, the calibration of ``folder`` held."""
    doc = yaml.safe_load((folder / 'calibration.yaml').read_text())
    value = {p['name']: p['value'] for p in doc['parameters']}
    q, points, rotations = _table(table)
    flange = _flange((folder / 'robot_description_calibrated.urdf').read_text(), q)

    def residual(x: np.ndarray) -> np.ndarray:
        return np.concatenate([m.ravel() for m in _misses(
            dict(value, **dict(zip(names, x))), flange, points, rotations)])
    fit = scipy.optimize.least_squares(residual, [value[n] for n in names], xtol=1e-15,
                                       ftol=1e-15, gtol=1e-15)
    miss = _misses(dict(value, **dict(zip(names, fit.x))), flange, points, rotations)[0]
    return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))


@pytest.fixture(scope='module')
def campaign(tmp_path_factory):
    """Bags of 2000 poses of A and both halves of D (random, seed 0), as import-csv makes
    them; D's stamps are not usable (the rows' order is its time axis)."""
    folder = tmp_path_factory.mktemp('ur10')
    series_a = DATA / 'Series_A' / 'measurements_grid.csv'
    series_d = DATA / 'Series_D' / 'measurements_iso_cubes.csv'
    rng = np.random.default_rng(0)
    tables = {'A': _rows(series_a, folder / 'A.csv', rng.choice(11911, A_POSES, replace=False))}
    order = np.random.default_rng(0).permutation(632)
    tables['D'] = _rows(series_d, folder / 'D.csv', order[:316])
    tables['D_heldout'] = _rows(series_d, folder / 'D_heldout.csv', order[316:])
    rows_only = yaml.safe_load(MAPPING.read_text())
    for key in ('stamp_columns', 'stamp_format', 'stamp_timezone'):
        rows_only.pop(key)
    (folder / 'rows.yaml').write_text(yaml.safe_dump(rows_only))
    for name, table in tables.items():
        mapping = MAPPING if name == 'A' else folder / 'rows.yaml'
        assert main(['import-csv', str(table), '--mapping', str(mapping), '--out',
                     str(folder / f'{name}.mcap')]) == 0
    return folder, tables


@pytest.mark.slow
def test_ur10_a_and_remounted_d_identified_together_read_back_and_checked(campaign, capsys):
    folder, tables = campaign
    cell = ['--cell', str(CELL)]
    joint, alone = folder / 'joint', folder / 'alone'
    assert main(['identify', *cell, '--bag', str(folder / 'A.mcap'), '--bag',
                 str(folder / 'D.mcap'), '--remounted', 'D', '--out', str(joint)]) == 0
    text = capsys.readouterr().out
    doc = yaml.safe_load((joint / 'calibration.yaml').read_text())
    rec_a, rec_d = doc['recordings']
    assert (rec_a['name'], rec_a['poses'], rec_d['name'], rec_d['poses']) == ('A', 2000, 'D', 316)
    assert rec_d['reflector_remounted'] and not rec_d['against_nominal']['worse_than_nominal']
    # D's tracker is another station: its base turned by 71° about the vertical from A's
    value = {p['name']: p['value'] for p in doc['parameters']}
    yaw = value['recording.D.base.yaw'] - value['base.yaw']
    assert 1.0 < abs(yaw) < 1.5 and abs(value['recording.D.base.roll']) < 0.02

    # Independent: the written URDF and placements predict every row as the tool's residuals
    urdf = (joint / 'robot_description_calibrated.urdf').read_text()
    points, angles = [], []
    for name, prefix in (('A', ''), ('D', 'recording.D.')):
        q, eta, rotations = _table(tables[name])
        mine = {n: value[prefix + n] for n in BASE + PROBE}
        point_miss, angle_miss = _misses(mine, _flange(urdf, q), eta, rotations)
        rms = np.sqrt(np.mean(np.sum(point_miss ** 2, axis=1)))
        assert rms == pytest.approx(doc['recordings'][len(points)]['rms_m'], abs=1e-12)
        points.append(point_miss)
        angles.append(angle_miss)
    tool = np.array(doc['residuals_m'])  # a point row, then its rotation row, per pose
    for rows, mine in ((tool[0::2], np.concatenate(points)), (tool[1::2], np.concatenate(angles))):
        distance, index = cKDTree(mine).query(rows)
        assert len(rows) == len(mine) == len(set(index.tolist()))
        assert distance.max() < 1e-9

    # Read back: validate D's held-out half (base and probe re-fitted) equals the same
    # registration done here; and against calibration on A alone
    def validate(calibration: Path, out: str) -> float:
        assert main(['validate', *cell, '--calibration', str(calibration / 'calibration.yaml'),
                     '--bag', str(folder / 'D_heldout.mcap'), '--register', 'base+reflector',
                     '--out', str(folder / out)]) in (0, 1)
        figures = json.loads((folder / out / 'validation.json').read_text())
        assert figures['registration']['dof'] == 9
        assert figures['rms_m'] == pytest.approx(
            _registered_rms(calibration, tables['D_heldout'], BASE + PROBE), abs=1e-9)
        return figures['rms_m']
    assert main(['identify', *cell, '--bag', str(folder / 'A.mcap'), '--out', str(alone)]) == 0
    together, from_a = validate(joint, 'val_joint'), validate(alone, 'val_alone')
    capsys.readouterr()
    print(f'D held out, registered: {together * 1e3:.3f} mm from A and D, '
          f'{from_a * 1e3:.3f} mm from A alone')
    # D predicted no worse than from A alone, beyond what 316 points' rms varies by
    assert together <= from_a * (1 + 1 / np.sqrt(2 * 316))
    assert 'recording D: 316 poses' in text
    # The file as the prior of the next calibration (D alone cannot be registered: its
    # probe keeps one orientation, exit 2 and said so)
    assert main(['identify', *cell, '--bag', str(folder / 'A.mcap'), '--prior',
                 str(joint / 'calibration.yaml'), '--out', str(folder / 'next')]) in (0, 1)
    assert 'Traceback' not in capsys.readouterr().err
    again = yaml.safe_load((folder / 'next' / next(
        p.name for p in (folder / 'next').glob('calibration*.yaml'))).read_text())
    assert again['pairing']['accepted'] == A_POSES

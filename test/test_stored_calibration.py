"""A calibration.yaml read back for the node's cell: the calibration the node published
comes back exactly (the same values, covariance, TCP and calibrated URDF, and the same TCP
predicted at new joints), and a damaged file, an invalid calibration or one of another
cell or robot is refused with the file and the reason named."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.learned_residual import predict_tcp
from kpi_calib_ros.app.stored_calibration import read_stored_calibration
from kpi_calib_ros.core.acquisition.outcomes import PairingResult
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell, with_overrides
from kpi_calib_ros.ros import job_work

N_POSES = 30
ROBOTS = DEFAULT_CELL.parent.parent / 'robots'


@pytest.fixture(scope='module')
def identified(tmp_path_factory):
    """The built-in cell identified from 30 simulated poses as the node's ~/identify
    does (calibration.yaml and the calibrated URDF in data_dir); fresh poses."""
    data_dir = tmp_path_factory.mktemp('stored')
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    rng = np.random.default_rng(5)
    p = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, p, N_POSES + 5, rng)
    eta = simulate_measurements(cm.model, p, q[:N_POSES], cm.cell.sigma, rng).eta
    stamps = 10 ** 18 + np.arange(N_POSES, dtype=np.int64) * 10 ** 9
    pairing = PairingResult(cm.joint_names, cm.cell.tracker_frame, q[:N_POSES], eta, stamps)
    out = job_work.identify_work(cm, Measurements(q=q[:N_POSES], eta=eta, stamps_ns=stamps),
                                 pairing, data_dir)
    cal, text, urdf = out.calibration, out.text, out.urdf
    assert cal is not None and cal.valid
    return cm, cal.result, text, urdf, data_dir / 'calibration.yaml', q[N_POSES:]


def test_a_stored_calibration_serves_what_the_identification_published(identified):
    cm, result, text, urdf, path, fresh = identified
    stored = read_stored_calibration(cm, path)
    assert stored.text == text and stored.urdf == urdf
    assert stored.summary() == f'restored from {path}, identified at {10 ** 18 + 29 * 10 ** 9} ns'
    assert stored.estimated == result.estimated
    np.testing.assert_array_equal(stored.values, result.values)
    np.testing.assert_array_equal(stored.covariance, result.covariance)
    np.testing.assert_array_equal(stored.tcp, result.tcp)
    np.testing.assert_array_equal(stored.tcp_covariance, result.tcp_covariance)
    # ~/tcp_query's answer at new joints: the same prediction and covariance.
    before = predict_tcp(cm.model, result.values, result.estimated, result.covariance, None,
                         fresh)
    after = predict_tcp(stored.cell.model, stored.values, stored.estimated, stored.covariance,
                        None, fresh)
    np.testing.assert_array_equal(after.position, before.position)
    np.testing.assert_array_equal(after.covariance, before.covariance)


def edited(path, tmp_path, change):
    doc = yaml.safe_load(path.read_text())
    change(doc)
    out = tmp_path / 'calibration.yaml'
    out.write_text(yaml.safe_dump(doc, sort_keys=False))
    return out


def not_valid(doc):
    doc['valid'], doc['invalid_reasons'] = False, ['identification did not converge: x']


def another_effect(doc):
    doc['effects'] = ['joint_compliance:joint_3']


def a_seventh_joint(doc):
    doc['parameters'].append({'name': 'joint_7.offset', 'value': 0.0, 'unit': 'rad',
                              'estimated': False})


def other_working_poses(doc):
    doc['tcp'][0]['name'] = 'somewhere_else'


@pytest.mark.parametrize('change, why', [
    (not_valid, 'not a valid calibration (identification did not converge: x)'),
    (another_effect, 'its model does not fit this cell'),
    (a_seventh_joint, "not those of this cell's model (unknown here: ['joint_7.offset'])"),
    (other_working_poses, "its TCP is for the working poses ['somewhere_else']"),
])
def test_an_invalid_or_foreign_calibration_is_refused(identified, tmp_path, change, why):
    cm, *_, path, _ = identified
    bad = edited(path, tmp_path, change)
    with pytest.raises(DataError) as info:
        read_stored_calibration(cm, bad)
    assert str(info.value).startswith(f'{bad} not used: ') and why in str(info.value), info.value


def test_a_damaged_file_is_refused(identified, tmp_path):
    cm, *_, path, _ = identified
    bad = tmp_path / 'calibration.yaml'
    bad.write_text(path.read_text()[:len(path.read_text()) // 2])  # torn mid-document
    with pytest.raises(DataError) as info:
        read_stored_calibration(cm, bad)
    assert str(info.value).startswith(f'{bad} not used: not readable: '), info.value


def test_a_calibration_of_another_robot_or_cell_is_refused(identified):
    cm, *_, path, _ = identified
    # Another robot with the same joint names: its geometry is not the calibration's.
    kr300 = build_cell_model(with_overrides(cm.cell, urdf_xml=(
        ROBOTS / 'kr300_class.urdf').read_text()))
    with pytest.raises(DataError, match='identified on another robot description'):
        read_stored_calibration(kr300, path)
    # The same robot, its cell now with an effect the calibration was identified without.
    compliant = build_cell_model(dataclasses.replace(cm.cell,
                                                     effects=('joint_compliance:joint_2',)))
    with pytest.raises(DataError, match='its model does not fit this cell'):
        read_stored_calibration(compliant, path)


def test_a_working_pose_changed_since_the_calibration_is_refused(identified):
    """The node's working pose moved since the calibration (joint_2 + 0.35 rad): the written
    TCP is no longer where the calibration puts that pose, and restoring it would publish
    the former place, 0.39 m off; refused, naming the pose and the fix. The pose as it was,
    or given a payload the geometric model does not feel, restores."""
    cm, *_, path, _ = identified
    pose = cm.cell.working_poses[0]
    moved = dataclasses.replace(pose, joints={**pose.joints, 'joint_2':
                                              pose.joints['joint_2'] + 0.35})
    other = build_cell_model(with_overrides(cm.cell, working_poses=(moved,)))
    with pytest.raises(DataError, match=f"working pose '{pose.name}' is 3.* mm from where "
                       'its parameters put that pose now.*identify again'):
        read_stored_calibration(other, path)
    for same in (pose, dataclasses.replace(pose, payload=(12.0, None))):
        here = build_cell_model(with_overrides(cm.cell, working_poses=(same,)))
        assert read_stored_calibration(here, path).tcp.shape == (1, 3)

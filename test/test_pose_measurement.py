"""A tracked 6-DoF pose (position and orientation of a body on the tool) as a measurement:
the SO(3) logarithm and the rotation rows' exact Jacobian, the cell keys, a simulated
campaign identified to its truth, what the orientation adds to the TCP precision, and
Monte Carlo agreement of χ² and the TCP covariance."""
import copy
import dataclasses
import json

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest
import yaml
from geometry_msgs.msg import PoseStamped

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.acquisition.pairing import pair_measurements
from kpi_calib_ros.core.acquisition.streams import PointSample, synthesize_streams
from kpi_calib_ros.core.diagnosis.screening import screen_effects
from kpi_calib_ros.core.diagnosis.validation import validate
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.cross_validation import region_validation, validation_rms
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.precision import typical_held_out_rms
from kpi_calib_ros.core.estimation.residuals import residual_report
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.pose import (
    log3_expression,
    noisy_rotations,
    pose_matrix,
    quaternion_from_rotation,
    rotation_from_quaternion,
    rotation_from_rpy,
)
from kpi_calib_ros.core.measurement.pose_rows import with_rotation_rows
from kpi_calib_ros.core.model.kinematics import pose6
from kpi_calib_ros.core.simulation import (
    random_configurations,
    smooth_joint_map,
    true_parameters,
)
from kpi_calib_ros.io.bag import read_bag, write_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document
from kpi_calib_ros.io.ros_messages import pose_sample_from_message

SIGMA = 2e-5            # m per axis, the default cell's
SIGMA_ROTATION = 1e-4   # rad: a 6-DoF probe's orientation noise (~0.006°)
BODY_RPY = [0.1, -0.2, 0.3]
N_POSES = 60


def pose_doc(orientation=None, sigma_rotation=SIGMA_ROTATION):
    doc = copy.deepcopy(read_cell_document(DEFAULT_CELL))
    del doc['reflector']['offset']
    body = {'name': 'probe', 'offset': [0.0, 0.02, 0.03],
            'orientation': orientation or {'rpy': BODY_RPY}}
    doc['reflectors'] = [body]
    doc['noise']['sigma_rotation'] = sigma_rotation
    return doc


@pytest.fixture(scope='module')
def cm():
    return build_cell_model(cell_from_dict(pose_doc(), DEFAULT_CELL.parent))


def campaign(cm, p_true, q, rng, with_orientation=True):
    """Points of the probe's origin (σ per axis) and, with orientation, its rotation
    (σ_rot in the body frame) at every configuration of ``q``."""
    ref = np.zeros(len(q), dtype=int)
    eta = cm.model.predict(p_true, q, reflector=ref) + rng.normal(size=(len(q), 3)) * SIGMA
    rotations = noisy_rotations(cm.model.body_rotations(p_true, q, 0), SIGMA_ROTATION, rng)
    points = Measurements(q=q, eta=eta, reflector=ref)
    return with_rotation_rows(cm.model, points, rotations) if with_orientation else points


def equivalent_truth(cm, p_true, result, seed):
    """The true robot in ``result``'s parameterisation: its identified parameters fitted
    noise-free to the true points and rotations at 400 configurations drawn with ``seed``,
    from the truth (the dropped ones at their identified values)."""
    kept = result.estimated
    start = result.values.copy()
    start[cm.model.params.indices(kept)] = p_true[cm.model.params.indices(kept)]
    q_dense = random_configurations(cm.model, cm.model.params.nominal, 400,
                                    np.random.default_rng(seed))
    truth = campaign(cm, p_true, q_dense, np.random.default_rng(0), True)
    exact = with_rotation_rows(cm.model, Measurements(
        q=q_dense, eta=cm.model.predict(p_true, q_dense, reflector=np.zeros(len(q_dense), int)),
        reflector=np.zeros(len(q_dense), int)), cm.model.body_rotations(p_true, q_dense, 0))
    assert len(truth) == len(exact)
    idx = cm.model.params.indices(kept)
    p = np.array(start, float)
    for _ in range(20):
        pred, jac = cm.model.jacobian(p, exact.q, None, exact.reflector, exact.rotation)
        f = jac.reshape(-1, len(p))[:, idx]
        scale = np.linalg.norm(f, axis=0)
        step, *_ = np.linalg.lstsq(f / scale, (exact.eta - pred).ravel(), rcond=None)
        p[idx] += step / scale
    pred = cm.model.predict(p, exact.q, None, exact.reflector, exact.rotation)
    return p, float(np.max(np.abs(exact.eta - pred)))


# ----------------------------------------------------------------- the model
@pytest.mark.parametrize('angle', [0.0, 1e-9, 1e-5, 0.3, 2.0, 3.1])
def test_log3_equals_pinocchio(angle):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    rotation = pin.exp3(axis * angle)
    sym = ca.SX.sym('R', 3, 3)
    log3 = ca.Function('log3', [sym], [log3_expression(sym)])
    assert np.allclose(np.array(log3(rotation)).ravel(), pin.log3(rotation), atol=1e-12)


def test_quaternion_and_rpy_conversions_agree_with_pinocchio():
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        expected = pin.Quaternion(q[3], q[0], q[1], q[2]).toRotationMatrix()
        assert np.allclose(rotation_from_quaternion(q), expected, atol=1e-12)
        assert np.allclose(quaternion_from_rotation(expected), q * np.sign(q[3]), atol=1e-12)
        rpy = rng.uniform(-1.5, 1.5, 3)
        assert np.allclose(rotation_from_rpy(rpy), pin.rpy.rpyToMatrix(*rpy), atol=1e-12)
    with pytest.raises(ValueError, match='length'):
        rotation_from_quaternion([0.0, 0.0, 0.0, 2.0])


def test_the_numeric_pose_matrix_is_the_symbolic_pose_to_the_bit():
    """The cell model's tracker pose is computed without CasADi; the numbers must be those
    the symbolic model (pose6) gives, bit for bit, so results do not move."""
    rng = np.random.default_rng(5)
    for pose in rng.uniform(-np.pi, np.pi, (200, 6)):
        assert np.array_equal(pose_matrix(pose), np.array(ca.DM(pose6(ca.DM(pose)))))
    with pytest.raises(ValueError, match='6 numbers'):
        pose_matrix([0.0, 1.0])


def test_rotation_row_is_the_scaled_log_and_its_jacobian_is_exact(cm):
    rng = np.random.default_rng(4)
    p0 = cm.model.params.nominal
    p = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, p0, 6, rng)
    measured = cm.model.body_rotations(p, q, 0)
    channel = np.full(len(q), cm.model.rotation_channel(0))
    pred, jac = cm.model.jacobian(p0, q, None, channel, measured)
    nominal = cm.model.body_rotations(p0, q, 0)
    scale = SIGMA / SIGMA_ROTATION
    for i in range(len(q)):  # residual 0 - h = log3(R(p0)ᵀ R_m) · σ/σ_rot
        assert np.allclose(-pred[i], pin.log3(nominal[i].T @ measured[i]) * scale, atol=1e-14)
    for k in range(0, len(p0), 7):
        step = np.zeros(len(p0))
        step[k] = 1e-7
        fd = (cm.model.predict(p0 + step, q, None, channel, measured)
              - cm.model.predict(p0 - step, q, None, channel, measured)) / 2e-7
        assert np.allclose(jac[:, :, k], fd, atol=1e-7 * scale, rtol=1e-6)
    # At the truth the residual is zero and the Jacobian finite (the log's series branch).
    pred, jac = cm.model.jacobian(p, q, None, channel, measured)
    assert np.abs(pred).max() < 1e-12 and np.all(np.isfinite(jac))


def test_rotation_rows_need_the_measured_rotations(cm):
    q = cm.q_work
    with pytest.raises(ValueError, match='measured rotations'):
        cm.model.predict(cm.model.params.nominal, q, None,
                         np.full(len(q), cm.model.rotation_channel(0)))


# ----------------------------------------------------------------- cell keys
@pytest.mark.parametrize('change, key', [
    (lambda d: d['reflectors'][0].update(orientation={'rpy': [0, 0]}),
     'reflectors[0].orientation.rpy'),
    (lambda d: d['reflectors'][0].update(orientation={'rpy': [0, 0, 90]}),
     'reflectors[0].orientation.rpy'),
    (lambda d: d['reflectors'][0].update(orientation={'quaternion': [0, 0, 0, 2]}),
     'reflectors[0].orientation.quaternion'),
    (lambda d: d['reflectors'][0].update(orientation={'euler': [0, 0, 0]}),
     'reflectors[0].orientation'),
    (lambda d: d['reflectors'][0].update(colour='red'), 'reflectors[0].colour'),
    (lambda d: d['noise'].pop('sigma_rotation'), 'noise.sigma_rotation'),
    (lambda d: d['noise'].update(sigma_rotation=0.5), 'noise.sigma_rotation'),
    (lambda d: d['noise'].update(sigma_rotation='1e-4'), 'noise.sigma_rotation'),
    (lambda d: d['reflector'].update(orientation={'rpy': [0, 0, 0]}), 'reflector.orientation'),
])
def test_bad_orientation_keys_are_named(change, key):
    doc = pose_doc()
    change(doc)
    if key == 'reflector.orientation':
        doc['reflector']['offset'] = [0, 0, 0.03]
        del doc['reflectors']
    with pytest.raises(ConfigError) as err:
        cell_from_dict(doc, DEFAULT_CELL.parent)
    assert err.value.key == key


def test_quaternion_and_rpy_forms_give_the_same_cell():
    quaternion = quaternion_from_rotation(rotation_from_rpy(BODY_RPY)).tolist()
    a = cell_from_dict(pose_doc(), DEFAULT_CELL.parent)
    b = cell_from_dict(pose_doc({'quaternion': quaternion}), DEFAULT_CELL.parent)
    assert np.allclose(a.reflector_orientations[0][1], b.reflector_orientations[0][1],
                       atol=1e-12)
    assert a.sigma_rotation == SIGMA_ROTATION


# ----------------------------------------------------------- identification
@pytest.fixture(scope='module')
def identified(cm):
    rng = np.random.default_rng(11)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, cm.model.params.nominal, N_POSES, rng)
    seed = np.random.default_rng(12)
    data = campaign(cm, p_true, q, seed)
    with_rot = identify(cm.model, data, cm.cell.sigma, cm.q_work)
    points = data.subset(data.reflector == 0)
    without = identify(cm.model, points, cm.cell.sigma, cm.q_work)
    return p_true, q, data, with_rot, without


def test_a_pose_campaign_recovers_the_truth_within_3_sigma(cm, identified):
    p_true, q, data, result, _ = identified
    assert result.converged and len(data) == 2 * N_POSES
    idx = cm.model.params.indices(result.estimated)
    p_equiv, representation = equivalent_truth(cm, p_true, result, 13)
    z = (result.values[idx] - p_equiv[idx]) / result.std
    print(f'identified {len(idx)} parameters with orientation, within 3σ '
          f'{np.mean(np.abs(z) < 3):.3f}, max |z| {np.abs(z).max():.2f}, '
          f'representation error {representation * 1e6:.3f} µm (σ units: m at σ)')
    assert representation < SIGMA / 2
    assert np.mean(np.abs(z) < 3) >= 0.95
    # The TCP point (probe origin at the working pose) too, against its own std.
    tcp_true = cm.model.predict(p_true, cm.q_work)
    for t, cov in zip(tcp_true - result.tcp, result.tcp_covariance):
        assert t @ np.linalg.solve(cov, t) < 14.2  # χ²₃ 0.997 quantile (3σ)


def test_the_orientation_identifies_more_and_shrinks_the_tcp_std(cm, identified):
    _, _, _, with_rot, without = identified
    std_with = np.sqrt(np.trace(with_rot.tcp_covariance, axis1=1, axis2=2))
    std_without = np.sqrt(np.trace(without.tcp_covariance, axis1=1, axis2=2))
    print(f'TCP std (sqrt trace) {std_with[0] * 1e6:.2f} µm with orientation, '
          f'{std_without[0] * 1e6:.2f} µm without; identified {len(with_rot.estimated)} vs '
          f'{len(without.estimated)} parameters')
    assert len(with_rot.estimated) > len(without.estimated)
    assert np.all(std_with < std_without)


@pytest.mark.slow
def test_held_out_figures_of_a_pose_campaign_are_lengths_of_its_points(cm):
    """A tracked body's rotation rows are held out with their pose but are no length: every
    held-out rms (m) is that of the points and predicts fresh poses' point error. Here the
    points carry a misfit no parameter describes (a smooth 0.2 mm map) and the rotations
    only their noise: averaged with the rotation rows the figures fell to 0.78 of it,
    below the fit's own rms."""
    rng = np.random.default_rng(21)
    p_true = true_parameters(cm.model.params, rng)
    phase = rng.uniform(0, 2 * np.pi, 6)
    q = random_configurations(cm.model, cm.model.params.nominal, N_POSES, rng)
    data = campaign(cm, p_true, q, rng)
    points = data.reflector == 0
    eta = data.eta.copy()
    eta[points] += smooth_joint_map(data.q[points], (1, 2), 2e-4, phase)
    data = dataclasses.replace(data, eta=eta)
    result = identify(cm.model, data, cm.cell.sigma, cm.q_work)
    fresh = random_configurations(cm.model, cm.model.params.nominal, 400, rng)
    ref = np.zeros(len(fresh), dtype=int)
    truth = (cm.model.predict(p_true, fresh, reflector=ref)
             + smooth_joint_map(fresh, (1, 2), 2e-4, phase))
    error = truth + rng.normal(size=(400, 3)) * SIGMA - cm.model.predict(
        result.values, fresh, reflector=ref)
    fresh_rms = float(np.sqrt(np.mean(np.sum(error ** 2, axis=1))))
    figures = {'leave one pose out': validation_rms(cm.model, data, result),
               'typical held out': typical_held_out_rms(cm.model, data, result)[0],
               'in region': region_validation(cm.model, data, result).in_region_m}
    print({k: f'{v * 1e6:.1f} µm' for k, v in figures.items()},
          f'fresh poses {fresh_rms * 1e6:.1f} µm, fit {result.rms_m * 1e6:.1f} µm')
    for name, value in figures.items():
        # A held-out residual is never below its fitted one: nor is their rms.
        assert value > result.rms_m and 0.85 < value / fresh_rms < 1.2, (name, value)
    # The effect screen states the fit's rms before each candidate: the same point rows.
    screened, _ = screen_effects(cm.model, data, result)
    assert screened and all(f'rms {result.rms_m * 1e6:.1f} -> ' in c.explanation
                            for c in screened)


def test_the_residual_report_of_a_pose_campaign_is_lengths_of_its_points(cm, identified):
    """diagnose's headline rms and percentiles of |r| are those of the points: with the
    rotation rows (rad scaled to σ) averaged in, the real UR10's 298 probe poses were stated
    at 310 µm, median 87 µm, where its points miss by 437 µm, median 357 µm."""
    _, _, data, result, _ = identified
    report = residual_report(cm.model, data, result)
    points = data.reflector == 0
    norms = np.linalg.norm(data.eta[points] - cm.model.predict(
        result.values, data.q[points], reflector=data.reflector[points]), axis=1)
    assert report.rms_m == pytest.approx(np.sqrt(np.mean(norms ** 2)), rel=1e-9)
    assert report.rms_m == pytest.approx(result.rms_m, rel=1e-9)
    assert report.max_m == pytest.approx(norms.max(), rel=1e-9)
    for k, v in report.percentiles_m.items():
        assert v == pytest.approx(np.percentile(norms, k), rel=1e-9)


def test_validate_takes_rotation_rows_and_holds_on_fresh_poses(cm, identified):
    p_true, q, _, result, _ = identified
    rng = np.random.default_rng(21)
    fresh = campaign(cm, p_true, random_configurations(cm.model, cm.model.params.nominal,
                                                       30, rng), rng)
    idx = cm.model.params.indices(result.estimated)
    check = validate(cm.model, result.values, idx, result.covariance, cm.cell.sigma, fresh,
                     q.min(axis=0), q.max(axis=0))
    print(f'validation on 30 fresh poses: chi2 {check.chi2:.1f} / {check.dof}, '
          f'p = {check.p_value:.3f}')
    assert check.dof == 3 * 60 and check.holds
    # Counted in points, as the rms beside them: the real UR10's Series D, 632 probe
    # poses, was said to have 806 points outside the training ranges (rows with rotations).
    from kpi_calib_ros.app.validate import validation_to_dict
    middle = q.mean(axis=0)
    outside = validate(cm.model, result.values, idx, result.covariance, cm.cell.sigma, fresh,
                       middle, middle)
    assert len(outside.residuals) == 60 and outside.outside.all()
    assert validation_to_dict(outside, fresh, None, cm)['outside_training_range'] == 30
    repeated = validate(cm.model, result.values, idx, result.covariance, cm.cell.sigma, fresh,
                        fresh.q.min(axis=0) - 1, fresh.q.max(axis=0) + 1, training_q=fresh.q)
    assert repeated.repeated.all()
    assert validation_to_dict(repeated, fresh, None, cm)['repeated_from_training'] == 30
    # A body rotated by 1 mrad more than calibrated is seen: rows 3σ_rot off each.
    tilted = copy.copy(fresh)
    rot = fresh.rotation.copy()
    rot[fresh.reflector == 1] = rot[fresh.reflector == 1] @ pin.exp3(np.array([1e-3, 0, 0]))
    tilted = Measurements(q=fresh.q, eta=fresh.eta, reflector=fresh.reflector, rotation=rot)
    assert not validate(cm.model, result.values, idx, result.covariance, cm.cell.sigma,
                        tilted, q.min(axis=0), q.max(axis=0)).holds


@pytest.mark.slow
def test_monte_carlo_chi2_and_tcp_covariance_agree_with_eq_19(cm):
    """Fixed robot and poses, fresh noise M times: mean χ² = dof and the scatter of the
    TCP estimates = the eq. (19) covariance, within their Monte Carlo uncertainty."""
    rng = np.random.default_rng(31)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, cm.model.params.nominal, 40, rng)
    runs = 200
    chi2, dofs, tcps, covs = [], [], [], []
    for m in range(runs):
        data = campaign(cm, p_true, q, np.random.default_rng(1000 + m))
        result = identify(cm.model, data, cm.cell.sigma, cm.q_work)
        assert result.converged
        chi2.append(result.chi2)
        dofs.append(result.dof)
        tcps.append(result.tcp[0])
        covs.append(result.tcp_covariance[0])
    dof = dofs[0]
    assert len(set(dofs)) == 1
    mean_chi2 = float(np.mean(chi2))
    se = np.sqrt(2 * dof / runs)
    scatter = np.cov(np.array(tcps).T)
    predicted = np.mean(covs, axis=0)
    ratio = np.trace(scatter) / np.trace(predicted)
    # var of a sample trace ≈ 2 tr(C²)/(M-1): its relative standard error
    rel_se = np.sqrt(2 * np.trace(predicted @ predicted) / (runs - 1)) / np.trace(predicted)
    print(f'Monte Carlo ({runs} runs, 40 poses): mean chi2 {mean_chi2:.1f} / dof {dof} '
          f'(SE {se:.1f}); TCP trace MC/eq.(19) {ratio:.3f} (SE {rel_se:.3f}); TCP std '
          f'{np.sqrt(np.trace(predicted)) * 1e6:.2f} µm predicted, '
          f'{np.sqrt(np.trace(scatter)) * 1e6:.2f} µm Monte Carlo')
    assert abs(mean_chi2 - dof) < 3 * se
    assert abs(ratio - 1) < 3 * rel_se
    # The truth's TCP is the mean of the estimates (no bias beyond 3 standard errors).
    bias = np.mean(tcps, axis=0) - cm.model.predict(p_true, cm.q_work)[0]
    assert bias @ np.linalg.solve(predicted / runs, bias) < 14.2


# ------------------------------------------------- messages, bags, command line
def _write_cell(tmp_path, doc):
    doc = copy.deepcopy(doc)
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    path = tmp_path / 'pose_cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def test_pose_stamped_round_trips_through_a_bag(tmp_path):
    rng = np.random.default_rng(5)
    joints, _ = synthesize_streams(np.zeros((2, 6)), [f'joint_{i}' for i in range(1, 7)],
                                   np.zeros((2, 3)), 'laser_tracker')
    rotations = [rotation_from_quaternion(q / np.linalg.norm(q)) for q in rng.normal(size=(3, 4))]
    poses = [PointSample(10 + i, 'laser_tracker#probe', rng.normal(size=3),
                         quaternion_from_rotation(r)) for i, r in enumerate(rotations)]
    plain = [PointSample(20, 'laser_tracker#ball', [1.0, 2.0, 3.0])]
    path = write_bag(tmp_path / 'poses.mcap', joints, poses + plain)
    _, points = read_bag(path)
    read = {p.stamp_ns: p for p in points}
    assert read[20].rotation is None and np.array_equal(read[20].xyz, [1.0, 2.0, 3.0])
    for pose in poses:
        got = read[pose.stamp_ns]
        assert got.frame_id == 'laser_tracker#probe'
        assert np.array_equal(got.xyz, pose.xyz)
        assert np.array_equal(got.orientation, pose.orientation)  # as published, exactly
        assert np.allclose(got.rotation, pose.rotation, atol=1e-15)
    # A bag without tracked poses has no pose channel (as before).
    _, points = read_bag(write_bag(tmp_path / 'plain.mcap', joints, plain))
    assert [p.rotation for p in points] == [None]


def test_a_bad_quaternion_is_rejected_when_paired_not_normalised():
    message = PoseStamped()
    message.header.frame_id = 'laser_tracker#probe'
    message.pose.orientation.w = 2.0  # not unit length
    sample = pose_sample_from_message(message)
    assert np.all(np.isnan(sample.rotation))
    names = [f'joint_{i}' for i in range(1, 7)]
    joints, _ = synthesize_streams(np.zeros((1, 6)), names, np.zeros((1, 3)), 'laser_tracker')
    bad = PointSample(joints[len(joints) // 2].stamp_ns, sample.frame_id, [1.0, 0.0, 0.0],
                      sample.orientation)
    result = pair_measurements(joints, [bad], names, 'laser_tracker', reflectors=('probe',))
    assert len(result) == 0 and result.rejections == {'invalid_orientation': 1}


def test_a_pose_for_a_reflector_without_orientation_names_the_cell_key(tmp_path, capsys):
    doc = pose_doc()
    del doc['reflectors'][0]['orientation']
    cell = _write_cell(tmp_path, doc)
    (tmp_path / 'rich').mkdir()
    rich = _write_cell(tmp_path / 'rich', pose_doc())
    bag = tmp_path / 'run.mcap'
    assert main(['simulate', '--cell', str(rich), '--n', '12', '--out', str(bag),
                 '--seed', '2']) == 0
    capsys.readouterr()
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out',
                 str(tmp_path / 'out')]) == 2
    assert 'reflectors[i].orientation' in capsys.readouterr().err


@pytest.fixture(scope='module')
def pose_bag(tmp_path_factory):
    folder = tmp_path_factory.mktemp('pose_campaign')
    cell = _write_cell(folder, pose_doc())
    bag = folder / 'run.mcap'
    assert main(['simulate', '--cell', str(cell), '--n', '40', '--out', str(bag),
                 '--seed', '7']) == 0
    return folder, cell, bag


def test_simulate_writes_pose_stamped_and_identify_recovers_the_tcp(pose_bag, capsys):
    folder, cell, bag = pose_bag
    _, points = read_bag(bag)
    assert len(points) == 40 and all(p.rotation is not None for p in points)
    assert {p.frame_id for p in points} == {'laser_tracker#probe'}
    out = folder / 'result'
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out', str(out)]) == 0
    doc = yaml.safe_load((out / 'calibration.yaml').read_text())
    truth = yaml.safe_load((folder / 'run.truth.yaml').read_text())
    assert len(doc['residuals_m']) == 80  # 40 point rows and 40 rotation rows
    error = np.array(doc['tcp'][0]['position']) - np.array(truth['tcp_true'][0])
    cov = np.array(doc['tcp'][0]['covariance'])
    d2 = float(error @ np.linalg.solve(cov, error))
    print(f'TCP error {np.linalg.norm(error) * 1e6:.2f} µm, Mahalanobis² {d2:.2f}')
    assert d2 < 14.2  # 3σ of χ²₃
    assert doc['valid']


@pytest.mark.slow
def test_validate_a_pose_calibration_on_a_new_pose_recording(pose_bag, tmp_path):
    folder, cell, bag = pose_bag
    out = folder / 'result_for_validation'
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out', str(out)]) == 0
    fresh = tmp_path / 'fresh.mcap'
    # Same cell, same true robot (seed 7 draws the same truth first), new poses: holds.
    from kpi_calib_ros.app.simulate import simulate_campaign, truth_cell_model
    from kpi_calib_ros.io.cell import load_cell
    truth = yaml.safe_load((folder / 'run.truth.yaml').read_text())['parameters']
    cm, _ = truth_cell_model(load_cell(cell))
    p_true = np.array([truth[n] for n in cm.model.params.names])
    simulate_campaign(cell, 25, fresh, seed=99, cm=cm, p_true=p_true)
    code = main(['validate', '--cell', str(cell), '--calibration',
                 str(out / 'calibration.yaml'), '--bag', str(fresh), '--out',
                 str(tmp_path / 'val')])
    report = json.loads((tmp_path / 'val' / 'validation.json').read_text())
    print(f"validation: chi2 {report['chi2']:.1f} / {report['dof']}, p {report['p_value']:.3f}")
    assert report['dof'] == 3 * 50 and code == 0 and report['holds']
    # rms over the 25 point rows in metres; the orientation residual in rad on its own:
    # E‖ω‖² = 3σ_rot² (plus the small parameter share), χ²(75)/75 within ±3·0.16.
    ratio_points = report['rms_per_reflector_m']['probe'] ** 2 / (3 * SIGMA ** 2)
    ratio_rotation = report['rotation_rms_rad']['probe'] ** 2 / (3 * SIGMA_ROTATION ** 2)
    print(f'point rms / (σ√3) squared {ratio_points:.3f}, rotation {ratio_rotation:.3f}')
    assert report['rms_m'] == report['rms_per_reflector_m']['probe']
    assert 0.5 < ratio_points < 1.6 and 0.5 < ratio_rotation < 1.6


@pytest.mark.slow
def test_model_choice_and_diagnosis_take_a_pose_campaign(pose_bag, capsys):
    """The out-of-sample prediction (model choice, diagnose) uses the rotation rows as
    information and predicts fresh poses as points: a 40-pose pose campaign of a robot
    the geometric model describes gets the geometric level, and its predicted error at
    the measured poses is the noise floor σ√3 within the scatter of a 40-pose fit."""
    folder, cell, bag = pose_bag
    out = folder / 'auto'
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out', str(out),
                 '--model', 'auto']) == 0
    doc = yaml.safe_load((out / 'calibration.yaml').read_text())
    assert doc['model']['level'] == 'geometric', doc['model']
    assert main(['diagnose', '--cell', str(cell), '--bag', str(bag), '--out',
                 str(folder / 'diag')]) == 0
    capsys.readouterr()
    report = json.loads((folder / 'diag' / 'diagnosis.json').read_text())
    like = report['out_of_sample']['like_measured']
    ratio = like['rms_m'] / (SIGMA * np.sqrt(3))
    print(f'predicted out-of-sample rms / σ√3 at the measured poses: {ratio:.3f}')
    assert like['estimable'] and 0.8 < ratio < 1.3


# ------------------------------------------------ the body's orientation identified
TURNED_RPY = [0.35, -0.3, 0.45]   # the true body, 38.8° from the identity the cell guesses


@pytest.mark.slow
def test_a_body_turned_from_the_stated_orientation_is_identified_within_3_sigma():
    """``orientation: identify``: the body's orientation in the tip frame is three
    parameters started at the identity; a body turned by 38.8° is identified within 3σ of
    the truth (of the equivalent truth, as every parameter), the plausibility gate passes;
    without rotation rows the gate says it is not identified."""
    from scipy.spatial.transform import Rotation

    from kpi_calib_ros.app.identify import calibrate_cell
    from kpi_calib_ros.core.measurement.pose import orientation_names, rotation_exp

    cm = build_cell_model(cell_from_dict(pose_doc('identify'), DEFAULT_CELL.parent))
    names = orientation_names('reflector.probe')
    idx_o = cm.model.params.indices(names)
    assert np.all(cm.model.params.nominal[idx_o] == 0)
    turned = rotation_from_rpy(TURNED_RPY)
    omega = Rotation.from_matrix(turned).as_rotvec()
    assert np.allclose(rotation_exp(omega), turned, atol=1e-12)
    assert 20 < np.degrees(np.linalg.norm(omega)) < 40
    rng = np.random.default_rng(21)
    p_true = true_parameters(cm.model.params, rng, overrides=dict(zip(names, omega)))
    p_true[idx_o] = omega
    q = random_configurations(cm.model, cm.model.params.nominal, N_POSES, rng)
    data = campaign(cm, p_true, q, np.random.default_rng(22))
    cal = calibrate_cell(cm, data, model='geometric')
    result = cal.result
    assert cal.valid and not cal.implausible, (cal.problems, cal.implausible)
    assert set(names) <= set(result.estimated)
    p_equiv, representation = equivalent_truth(cm, p_true, result, 23)
    assert representation < SIGMA / 2
    std = dict(zip(result.estimated, result.std))
    z = [(result.values[i] - p_equiv[i]) / std[n] for n, i in zip(names, idx_o)]
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(
        rotation_exp(result.values[idx_o]).T @ turned).as_rotvec()))
    print(f'body turned {np.degrees(np.linalg.norm(omega)):.1f}° from the guess: identified '
          f'to {angle * 3600:.2f}" of the truth, z {np.round(z, 2).tolist()}, std '
          f'{[f"{std[n]:.2e}" for n in names]} rad')
    assert np.all(np.abs(z) < 3)
    # Points alone cannot identify it: the gate says so.
    points = data.subset(data.reflector == 0)
    alone = calibrate_cell(cm, points, model='geometric')
    assert any('body orientation reflector.probe' in v and 'not identified' in v
               for v in alone.implausible), alone.implausible


def test_an_identified_body_orientation_is_drawn_and_judged_in_radians():
    """The three orientation parameters of ``orientation: identify`` are angles: the
    simulation draws their errors as a mounting's rotation (0.1–0.5°), never the reflector
    offset's millimetres read as milliradians, and the diagnosis's identifiability check
    judges them against ``identification.tolerances.rotation``, not the offset's metres."""
    from kpi_calib_ros.core.diagnosis.candidate_plausibility import _tolerance_of
    from kpi_calib_ros.core.estimation.plausibility import Tolerances
    from kpi_calib_ros.core.measurement.pose import orientation_names
    from kpi_calib_ros.core.simulation import ErrorMagnitudes

    cm = build_cell_model(cell_from_dict(pose_doc('identify'), DEFAULT_CELL.parent))
    names = orientation_names('reflector.probe')
    idx = cm.model.params.indices(names)
    drawn = np.array([true_parameters(cm.model.params, np.random.default_rng(seed))[idx]
                      for seed in range(50)])
    low, high = ErrorMagnitudes().base_rotation
    assert np.all(np.abs(drawn) >= low - 1e-15) and np.all(np.abs(drawn) <= high + 1e-15)
    units = dict(zip(cm.model.params.names, cm.model.params.units))
    tolerances = Tolerances(reflector_offset=0.002, rotation=0.05)
    assert [_tolerance_of(n, units[n], tolerances) for n in names] == [0.05] * 3
    offset = [n for n in cm.model.params.names
              if n.startswith('reflector.') and n not in names][0]
    assert _tolerance_of(offset, units[offset], tolerances) == 0.002


def _remounted_campaign(cm, omega, n, rng, noise=1.0, p_robot=None):
    """Set-ups a and b of the tracked probe (its orientation identified), b with the tracker
    moved and the probe remounted: its offset moved by 1 cm and its body turned by
    exp(``omega``). Returns the recordings, the joint data and the true values of b's
    placement. ``noise`` scales both noises (0: exact); ``p_robot``: the true robot
    (default: drawn)."""
    from scipy.spatial.transform import Rotation

    from kpi_calib_ros.core.measurement import recordings as rec
    from kpi_calib_ros.core.measurement.tracker import MeasurementModel
    m = cm.model
    turned = MeasurementModel(m.robot, m.geometric, m.effects, m.reflector_axis,
                              {0: m.orientations[0] @ Rotation.from_rotvec(omega).as_matrix()},
                              m.rotation_scale, m.joint_sigma, m.joint_temperatures)
    if p_robot is None:
        p_robot = true_parameters(m.params, rng)
        p_robot[m.params.indices(ORIENTATION)] = 0.0  # the stated orientation is a's
    p_b = p_robot.copy()
    p_b[:6] += np.array([-1.2, 1.5, 0.1, 0.02, -0.03, 0.6])
    offset = m.params.indices(['reflector.probe.x', 'reflector.probe.y', 'reflector.probe.z'])
    p_b[offset] += [0.004, -0.003, 0.01]
    parts = []
    for model, p in ((m, p_robot), (turned, p_b)):
        q = random_configurations(m, p, n, rng)
        ref = np.zeros(n, dtype=int)
        eta = model.predict(p, q, reflector=ref) + rng.normal(size=(n, 3)) * SIGMA * noise
        rotations = model.body_rotations(p, q, 0)
        if noise:
            rotations = noisy_rotations(rotations, SIGMA_ROTATION * noise, rng)
        parts.append(with_rotation_rows(model, Measurements(q=q, eta=eta, reflector=ref),
                                        rotations))
    recordings = [rec.Recording('a'), rec.Recording('b', True)]
    truth = {**dict(zip(ORIENTATION, [0.0] * 3)),
             **dict(zip(rec.base_names('b'), p_b[:6])),
             **dict(zip(rec.reflector_names('b', 'reflector.probe'), p_b[offset])),
             **{f'recording.b.reflector.probe.r{c}': w for c, w in zip('xyz', omega)}}
    return recordings, rec.combine(parts, recordings), truth, p_robot


ORIENTATION = ['reflector.probe.rx', 'reflector.probe.ry', 'reflector.probe.rz']


@pytest.mark.slow
def test_a_remounted_tracked_body_has_its_own_orientation_identified_within_3_sigma():
    """Two set-ups of the tracked probe whose orientation the cell identifies, the second
    with the tracker moved metres and the probe remounted, its body turned by
    (0.05, −0.03, 0.08) rad. The joint model gives the remounted body its own orientation
    (``recording.b.reflector.probe.r*``): a's and b's orientations and every placement of b
    are recovered within 3σ of the equivalent truth (the true cell in the identified
    parameters, a noise-free fit to 300 exact poses of each set-up: the tip frame's turn and
    the bodies' share a gauge), and the rotation rows fit at their noise. With the body's
    orientation shared between the set-ups, as before, b's rotation rows misfit by the turn
    (χ² rejects the fit)."""
    from kpi_calib_ros.app.measurements import with_recordings
    from kpi_calib_ros.app.placement import recordings_start
    from kpi_calib_ros.core.measurement.tracker import MeasurementModel
    from kpi_calib_ros.core.model.parameters import ParameterSet
    doc = pose_doc(orientation={'rpy': BODY_RPY, 'identify': True})
    cm = build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))
    omega = np.array([0.05, -0.03, 0.08])
    recordings, data, truth, p_robot = _remounted_campaign(cm, omega, 40,
                                                           np.random.default_rng(4))
    placed = with_recordings(cm, recordings)
    names = list(placed.model.params.names)
    assert [n for n in names if n.startswith('recording.b.reflector.probe.r')] == [
        'recording.b.reflector.probe.rx', 'recording.b.reflector.probe.ry',
        'recording.b.reflector.probe.rz']
    start, _ = recordings_start(placed, data)
    result = identify(placed.model, data, SIGMA, cm.q_work, p0=start)
    assert result.converged and result.p_value > 1e-3, result.p_value
    _, dense, _, _ = _remounted_campaign(cm, omega, 300, np.random.default_rng(5), noise=0.0,
                                         p_robot=p_robot)
    equivalent = identify(placed.model, dense, SIGMA, cm.q_work, p0=result.values,
                          free=list(result.estimated))
    assert equivalent.rms_m < 1e-9
    for name in truth:
        assert name in result.estimated, name
        error = result.value(name) - equivalent.value(name)
        assert abs(error) < 3 * result.std_of(name), (name, error / result.std_of(name))
    # the turn b's body is identified with is the remount's, to its std
    turn = [equivalent.value(f'recording.b.reflector.probe.r{c}') for c in 'xyz']
    print('b turn (equivalent truth)', turn, 'true', omega)
    # as identify publishes it: valid, the turn judged against the rotation tolerance
    # (0.05 rad, a length tolerance before), within 3σ of the equivalent truth there too
    from kpi_calib_ros.app.identify import calibrate_cell
    cal = calibrate_cell(placed, data, model='geometric')
    assert cal.valid and not cal.implausible, cal.implausible
    for c in 'xyz':
        name = f'recording.b.reflector.probe.r{c}'
        assert abs(cal.result.value(name) - equivalent.value(name)) < 3 * cal.result.std_of(name)
    # the former model: b's probe offset its own, its body's orientation the first's
    m = placed.model
    keep = [i for i, n in enumerate(names) if not n.startswith('recording.b.reflector.probe.r')]
    g = m.geometric
    n_geo = len(g.names)
    shared_geo = ParameterSet(tuple(g.names[i] for i in keep if i < n_geo),
                              g.nominal[[i for i in keep if i < n_geo]],
                              tuple(g.units[i] for i in keep if i < n_geo))
    shared = MeasurementModel(m.robot, shared_geo, m.effects, m.reflector_axis,
                              m.orientations, m.rotation_scale, m.joint_sigma,
                              m.joint_temperatures)
    assert len(shared.params) == len(names) - 3
    before = identify(shared, data, SIGMA, cm.q_work, p0=start[keep])
    assert before.p_value < 1e-6

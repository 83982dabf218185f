"""Robust identification: σ from the residuals, outliers named and excluded, robust losses,
KPI estimability, model size by cross-validation (simulated faults on the default cell)."""
from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import pytest
import scipy.stats
import yaml

from kpi_calib_ros.app.calibration_document import add_robust_sections, calibration_document
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.app.simulate import simulate_campaign
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.estimability import kpi_estimability
from kpi_calib_ros.core.estimation.robust import (
    OutlierSettings,
    loss_weights,
    outlier_threshold,
    robust_sigma,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.bag_writing import write_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.cell_settings import identification_settings
from kpi_calib_ros.io.names import CALIBRATION_FILE, DIAGNOSIS_FILE, FAILED_CALIBRATION_FILE

SIGMA = 20e-6
CELL = str(DEFAULT_CELL)
OUTLIERS = {5: 10.0, 17: 1e-3, 33: 1e-3, 48: 1e-3}  # index -> distance added, m



@pytest.fixture(scope='module')
def truth(cm):
    rng = np.random.default_rng(2024)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, cm.model.params.nominal, 60, rng)
    return p_true, q, rng


def _campaign(cm, p_true, q, seed):
    rng = np.random.default_rng(seed)
    data = simulate_measurements(cm.model, p_true, q, SIGMA, rng)
    return Measurements(q=data.q, eta=data.eta, stamps_ns=1_000_000 * (np.arange(len(q)) + 1))


def _with_outliers(data, seed):
    rng = np.random.default_rng(seed)
    eta = data.eta.copy()
    for i, size in OUTLIERS.items():
        d = rng.normal(size=3)
        eta[i] += size * d / np.linalg.norm(d)
    return dataclasses.replace(data, eta=eta)


def test_robust_sigma_estimates_sigma_and_ignores_wild_points():
    rng = np.random.default_rng(1)
    r = rng.normal(scale=SIGMA, size=(2000, 3))
    assert robust_sigma(r, r.size) == pytest.approx(SIGMA, rel=0.05)
    r[:20] += 0.01  # 1 % wild points move it by a few per cent, the plain std by 100×
    assert robust_sigma(r, r.size) == pytest.approx(SIGMA, rel=0.08)
    assert np.std(r) > 20 * SIGMA


def test_loss_weights_are_one_inside_and_fall_outside():
    d = np.array([0.0, 1.0, 100.0]) * SIGMA
    for loss in ('huber', 'soft_l1'):
        w = loss_weights(loss, d, SIGMA)
        assert w[0] == 1.0 and w[1] > 0.9 and w[2] < 0.05
    assert np.all(loss_weights('linear', d, SIGMA) == 1.0)


@pytest.mark.parametrize('seed', [3, 4])
def test_outliers_of_10_m_and_1_mm_are_excluded_and_named(cm, truth, seed):
    p_true, q, _ = truth
    data = _with_outliers(_campaign(cm, p_true, q, seed), seed)
    cal = calibrate_cell(cm, data)
    assert cal.valid
    excluded = {e.index: e for e in cal.robust.excluded}
    assert set(excluded) == set(OUTLIERS)
    for i, size in OUTLIERS.items():
        assert excluded[i].stamp_ns == data.stamps_ns[i]
        assert excluded[i].distance_m == pytest.approx(size, rel=0.05)
    error = cal.result.tcp[0] - cm.model.predict(p_true, cm.q_work)[0]
    std = np.sqrt(np.diag(cal.result.tcp_covariance[0]))
    assert np.all(np.abs(error) < 3 * std), (error, std)
    assert 0.5 < cal.robust.sigma_ratio < 2 and not cal.robust.warnings
    doc = add_robust_sections(calibration_document(cm, cal.result), cal)
    listed = {e['index']: e for e in doc['robust']['excluded']}
    assert set(listed) == set(OUTLIERS) and listed[17]['stamp_ns'] == int(data.stamps_ns[17])
    assert len(doc['residuals_m']) == len(data) - len(OUTLIERS)


def test_outliers_only_reported_when_exclusion_is_off(cm, truth):
    p_true, q, _ = truth
    data = _with_outliers(_campaign(cm, p_true, q, 3), 3)
    data = dataclasses.replace(data, eta=np.delete(data.eta, 5, 0), q=np.delete(data.q, 5, 0),
                               stamps_ns=np.delete(data.stamps_ns, 5))  # 1 mm ones only
    off = dataclasses.replace(cm.cell.identification, outliers=OutlierSettings(exclude=False))
    for loss in ('linear', 'huber', 'soft_l1'):
        settings = dataclasses.replace(off, loss=loss)
        cell = dataclasses.replace(cm.cell, identification=settings)
        cal = calibrate_cell(dataclasses.replace(cm, cell=cell), data)
        assert not cal.robust.excluded and cal.robust.kept.all()
        assert set(cal.robust.outliers) == {16, 32, 47}  # indices after the deletion
        assert any('kept in the fit' in w for w in cal.robust.warnings)
        if loss != 'linear':  # the robust losses give the 1 mm points almost no weight
            assert np.all(cal.robust.point_weights[[16, 32, 47]] < 0.1)
            # Good points: Huber leaves them in its quadratic zone, soft-L1 trims a little.
            floor = 0.99 if loss == 'huber' else 0.8
            assert np.median(cal.robust.point_weights) > floor


def test_sigma_stated_250_times_too_large_is_warned(cm, truth):
    p_true, q, _ = truth
    data = _campaign(cm, p_true, q, 5)
    cell = dataclasses.replace(cm.cell, sigma=np.full(3, 250 * SIGMA))
    cal = calibrate_cell(dataclasses.replace(cm, cell=cell), data)
    assert cal.robust.sigma_ratio == pytest.approx(1 / 250, rel=0.3)
    assert len(cal.robust.warnings) == 1 and 'stated noise.sigma' in cal.robust.warnings[0]


def test_kpi_in_row_space_is_estimable_and_outside_is_not():
    rng = np.random.default_rng(0)
    data = rng.normal(size=(30, 4)) @ np.diag([1.0, 1e-3, 1e3, 1.0]) @ np.array(
        [[1, 0, 0, 0, 0], [0, 1, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, 0, 1, 1.0]])
    names = ['a', 'b', 'c', 'd', 'e']
    inside = rng.normal(size=(3, 4)) @ np.array(
        [[1, 0, 0, 0, 0], [0, 1, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, 0, 1, 1.0]])
    outside = inside.copy()
    outside[:, 3] += 0.5  # d − e is not measured
    est = kpi_estimability(data, np.vstack([inside, outside]), names, ['in', 'out'])
    assert est.estimable.tolist() == [True, False]
    assert est.relative_residual[0] < 1e-12 and est.relative_residual[1] > 100 * est.tolerance
    assert set(est.missing[1]) == {'d', 'e'}


def test_one_pose_campaign_reports_the_kpi_not_estimable(cm, truth):
    p_true, q, _ = truth
    data = _campaign(cm, p_true, np.repeat(q[:1], 60, axis=0), 6)
    cal = calibrate_cell(cm, data)
    assert not cal.valid and not cal.estimability.all_estimable
    true_error = np.linalg.norm(cal.result.tcp[0] - cm.model.predict(p_true, cm.q_work)[0])
    assert true_error > 1e-3  # the number it would have reported as "µm" is millimetres off
    doc = add_robust_sections(calibration_document(cm, cal.result), cal)
    assert doc['tcp_estimable'] is False and doc['tcp'][0]['std'] is None
    assert doc['tcp_estimability']['poses'][0]['not_determined']


def test_auto_picks_geometric_for_60_poses_and_smaller_for_8(cm, truth):
    p_true, q, _ = truth
    big = calibrate_cell(cm, _campaign(cm, p_true, q, 7), model='auto')
    assert big.choice.level == 'geometric'
    assert set(big.choice.cv_rms_m) == {'registration', 'joint_offsets', 'geometric'}
    assert big.choice.cv_rms_m['geometric'] < 3 * SIGMA * np.sqrt(3)
    small = calibrate_cell(cm, _campaign(cm, p_true, q[:8], 8), model='auto')
    for n, cal in ((60, big), (8, small)):   # the README quotes these figures
        print(f'{n} poses -> {cal.choice.level}; predicted rms (µm):',
              {k: None if v is None else round(v * 1e6, 1)
               for k, v in cal.choice.predicted_rms_m.items()})
    assert big.choice.predicted_rms_m['geometric'] < 3 * SIGMA * np.sqrt(3)
    assert small.choice.predicted_rms_m['geometric'] is None
    assert small.choice.level in ('registration', 'joint_offsets')
    assert 'geometric' in small.choice.reason and small.valid
    assert len(small.free) < len(big.free)


def test_fixed_level_frees_only_its_parameters(cm, truth):
    p_true, q, _ = truth
    cal = calibrate_cell(cm, _campaign(cm, p_true, q, 9), model='registration')
    assert set(cal.free) == {f'base.{c}' for c in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')} | \
        {'reflector.x', 'reflector.y', 'reflector.z'}
    assert set(cal.result.estimated) <= set(cal.free)


def test_identification_keys_are_validated():
    assert identification_settings({'model': 'auto', 'loss': 'huber'}).loss == 'huber'
    for raw, key in [({'model': 'big'}, 'identification.model'),
                     ({'loss': 'l2'}, 'identification.loss'),
                     ({'outliers': {'threshold': 0.5}}, 'identification.outliers.threshold'),
                     ({'outliers': {'exclude': 'yes'}}, 'identification.outliers.exclude'),
                     ({'cv_folds': 1}, 'identification.cv_folds'),
                     ({'modle': 'auto'}, 'identification.modle')]:
        with pytest.raises(ConfigError, match=key.replace('.', r'\.')):
            identification_settings(raw)
    assert outlier_threshold(60) == pytest.approx(np.sqrt(scipy.stats.chi2.isf(0.01 / 60, 3)))


@pytest.mark.slow
def test_cli_one_pose_campaign_exits_nonzero_and_keeps_the_good_calibration(cm, tmp_path,
                                                                           capsys):
    good = tmp_path / 'good.mcap'
    assert main(['simulate', '--cell', CELL, '--n', '40', '--out', str(good), '--seed', '2']) == 0
    out = tmp_path / 'out'
    assert main(['identify', '--cell', CELL, '--bag', str(good), '--out', str(out),
                 '--model', 'auto']) == 0
    text = capsys.readouterr().out
    assert 'cross-validated rms per level' in text and 'TCP estimable' in text
    assert 'predicted out-of-sample rms per level' in text
    before = (out / CALIBRATION_FILE).read_text()
    assert yaml.safe_load(before)['valid'] is True
    one = tmp_path / 'one.mcap'
    q = random_configurations(cm.model, cm.model.params.nominal, 1, np.random.default_rng(3))
    simulate_campaign(CELL, 60, one, 3, poses=(cm.joint_names, np.repeat(q, 60, axis=0)))
    assert main(['identify', '--cell', CELL, '--bag', str(one), '--out', str(out)]) == 1
    text = capsys.readouterr().out
    assert 'NOT DETERMINED' in text and 'CALIBRATION NOT VALID' in text
    assert (out / CALIBRATION_FILE).read_text() == before
    failed = yaml.safe_load((out / FAILED_CALIBRATION_FILE).read_text())
    assert failed['valid'] is False and failed['tcp_estimable'] is False


def test_design_estimability_says_when_the_kpi_is_not_determined(cm, truth):
    from kpi_calib_ros.app.design import design_estimability
    _, q, _ = truth
    assert design_estimability(cm, q).all_estimable
    one = design_estimability(cm, np.repeat(q[:1], 30, axis=0))
    assert not one.all_estimable and 'NOT estimable' in one.summary()


def test_node_job_never_writes_an_invalid_calibration_over_the_last_good_one(cm, truth,
                                                                             tmp_path):
    from kpi_calib_ros.ros.job_work import identify_work
    p_true, q, _ = truth
    good = _campaign(cm, p_true, q, 10)
    out = identify_work(cm, good, None, tmp_path)
    assert out.calibration.valid and out.urdf and len(out.tcp) == 1
    before = (tmp_path / CALIBRATION_FILE).read_text()
    assert out.text == before
    bad = _campaign(cm, p_true, np.repeat(q[:1], 60, axis=0), 11)
    out = identify_work(cm, bad, None, tmp_path)
    assert not out.calibration.valid and out.urdf == '' and out.tcp == ()
    assert (tmp_path / CALIBRATION_FILE).read_text() == before
    assert yaml.safe_load((tmp_path / FAILED_CALIBRATION_FILE).read_text())['valid'] is False


def test_diagnosis_outliers_against_the_robust_scale_when_sigma_is_understated(cm, truth):
    from kpi_calib_ros.core.estimation.least_squares import identify
    from kpi_calib_ros.core.estimation.residuals import residual_report
    p_true, q, _ = truth
    data = _campaign(cm, p_true, q, 12)
    small = SIGMA / 10  # stated σ 10× too small: against it nearly every point is "outlier"
    result = identify(cm.model, data, small, cm.q_work)
    report = residual_report(cm.model, data, result)
    assert not report.adequate
    assert report.sigma_robust_m == pytest.approx(SIGMA, rel=0.3)
    assert 'stated noise.sigma' in report.sigma_warning
    assert report.outlier.sum() <= 1


def test_diagnose_screens_against_the_chosen_model_level(cm, truth):
    from kpi_calib_ros.app.diagnose import diagnose_cell
    from kpi_calib_ros.core.diagnosis.model_selection import level_free
    p_true, q, _ = truth
    cd = diagnose_cell(cm, _campaign(cm, p_true, q, 13), add_best=False, model='joint_offsets')
    free = set(level_free(cm.model.params, 'joint_offsets', len(cm.geometric)))
    assert set(cd.result.estimated) <= free
    # The placements this level leaves out are missed: the verdict says inadequate.
    assert not cd.diagnosis.model_adequate


def test_too_few_after_exclusion_names_the_excluded_measurements(cm, truth):
    """10 accepted points, one 10 m off: the 9 left are too few for 27 parameters; the
    error says 9 of the 10 were used and why the tenth was left out."""
    from kpi_calib_ros.core.errors import DataError
    p_true, q, _ = truth
    data = _campaign(cm, p_true, q[:10], 5)
    eta = data.eta.copy()
    eta[2] += [10.0, 0.0, 0.0]
    with pytest.raises(DataError, match=r'too few measurements: 9 points') as info:
        calibrate_cell(cm, dataclasses.replace(data, eta=eta))
    assert 'after excluding 1 of the 10 measurements: 2: gross' in str(info.value)


def _joint_1_only(cm, n):
    """Poses that turn joint_1 alone, every other joint at a random pose's value."""
    q = np.repeat(random_configurations(cm.model, cm.model.params.nominal, 1,
                                        np.random.default_rng(5)), n, axis=0)
    q[:, 0] = np.linspace(-1.5, 1.5, n)
    return q


@pytest.mark.slow
@pytest.mark.parametrize('design', ['one pose ten times', 'joint_1 only'])
def test_diagnose_says_the_tcp_is_not_estimable_where_identify_does(cm, tmp_path, capsys,
                                                                     design):
    if design == 'joint_1 only':
        q = _joint_1_only(cm, 12)
    else:
        q = np.repeat(random_configurations(cm.model, cm.model.params.nominal, 1,
                                            np.random.default_rng(3)), 10, axis=0)
    bag = tmp_path / 'design.mcap'
    simulate_campaign(CELL, len(q), bag, 3, poses=(cm.joint_names, q))
    assert main(['identify', '--cell', CELL, '--bag', str(bag), '--out',
                 str(tmp_path / 'identify')]) == 1
    assert 'TCP NOT estimable' in capsys.readouterr().out
    assert main(['diagnose', '--cell', CELL, '--bag', str(bag), '--out',
                 str(tmp_path / 'diagnose')]) == 1
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith('TCP NOT estimable')
    assert 'expected error' not in out and 'model adequate' not in out
    assert 'what is missing: poses that determine the TCP' in out
    doc = json.loads((tmp_path / 'diagnose' / DIAGNOSIS_FILE).read_text())
    assert doc['tcp_estimability']['tcp_estimable'] is False
    assert doc['model_adequate'] is False and 'expected_tcp_error' not in doc


@pytest.mark.slow
def test_diagnose_prints_its_verdict_before_the_outlier_rounds(cm, truth, tmp_path, capsys,
                                                              monkeypatch):
    # One terminal: stderr's progress lines and stdout's summary in the order written.
    monkeypatch.setattr(sys, 'stderr', sys.stdout)
    p_true, q, _ = truth
    data = _campaign(cm, p_true, q, 11)
    eta = data.eta.copy()
    eta[7] += [5e-3, 0.0, 0.0]  # a 5 mm fault identify excludes
    joints, points = synthesize_streams(data.q, cm.joint_names, eta, cm.cell.tracker_frame)
    bag = tmp_path / 'fault.mcap'
    write_bag(bag, joints, points)
    assert main(['diagnose', '--cell', CELL, '--bag', str(bag), '--out',
                 str(tmp_path / 'out')]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith('model ')
    assert 'excluded as outliers: [7]' in '\n'.join(lines)
    assert any(line.startswith('outliers: round 1') for line in lines[1:])

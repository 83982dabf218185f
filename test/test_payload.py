"""Payloads per row: the gravity torques of each row with its own load (``payload.mass``,
``payload.com.*``), validated; joint compliance identified from two loads within 3σ, a third
load predicted at the noise floor, and the TCP of a working pose with the payload the cell
states for it."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell, with_effects
from kpi_calib_ros.app.measurements import check_payload_limit
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.effects.registry import parse_effect_spec
from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.payload import row_payloads
from kpi_calib_ros.core.measurement.recordings import stated_conditions
from kpi_calib_ros.core.measurement.weighting import row_torques
from kpi_calib_ros.core.model.robot import Payload, RobotModel
from kpi_calib_ros.core.simulation import (
    held_deflection,
    random_configurations,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document
from kpi_calib_ros.io.cell_inputs import check_covariate_name

SIGMA = 20e-6
COMPLIANCE = {'joint_2': -2e-6, 'joint_3': -3e-6}


def test_each_row_carries_its_own_payload(cm):
    rng = np.random.default_rng(0)
    q = random_configurations(cm.model, cm.model.params.nominal, 6, rng)
    robot = cm.robot
    assert robot.payload.mass == 5.0  # the default cell's
    bare = RobotModel(cm.cell.urdf_xml, cm.cell.base_frame, cm.cell.tip_frame)
    com = robot.payload.com
    loads = [Payload(0.0, com), Payload(5.0, com), Payload(2.5, com)] * 2
    tau = robot.gravity_torques(q, loads)
    np.testing.assert_allclose(tau[[0, 3]], bare.gravity_torques(q[[0, 3]]), atol=1e-9)
    np.testing.assert_allclose(tau[[1, 4]], robot.gravity_torques(q[[1, 4]]), atol=1e-9)
    # linear in the mass: 2.5 kg is half-way between 0 and 5 kg
    half = 0.5 * (bare.gravity_torques(q[[2, 5]]) + robot.gravity_torques(q[[2, 5]]))
    np.testing.assert_allclose(tau[[2, 5]], half, atol=1e-9)
    # the rows' torques follow their covariates; without, the cell's payload
    data = Measurements(q=q, eta=np.zeros((6, 3)),
                        covariates={'payload.mass': np.array([0.0, 5.0, 2.5] * 2)})
    model = augmented_model(cm.model, (parse_effect_spec('joint_compliance:joint_2', robot),))
    # each row's torques, then their gradient ∂τ/∂q (the torque at the deflected configuration)
    held = row_torques(model, data)
    assert held.shape == (6, 6 + 36)
    np.testing.assert_allclose(held[:, :6], tau, atol=1e-12)
    step = np.zeros(6)
    step[1] = 1e-4
    slope = (robot.gravity_torques(q + step, loads) - robot.gravity_torques(q - step, loads)) / 2e-4
    np.testing.assert_allclose(held[:, 6:].reshape(6, 6, 6)[:, :, 1], slope,
                               atol=1e-6 * np.abs(slope).max())
    np.testing.assert_allclose(row_torques(model, dataclasses.replace(data, covariates=None))
                               [:, :6], robot.gravity_torques(q), atol=1e-12)
    assert row_torques(cm.model, data) is None  # no effect reads a torque


def test_a_payload_that_is_none_is_refused():
    default = Payload(5.0, (0.0, 0.0, 0.05))
    with pytest.raises(ValueError, match='row 1: payload -1.0 kg'):
        row_payloads({'payload.mass': np.array([0.0, -1.0])}, 2, default)
    with pytest.raises(ValueError, match='row 0: payload nan kg'):
        row_payloads({'payload.mass': np.array([np.nan, 1.0])}, 2, default)
    with pytest.raises(ValueError, match=r"needs all of \['payload.com.x'"):
        row_payloads({'payload.mass': np.ones(2), 'payload.com.z': np.ones(2)}, 2, default)
    got = row_payloads({'payload.mass': np.array([1.0, 2.0])}, 2, default)
    assert got == [Payload(1.0, (0.0, 0.0, 0.05)), Payload(2.0, (0.0, 0.0, 0.05))]


def test_a_payload_centre_in_millimetres_or_a_misspelled_payload_input_is_refused():
    """Before, a centre of 80 (mm written as m) gave torques of an 80 m lever, a centre
    without a mass and ``payload.mas`` were ignored: the rows were fitted with the cell's
    payload."""
    default = Payload(5.0, (0.0, 0.0, 0.05))
    com = {f'payload.com.{a}': np.array([0.0, 80.0 if a == 'z' else 0.0]) for a in 'xyz'}
    with pytest.raises(ValueError, match='row 1: .*within 2 m of the tip frame'):
        row_payloads({'payload.mass': np.ones(2), **com}, 2, default)
    with pytest.raises(ValueError, match='a payload centre without a mass'):
        row_payloads({**com}, 2, default)
    with pytest.raises(ValueError, match="'payload.mas' is no payload input"):
        row_payloads({'payload.mas': np.ones(2)}, 2, default)
    for key, value, named in (('payload.mas', 5.0, 'covariates.payload.mas'),
                              ('payload.com.z', 80.0, 'covariates.payload.com.z')):
        with pytest.raises(ConfigError) as info:
            stated_conditions({key: value}, 'covariates')
        assert info.value.key == named
    assert stated_conditions({'payload.com.z': 0.08, 'payload.mass': 5}, 'c') == \
        {'payload.com.z': 0.08, 'payload.mass': 5.0}
    with pytest.raises(ConfigError, match="'payload.mas' is no payload input"):
        check_covariate_name('payload.mas', 'mapping.covariates')


def _cell_with_working_payload(payload):
    doc = read_cell_document(DEFAULT_CELL)
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['working_poses'] = [{'name': 'half_load', 'payload': payload,
                             'joints': {'joint_1': 0.0, 'joint_2': 0.45, 'joint_3': -0.35,
                                        'joint_4': 0.0, 'joint_5': 0.9, 'joint_6': 0.0}}]
    return cell_from_dict(doc, DEFAULT_CELL.parent)


def test_a_working_pose_states_its_payload():
    cell = _cell_with_working_payload({'mass': 2.5})
    assert cell.working_poses[0].payload == (2.5, None)
    for bad, key in (({'mass': -1}, 'working_poses[0].payload.mass'),
                     ({'mass': 2.0, 'colour': 1}, 'working_poses[0].payload'),
                     ({'mass': 2.0, 'com': [0, 0]}, 'working_poses[0].payload.com')):
        with pytest.raises(ConfigError, match=key.replace('[', r'\[').replace(']', r'\]')):
            _cell_with_working_payload(bad)


def _two_loads(cm, seed):
    """The same 40 poses measured without and with 5 kg, 40 fresh poses with 2.5 kg."""
    rng = np.random.default_rng(seed)
    effects = tuple(parse_effect_spec(f'joint_compliance:{j}', cm.robot) for j in COMPLIANCE)
    truth = augmented_model(cm.model, effects)
    p_true = np.concatenate([true_parameters(cm.model.params, rng), list(COMPLIANCE.values())])

    def measure(q, mass):
        cov = {'payload.mass': np.full(len(q), mass)}
        clean = truth.predict(p_true, q, covariates=cov)
        return Measurements(q=q, eta=clean + rng.normal(0.0, SIGMA, clean.shape),
                            covariates=cov)
    q = random_configurations(cm.model, cm.model.params.nominal, 40, rng)
    both = [measure(q, 0.0), measure(q, 5.0)]
    data = Measurements(q=np.vstack([d.q for d in both]), eta=np.vstack([d.eta for d in both]),
                        covariates={'payload.mass': np.concatenate(
                            [d.covariates['payload.mass'] for d in both])})
    fresh = measure(random_configurations(cm.model, cm.model.params.nominal, 40, rng), 2.5)
    return data, fresh, effects, truth, p_true


@pytest.mark.slow
def test_compliance_is_identified_from_two_loads_and_predicts_a_third(cm):
    data, fresh, effects, truth, p_true = _two_loads(cm, 4)
    cell = _cell_with_working_payload({'mass': 2.5})
    loaded = with_effects(build_cell_model(cell), effects)
    cal = calibrate_cell(loaded, data, model='geometric')
    for joint, c in COMPLIANCE.items():
        name = f'joint_compliance.{joint}.c'
        assert abs(cal.result.value(name) - c) < 3 * cal.result.std_of(name), name
    miss = fresh.eta - loaded.model.predict(cal.result.values, fresh.q,
                                            covariates=fresh.covariates)
    assert np.sqrt(np.mean(np.sum(miss ** 2, axis=1))) <= 1.2 * np.sqrt(3) * SIGMA
    # the working pose's TCP is the one with its 2.5 kg, within its stated covariance
    tcp_true = truth.predict(p_true, loaded.q_work, covariates={'payload.mass': np.array([2.5])})
    error = cal.result.tcp[0] - tcp_true[0]
    assert error @ np.linalg.solve(cal.result.tcp_covariance[0], error) < 16.27  # χ²₃ 99.9 %


def test_the_design_and_the_campaign_take_the_working_pose_payload():
    """The KPI rows of the design (and of a sequential campaign) are those of the working
    pose with the payload the cell states for it."""
    cell = _cell_with_working_payload({'mass': 2.5, 'com': [0.0, 0.0, 0.1]})
    cm = build_cell_model(cell, effects=('joint_compliance:joint_2',))
    expected = cm.robot.gravity_torques(cm.q_work, [Payload(2.5, (0.0, 0.0, 0.1))])
    np.testing.assert_allclose(cm.tau_work[:, :6], expected, atol=1e-12)
    np.testing.assert_allclose(cm.design_cell().tau_work[:, :6], expected, atol=1e-12)
    assert not np.allclose(expected, cm.robot.gravity_torques(cm.q_work))  # not the 5 kg
    assert build_cell_model(cell).tau_work is None  # no effect reads a torque


def _finite_differences(model, p, q, names, **kw):
    """(3N, k) Jacobian of model.predict in the parameters ``names``, central differences."""
    cols = []
    for i in model.params.indices(list(names)):
        step = np.zeros_like(p)
        step[i] = 1e-7
        cols.append(((model.predict(p + step, q, **kw) - model.predict(p - step, q, **kw))
                     / 2e-7).reshape(-1))
    return np.array(cols).T


def test_the_estimability_verdict_is_that_of_each_rows_torques_and_the_working_payload(
        cm, monkeypatch):
    """identify's TCP estimability projects the working pose's TCP gradient WITH ITS OWN
    payload (2.5 kg, not the cell's 5 kg) on the information of the rows as measured (each
    with its payload, or the joint torques they recorded): both Jacobians it is given equal
    central differences of the model's predictions."""
    import kpi_calib_ros.core.estimation.estimability as estimability
    seen = []
    original = estimability.kpi_estimability

    def spy(data_jac, kpi_jac, names, *args, **kw):
        seen.append((np.array(data_jac), np.array(kpi_jac), list(names)))
        return original(data_jac, kpi_jac, names, *args, **kw)
    monkeypatch.setattr(estimability, 'kpi_estimability', spy)
    data, _, effects, _, _ = _two_loads(cm, 5)
    loaded = with_effects(build_cell_model(_cell_with_working_payload({'mass': 2.5})), effects)
    rng = np.random.default_rng(1)
    measured_tau = row_torques(loaded.model, data)[:, :6] + rng.normal(0.0, 2.0, (len(data), 6))
    for rows, kw in ((data, {'covariates': data.covariates}),
                     (dataclasses.replace(data, tau=measured_tau), {'tau': measured_tau})):
        seen.clear()
        cal = calibrate_cell(loaded, rows, model='geometric')
        data_jac, kpi_jac, names = seen[-1]
        p = cal.result.values
        work = _finite_differences(loaded.model, p, loaded.q_work, names,
                                   covariates={'payload.mass': np.array([2.5])})
        np.testing.assert_allclose(kpi_jac, work, atol=1e-6 * np.abs(work).max())
        cell_payload = _finite_differences(loaded.model, p, loaded.q_work, names)
        assert np.abs(cell_payload - work).max() > 1e-3 * np.abs(work).max()
        kept = rows.subset(cal.robust.kept)
        kept_kw = {k: (v[cal.robust.kept] if k == 'tau' else
                       {c: x[cal.robust.kept] for c, x in v.items()}) for k, v in kw.items()}
        rows_jac = _finite_differences(loaded.model, p, kept.q, names, **kept_kw) / SIGMA
        np.testing.assert_allclose(data_jac, rows_jac, atol=1e-6 * np.abs(rows_jac).max())


def test_a_row_payload_beyond_what_the_robot_carries_is_refused(cm, tmp_path, capsys):
    """Payloads in grams written as kg (0 and 5000) passed the 5000 kg any arm may lift, and
    a fit published compliances 400-800 times too small as valid. A row's payload is now
    bounded by the robot's moving links' mass in the URDF (the KR15-class arm: 186 kg), or
    by the cell's payload.limit; beyond it the rows are refused naming the field and fix."""
    assert cm.robot.moving_mass_kg == pytest.approx(186.0)
    grams = {'payload.mass': np.array([0.0, 5000.0, 0.0, 5000.0])}
    with pytest.raises(DataError, match=r'payload.mass of 2 of 4 rows beyond what the robot '
                                        r'carries, 186 kg .*largest 5000 kg at row 1.*'
                                        r'grams\? divide by 1000.*payload.limit'):
        check_payload_limit(cm, grams, 'bag')
    check_payload_limit(cm, {'payload.mass': np.array([0.0, 5.0])}, 'bag')  # kilograms pass
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['payload'] = dict(doc.get('payload') or {}, limit=5000.0)
    rated = build_cell_model(cell_from_dict(doc, tmp_path))
    check_payload_limit(rated, grams, 'bag')  # a heavy-duty rating stated: accepted
    doc['payload']['limit'] = 1.0  # below the cell's own payload (5 kg)
    with pytest.raises(ConfigError, match='payload.limit'):
        cell_from_dict(doc, tmp_path)


def test_a_working_pose_loaded_beyond_the_measured_payloads_is_warned_of(cm, tmp_path):
    """A 7-DoF arm calibrated at 0 kg stated 1.6 mm of expected error at a 2.5 kg working
    pose it missed by 7.8 mm, without a word about the load. The payloads measured are now
    stored (``training_payload_kg``) and a working pose loaded beyond them is warned of;
    calibrated from 0 and 5 kg, the 2.5 kg pose lies within and nothing is said."""
    from kpi_calib_ros.app.calibration_document import (
        add_robust_sections,
        calibration_document,
        robust_summary,
    )
    from kpi_calib_ros.io.calibration_file import read_calibration_document
    from kpi_calib_ros.io.results import write_calibration
    data, _, effects, _, _ = _two_loads(cm, 5)
    loaded = with_effects(build_cell_model(_cell_with_working_payload({'mass': 2.5})), effects)
    unloaded = data.subset(data.covariates['payload.mass'] == 0.0)
    for rows, warned in ((unloaded, True), (data, False)):
        cal = calibrate_cell(loaded, rows, model='geometric')
        doc = add_robust_sections(calibration_document(loaded, cal.result), cal)
        heaviest = float(rows.covariates['payload.mass'].max())
        assert doc['training_payload_kg'] == [0.0, heaviest]
        outside = doc['precision'].get('working_payloads_outside_training', {})
        assert outside == ({'half_load': 2.5} if warned else {})
        text = robust_summary(doc)
        assert ('WARNING: working pose half_load carries 2.5 kg, outside the payloads measured '
                '(0 to 0 kg' in text) is warned
        assert read_calibration_document(write_calibration(tmp_path, doc))[
            'training_payload_kg'] == [0.0, heaviest]
    doc['training_payload_kg'] = [5.0, 0.0]
    with pytest.raises(ConfigError, match='training_payload_kg'):
        read_calibration_document(write_calibration(tmp_path, doc))


def _held_deflection(cm, c, q, payloads):
    """δ = c τ(q + δ) solved by fixed point on Pinocchio's gravity torques (to 1e-14 rad),
    and the torques there: how a joint that bends under its load is held."""
    return held_deflection(cm.robot, c, q, payloads)


STIFF = {'joint_2': -3e-5, 'joint_3': -4e-5}  # 19 mrad of sag at joint 2 under 10 kg


def _compliant_cell():
    cm0 = build_cell_model(cell_from_dict(read_cell_document(DEFAULT_CELL), DEFAULT_CELL.parent))
    effects = tuple(parse_effect_spec(f'joint_compliance:{j}', cm0.robot) for j in STIFF)
    cm = with_effects(cm0, effects)
    c = np.zeros(cm.robot.n_joints)
    c[[cm.robot.joint_names.index(j) for j in STIFF]] = list(STIFF.values())
    return cm0, cm, c


def test_a_joint_is_held_by_the_torque_of_where_it_bent_to():
    """The model's compliance takes the gravity torque at the deflected configuration: its
    prediction is within 14 µm (4 µm rms) of the exact fixed point δ = c τ(q + δ) (the
    torques there given as measured ones) for 24 mrad of sag, the curvature of τ over δ,
    where the torque at the encoder's reading misses by 459 µm (191 µm rms)."""
    cm0, cm, c = _compliant_cell()
    rng = np.random.default_rng(2)
    p = np.concatenate([true_parameters(cm0.model.params, rng), list(STIFF.values())])
    q = random_configurations(cm.model, cm.model.params.nominal, 50, rng)
    cov = {'payload.mass': np.full(len(q), 10.0)}
    d, held = _held_deflection(cm, c, q, row_payloads(cov, len(q), cm.robot.payload))
    exact = cm.model.predict(p, q, tau=held, covariates=cov)
    model = cm.model.predict(p, q, covariates=cov)
    at_reading = cm.model.predict(p, q, tau=cm.robot.gravity_torques(
        q, row_payloads(cov, len(q), cm.robot.payload)), covariates=cov)
    assert np.max(np.abs(d)) > 0.02
    held_miss = np.linalg.norm(model - exact, axis=1)
    reading_miss = np.linalg.norm(at_reading - exact, axis=1)
    assert np.max(held_miss) < 20e-6 and np.sqrt(np.mean(held_miss ** 2)) < 5e-6
    assert np.max(reading_miss) > 300e-6 and np.sqrt(np.mean(reading_miss ** 2)) > 150e-6


def test_a_servo_soft_compliance_is_identified_at_the_deflected_configuration():
    """A KR15-class arm 20× softer than its gearboxes (19 mrad of sag under 10 kg), the truth
    solved by fixed point on Pinocchio's torques: measured at 0 and 10 kg, both compliances
    within 3σ and a 5 kg load predicted at ≤ 1.2× the noise floor. With the torque at the
    encoder's reading, joint 2's compliance came out 6.9σ off, the fit at 124 µm rms (floor
    34.6 µm) and the 5 kg load at 3.5× the floor."""
    cm0, cm, c = _compliant_cell()
    rng = np.random.default_rng(3)
    p_true = np.concatenate([true_parameters(cm0.model.params, rng), list(STIFF.values())])

    def measure(q, mass):
        cov = {'payload.mass': np.full(len(q), mass)}
        _, held = _held_deflection(cm, c, q, row_payloads(cov, len(q), cm.robot.payload))
        eta = cm.model.predict(p_true, q, tau=held, covariates=cov)
        return Measurements(q=q, eta=eta + rng.normal(0, SIGMA, eta.shape), covariates=cov)
    q = random_configurations(cm.model, cm.model.params.nominal, 60, rng)
    a, b = measure(q, 0.0), measure(q, 10.0)
    data = Measurements(q=np.vstack([a.q, b.q]), eta=np.vstack([a.eta, b.eta]),
                        covariates={'payload.mass': np.concatenate(
                            [a.covariates['payload.mass'], b.covariates['payload.mass']])})
    fresh = measure(random_configurations(cm.model, cm.model.params.nominal, 60, rng), 5.0)
    cal = calibrate_cell(cm, data, model='geometric')
    for joint, value in STIFF.items():
        name = f'joint_compliance.{joint}.c'
        assert abs(cal.result.value(name) - value) < 3 * cal.result.std_of(name), name
    miss = fresh.eta - cm.model.predict(cal.result.values, fresh.q, covariates=fresh.covariates)
    assert np.sqrt(np.mean(np.sum(miss ** 2, axis=1))) <= 1.2 * np.sqrt(3) * SIGMA


def test_validate_says_when_new_points_carry_a_payload_the_calibration_never_measured(cm):
    """validate reads training_payload_kg: new rows loaded beyond the calibration's payloads
    are counted and named (a miss there is the load's deflection before the calibration's);
    rows within them, or a calibration that stored none, say nothing."""
    from kpi_calib_ros.app.validate import payloads_outside
    from kpi_calib_ros.app.validation_text import validation_text
    q = random_configurations(cm.model, cm.model.params.nominal, 4, np.random.default_rng(0))
    rows = Measurements(q=q, eta=np.zeros((4, 3)),
                        covariates={'payload.mass': np.array([0.0, 2.5, 5.0, 0.2])})
    said = payloads_outside(cm, {'training_payload_kg': [0.0, 0.0]}, rows)
    assert said == {'points': 3, 'new_kg': [0.0, 5.0], 'training_kg': [0.0, 0.0],
                    'reads_load': False}
    assert payloads_outside(cm, {'training_payload_kg': [0.0, 5.0]}, rows) is None
    assert payloads_outside(cm, {}, rows) is None
    # no payload per row: the cell's, 5 kg
    assert payloads_outside(cm, {'training_payload_kg': [0.0, 0.0]},
                            dataclasses.replace(rows, covariates=None))['points'] == 4
    text = validation_text({'verdict': 'calibration holds', 'chi2': 1.0, 'dof': 1,
                            'p_value': 0.5, 'alpha': 0.01, 'measurements': 4, 'rms_m': 1e-5,
                            'training_rms_m': 1e-5, 'predicted_std_median_m': 1e-5,
                            'rms_inside_training_range_m': 1e-5, 'outside_training_range': 0,
                            'rms_outside_training_range_m': None,
                            'payloads_outside_training': said})
    assert 'WARNING: 3 points carry a payload outside those the calibration measured' in text

"""Temperature sensors per link: the cell's ``temperature.sensors`` mapping (frame id -> joints)
validated with the key and the fix; a joint's thermal effects bound to read its own sensor's ΔT
(the spec unchanged), one material's growth at each link's own temperature, exact; candidates
only where the data carry what they read; and a campaign whose upper arm and forearm warm
differently recovered within 3σ with the χ² test passed, where the mean of the sensors fails."""
from __future__ import annotations

import copy

import numpy as np
import pytest

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import identify_cell, with_effects
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.diagnosis.screening import default_candidates, screen_effects
from kpi_calib_ros.core.effects.registry import candidate_effects, parse_effect_spec
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA
from kpi_calib_ros.core.measurement.covariates import DELTA_TEMPERATURE, delta_temperature_name
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_two_sensor_shift,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document

from jacobian_checks import assert_jacobian_equals_finite_differences

SIGMA = 20e-6  # the default cell's tracker σ
UPPER, FORE = delta_temperature_name('upper_arm'), delta_temperature_name('forearm')
# The KR15-class arm: joint_3's origin is the upper arm (0.68 m), joint_4's the forearm (0.67 m).
BY_LINK = {'upper_arm': ['joint_3'], 'forearm': ['joint_4', 'joint_5']}


@pytest.fixture(scope='module')
def doc():
    base = read_cell_document(DEFAULT_CELL)
    base['robot']['urdf'] = str((DEFAULT_CELL.parent / base['robot']['urdf']).resolve())
    return base


def _cell_model(doc, sensors, effects=()):
    d = copy.deepcopy(doc)
    d['temperature'] = {'sensors': sensors}
    d['effects'] = list(effects)
    return build_cell_model(cell_from_dict(d, DEFAULT_CELL.parent))


# ------------------------------------------------------------------ the cell key
@pytest.mark.parametrize('sensors, key, says', [
    ({'upper_arm': ['joint_3'], 'forearm': ['elbow']}, 'temperature.sensors.forearm',
     "'elbow' is not a joint of the robot chain"),
    ({'upper_arm': ['joint_3'], 'forearm': ['joint_4', 'joint_3']},
     'temperature.sensors.forearm', "joint 'joint_3' is given twice (also under 'upper_arm')"),
    ({'upper_arm': ['joint_3', 'joint_3']}, 'temperature.sensors.upper_arm', 'given twice'),
    ({'upper_arm': []}, 'temperature.sensors.upper_arm', 'non-empty list of joint names'),
    ({'upper_arm': 'joint_3'}, 'temperature.sensors.upper_arm', 'non-empty list'),
    ({'upper_arm': [3]}, 'temperature.sensors.upper_arm', 'not a joint name'),
    ({'upper arm': ['joint_3']}, 'temperature.sensors', "'upper arm' is not a frame id"),
    ({7: ['joint_3']}, 'temperature.sensors', '7 is not a frame id'),
    ({}, 'temperature.sensors', 'empty mapping names no sensor'),
    (['upper_arm', ''], 'temperature.sensors', 'or a mapping frame_id: [joint names]'),
])
def test_a_bad_sensor_mapping_is_refused_naming_the_key_and_the_fix(doc, sensors, key, says):
    with pytest.raises(ConfigError) as exc:
        _cell_model(doc, sensors)
    assert exc.value.key == key, str(exc.value)
    assert says in str(exc.value)
    if 'not a joint of the robot chain' in says:
        assert 'joint_1' in str(exc.value) and 'joint_6' in str(exc.value)  # the valid names


def test_the_mapping_names_the_sensors_of_the_mean_and_the_joints_of_each(doc):
    cm = _cell_model(doc, BY_LINK)
    assert cm.cell.temperature.sensors == ('upper_arm', 'forearm')
    assert cm.model.joint_temperatures == {'joint_3': UPPER, 'joint_4': FORE, 'joint_5': FORE}
    # the list form keeps its meaning: every joint reads the mean
    assert _cell_model(doc, ['upper_arm', 'forearm']).model.joint_temperatures == {}


# ------------------------------------------------------------------- binding
def test_a_joint_reads_its_sensor_with_the_spec_and_parameter_names_unchanged(doc):
    cm = _cell_model(doc, BY_LINK, ['thermal_link_growth:joint_3', 'thermal_zero_drift:joint_6',
                                    'thermal_growth'])
    growth, drift, every = cm.model.effects
    assert (growth.name, growth.inputs) == ('thermal_link_growth:joint_3', (UPPER,))
    assert growth.parameter_names == ('thermal_link_growth.joint_3.alpha',)
    assert drift.inputs == (DELTA_TEMPERATURE,)              # joint_6 is not listed: the mean
    # one material, each link at its own temperature: the mean (joint_1, joint_2), then the
    # sensors (joint_5 and joint_6 have no link before them to grow)
    assert every.inputs == (DELTA_TEMPERATURE, UPPER, FORE)
    assert cm.model.inputs == (UPPER, DELTA_TEMPERATURE, FORE)
    # an effect added by name later reads the cell's sensors too
    richer = with_effects(cm, ('thermal_zero_drift:joint_4',))
    assert richer.model.effects[-1].inputs == (FORE,)
    assert richer.model.joint_temperatures == cm.model.joint_temperatures
    assert augmented_model(cm.model, ()).joint_temperatures == cm.model.joint_temperatures


def test_one_material_grows_each_link_with_its_own_sensor_exactly(cm, doc):
    """thermal_growth with joint_3 under the upper-arm sensor, at ΔT 8 K there and 0 K on the
    mean: only the upper arm grows, exactly as a growth of joint_3's link alone at 8 K; and the
    forearm's zero drift turns joint 4 by d ΔT of the forearm sensor."""
    temperatures = {'joint_3': UPPER, 'joint_4': FORE}
    rng = np.random.default_rng(0)
    q = random_configurations(cm.model, cm.model.params.nominal, 6, rng)
    p0 = cm.model.params.nominal
    alpha, d = 23e-6, 4e-6
    every = parse_effect_spec('thermal_growth', cm.robot, temperatures=temperatures)
    model = augmented_model(cm.model, (every,))
    cov = {DELTA_TEMPERATURE: np.zeros(len(q)), UPPER: np.full(len(q), 8.0),
           FORE: np.zeros(len(q))}
    grown = model.predict(np.concatenate([p0, [alpha]]), q, covariates=cov)
    one_link = augmented_model(cm.model, (parse_effect_spec('thermal_link_growth:joint_3',
                                                            cm.robot),))
    expected = one_link.predict(np.concatenate([p0, [alpha]]), q,
                                covariates={DELTA_TEMPERATURE: np.full(len(q), 8.0)})
    np.testing.assert_allclose(grown, expected, rtol=0, atol=1e-12)
    assert np.min(np.linalg.norm(grown - cm.model.predict(p0, q), axis=1)) > 1e-5  # it grew
    drift = augmented_model(cm.model, (parse_effect_spec('thermal_zero_drift:joint_4', cm.robot,
                                                         temperatures=temperatures),))
    turned = drift.predict(np.concatenate([p0, [d]]), q,
                           covariates={FORE: np.full(len(q), 5.0)})
    q_turned = q.copy()
    q_turned[:, 3] += d * 5.0
    np.testing.assert_allclose(turned, cm.model.predict(p0, q_turned), rtol=0, atol=1e-12)


def test_the_jacobian_of_a_growth_per_sensor_equals_finite_differences(cm):
    rng = np.random.default_rng(1)
    every = parse_effect_spec('thermal_growth', cm.robot,
                              temperatures={'joint_3': UPPER, 'joint_4': FORE})
    model = augmented_model(cm.model, (every,))
    q = random_configurations(cm.model, cm.model.params.nominal, 4, rng)
    cov = {name: rng.uniform(-5, 10, len(q)) for name in (DELTA_TEMPERATURE, UPPER, FORE)}
    p = np.concatenate([true_parameters(cm.model.params, rng), [2e-5]])
    assert_jacobian_equals_finite_differences(
        model, p, q, cov, (len(p) - 1, model.params.names.index('joint_4.placement.tx')))
    with pytest.raises(ValueError, match='delta_temperature.forearm'):
        model.predict(p, q, covariates={DELTA_TEMPERATURE: cov[DELTA_TEMPERATURE],
                                        UPPER: cov[UPPER]})


def test_a_candidate_is_offered_only_where_the_data_carry_what_it_reads(cm):
    temperatures = {'joint_3': UPPER, 'joint_4': FORE}
    full = {e.name: e for e in candidate_effects(
        cm.robot, covariates=[DELTA_TEMPERATURE, UPPER, FORE], temperatures=temperatures)}
    assert full['thermal_link_growth:joint_3'].inputs == (UPPER,)
    assert full['thermal_zero_drift:joint_4'].inputs == (FORE,)
    assert full['thermal_zero_drift:joint_1'].inputs == (DELTA_TEMPERATURE,)
    assert 'thermal_growth' in full
    # data without the forearm's own ΔT: nothing that reads it
    some = {e.name for e in candidate_effects(cm.robot, covariates=[DELTA_TEMPERATURE, UPPER],
                                              temperatures=temperatures)}
    assert 'thermal_link_growth:joint_3' in some and 'thermal_zero_drift:joint_1' in some
    assert not {'thermal_link_growth:joint_4', 'thermal_zero_drift:joint_4',
                'thermal_growth'} & some


# ------------------------------------------------------------- the campaign
def _two_sensor_shift(doc, seed, n=60, n_fresh=40):
    """``n`` poses over an 8 h shift, and ``n_fresh`` more at fresh times of it
    (:func:`simulate_two_sensor_shift`): the upper arm (aluminium, α 23e-6 /K) warms by 10 K
    (95 % after 4 h), the forearm (steel, 12e-6 /K) swings ±3 K over the shift and warms by
    2 K within the first hour: a sensor each, histories that differ, each link growing with
    its own."""
    truth_cm = _cell_model(doc, BY_LINK, ['thermal_link_growth:joint_3',
                                          'thermal_link_growth:joint_4'])
    rng = np.random.default_rng(seed)
    truth = {'thermal_link_growth.joint_3.alpha': 23e-6,
             'thermal_link_growth.joint_4.alpha': 12e-6}
    p_true = np.concatenate([true_parameters(truth_cm.geometric, rng), list(truth.values())])
    return (simulate_two_sensor_shift(truth_cm.model, p_true, n, SIGMA, rng),
            simulate_two_sensor_shift(truth_cm.model, p_true, n_fresh, SIGMA, rng), truth)


@pytest.mark.slow
@pytest.mark.parametrize('seed', [0, 3])
def test_links_that_warm_differently_are_recovered_with_their_own_sensors(doc, seed):
    """The upper arm grows with the upper-arm sensor and the forearm with the forearm sensor.
    With the sensors assigned, both α come back within 3σ and the χ² test passes; with their
    mean (the list form) the same two effects leave a misfit the χ² test rejects and predict
    fresh poses of the shift worse."""
    effects = ['thermal_link_growth:joint_3', 'thermal_link_growth:joint_4']
    per = _cell_model(doc, BY_LINK, effects)
    mean = _cell_model(doc, ['upper_arm', 'forearm'], effects)
    data, fresh, truth = _two_sensor_shift(doc, seed)
    assert np.std(data.covariates[UPPER] - data.covariates[FORE]) > 1.5  # K: they differ
    fits = {name: identify_cell(cm, data) for name, cm in (('per', per), ('mean', mean))}
    own = fits['per']
    for name, value in truth.items():
        assert abs(own.value(name) - value) < 3 * own.std_of(name), (name, own.value(name))
    assert own.p_value > ADEQUACY_ALPHA, own.p_value
    assert own.covariance_scale == 1.0  # stated σ: the model is adequate
    assert fits['mean'].p_value < 1e-5, fits['mean'].p_value
    assert fits['mean'].chi2 / fits['mean'].dof > 1.5 * own.chi2 / own.dof

    def fresh_rms(cm, result):
        miss = fresh.eta - cm.model.predict(result.values, fresh.q, covariates=fresh.covariates)
        return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))
    rms_own, rms_mean = fresh_rms(per, own), fresh_rms(mean, fits['mean'])
    print(f'\nseed {seed}: χ²/dof {own.chi2:.1f}/{own.dof} (p {own.p_value:.3g}) vs mean '
          f'{fits["mean"].chi2:.1f}/{fits["mean"].dof} (p {fits["mean"].p_value:.3g}); fresh '
          f'rms {rms_own * 1e6:.1f} vs {rms_mean * 1e6:.1f} µm')
    assert rms_own <= 1.3 * np.sqrt(3) * SIGMA, rms_own
    assert rms_mean > 1.15 * rms_own


def test_the_diagnosis_screens_each_link_at_its_own_temperature(doc):
    """The screen's candidates of a cell with the mapping read the sensors as the cell says."""
    per = _cell_model(doc, BY_LINK)
    data, _, _ = _two_sensor_shift(doc, 5, n=20, n_fresh=1)
    result = identify_cell(per, data)
    found = {e.name: e.inputs for e in default_candidates(per.model, data, result, False)[0]}
    assert found['thermal_link_growth:joint_3'] == (UPPER,)
    assert found['thermal_link_growth:joint_4'] == (FORE,)
    assert found['thermal_zero_drift:joint_1'] == (DELTA_TEMPERATURE,)
    # The report says which sensor a candidate read.
    ranked, _ = screen_effects(per.model, data, result)
    said = {c.spec: c.explanation for c in ranked}
    assert f'reads {FORE}' in said['thermal_link_growth:joint_4'], said
    assert 'reads' not in said['thermal_zero_drift:joint_1'], said


@pytest.mark.slow
def test_auto_adds_each_links_growth_at_its_own_temperature(doc):
    """``auto`` on a cell with the sensors mapped and no effects: the screen offers each
    link's growth at its own sensor, both are added and the χ² test passes; on the cell with
    the mean it finds no model the χ² test accepts (seed 0; ``bench/thermal_sensors.py``
    gives 10 seeds)."""
    from kpi_calib_ros.app.identify import calibrate_cell
    data, fresh, _ = _two_sensor_shift(doc, 0)
    own = calibrate_cell(_cell_model(doc, BY_LINK), data, model='auto')
    assert set(own.choice.effects) == {'thermal_link_growth:joint_3',
                                       'thermal_link_growth:joint_4'}, own.choice.effects
    assert [e.inputs for e in own.cell.model.effects] in ([(UPPER,), (FORE,)],
                                                         [(FORE,), (UPPER,)])
    assert own.result.p_value > ADEQUACY_ALPHA
    mean = calibrate_cell(_cell_model(doc, ['upper_arm', 'forearm']), data, model='auto')
    assert mean.result.p_value < 1e-5, (mean.choice.effects, mean.result.p_value)


def test_a_table_with_a_column_per_sensor_reaches_each_links_temperature(doc, tmp_path):
    """A shop-floor table with a temperature column per sensor: the mapping's
    ``temperature: {frame id: column}`` writes each on the temperature topic with its frame
    id, and the cell's sensor-per-link mapping gives every posture its sensors' ΔT back,
    exactly as simulated."""
    import csv

    import yaml

    from kpi_calib_ros.app.measurements import load_measurements
    from kpi_calib_ros.cli import main
    data, _, _ = _two_sensor_shift(doc, 7, n=12, n_fresh=1)
    cm = _cell_model(doc, BY_LINK)
    table = tmp_path / 'postures.csv'
    with table.open('w', newline='') as f:
        out = csv.writer(f)
        out.writerow([*cm.joint_names, 'x', 'y', 'z', 't', 'T_upper', 'T_fore'])
        for i in range(len(data)):
            out.writerow([*data.q[i], *data.eta[i], data.stamps_ns[i] / 1e9,
                          data.covariates['temperature.upper_arm'][i],
                          data.covariates['temperature.forearm'][i]])
    mapping = tmp_path / 'columns.yaml'
    mapping.write_text(yaml.safe_dump({
        'frame_id': cm.cell.tracker_frame, 'joints': list(cm.joint_names),
        'markers': {'probe': ['x', 'y', 'z']}, 'stamp_columns': ['t'],
        'temperature': {'upper_arm': 'T_upper', 'forearm': 'T_fore'}}))
    cell = copy.deepcopy(doc)
    cell['temperature'] = {'sensors': BY_LINK}
    cell['reflectors'] = [{'name': 'probe', 'offset': cell['reflector'].pop('offset')}]
    (tmp_path / 'cell.yaml').write_text(yaml.safe_dump(cell))
    bag = tmp_path / 'postures.mcap'
    assert main(['import-csv', str(table), '--mapping', str(mapping), '--out', str(bag)]) == 0
    _, read, _ = load_measurements(tmp_path / 'cell.yaml', bag)
    order = np.searchsorted(data.stamps_ns, read.stamps_ns)
    assert len(read) == len(data)
    for name in (UPPER, FORE, DELTA_TEMPERATURE):
        np.testing.assert_allclose(read.covariates[name], data.covariates[name][order],
                                   rtol=0, atol=1e-9)
    assert not np.allclose(read.covariates[UPPER], read.covariates[FORE])

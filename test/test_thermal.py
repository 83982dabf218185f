"""Covariates and the thermal effects: temperature paired to points by time (exact linear
interpolation, refusal outside the recording), exact Jacobians, the growth as written, and
a hidden thermal growth under a shift's warm-up found, recovered within 3σ and predicting
fresh poses at the noise floor; no thermal effect on data the geometry explains."""
from __future__ import annotations

import re

import numpy as np
import pytest

from kpi_calib_ros.app.diagnose import diagnose_cell, recorded_covariates
from kpi_calib_ros.app.identify import calibrate_cell, geometric_only, identify_cell, with_effects
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.diagnosis.residual_analysis import analyse_calibration
from kpi_calib_ros.core.diagnosis.residual_inputs import residual_inputs
from kpi_calib_ros.core.effects.registry import candidate_effects, parse_effect_spec
from kpi_calib_ros.core.measurement.covariates import (
    DELTA_TEMPERATURE,
    TemperatureSample,
    interpolate,
    shift_temperature,
    temperature_covariates,
    with_covariates,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell_settings import hidden_effects

from jacobian_checks import assert_jacobian_equals_finite_differences

SIGMA = 20e-6  # the default cell's tracker σ
S = 10**9


def test_interpolation_is_exact_for_a_linear_signal_and_refuses_outside():
    t0 = 1_700_000_000 * S  # real epoch stamps: exact despite their size
    samples = t0 + np.arange(0, 600, 10) * S
    values = 20.0 + 0.01 * (samples - t0) / S        # 0.01 K/s
    stamps = t0 + np.array([5, 17.5, 300, 590, 600, 700, -5, -200]) * S
    got = interpolate(stamps.astype(np.int64), samples, values, max_gap_ns=60 * S)
    expected = 20.0 + 0.01 * (stamps - t0) / S
    np.testing.assert_allclose(got[:4], expected[:4], rtol=0, atol=1e-12)
    assert got[4] == values[-1] and got[6] == values[0]   # held within the tolerance
    assert np.isnan(got[5]) and np.isnan(got[7])            # beyond it: refused
    # a gap longer than the tolerance gives no value inside it
    sparse = np.delete(samples, np.arange(20, 40))
    got = interpolate(np.array([t0 + 300 * S]), sparse, 20.0 + 0.01 * (sparse - t0) / S,
                      max_gap_ns=60 * S)
    assert np.isnan(got[0])


def test_temperature_covariates_per_sensor_mean_and_refused_rows():
    stamps = np.arange(0, 3600, 60) * S
    samples = [TemperatureSample(int(t), f, base + 1e-3 * t / S)
               for t in stamps for f, base in (('arm', 22.0), ('base', 24.0))]
    points = np.array([30, 1200, 4000]) * S                # the last after the recording
    cov = temperature_covariates(points, samples, reference_c=20.0, max_gap_ns=120 * S)
    np.testing.assert_allclose(cov['temperature.arm'][:2], 22.0 + 1e-3 * points[:2] / S)
    np.testing.assert_allclose(cov[DELTA_TEMPERATURE][:2], 3.0 + 1e-3 * points[:2] / S)
    # each sensor's own ΔT beside the mean; only the sensors of the mean get one
    np.testing.assert_allclose(cov['delta_temperature.arm'][:2], 2.0 + 1e-3 * points[:2] / S)
    np.testing.assert_allclose(cov['delta_temperature.base'][:2], 4.0 + 1e-3 * points[:2] / S)
    one = temperature_covariates(points, samples, sensors=['base'], reference_c=20.0,
                                 max_gap_ns=120 * S)
    assert 'delta_temperature.arm' not in one and 'temperature.arm' in one
    np.testing.assert_array_equal(one[DELTA_TEMPERATURE], one['delta_temperature.base'])
    data = Measurements(q=np.zeros((3, 6)), eta=np.zeros((3, 3)), stamps_ns=points)
    kept, refused = with_covariates(data, cov)
    assert len(kept) == 2 and [i for i, _ in refused] == [2]
    np.testing.assert_array_equal(kept.subset([1]).covariates['temperature.base'],
                                  cov['temperature.base'][1:2])
    with pytest.raises(ValueError, match='nope'):
        temperature_covariates(points, samples, sensors=['nope'])


def test_thermal_effects_are_candidates_only_with_a_temperature(cm):
    plain = {e.name for e in candidate_effects(cm.robot)}
    warm = {e.name for e in candidate_effects(cm.robot, covariates=[DELTA_TEMPERATURE])}
    assert not any(n.startswith('thermal') for n in plain)
    assert {'thermal_growth', 'thermal_zero_drift:joint_2',
            'thermal_link_growth:joint_3'} <= warm


def test_link_growth_lengthens_the_link_and_drift_turns_the_joint(cm):
    """α ΔT grows joint 3's origin translation t (the upper arm) by α ΔT |t|: the tip moves
    by exactly that vector turned by joint 2's frame; zero drift moves joint 2 by d ΔT."""
    rng = np.random.default_rng(0)
    q = random_configurations(cm.model, cm.model.params.nominal, 5, rng)
    p0 = cm.model.params.nominal
    growth = parse_effect_spec('thermal_link_growth:joint_3', cm.robot)
    drift = parse_effect_spec('thermal_zero_drift:joint_2', cm.robot)
    model = augmented_model(cm.model, (growth, drift))
    dt = np.full(len(q), 8.0)
    alpha, d = 12e-6, 3e-6
    moved = model.predict(np.concatenate([p0, [alpha, 0.0]]), q,
                          covariates={DELTA_TEMPERATURE: dt})
    still = model.predict(np.concatenate([p0, [alpha, 0.0]]), q)   # ΔT = 0: no growth
    np.testing.assert_allclose(still, cm.model.predict(p0, q), atol=1e-12)
    t = cm.robot.joints[2].placement[:3, 3]
    frames = cm.model.chain.link_transforms(p0, q[0])
    # the shift is α ΔT t expressed in joint 2's child frame, then in the tracker frame
    base = np.array(cm.model.chain.base_in_tracker(p0))[:3, :3]
    expected = base @ np.array(frames[1])[:3, :3] @ (alpha * 8.0 * t)
    np.testing.assert_allclose(moved[0] - cm.model.predict(p0, q[:1])[0], expected, atol=1e-12)
    turned = model.predict(np.concatenate([p0, [0.0, d]]), q, covariates={DELTA_TEMPERATURE: dt})
    q_turned = q.copy()
    q_turned[:, 1] += d * 8.0
    np.testing.assert_allclose(turned, cm.model.predict(p0, q_turned), atol=1e-12)


@pytest.mark.parametrize('spec', ['thermal_growth', 'thermal_zero_drift:joint_2',
                                  'thermal_link_growth:joint_3'])
def test_thermal_jacobian_equals_finite_differences(cm, spec):
    rng = np.random.default_rng(1)
    model = augmented_model(cm.model, (parse_effect_spec(spec, cm.robot),))
    q = random_configurations(cm.model, cm.model.params.nominal, 4, rng)
    cov = {DELTA_TEMPERATURE: rng.uniform(-5, 10, len(q))}
    p = np.concatenate([true_parameters(cm.model.params, rng), [1e-5]])
    assert_jacobian_equals_finite_differences(
        model, p, q, cov, (len(p) - 1, model.params.names.index('joint_3.placement.tx')))
    with pytest.raises(ValueError, match='delta_temperature'):
        model.predict(p, q, covariates={'temperature.arm': np.zeros(len(q))})


def _shift(cm, hidden, seed, n=60, rise=8.0):
    """A campaign of ``n`` poses over an 8 h shift whose arm warms by ``rise`` K."""
    rng = np.random.default_rng(seed)
    effects, overrides = hidden_effects(hidden, cm.robot)
    truth = augmented_model(cm.model, effects)
    p_true = np.concatenate([true_parameters(cm.model.params, rng),
                             [overrides[k] for e in effects for k in e.parameter_names]])

    def measure(count, start_h):
        q = random_configurations(cm.model, cm.model.params.nominal, count, rng)
        stamps = ((start_h + np.sort(rng.uniform(0, 8, count))) * 3600 * S).astype(np.int64)
        celsius = shift_temperature(stamps, 20.0, rise, 4.0, start_ns=0)
        cov = {'temperature.arm': celsius, DELTA_TEMPERATURE: celsius - 20.0}
        return simulate_measurements(truth, p_true, q, SIGMA, rng, covariates=cov,
                                     stamps_ns=stamps)
    return measure(n, 0.0), measure(40, 0.0), dict(zip(truth.params.names, p_true))


@pytest.mark.slow
def test_a_hidden_thermal_growth_is_found_recovered_and_predicts_at_the_noise_floor(cm):
    alpha = 23e-6  # an aluminium upper arm
    data, fresh, truth = _shift(cm, {'thermal_link_growth:joint_3': {'alpha': alpha}}, 1)
    cal = calibrate_cell(cm, data, model='auto')
    assert cal.choice.effects == ('thermal_link_growth:joint_3',)
    name = 'thermal_link_growth.joint_3.alpha'
    assert abs(cal.result.value(name) - alpha) < 3 * cal.result.std_of(name)
    assert cal.cell is not None
    # fresh poses at fresh times of the same shift: the noise alone is left
    miss = fresh.eta - cal.cell.model.predict(cal.result.values, fresh.q,
                                              covariates=fresh.covariates)
    rms = float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))
    assert rms <= 1.5 * np.sqrt(3) * SIGMA, rms
    # without the effect part of the warm-up stays in the error
    plain = calibrate_cell(cm, data, model='geometric')
    miss = fresh.eta - cm.model.predict(plain.result.values, fresh.q)
    assert float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1)))) > rms


@pytest.mark.slow
def test_no_thermal_effect_on_a_warm_up_the_geometry_explains(cm):
    data, _, _ = _shift(cm, {}, 2)
    cal = calibrate_cell(cm, data, model='auto')
    assert not any(e.startswith('thermal') for e in cal.choice.effects), cal.choice.effects


def _recorded(cm, tmp_path, temperatures, n=6, seed=3):
    """A bag of ``n`` poses (joint states, points) and ``temperatures`` [(stamp, frame, °C)]
    on the default temperature topic; the points' stamps."""
    from kpi_calib_ros.core.acquisition.streams import synthesize_streams
    from kpi_calib_ros.io.bag_writing import BagStream
    from kpi_calib_ros.io.names import DEFAULT_TEMPERATURE_TOPIC
    rng = np.random.default_rng(seed)
    q = random_configurations(cm.model, cm.model.params.nominal, n, rng)
    eta = cm.model.predict(cm.model.params.nominal, q)
    joints, points = synthesize_streams(q, cm.joint_names, eta, cm.cell.tracker_frame)
    path = tmp_path / 'warm.mcap'
    with BagStream(path, temperature_topic=DEFAULT_TEMPERATURE_TOPIC) as bag:
        messages = ([(j.stamp_ns, 0, j) for j in joints] + [(p.stamp_ns, 1, p) for p in points]
                    + [(t, 2, (f, c)) for t, f, c in temperatures])
        for stamp, kind, item in sorted(messages, key=lambda m: (m[0], m[1])):
            if kind == 0:
                bag.write_joint(item)
            elif kind == 1:
                bag.write_point(item)
            else:
                bag.write_temperature(stamp, *item)
    return path, np.array([p.stamp_ns for p in points])


def test_temperature_messages_in_a_bag_are_paired_to_the_points(cm, tmp_path):
    import dataclasses

    from kpi_calib_ros.app.measurements import measurements_from_bag
    from kpi_calib_ros.io.bag import read_temperatures
    from kpi_calib_ros.io.cell_temperature import TemperatureSettings
    start = 1_700_000_000 * S
    # two sensors every 7 s over the whole recording, rising linearly at different rates
    ticks = start + np.arange(-7, 80, 7) * S
    temps = [(int(t), f, base + rate * (t - start) / S) for t in ticks
             for f, base, rate in (('upper_arm', 22.0, 0.02), ('forearm', 25.0, -0.01))]
    path, point_stamps = _recorded(cm, tmp_path, temps)
    assert len(read_temperatures(path)) == len(temps)
    warm = dataclasses.replace(cm, cell=dataclasses.replace(
        cm.cell, temperature=TemperatureSettings(sensors=('upper_arm', 'forearm'),
                                                 reference_c=21.0)))
    data, _ = measurements_from_bag(warm, path)
    assert len(data) == len(point_stamps)
    t = (np.asarray(data.stamps_ns) - start) / S
    np.testing.assert_allclose(data.covariates['temperature.upper_arm'], 22.0 + 0.02 * t,
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(data.covariates['temperature.forearm'], 25.0 - 0.01 * t,
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(data.covariates[DELTA_TEMPERATURE],
                               (22.0 + 0.02 * t + 25.0 - 0.01 * t) / 2 - 21.0, atol=1e-9)
    # and each sensor's own ΔT beside the mean
    np.testing.assert_allclose(data.covariates['delta_temperature.upper_arm'],
                               22.0 + 0.02 * t - 21.0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(data.covariates['delta_temperature.forearm'],
                               25.0 - 0.01 * t - 21.0, rtol=0, atol=1e-9)
    # without the section nothing is read
    assert measurements_from_bag(cm, path)[0].covariates is None


def test_a_cell_that_maps_sensors_to_joints_reads_each_link_from_a_bag(tmp_path):
    """A cell file whose ``temperature.sensors`` maps the upper-arm and forearm sensors to
    their joints, a bag with both sensors, effects given as on the command line
    (``--effects``): each point carries each sensor's ΔT, and the effects the model holds
    read them, so its prediction grows the upper arm with the upper-arm temperature alone."""
    import yaml

    from kpi_calib_ros.app.measurements import load_measurements
    from kpi_calib_ros.io.cell import DEFAULT_CELL
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['temperature'] = {'reference': 21.0, 'sensors': {'upper_arm': ['joint_2', 'joint_3'],
                                                         'forearm': ['joint_4']}}
    cell_path = tmp_path / 'cell.yaml'
    cell_path.write_text(yaml.safe_dump(doc))
    start = 1_700_000_000 * S
    ticks = start + np.arange(-7, 80, 7) * S
    temps = [(int(t), f, base + rate * (t - start) / S) for t in ticks
             for f, base, rate in (('upper_arm', 22.0, 0.02), ('forearm', 25.0, -0.01))]
    from kpi_calib_ros.app.cell_model import build_cell_model
    from kpi_calib_ros.io.cell import load_cell
    path, point_stamps = _recorded(build_cell_model(load_cell(cell_path)), tmp_path, temps)
    cm, data, _ = load_measurements(cell_path, path,
                                    'thermal_link_growth:joint_3,thermal_zero_drift:joint_4')
    assert len(data) == len(point_stamps)
    t = (np.asarray(data.stamps_ns) - start) / S
    upper, fore = 22.0 + 0.02 * t - 21.0, 25.0 - 0.01 * t - 21.0
    np.testing.assert_allclose(data.covariates['delta_temperature.upper_arm'], upper, atol=1e-9)
    np.testing.assert_allclose(data.covariates['delta_temperature.forearm'], fore, atol=1e-9)
    growth, drift = cm.model.effects
    assert growth.inputs == ('delta_temperature.upper_arm',)
    assert drift.inputs == ('delta_temperature.forearm',)
    # the model's prediction: the upper arm grown by α ΔT_upper (the mean would differ)
    p = cm.model.params.nominal.copy()
    p[cm.model.params.names.index('thermal_link_growth.joint_3.alpha')] = 20e-6
    grown = cm.model.predict(p, data.q, covariates=data.covariates)
    one = augmented_model(geometric_only(cm).model, (
        parse_effect_spec('thermal_link_growth:joint_3', cm.robot),))
    expected = one.predict(np.concatenate([cm.geometric.nominal, [20e-6]]), data.q,
                           covariates={DELTA_TEMPERATURE: upper})
    np.testing.assert_allclose(grown, expected, rtol=0, atol=1e-12)
    assert np.max(np.abs(data.covariates[DELTA_TEMPERATURE] - upper)) > 1.0


def test_points_beyond_the_temperature_recording_are_refused(cm, tmp_path):
    import dataclasses

    from kpi_calib_ros.app.measurements import measurements_from_bag
    from kpi_calib_ros.io.cell_temperature import TemperatureSettings
    start = 1_700_000_000 * S
    temps = [(int(start + k * S), 'arm', 22.0) for k in range(0, 12)]  # the first 11 s only
    path, point_stamps = _recorded(cm, tmp_path, temps)
    warm = dataclasses.replace(cm, cell=dataclasses.replace(
        cm.cell, temperature=TemperatureSettings(max_gap_s=5.0)))
    expected = int(np.sum(point_stamps <= start + 16 * S))
    with pytest.warns(UserWarning, match='refused'):
        data, _ = measurements_from_bag(warm, path)
    assert len(data) == expected < len(point_stamps)


def test_an_imported_table_carries_its_temperature_column_to_every_row(tmp_path):
    """Series A of the real UR10 as exported: import-csv writes the temperature column on
    /cell/temperature at each posture's stamp, and every row (point and rotation row of the
    6-DoF probe) gets its own posture's temperature back."""
    import dataclasses
    from pathlib import Path

    from kpi_calib_ros.app.cell_model import build_cell_model
    from kpi_calib_ros.app.measurements import measurements_from_bag
    from kpi_calib_ros.cli import main
    from kpi_calib_ros.io.cell import load_cell
    from kpi_calib_ros.io.cell_temperature import TemperatureSettings
    from kpi_calib_ros.io.csv_import import read_postures
    from kpi_calib_ros.io.csv_mapping import load_mapping
    here = Path(__file__).parent / 'data'
    beside = Path(__file__).resolve().parents[2] / 'shared' / 'data' / 'ipa_ur10'
    source = (beside if beside.is_dir() else Path('/work/shared/data/ipa_ur10')) \
        / 'Series_A' / 'measurements_grid.csv'
    lines = source.read_bytes().split(b'\r\n')
    table = tmp_path / 'grid.csv'
    table.write_bytes(b'\r\n'.join([lines[0], *[x for x in lines[1:] if x][::300][:30]])
                      + b'\r\n')
    bag = tmp_path / 'grid.mcap'
    assert main(['import-csv', str(table), '--mapping', str(here / 'ipa_ur10_mapping.yaml'),
                 '--out', str(bag)]) == 0
    cm = build_cell_model(load_cell(here / 'ipa_ur10_cell.yaml'))
    warm = dataclasses.replace(cm, cell=dataclasses.replace(
        cm.cell, temperature=TemperatureSettings()))
    data, _ = measurements_from_bag(warm, bag)
    rows = {r.stamp_ns: r.temperatures['laser_tracker'] for r in read_postures(
        table, load_mapping(here / 'ipa_ur10_mapping.yaml'))}
    expected = np.array([rows[int(t)] for t in data.stamps_ns])
    assert len(data) == 2 * len(rows)  # a point and a rotation row per posture
    np.testing.assert_array_equal(data.covariates['temperature.laser_tracker'], expected)
    np.testing.assert_allclose(data.covariates[DELTA_TEMPERATURE], expected - 20.0)


def test_at_one_temperature_a_thermal_effect_is_not_distinguishable(cm):
    """ΔT the same at every pose: link growth is a fixed change of the link lengths and a
    drift a fixed zero offset, which the geometry reproduces; the screen says so and asks for
    measurements while the temperature changes."""
    from kpi_calib_ros.core.diagnosis.screening import screen_effects
    from kpi_calib_ros.core.estimation.least_squares import identify
    rng = np.random.default_rng(5)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, cm.model.params.nominal, 40, rng)
    data = simulate_measurements(cm.model, p_true, q, SIGMA, rng,
                                 covariates={DELTA_TEMPERATURE: np.full(len(q), 5.0)})
    result = identify(cm.model, data, SIGMA, cm.q_work)
    candidates = [parse_effect_spec(s, cm.robot) for s in
                  ('thermal_zero_drift:joint_2', 'thermal_link_growth:joint_3')]
    ranked, rejected = screen_effects(cm.model, data, result, candidates)
    assert not ranked and {c.spec for c in rejected} == {e.name for e in candidates}
    assert all('temperature changes' in c.explanation for c in rejected)


@pytest.mark.slow
def test_diagnose_analyses_the_recorded_temperature_as_an_input(cm):
    """The temperature the measurements carry reaches the model-free residual analysis of
    ``diagnose`` without being passed: with a hidden link growth over a warm-up it is a
    flagged input, and the geometric fit leaves it the largest share among the inputs."""
    data, _, _ = _shift(cm, {'thermal_link_growth:joint_3': {'alpha': 60e-6}}, 2, n=120,
                        rise=12.0)
    assert set(recorded_covariates(data)) == {'temperature.arm'}
    cd = diagnose_cell(cm, data, model='geometric', add_best=False)
    scores = {s.name: s for s in cd.residual_analysis.scores}
    assert 'temperature.arm' in scores
    assert scores['temperature.arm'].significant


def test_diagnose_screens_the_thermal_effects_and_adds_a_hidden_growth(cm):
    """``diagnose`` (with its general effects) screens the thermal effects where the
    measurements carry a temperature, as ``auto`` does: a hidden link growth over a warm-up
    is the effect it adds, and the refit at every row's temperature passes the χ² test."""
    data, _, _ = _shift(cm, {'thermal_link_growth:joint_3': {'alpha': 23e-6}}, 1)
    cd = diagnose_cell(cm, data, model='geometric')
    thermal = {c.spec for c in cd.diagnosis.candidates if c.effect.startswith('thermal_')}
    print(f'\nadded {cd.added.name if cd.added else None}; thermal candidates screened '
          f'{len(thermal)}; χ² p after {cd.after.p_value if cd.after else None}')
    assert 'thermal_zero_drift:joint_2' in thermal and 'thermal_growth' in thermal
    # The growth of the longest link and of every link are nearly one signature.
    assert cd.added is not None
    assert cd.added.name in {'thermal_link_growth:joint_3', 'thermal_growth'}
    assert cd.after.p_value > 1e-3


def test_the_residual_analysis_of_a_thermal_model_shows_its_own_residuals(cm):
    """With a thermal effect in the model, the partial residuals the analysis plots are
    the fit's own residuals (predicted at each row's temperature), not those of the model
    at the reference temperature, which would put the modelled growth back."""
    data, _, _ = _shift(cm, {'thermal_link_growth:joint_3': {'alpha': 60e-6}}, 2, n=60,
                        rise=12.0)
    rich = with_effects(cm, (parse_effect_spec('thermal_link_growth:joint_3', cm.robot),))
    result = identify_cell(rich, data)
    analysis = analyse_calibration(rich.model, data, result, recorded_covariates(data))
    score = next(s for s in analysis.scores if s.name == 'temperature.arm')
    fields = next(i for i in residual_inputs(rich.model, data, result,
                                             recorded_covariates(data))
                  if i.name == 'temperature.arm').fields
    implied = (np.einsum('nak,na->nk', fields, result.residuals)
               / np.sum(fields ** 2, axis=1))
    np.testing.assert_allclose(score.implied, implied, rtol=1e-9, atol=1e-12)


def _warm_cell(tmp_path, **temperature):
    """The default cell reading sensor ``upper_arm`` (``temperature`` keys added), as a file."""
    import yaml

    from kpi_calib_ros.io.cell import DEFAULT_CELL
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['temperature'] = {'sensors': ['upper_arm'], **temperature}
    path = tmp_path / 'cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def _faulty_readings(bad):
    """A reading every 10 s over 200 s rising 0.01 K/s; the 6th (50 s) replaced by ``bad``."""
    start = 1_700_000_000 * S
    ticks = start + np.arange(-10, 200, 10) * S
    return [(int(t), 'upper_arm', bad if k == 6 else 22.0 + 0.01 * (t - start) / S)
            for k, t in enumerate(ticks)]


@pytest.mark.parametrize('bad', [1e12, 1e300, -500.0, 151.0])
def test_a_temperature_reading_no_cell_can_have_is_counted_and_never_used(cm, tmp_path, bad):
    from kpi_calib_ros.app.cell_model import build_cell_model
    from kpi_calib_ros.app.measurements import measurements_from_bag
    from kpi_calib_ros.io.cell import load_cell
    warm = build_cell_model(load_cell(_warm_cell(tmp_path)))
    path, _ = _recorded(cm, tmp_path, _faulty_readings(bad), n=8)
    with pytest.warns(UserWarning, match=r'1 temperature reading\(s\) outside '
                      r'temperature.valid_range \[-50, 150\] °C not used \(first: '
                      + re.escape(f'{bad:g} °C from sensor \'upper_arm\'')):
        data, _ = measurements_from_bag(warm, path)
    # the points are paired with the plausible readings around the fault (the linear rise)
    t = (np.asarray(data.stamps_ns) - 1_700_000_000 * S) / S
    np.testing.assert_allclose(data.covariates['temperature.upper_arm'], 22.0 + 0.01 * t,
                               rtol=0, atol=1e-9)


@pytest.mark.slow
def test_identify_with_a_temperature_of_1e300_gives_the_calibration_without_it(cm, tmp_path,
                                                                             capsys):
    import yaml

    from kpi_calib_ros.cli import main
    from kpi_calib_ros.io.names import CALIBRATION_FILE, FAILED_CALIBRATION_FILE
    cell = str(_warm_cell(tmp_path))
    tcp, verdicts = {}, {}
    for name, bad in (('clean', None), ('faulty', 1e300)):
        readings = [r for r in _faulty_readings(bad) if r[2] is not None]
        folder = tmp_path / name
        folder.mkdir()
        path, _ = _recorded(cm, folder, readings, n=30, seed=4)
        out = folder / 'out'
        argv = ['identify', '--cell', cell, '--bag', str(path), '--out', str(out),
                '--effects', 'thermal_growth']
        if bad is None:
            code = main(argv)
        else:
            with pytest.warns(UserWarning, match='1 temperature reading'):
                code = main(argv)
        # The simulated robot is built exactly to its URDF and measured without noise: the
        # 30 poses' geometric calibration is less certain at the working pose than the
        # registered nominal robot (not valid, calibration.failed.yaml), with the fault
        # or without it alike.
        written = out / (CALIBRATION_FILE if code == 0 else FAILED_CALIBRATION_FILE)
        doc = yaml.safe_load(written.read_text())
        verdicts[name] = (code, doc['valid'], doc['invalid_reasons'])
        tcp[name] = np.array(doc['tcp'][0]['position'], float)
    assert verdicts['faulty'] == verdicts['clean']
    np.testing.assert_allclose(tcp['faulty'], tcp['clean'], rtol=0, atol=1e-6)


def test_a_recording_whose_every_temperature_is_implausible_is_exit_2(cm, tmp_path, capsys):
    from kpi_calib_ros.cli import main
    cell = str(_warm_cell(tmp_path, valid_range=[0.0, 60.0]))
    readings = [(t, f, 1e12) for t, f, _ in _faulty_readings(None)]
    path, _ = _recorded(cm, tmp_path, readings, n=8)
    assert main(['identify', '--cell', cell, '--bag', str(path), '--out',
                 str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err
    assert ('all 21 temperature readings on \'/cell/temperature\' lie outside '
            'temperature.valid_range [0.0, 60.0] °C (first: 1e+12 °C') in err


@pytest.mark.parametrize('valid_range, message', [
    ([-500, 100], 'low -500 °C is below absolute zero'),
    ([0, 2000], '[0, 2000] °C is not a range a robot cell can read'),
    ([60, 0], '[60, 0] °C is not a range a robot cell can read'),
    ('hot', "give [low, high] in °C with -273.15 <= low < high <= 1000 (default [-50.0, "
            "150.0]), got 'hot'"),
])
def test_the_valid_temperature_range_is_checked_naming_the_key(valid_range, message):
    from kpi_calib_ros.core.errors import ConfigError
    from kpi_calib_ros.io.cell_temperature import temperature_settings
    with pytest.raises(ConfigError, match='temperature.valid_range') as err:
        temperature_settings({'valid_range': valid_range})
    assert message in str(err.value)
    assert temperature_settings({}).valid_range_c == (-50.0, 150.0)

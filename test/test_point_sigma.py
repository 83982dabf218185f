"""The tracker's own per-point uncertainty (``Measurements.sigma``), which grows with the
distance (a laser tracker: 15 µm + 6 µm/m), weighs every row in place of the cell's single
noise.sigma: χ², the TCP precision and the statistics in units of σ follow it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.stats
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.app.placement import registered_start
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.measurement.data import Measurements, row_sigma
from kpi_calib_ros.core.measurement.weighting import noise_weights
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.names import DEFAULT_POINT_TOPIC, DEFAULT_POSE_TOPIC, point_sigma_topic

from real_data import UR10_DATA

# An AT960's maximum permissible error, per axis: 15 µm + 6 µm/m of distance.
SIGMA_0_M, SIGMA_PER_M = 15e-6, 6e-6
POSES = 30


@pytest.fixture(scope='module')
def cell(cm):
    """The built-in cell file as loaded (conftest's shared model's)."""
    return cm.cell


def tracker_sigma(points: np.ndarray) -> np.ndarray:
    """(N, 3) σ per axis of points (N, 3) in the tracker frame (the tracker at the origin)."""
    distance = np.linalg.norm(points, axis=1)
    return np.repeat((SIGMA_0_M + SIGMA_PER_M * distance)[:, None], 3, axis=1)


def campaign(cm, seed: int, poses: int = POSES):
    rng = np.random.default_rng(seed)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, p_true, poses, rng)
    return p_true, q, rng


def measure(cm, p_true, q, rng) -> Measurements:
    """Points with noise N(0, σ_i²) growing with the distance, each σ_i recorded."""
    clean = cm.model.predict(p_true, q)
    sigma = tracker_sigma(clean)
    return Measurements(q=q, eta=clean + rng.normal(size=clean.shape) * sigma, sigma=sigma)


@pytest.mark.slow
def test_chi2_p_values_are_uniform_with_the_point_sigma(cm, cell):
    """50 campaigns, noise 15 µm + 6 µm/m (22-35 µm here): weighed by each point's σ the
    χ² p-values are uniform (KS); weighed by the cell's single 20 µm, χ² rejects most."""
    own, single = [], []
    for seed in range(50):
        p_true, q, rng = campaign(cm, seed)
        data = measure(cm, p_true, q, rng)
        own.append(identify(cm.model, data, cell.sigma, cm.q_work).p_value)
        plain = Measurements(q=data.q, eta=data.eta)
        single.append(identify(cm.model, plain, cell.sigma, cm.q_work).p_value)
    assert scipy.stats.kstest(own, 'uniform').pvalue > 0.01, np.round(own, 3)
    assert np.mean(np.array(single) < 0.01) > 0.8, np.round(single, 3)


@pytest.mark.slow
def test_tcp_std_matches_monte_carlo_with_the_point_sigma(cm, cell):
    """One robot and design, 100 draws of distance-dependent noise: the TCP std from the
    points' σ (sqrt(trace) at the working pose) equals the Monte Carlo spread within 20 %;
    from the cell's single 20 µm it is more than 20 % short."""
    p_true, q, _ = campaign(cm, 11)
    rng = np.random.default_rng(12)
    tcp, own, single = [], [], []
    for _ in range(100):
        data = measure(cm, p_true, q, rng)
        result = identify(cm.model, data, cell.sigma, cm.q_work)
        tcp.append(result.tcp)
        own.append(np.trace(result.tcp_covariance, axis1=1, axis2=2))
        plain = identify(cm.model, Measurements(q=data.q, eta=data.eta), cell.sigma, cm.q_work)
        single.append(np.trace(plain.tcp_covariance, axis1=1, axis2=2))
    monte_carlo = np.sqrt(np.sum(np.var(np.array(tcp), axis=0, ddof=1), axis=1))
    np.testing.assert_allclose(np.sqrt(np.mean(own, axis=0)) / monte_carlo, 1.0, atol=0.2)
    assert np.all(np.sqrt(np.mean(single, axis=0)) / monte_carlo < 0.8)


def test_a_point_without_sigma_takes_the_cell_sigma(cm, cell):
    """Rows whose σ is NaN are weighed by the cell's σ: the fit equals the one with the cell's
    σ written into those rows, and the σ carried per row says so."""
    p_true, q, rng = campaign(cm, 3)
    data = measure(cm, p_true, q, rng)
    partial = data.sigma.copy()
    partial[::2] = np.nan
    filled = data.sigma.copy()
    filled[::2] = cell.sigma
    a = identify(cm.model, Measurements(q=data.q, eta=data.eta, sigma=partial), cell.sigma,
                 cm.q_work)
    b = identify(cm.model, Measurements(q=data.q, eta=data.eta, sigma=filled), cell.sigma,
                 cm.q_work)
    np.testing.assert_allclose(a.point_sigma, filled)
    np.testing.assert_allclose(a.values, b.values, rtol=0, atol=1e-12)
    assert a.chi2 == pytest.approx(b.chi2, rel=1e-9)
    np.testing.assert_allclose(row_sigma(cell.sigma, partial, len(q)), filled)
    np.testing.assert_allclose(noise_weights(cm.model, a.values, Measurements(
        q=data.q, eta=data.eta, sigma=partial), cell.sigma), 1.0 / filled)


@pytest.mark.parametrize('bad', [0.0, -1e-6, np.inf])
def test_a_bad_point_sigma_is_a_data_error(cm, cell, bad):
    p_true, q, rng = campaign(cm, 4, 10)
    data = measure(cm, p_true, q, rng)
    sigma = data.sigma.copy()
    sigma[2, 1] = bad
    with pytest.raises(DataError, match='per-row sigma'):
        identify(cm.model, Measurements(q=data.q, eta=data.eta, sigma=sigma), cell.sigma,
                 cm.q_work)


@pytest.mark.parametrize('loss', ['linear', 'huber'])
def test_robust_statistics_count_each_point_in_its_own_sigma(cm, loss):
    """120 poses, the cell states 5 µm, the points their own 22-35 µm: the robust σ̂ reads the
    points' σ as stated (ratio within 1.5×, no σ warning) and no good point is an outlier;
    the residual report agrees. Taken as metres against 5 µm they read as 5-7× the σ."""
    from kpi_calib_ros.core.estimation.residuals import residual_report
    from kpi_calib_ros.core.estimation.robust import OutlierSettings, robust_identify
    cell_sigma = np.full(3, 5e-6)

    def fit(d, free=None, **kw):
        return identify(cm.model, d, cell_sigma, cm.q_work, **kw)
    for seed in range(3):
        p_true, q, rng = campaign(cm, 40 + seed, 120)
        data = measure(cm, p_true, q, rng)
        robust = robust_identify(cm.model, data, cell_sigma, fit, loss, OutlierSettings())
        assert 1 / 1.5 < robust.sigma_ratio < 1.5, robust.sigma_ratio
        assert not robust.warnings and not robust.excluded, robust.warnings
        report = residual_report(cm.model, data, robust.result)
        assert not report.sigma_warning and not report.outlier.any()
        # σ̂ in metres against the σ the points state (their rms), not the cell's 5 µm.
        assert 1 / 1.5 < report.sigma_robust_m / report.sigma_stated_m < 1.5
        assert report.sigma_stated_m == pytest.approx(robust.sigma_stated, rel=1e-12)
        assert robust.result.p_value > 1e-3


def test_the_robust_sigma_with_point_sigma_is_the_noise_of_the_residuals(cm):
    """The points state 10 µm, the cell 20 µm, the noise is 20.9 µm per axis: σ̂ reads
    20.9 µm (within 10 %), 2.09× the stated 10 µm, in the fit's robust statistics, the
    residual report and the warning; not 41.8 µm, 2.09× the cell's 20 µm."""
    from kpi_calib_ros.core.estimation.residuals import residual_report
    from kpi_calib_ros.core.estimation.robust import OutlierSettings, robust_identify
    cell_sigma, stated, noise = np.full(3, 20e-6), 10e-6, 20.9e-6

    def fit(d, free=None, **kw):
        return identify(cm.model, d, cell_sigma, cm.q_work, **kw)
    p_true, q, rng = campaign(cm, 61, 120)
    clean = cm.model.predict(p_true, q)
    data = Measurements(q=q, eta=clean + rng.normal(size=clean.shape) * noise,
                        sigma=np.full(clean.shape, stated))
    robust = robust_identify(cm.model, data, cell_sigma, fit, 'linear',
                             OutlierSettings(exclude=False))
    report = residual_report(cm.model, data, robust.result)
    for sigma_hat in (robust.sigma_robust, report.sigma_robust_m):
        assert abs(sigma_hat / noise - 1) < 0.1, sigma_hat
    assert abs(robust.sigma_ratio / (noise / stated) - 1) < 0.1
    assert robust.sigma_stated == pytest.approx(stated) == report.sigma_stated_m
    # Below the 2× of a warning; one that warns names the points' σ, not noise.sigma.
    from kpi_calib_ros.core.estimation.robust import sigma_warning, stated_source
    assert not report.sigma_warning and not robust.warnings
    assert "stated the points' own stated sigma (10 µm)" in sigma_warning(
        25e-6, report.sigma_stated_m, stated_source(data))


def test_validation_holds_new_points_in_their_own_sigma(cm, cell):
    """20 robots, each calibrated and then validated on a new campaign whose points state
    their σ: the validation χ² p-values are uniform (KS); with the cell's 20 µm for the
    new points it fails most."""
    from kpi_calib_ros.core.diagnosis.validation import validate
    lower, upper = np.full(6, -np.inf), np.full(6, np.inf)
    own, single = [], []
    for seed in range(20):
        p_true, q, rng = campaign(cm, 200 + seed, 60)
        result = identify(cm.model, measure(cm, p_true, q, rng), cell.sigma, cm.q_work)
        idx = cm.model.params.indices(result.estimated)
        new = measure(cm, p_true, random_configurations(cm.model, p_true, 30, rng), rng)
        own.append(validate(cm.model, result.values, idx, result.covariance, cell.sigma, new,
                            lower, upper).p_value)
        single.append(validate(cm.model, result.values, idx, result.covariance, cell.sigma,
                               Measurements(q=new.q, eta=new.eta), lower, upper).p_value)
    assert scipy.stats.kstest(own, 'uniform').pvalue > 0.01, np.round(own, 3)
    assert np.mean(np.array(single) < 0.01) > 0.5, np.round(single, 3)


def test_out_of_sample_error_holds_the_points_own_sigma(cm):
    """One robot and design, 30 draws, the cell stating 5 µm: the predicted like-measured
    error of a new measurement equals the mean true square error ‖h_true − ĥ‖² + Σσ_i²
    (the points' own σ, 22-35 µm) at the measured poses."""
    from kpi_calib_ros.core.diagnosis.out_of_sample import out_of_sample_error
    p_true, q, _ = campaign(cm, 21)
    rng = np.random.default_rng(22)
    predicted, true = [], []
    for _ in range(30):
        data = measure(cm, p_true, q, rng)
        result = identify(cm.model, data, np.full(3, 5e-6), cm.q_work)
        oos = out_of_sample_error(cm.model, data, result, domains=('like_measured',))
        predicted.append(oos.domains['like_measured'].rms_m ** 2)
        miss = cm.model.predict(p_true, q) - cm.model.predict(result.values, q)
        true.append(float(np.mean(np.sum(miss ** 2, axis=1)))
                    + float(np.mean(np.sum(data.sigma ** 2, axis=1))))
    ratio = np.mean(predicted) / np.mean(true)
    error = (np.std(predicted) + np.std(true)) / np.mean(true) / np.sqrt(30)
    assert abs(ratio - 1) < 3 * error + 0.02, (ratio, error)


UR10 = UR10_DATA
HERE = Path(__file__).resolve().parent / 'data'


def test_import_csv_carries_the_table_sigma_to_identify(tmp_path, capsys):
    """A UR10 table with the tracker's σ per point (mm): import-csv writes it beside each
    point on '<point topic>/sigma' (Vector3Stamped, same stamp and frame id), and the
    measurements identify reads carry it in m on the point rows (rotation rows: NaN, the
    cell's σ); identify weighs the point rows by exactly those."""
    table = tmp_path / 'cubes.csv'
    lines = (UR10 / 'Series_D' / 'measurements_iso_cubes.csv').read_bytes().split(b'\r\n')
    table.write_bytes(b'\r\n'.join([lines[0], *[x for x in lines[1:] if x][:30]]) + b'\r\n')
    doc = yaml.safe_load((HERE / 'ipa_ur10_mapping.yaml').read_text())
    del doc['stamp_columns']
    doc['markers']['tmac']['sigma'] = ['measurement_std_x', 'measurement_std_y',
                                       'measurement_std_z']
    mapping = tmp_path / 'mapping.yaml'
    mapping.write_text(yaml.safe_dump(doc))
    bag = tmp_path / 'cubes.mcap'
    assert main(['import-csv', str(table), '--mapping', str(mapping), '--out', str(bag)]) == 0
    assert 'written to /laser_tracker/point/sigma: identify weighs' in capsys.readouterr().out
    header = lines[0].decode().split(';')
    rows = [x.decode().split(';') for x in lines[1:] if x][:30]
    expected = np.array([[float(r[header.index(f'measurement_std_{a}')].replace(',', '.'))
                          for a in 'xyz'] for r in rows]) * 1e-3
    with open(bag, 'rb') as f:
        messages = [(channel.topic, m) for _, channel, _, m in make_reader(
            f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    sigma_messages = [m for t, m in messages if t == point_sigma_topic(DEFAULT_POINT_TOPIC)]
    poses = [m for t, m in messages if t == DEFAULT_POSE_TOPIC]
    assert [(m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id)
            for m in sigma_messages] == [(m.header.stamp.sec, m.header.stamp.nanosec,
                                         m.header.frame_id) for m in poses]
    np.testing.assert_allclose([[m.vector.x, m.vector.y, m.vector.z] for m in sigma_messages],
                               expected, rtol=1e-12)

    cm = build_cell_model(load_cell(HERE / 'ipa_ur10_cell.yaml'))
    data, _ = measurements_from_bag(cm, bag)
    points = np.asarray(data.reflector) < cm.model.n_reflectors
    np.testing.assert_allclose(data.sigma[points], expected, rtol=1e-12)
    assert np.isnan(data.sigma[~points]).all() and (~points).sum() == 30
    start, _ = registered_start(cm, data)
    result = identify(cm.model, data, cm.cell.sigma, cm.q_work, p0=start,
                      free=[n for n in cm.model.params.names if n.startswith('base.')])
    np.testing.assert_allclose(result.point_sigma[points], expected, rtol=1e-12)
    np.testing.assert_allclose(result.point_sigma[~points],
                               np.broadcast_to(cm.cell.sigma, ((~points).sum(), 3)))


def test_a_bag_without_the_sigma_topic_takes_the_cell_sigma(tmp_path):
    """A recording with no '<point topic>/sigma' (the node's, a simulated bag): no row
    states a σ, every row is weighed by the cell's noise.sigma as before."""
    bag = tmp_path / 'run.mcap'
    assert main(['simulate', '--cell', str(DEFAULT_CELL), '--n', '20', '--out', str(bag),
                 '--seed', '1']) == 0
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    data, _ = measurements_from_bag(cm, bag)
    assert len(data) == 20 and data.sigma is None
    assert identify(cm.model, data, cm.cell.sigma, cm.q_work).point_sigma is None


def test_a_non_positive_table_sigma_is_exit_2_naming_line_and_column(tmp_path, capsys):
    table = tmp_path / 't.csv'
    table.write_text('j1;j2;j3;j4;j5;j6;x;y;z;sx;sy;sz\n'
                     '0;0;0;0;0;0;1;2;3;0.01;0.01;0.01\n0;0;0;0;0;0;1;2;3;0.01;0;0.01\n')
    mapping = tmp_path / 'm.yaml'
    mapping.write_text(yaml.safe_dump({
        'frame_id': 'laser_tracker', 'point_unit': 'mm',
        'joints': {n: f'j{i + 1}' for i, n in enumerate(cm_joint_names())},
        'markers': {'r': {'position': ['x', 'y', 'z'], 'sigma': ['sx', 'sy', 'sz']}}}))
    assert main(['import-csv', str(table), '--mapping', str(mapping), '--out',
                 str(tmp_path / 'o.mcap')]) == 2
    err = capsys.readouterr().err
    assert 'line 3' in err and "'sy'" in err and 'sigma' in err


def cm_joint_names() -> list[str]:
    return list(build_cell_model(load_cell(DEFAULT_CELL)).joint_names)


def test_a_sequential_campaign_keeps_the_stated_sigma_of_its_rows(cm):
    """Rows appended to a campaign keep their stated σ; rows without one get NaN (the
    cell's σ), never a σ of another row."""
    from kpi_calib_ros.core.campaigns.sequential import _concatenate
    p_true, q, rng = campaign(cm, 6, 6)
    a = measure(cm, p_true, q[:4], rng)
    b = Measurements(q=q[4:], eta=cm.model.predict(p_true, q[4:]))
    both = _concatenate(a, b)
    np.testing.assert_array_equal(both.sigma[:4], a.sigma)
    assert np.isnan(both.sigma[4:]).all()
    assert _concatenate(b, b).sigma is None

"""Joint-reading noise stated in the cell (noise.joint_sigma) carried into every point's
covariance Σ_i = σ²I + J_q Σ_q J_qᵀ: χ², the TCP std and the diagnosis, on simulated
campaigns whose joint readings carry 0.03° of noise."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.stats

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.diagnosis.verdict import diagnose, equivalent_joint_sigma
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.precision import honest_precision, precision_statement
from kpi_calib_ros.core.measurement.weighting import unweighted, weighted_residuals, weighted_rows
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell

JOINT_SIGMA = np.deg2rad(0.03)   # a controller read-back (the real-data issue: 0.02-0.05°)
POSES = 30


@pytest.fixture(scope='module')
def cell(cm):
    """The built-in cell file as loaded (conftest's shared model's)."""
    return cm.cell


@pytest.fixture(scope='module')
def exact(cm):
    """The cell as written: exact joint readings (conftest's shared model)."""
    return cm


@pytest.fixture(scope='module')
def stated(cell):
    """The cell with noise.joint_sigma: 0.03° on every joint."""
    return build_cell_model(dataclasses.replace(cell, joint_sigma=JOINT_SIGMA))


def campaign(cm, seed: int, poses: int = POSES):
    rng = np.random.default_rng(seed)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, p_true, poses, rng)
    return p_true, q, rng


def test_whitening_gives_the_identity_covariance(stated, cell):
    """W_i Σ_i W_iᵀ = I with Σ_i = σ²I + J_q Σ_q J_qᵀ, and weighted/unweighted invert."""
    p_true, q, _ = campaign(stated, 0, 5)
    w = stated.model.whitening(p_true, q, cell.sigma)
    jq = stated.model.joint_jacobian(p_true, q) * JOINT_SIGMA
    cov = np.einsum('nak,nbk->nab', jq, jq) + np.diag(cell.sigma ** 2)
    np.testing.assert_allclose(np.einsum('nab,nbc,ndc->nad', w, cov, w),
                               np.broadcast_to(np.eye(3), (5, 3, 3)), atol=1e-9)
    r = np.random.default_rng(1).normal(size=(5, 3)) * 1e-4
    np.testing.assert_allclose(unweighted(weighted_residuals(r, w), w), r, atol=1e-15)
    np.testing.assert_allclose(weighted_residuals(r, w),
                               weighted_rows(r[:, :, None], w)[:, 0])


@pytest.mark.slow
def test_chi2_p_values_are_uniform_with_the_joint_noise_stated(exact, stated, cell):
    """100 campaigns with 0.03° joint noise: stated, χ²'s p-values are uniform (KS); unstated,
    χ² rejects every one (the joint noise moves the points by ~0.5 mm, σ is 20 µm)."""
    p_stated, p_unstated = [], []
    for seed in range(100):
        p_true, q, rng = campaign(exact, seed)
        data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng, JOINT_SIGMA)
        p_stated.append(identify(stated.model, data, cell.sigma, stated.q_work).p_value)
        p_unstated.append(identify(exact.model, data, cell.sigma, exact.q_work).p_value)
    assert scipy.stats.kstest(p_stated, 'uniform').pvalue > 0.01, np.round(p_stated, 3)
    assert max(p_unstated) < 0.01


@pytest.mark.slow
def test_diagnosis_suggests_no_effect_with_the_joint_noise_stated(exact, stated, cell):
    """The joint noise stated: the model is adequate and no effect is proposed. Unstated, the
    verdict names the joint readings and the noise they would need (0.03° ± 30 %)."""
    p_true, q, rng = campaign(exact, 3, 40)
    data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng, JOINT_SIGMA)
    result = identify(stated.model, data, cell.sigma, stated.q_work)
    diagnosis = diagnose(stated.model, data, result)
    assert diagnosis.model_adequate, diagnosis.verdict
    assert diagnosis.best is None
    assert not any(c.significant for c in diagnosis.candidates)
    assert 'joint readings' not in diagnosis.verdict
    plain = identify(exact.model, data, cell.sigma, exact.q_work)
    verdict = diagnose(exact.model, data, plain).verdict
    assert 'The joint readings may be the cause' in verdict and 'noise.joint_sigma' in verdict
    assert equivalent_joint_sigma(exact.model, data, plain) == pytest.approx(JOINT_SIGMA,
                                                                              rel=0.3)


@pytest.mark.slow
def test_tcp_std_matches_monte_carlo_with_joint_noise(exact, stated, cell):
    """One robot and design, 100 draws of tracker and joint noise: the stated TCP std
    (sqrt(trace) at every working pose) equals the Monte Carlo spread within 20 %."""
    p_true, q, _ = campaign(exact, 11)
    rng = np.random.default_rng(12)
    tcp, stated_trace = [], []
    for _ in range(100):
        data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng, JOINT_SIGMA)
        result = honest_precision(identify(stated.model, data, cell.sigma, stated.q_work))
        tcp.append(result.tcp)
        stated_trace.append(np.trace(result.tcp_covariance, axis1=1, axis2=2))
    tcp = np.array(tcp)                                     # (100, t, 3)
    monte_carlo = np.sqrt(np.sum(np.var(tcp, axis=0, ddof=1), axis=1))
    predicted = np.sqrt(np.mean(stated_trace, axis=0))
    np.testing.assert_allclose(predicted / monte_carlo, 1.0, atol=0.2)


def test_unstated_joint_noise_warning_names_the_joint_readings(exact, stated, cell):
    """The χ² warning of the std (files, summary, node) names the joint readings as a cause
    when the cell states none, and not when it states them."""
    p_true, q, rng = campaign(exact, 5)
    data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng, JOINT_SIGMA)
    plain = honest_precision(identify(exact.model, data, cell.sigma, exact.q_work))
    assert plain.covariance_scale > 10
    text = precision_statement(plain.covariance_scale, plain.joint_sigma)
    assert 'joint readings' in text and 'noise.joint_sigma' in text
    with_noise = identify(stated.model, data, cell.sigma, stated.q_work)
    np.testing.assert_allclose(with_noise.joint_sigma, np.full(6, JOINT_SIGMA))
    assert 'joint readings' not in precision_statement(9.0, with_noise.joint_sigma)


def test_no_joint_noise_keeps_every_figure(exact, cell):
    """joint_sigma 0 on every joint gives the same fit as none (the weights reduce to 1/σ)."""
    zero = build_cell_model(dataclasses.replace(cell, joint_sigma=0.0))
    p_true, q, rng = campaign(exact, 2, 20)
    data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng)
    a = identify(exact.model, data, cell.sigma, exact.q_work)
    b = identify(zero.model, data, cell.sigma, zero.q_work)
    np.testing.assert_allclose(b.chi2, a.chi2, rtol=1e-9)
    np.testing.assert_allclose(b.tcp_covariance, a.tcp_covariance, rtol=1e-7)


@pytest.mark.parametrize('value, key', [
    (-1e-4, 'noise.joint_sigma'), (0.5, 'noise.joint_sigma'), ('small', 'noise.joint_sigma'),
    ({'joint_2': 0.2}, 'noise.joint_sigma.joint_2')])
def test_bad_joint_sigma_names_the_key(tmp_path, value, key):
    import yaml
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['noise']['joint_sigma'] = value
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    path = tmp_path / 'cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=key.replace('.', r'\.')):
        load_cell(path)


def test_joint_sigma_is_matched_by_name(cell):
    cm = build_cell_model(dataclasses.replace(cell, joint_sigma={'joint_5': 1e-4,
                                                                 'joint_2': 2e-4}))
    np.testing.assert_allclose(cm.model.joint_sigma, [0, 2e-4, 0, 0, 1e-4, 0])
    with pytest.raises(ConfigError, match='unknown joint'):
        build_cell_model(dataclasses.replace(cell, joint_sigma={'elbow': 1e-4}))


def test_out_of_sample_prediction_holds_the_joint_noise(exact, stated, cell):
    """One robot and design, 30 draws: the predicted like-measured error of a new
    measurement (tracker and joint noise, parameter error) equals the mean true square error
    ‖h_true − ĥ‖² + Σσ² + tr(J_q Σ_q J_qᵀ) at the measured poses."""
    from kpi_calib_ros.core.diagnosis.out_of_sample import out_of_sample_error
    p_true, q, _ = campaign(exact, 21)
    rng = np.random.default_rng(22)
    jq = stated.model.joint_jacobian(p_true, q) * JOINT_SIGMA
    noise = float(np.sum(cell.sigma ** 2) + np.mean(np.sum(jq ** 2, axis=(1, 2))))
    predicted, true = [], []
    for _ in range(30):
        data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng, JOINT_SIGMA)
        result = identify(stated.model, data, cell.sigma, stated.q_work)
        oos = out_of_sample_error(stated.model, data, result, domains=('like_measured',))
        predicted.append(oos.domains['like_measured'].rms_m ** 2)
        miss = exact.model.predict(p_true, q) - stated.model.predict(result.values, q)
        true.append(float(np.mean(np.sum(miss ** 2, axis=1))) + noise)
    ratio = np.mean(predicted) / np.mean(true)
    error = (np.std(predicted) + np.std(true)) / np.mean(true) / np.sqrt(30)
    assert abs(ratio - 1) < 3 * error + 0.02, (ratio, error)
    assert noise > 20 * np.sum(cell.sigma ** 2)   # the joint noise is what is predicted


def test_validation_holds_new_points_with_the_joint_noise(exact, stated, cell):
    """A calibration with the joint noise stated predicts new points of the same robot,
    read with the same joint noise, within its own errors: the validation χ² holds over
    20 new campaigns at the level's rate (p-values uniform, KS); without the J_q Σ_q J_qᵀ
    term it fails every one."""
    from kpi_calib_ros.core.diagnosis.validation import validate
    p_true, q, rng = campaign(exact, 31)
    data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng, JOINT_SIGMA)
    result = identify(stated.model, data, cell.sigma, stated.q_work)
    idx = stated.model.params.indices(result.estimated)
    lower, upper = np.full(6, -np.inf), np.full(6, np.inf)
    with_noise, without = [], []
    for seed in range(20):
        p_new, q_new, rng_new = campaign(exact, 100 + seed)
        new = simulate_measurements(exact.model, p_true, q_new, cell.sigma, rng_new,
                                    JOINT_SIGMA)
        with_noise.append(validate(stated.model, result.values, idx, result.covariance,
                                   cell.sigma, new, lower, upper).p_value)
        without.append(validate(exact.model, result.values, idx, result.covariance,
                                cell.sigma, new, lower, upper).p_value)
    assert scipy.stats.kstest(with_noise, 'uniform').pvalue > 0.01, np.round(with_noise, 3)
    assert max(without) < 0.01


@pytest.mark.slow
def test_simulate_and_identify_carry_the_cell_joint_noise(tmp_path, capsys):
    """kpi-calib simulate reads the joints with the cell's noise.joint_sigma; identify with
    that cell accepts the model and writes the joint noise it carried; with the joint
    noise left out of the cell the χ² warning names the joint readings."""
    import yaml

    from kpi_calib_ros.cli import main
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    plain = tmp_path / 'plain.yaml'
    plain.write_text(yaml.safe_dump(doc))
    doc['noise']['joint_sigma'] = float(JOINT_SIGMA)
    noisy = tmp_path / 'noisy.yaml'
    noisy.write_text(yaml.safe_dump(doc))
    bag = tmp_path / 'run.mcap'
    assert main(['simulate', '--cell', str(noisy), '--n', '40', '--out', str(bag),
                 '--seed', '4']) == 0
    assert main(['identify', '--cell', str(noisy), '--bag', str(bag), '--out',
                 str(tmp_path / 'a')]) == 0
    cal = yaml.safe_load((tmp_path / 'a' / 'calibration.yaml').read_text())
    assert cal['model_adequacy']['adequate'], cal['model_adequacy']
    assert cal['noise_joint_sigma_rad'] == pytest.approx([JOINT_SIGMA] * 6)
    capsys.readouterr()
    assert main(['identify', '--cell', str(plain), '--bag', str(bag), '--out',
                 str(tmp_path / 'b')]) == 0
    out = capsys.readouterr().out
    assert 'WARNING: std scaled by chi2/dof' in out and 'noise.joint_sigma' in out
    cal = yaml.safe_load((tmp_path / 'b' / 'calibration.yaml').read_text())
    assert cal['noise_joint_sigma_rad'] is None and not cal['model_adequacy']['adequate']


@pytest.mark.parametrize('loss', ['linear', 'huber'])
def test_robust_statistics_take_the_joint_noise_as_stated(exact, stated, cell, loss):
    """With the joint noise stated, the robust σ̂ is the tracker σ (within 1.5×, no σ
    warning) and no good point is an outlier, where the metric residuals (0.5 mm of joint
    noise) would read as a σ 15-20× the stated one; the residual report agrees."""
    from kpi_calib_ros.core.estimation.residuals import residual_report
    from kpi_calib_ros.core.estimation.robust import OutlierSettings, robust_identify

    def fit(d, free=None, **kw):
        return identify(stated.model, d, cell.sigma, stated.q_work, **kw)
    for seed in range(3):
        p_true, q, rng = campaign(exact, 40 + seed, 60)
        data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng, JOINT_SIGMA)
        robust = robust_identify(stated.model, data, cell.sigma, fit, loss, OutlierSettings())
        assert 1 / 1.5 < robust.sigma_robust / cell.sigma[0] < 1.5, robust.sigma_robust
        assert not robust.warnings and not robust.excluded, robust.warnings
        report = residual_report(stated.model, data, robust.result)
        assert not report.sigma_warning and not report.outlier.any()
        metric = np.sqrt(np.mean(robust.result.residuals ** 2))
        assert metric > 10 * cell.sigma[0]

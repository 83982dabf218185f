"""Maximum a posteriori identification: a Gaussian prior as extra residual rows."""
from __future__ import annotations

import numpy as np
import pytest

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.prior import Prior, drift_widened, tolerance_prior
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.calibration_file import prior_from_calibration
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.results import calibration_to_dict

SIGMA = 20e-6


@pytest.fixture(scope='module')
def campaign(cell):
    rng = np.random.default_rng(7)
    p_true = true_parameters(cell.model.params, rng)
    q = random_configurations(cell.model, cell.model.params.nominal, 40, rng)
    data = simulate_measurements(cell.model, p_true, q, SIGMA, rng)
    return data, identify(cell.model, data, SIGMA, cell.q_work)


def _relative(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def test_a_very_weak_prior_gives_the_plain_fit(cell, campaign):
    data, plain = campaign
    weak = tolerance_prior(cell.model.params, 1e3, 1e3, 1e3)
    result = identify(cell.model, data, SIGMA, cell.q_work, prior=weak)
    assert result.converged and result.dof == plain.dof
    pred = cell.model.predict(result.values, data.q)
    pred_plain = cell.model.predict(plain.values, data.q)
    # Predicted points relative to their size (the residuals themselves agree to the
    # Gauss-Newton's own stopping precision, about 1e-6 of the 20 µm noise).
    assert _relative(pred, pred_plain) < 1e-9
    assert _relative(result.tcp, plain.tcp) < 1e-9
    assert _relative(result.tcp_covariance, plain.tcp_covariance) < 1e-9
    assert result.chi2 == pytest.approx(plain.chi2, rel=1e-5)


def test_b_prior_on_a_parameter_the_data_cannot_see_is_the_posterior(cell, campaign):
    data, plain = campaign
    assert plain.dropped, 'the full model must have parameters the data cannot see'
    name = plain.dropped[0].name
    mean, std = plain.value(name) + 3e-4, 2e-4
    prior = Prior((name,), np.array([mean]), np.array([[std ** 2]]))
    result = identify(cell.model, data, SIGMA, cell.q_work, prior=prior)
    assert name in result.estimated  # determined by the prior: identified
    assert result.value(name) == pytest.approx(mean, rel=1e-6)
    assert result.std_of(name) == pytest.approx(std, rel=1e-6)
    # What the data see does not move: the predicted points and the TCP stay.
    assert _relative(cell.model.predict(result.values, data.q),
                     cell.model.predict(plain.values, data.q)) < 1e-9
    assert _relative(result.tcp_covariance, plain.tcp_covariance) < 1e-6
    assert result.dof == plain.dof


def _drawn_from_the_prior(cell, seed, poses):
    """A tolerance prior (0.1 mm, 0.1 mrad), its rng, ``poses`` random configurations and
    a function drawing a true robot from the prior (the rng's next normals)."""
    params = cell.model.params
    prior = tolerance_prior(params, 1e-4, 1e-4, 1e-4)
    rng = np.random.default_rng(seed)
    q = random_configurations(cell.model, params.nominal, poses, rng)
    idx = params.indices(list(prior.names))
    chol = np.linalg.cholesky(prior.covariance)

    def draw():
        p_true = np.array(params.nominal, float)
        p_true[idx] = prior.mean + chol @ rng.normal(size=len(idx))
        return p_true
    return prior, rng, q, draw


@pytest.mark.slow
def test_c_posterior_covariance_matches_monte_carlo_over_prior_and_noise(cell):
    # 8 poses give 24 equations for 51 parameters: the prior is what makes it solvable.
    params = cell.model.params
    prior, rng, q, draw = _drawn_from_the_prior(cell, seed=11, poses=8)
    tcp_err, p_err, chi2, first = [], [], [], None
    for _ in range(300):
        p_true = draw()
        data = simulate_measurements(cell.model, p_true, q, SIGMA, rng)
        result = identify(cell.model, data, SIGMA, cell.q_work, prior=prior)
        assert result.converged
        first = first or result
        assert result.estimated == first.estimated
        true_tcp = cell.model.predict(p_true, cell.q_work)
        tcp_err.append(result.tcp - true_tcp)
        p_err.append((result.values - p_true)[params.indices(list(result.estimated))])
        chi2.append(result.chi2)
    assert len(first.estimated) == len(params.names)  # everything identified
    tcp_err = np.array(tcp_err)
    empirical = np.einsum('nti,ntj->tij', tcp_err, tcp_err) / len(tcp_err)
    for emp, stated in zip(empirical, first.tcp_covariance):
        assert np.trace(emp) == pytest.approx(np.trace(stated), rel=0.15)
    p_err = np.array(p_err)
    emp_var = np.mean(p_err ** 2, axis=0)
    # Parameters the data inform (posterior well below prior) and those they do not.
    ratio = emp_var / first.std ** 2
    assert np.median(ratio) == pytest.approx(1.0, rel=0.15)
    mahal = np.einsum('ni,ij,nj->n', p_err, np.linalg.inv(first.covariance), p_err)
    assert np.mean(mahal) == pytest.approx(len(first.estimated), rel=0.15)
    # χ² of the data rows against the effective dof.
    assert np.mean(chi2) == pytest.approx(first.dof, rel=0.15)


def test_tolerance_prior_leaves_the_placement_free(cell):
    params = cell.model.params
    prior = tolerance_prior(params, 1e-3, 2e-3, 3e-3)
    assert not any(n.startswith(('base.', 'reflector')) for n in prior.names)
    std = dict(zip(prior.names, prior.std))
    joint = cell.robot.joints[1].name
    assert std[f'{joint}.offset'] == pytest.approx(3e-3)
    assert std[f'{joint}.placement.tx'] == pytest.approx(1e-3)
    assert std[f'{joint}.placement.rx'] == pytest.approx(2e-3)
    assert len(prior.names) == 7 * cell.robot.n_joints


def test_calibration_document_round_trips_into_a_widened_prior(cell, campaign):
    _, plain = campaign
    doc = calibration_to_dict(plain)
    prior = prior_from_calibration(doc)
    robot = [n for n in plain.estimated if not n.startswith(('base.', 'reflector'))]
    assert list(prior.names) == robot
    sub = plain.covariance[np.ix_(*[[plain.estimated.index(n) for n in robot]] * 2)]
    assert np.allclose(prior.covariance, sub)
    assert np.allclose(prior.mean, [plain.value(n) for n in robot])
    x = next(n for n in robot if n[-3:] in ('.tx', '.ty', '.tz'))
    off = next(n for n in robot if n.endswith(('.offset', '.rx', '.ry', '.rz')))
    wide = drift_widened(prior, 4.0, {x: 0.5}, length_rate=1e-5, angle_rate=2e-5)
    grow = np.diag(wide.covariance) - np.diag(prior.covariance)
    assert grow[prior.names.index(x)] == pytest.approx(4.0 * (1e-5 * 0.5) ** 2)
    assert grow[prior.names.index(off)] == pytest.approx(4.0 * (2e-5) ** 2)
    with pytest.raises(DataError, match='parameter_covariance'):
        prior_from_calibration({'parameters': doc['parameters']})


def test_bad_priors_are_refused(cell):
    with pytest.raises(DataError, match='positive definite'):
        Prior(('a',), np.zeros(1), np.zeros((1, 1)))
    with pytest.raises(DataError, match='unknown parameter'):
        Prior(('nope',), np.zeros(1), np.eye(1)).rows(cell.model.params)


@pytest.fixture(scope='module')
def run_bag(tmp_path_factory):
    from kpi_calib_ros.cli import main
    bag = tmp_path_factory.mktemp('run') / 'run.mcap'
    assert main(['simulate', '--cell', str(DEFAULT_CELL), '--n', '40', '--out', str(bag),
                 '--seed', '3']) == 0
    return bag


@pytest.mark.slow
def test_previous_calibration_as_prior_from_the_cli(run_bag, tmp_path, capsys):
    import yaml

    from kpi_calib_ros.app.measurements import measurements_from_bag
    from kpi_calib_ros.cli import main
    cell = str(DEFAULT_CELL)
    assert main(['identify', '--cell', cell, '--bag', str(run_bag), '--out',
                 str(tmp_path / 'old')]) == 0
    old = yaml.safe_load((tmp_path / 'old' / 'calibration.yaml').read_text())
    data, _ = measurements_from_bag(build_cell_model(load_cell(DEFAULT_CELL)), run_bag)
    assert old['identified_at_ns'] == int(np.max(data.stamps_ns))
    capsys.readouterr()
    assert main(['identify', '--cell', cell, '--bag', str(run_bag), '--out',
                 str(tmp_path / 'new'), '--prior', str(tmp_path / 'old' / 'calibration.yaml'),
                 '--drift-per-hour', '0,0']) == 0
    assert 'prior calibration widened for' in capsys.readouterr().out
    new = yaml.safe_load((tmp_path / 'new' / 'calibration.yaml').read_text())
    assert new['prior']['source'].endswith('calibration.yaml')
    # The same data twice: the prior (a marginal of the same information) at most doubles
    # the information, so the TCP variance shrinks, but by no more than half.
    before, after = old['tcp'][0]['trace_m2'], new['tcp'][0]['trace_m2']
    assert 0.5 * before <= after < before
    assert main(['identify', '--cell', cell, '--bag', str(run_bag), '--out',
                 str(tmp_path / 'bad'), '--prior', str(tmp_path / 'missing.yaml')]) == 2
    assert '--prior' in capsys.readouterr().err


def test_cell_prior_key_is_validated(tmp_path):
    import yaml

    from kpi_calib_ros.core.errors import ConfigError
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['identification'] = {'prior': {'translation': 1e-3, 'rotation': 1e-3, 'offset': 2e-3}}
    path = tmp_path / 'cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    assert load_cell(path).identification.prior == (1e-3, 1e-3, 2e-3)
    doc['identification']['prior'] = {'translation': 1e-3, 'rotation': -1.0, 'offset': 1e-3}
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match='identification.prior.rotation'):
        load_cell(path)
    doc['identification']['prior'] = {'translation': 1e-3}
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match='identification.prior'):
        load_cell(path)


def test_cross_validation_holds_out_whole_poses(cell, campaign):
    from kpi_calib_ros.core.diagnosis.model_selection import cross_validated_level_rms, level_free
    from kpi_calib_ros.core.measurement.data import Measurements
    data, _ = campaign
    # Each pose measured twice (as by two reflectors at the same joint values).
    twice = Measurements(q=np.repeat(data.q, 2, axis=0), eta=np.repeat(data.eta, 2, axis=0))
    trained: list[set] = []
    rows: list[int] = []

    def fit(d, free):
        trained.append({tuple(row) for row in d.q})
        rows.append(len(d.q))
        return identify(cell.model, d, SIGMA, cell.q_work, free=free)

    free = level_free(cell.model.params, 'joint_offsets')
    rms = cross_validated_level_rms(cell.model, twice, fit, free, folds=5)
    assert rms is not None and len(trained) == 5
    every = {tuple(row) for row in twice.q}
    for train, n_rows in zip(trained, rows):
        # Both rows of every training pose are in the training set (none split off).
        assert n_rows == 2 * len(train) and every - train
    assert set().union(*(every - t for t in trained)) == every


@pytest.mark.slow
def test_d_tolerances_weigh_against_the_noise_the_data_show(cell):
    """The stated σ is 5x too small: with it the data outweigh the tolerance prior 25x too
    much. Balanced (core.precision.balanced_prior) the prior is tightened by the χ²/dof
    the residuals show (≈ 25), the estimate is the posterior of the true noise (smaller
    TCP error than the unbalanced MAP) and the scaled covariance matches Monte Carlo."""
    from kpi_calib_ros.core.estimation.precision import balanced_prior, honest_precision
    prior, rng, q, draw = _drawn_from_the_prior(cell, seed=12, poses=12)
    true_sigma = 5 * SIGMA
    scales, err_bal, err_plain, stated = [], [], [], []
    for _ in range(100):
        p_true = draw()
        data = simulate_measurements(cell.model, p_true, q, true_sigma, rng)
        true_tcp = cell.model.predict(p_true, cell.q_work)

        def fit(pr, data=data):
            return identify(cell.model, data, SIGMA, cell.q_work, prior=pr)
        _, scale, balanced = balanced_prior(fit, prior)
        plain = fit(prior)
        assert balanced.converged and plain.converged
        scales.append(scale)
        balanced = honest_precision(balanced)
        err_bal.append(np.sum((balanced.tcp - true_tcp) ** 2))
        err_plain.append(np.sum((plain.tcp - true_tcp) ** 2))
        stated.append(np.trace(balanced.tcp_covariance[0]))
    # χ²/dof at the balance: the noise the data show, (5 σ)² / σ²
    assert np.median(scales) == pytest.approx(25.0, rel=0.15)
    # The posterior of the true noise predicts the TCP better than the unbalanced MAP.
    assert np.mean(err_bal) < 0.8 * np.mean(err_plain)
    # ... and states its error: E‖ŝ − s‖² against tr C_s (scaled by χ²/dof).
    assert np.mean(err_bal) == pytest.approx(np.mean(stated), rel=0.2)


def test_few_clean_poses_under_a_prior_name_no_outlier_and_no_misfit(cell):
    """Ten clean poses re-identified under a prior (the next station of a calibration): the
    prior determines most directions, so no point carries the leverage the data alone would
    give it. The outlier test reads each point's leverage with the prior and against the
    larger of σ̂ and the stated σ: none named over 20 seeds. Before, the leverage of the data
    alone (near 1 for every point) and a σ̂ of half the stated σ made points of 0.3 to 2.6 σ
    "outliers beyond 4 σ̂" and "model misfit" in 80 of 80 runs of a Baxter's second station."""
    from kpi_calib_ros.app.identify import calibrate_cell
    flagged = []
    for seed in range(20):
        prior, rng, q, draw = _drawn_from_the_prior(cell, 300 + seed, 10)
        data = simulate_measurements(cell.model, draw(), q, SIGMA, rng)
        robust = calibrate_cell(cell, data, model='geometric', prior=prior).robust
        if list(robust.outliers) or list(robust.misfit):
            flagged.append((seed, list(robust.outliers), list(robust.misfit)))
    assert flagged == []

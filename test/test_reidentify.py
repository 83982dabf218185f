"""Re-identification over work cycles: a previous calibration as prior, the cost test,
change detection."""
from __future__ import annotations

import numpy as np
import pytest

from kpi_calib_ros.core.estimation.gauss_newton import FTOL, STATISTICAL, Tolerances, gauss_newton
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL

SIGMA = 20e-6


@pytest.fixture(scope='module')
def truth(cell):
    rng = np.random.default_rng(11)
    return true_parameters(cell.model.params, rng), rng


def test_the_cost_test_stops_within_ftol_of_the_minimum(cell, truth):
    p_true, rng = truth
    q = random_configurations(cell.model, cell.model.params.nominal, 30, rng)
    data = simulate_measurements(cell.model, p_true, q, SIGMA, rng)
    plain = identify(cell.model, data, SIGMA, cell.q_work)
    assert plain.converged and plain.chi2 < 2 * plain.dof
    # The cost test alone, ftol = 1e-3: it holds on the first step that gained and
    # predicted less than 1e-3 of ½χ² with the linear model confirmed (gain ratio > 0.25).
    # From the nominal start (millimetres off) that is a step near the minimum: what is
    # left to gain is below ftol of the cost, not a stop on the way.
    idx = cell.model.params.indices(list(plain.estimated))
    w = np.full((len(q), 3), 1.0 / SIGMA)
    ftol = 1e-3
    p, status, message, used = gauss_newton(
        cell.model, cell.model.params.nominal.copy(), idx, data.q, data.eta, None, w, 50,
        Tolerances(ftol=ftol, gtol=0.0, xtol=0.0, pred_tol=0.0, roundoff=0.0, stat_tol=0.0))
    chi2 = float(np.sum(((data.eta - cell.model.predict(p, data.q)) / SIGMA) ** 2))
    print(message, used)
    assert status == FTOL and message.startswith('converged: cost test')
    assert used > 1  # the nominal start is far from the minimum: a step or more first
    assert -1e-6 < 0.5 * (chi2 - plain.chi2) < ftol * 0.5 * chi2
    # At the minimum (nothing left to gain) the cost test is convergence.
    again = identify(cell.model, data, SIGMA, cell.q_work, p0=plain.values,
                     tolerances=Tolerances(ftol=1.0, gtol=0.0, xtol=0.0, pred_tol=0.0,
                                           roundoff=0.0))
    assert again.converged and again.status in (FTOL, STATISTICAL)
    assert again.chi2 == pytest.approx(plain.chi2, rel=1e-6)


@pytest.fixture(scope='module')
def first_cycle(cell, truth):
    """A 60-pose calibration (the previous cycle) and its document."""
    from kpi_calib_ros.app.calibration_document import add_robust_sections, calibration_document
    from kpi_calib_ros.app.identify import calibrate_cell
    p_true, _ = truth
    rng = np.random.default_rng(12)
    q = random_configurations(cell.model, cell.model.params.nominal, 60, rng)
    cal = calibrate_cell(cell, simulate_measurements(cell.model, p_true, q, SIGMA, rng))
    assert cal.valid
    return cal, add_robust_sections(calibration_document(cell, cal.result), cal)


def _cycle_data(cell, p, n, seed):
    rng = np.random.default_rng(seed)
    q = random_configurations(cell.model, cell.model.params.nominal, n, rng)
    return simulate_measurements(cell.model, p, q, SIGMA, rng)


def test_the_previous_calibration_in_its_own_gauge_only_adds_information(cell, truth,
                                                                       first_cycle):
    from kpi_calib_ros.app.reidentify import cycle_prior, reidentify
    p_true, _ = truth
    cal, doc = first_cycle
    data = _cycle_data(cell, p_true, 10, 13)
    cp = cycle_prior(cell, doc, data, keep_placement=True, hours=0.0)
    assert set(cp.prior.names) == set(cal.result.estimated)
    out = reidentify(cell, data, cp)
    assert out.change.consistent and out.calibration is not None and out.calibration.valid
    # Same robot, no drift: 10 more poses can only shrink the TCP covariance (before the
    # held parameters were freed again and the TCP std grew from 16 to 49-62 µm).
    before = np.trace(cal.result.tcp_covariance[0])
    after = np.trace(out.calibration.result.tcp_covariance[0])
    assert after < before
    # Started at the prior mean, the MAP fit converges at once.
    assert out.fit.converged and out.fit.iterations <= 10
    err = np.linalg.norm(out.calibration.result.tcp[0]
                         - cell.model.predict(p_true, cell.q_work)[0])
    assert err < 4 * np.sqrt(after)


def test_innovation_chi2_follows_its_distribution_when_the_truth_is_drawn_from_the_prior(
        cell, first_cycle):
    from kpi_calib_ros.app.reidentify import cycle_prior, cycle_start
    from kpi_calib_ros.core.campaigns.change_detection import change_test
    cal, doc = first_cycle
    cp = cycle_prior(cell, doc, None, keep_placement=True, hours=2.0)
    start = cycle_start(cell, _cycle_data(cell, cal.result.values, 10, 0), cp)
    free = [n for n in cell.model.params.names if n in set(cp.allowed)]
    idx = cell.model.params.indices(list(cp.prior.names))
    chol = np.linalg.cholesky(cp.prior.covariance)
    rng = np.random.default_rng(21)
    chi2, dof, alarms, lr = [], set(), 0, []
    trials = 60
    for trial in range(trials):
        p_true = start.copy()
        p_true[idx] = cp.prior.mean + chol @ rng.normal(size=len(idx))
        data = _cycle_data(cell, p_true, 10, 100 + trial)
        fit = identify(cell.model, data, SIGMA, cell.q_work, p0=start, free=free,
                       prior=cp.prior)
        assert fit.converged
        test = change_test(cell.model, data, SIGMA, fit, cp.prior)
        chi2.append(test.chi2)
        dof.add(test.dof)
        alarms += not test.consistent
        lr += [m.lr for m in test.parameters]
    assert len(dof) == 1
    k = dof.pop()
    # E[J] = dof for the linear-Gaussian model; the mean of 60 within 3 std of it.
    assert abs(np.mean(chi2) - k) < 3 * np.sqrt(2 * k / trials)
    assert alarms <= 1  # family-wise α = 1e-3 per cycle: 0.06 expected
    assert np.mean(lr) == pytest.approx(1.0, abs=0.25)  # each LR_j ~ χ²(1)


@pytest.mark.parametrize('kind', ['translation', 'rotation'])
def test_a_bend_is_detected_and_the_moved_parameter_named(cell, truth, first_cycle, kind):
    from kpi_calib_ros.app.reidentify import cycle_prior, reidentify
    p_true, _ = truth
    cal, doc = first_cycle
    names = [n for n in cal.result.estimated if not n.startswith(('base.', 'reflector'))]
    moved = next(n for n in names if ('.placement.t' in n) == (kind == 'translation')
                 and n.startswith('joint_3'))
    size = 1e-3 if kind == 'translation' else 2e-3
    bent = p_true.copy()
    bent[cell.model.params.index(moved)] += size
    data = _cycle_data(cell, bent, 10, 14)
    out = reidentify(cell, data, cycle_prior(cell, doc, data, keep_placement=True, hours=1.0))
    assert out.calibration is None and not out.change.consistent
    top = out.change.moved[0]
    assert top.name == moved
    assert abs(top.shift - size) < 3 * top.shift_std + 0.1 * size
    assert 'CHANGE DETECTED' in out.change.summary() and moved in out.change.summary()


@pytest.mark.slow
def test_identify_with_prior_exits_3_on_a_different_robot_and_keeps_the_calibration(
        tmp_path, capsys):
    import yaml

    from kpi_calib_ros.cli import main
    cell = str(DEFAULT_CELL)
    old_bag, new_bag = tmp_path / 'old.mcap', tmp_path / 'new.mcap'
    assert main(['simulate', '--cell', cell, '--n', '40', '--out', str(old_bag),
                 '--seed', '3']) == 0
    # Another seed draws another true robot: millimetres away, a change.
    assert main(['simulate', '--cell', cell, '--n', '10', '--out', str(new_bag),
                 '--seed', '4']) == 0
    out = tmp_path / 'cal'
    assert main(['identify', '--cell', cell, '--bag', str(old_bag), '--out', str(out)]) == 0
    before = (out / 'calibration.yaml').read_bytes()
    capsys.readouterr()
    assert main(['identify', '--cell', cell, '--bag', str(new_bag), '--out', str(out),
                 '--prior', str(out / 'calibration.yaml')]) == 3
    text = capsys.readouterr()
    assert 'CHANGE DETECTED' in text.out and 'full campaign' in text.out
    assert (out / 'calibration.yaml').read_bytes() == before
    failed = yaml.safe_load((out / 'calibration.failed.yaml').read_text())
    assert failed['valid'] is False and failed['change_test']['consistent'] is False
    assert failed['change_test']['moved'] and failed['change_test']['p_value'] < 1e-3
    assert failed['change_test']['moved'][0]['name'] in text.err
    # The test drawn beside it (what the work cycles tutorial shows).
    assert (out / 'change_test.png').read_bytes()[:4] == b'\x89PNG'
    # The failed cycle is no prior for the next one, nor for a design: refused, exit 2.
    for command in (['identify', '--bag', str(new_bag), '--out', str(tmp_path / 'next')],
                    ['design', '--n', '5', '--out', str(tmp_path / 'design.yaml')]):
        assert main([command[0], '--cell', cell, *command[1:], '--prior',
                     str(out / 'calibration.failed.yaml')]) == 2
        err = capsys.readouterr().err
        assert (f"--prior: {out / 'calibration.failed.yaml'} is not a valid calibration "
                '(valid: false: CHANGE DETECTED') in err
        assert 'give the last valid calibration.yaml' in err
    assert not (tmp_path / 'next').exists() or not any((tmp_path / 'next').iterdir())
    # Nor is it validated: it was never published, so whether it holds is no question.
    assert main(['validate', '--cell', cell, '--calibration',
                 str(out / 'calibration.failed.yaml'), '--bag', str(new_bag), '--out',
                 str(tmp_path / 'validation')]) == 2
    assert (f"--calibration: {out / 'calibration.failed.yaml'} is not a valid calibration "
            '(valid: false: CHANGE DETECTED') in capsys.readouterr().err


def test_design_with_the_prior_predicts_the_map_covariance_of_its_poses(cell, first_cycle):
    from kpi_calib_ros.app.design import design_free
    from kpi_calib_ros.app.reidentify import cycle_prior
    from kpi_calib_ros.core.design.optimum import (
        DesignSettings,
        design_context,
        design_measurements,
    )
    from kpi_calib_ros.core.measurement.data import Measurements
    _, doc = first_cycle
    cp = cycle_prior(cell, doc, None, keep_placement=True, hours=1.0)
    p = cell.model.params.with_values(cp.values)
    settings = DesignSettings(candidates=400, nlp=False)
    rng = np.random.default_rng(3)
    ctx = design_context(cell.design_cell(), rng, settings, prior=cp.prior, p=p,
                         free=design_free(cell, cp.allowed))
    best = design_measurements(cell.design_cell(), 10, 'kpi', rng, settings, context=ctx)
    random = design_measurements(cell.design_cell(), 10, 'random', rng, settings, context=ctx)
    assert best.verification.ok
    assert best.objective < random.objective
    # The criterion is eq. (19) with the prior: the MAP identification of noiseless points
    # at the designed poses reports the same TCP covariance.
    q = best.configurations
    data = Measurements(q=q, eta=cell.model.predict(p, q))
    fit = identify(cell.model, data, SIGMA, cell.q_work, p0=p,
                   free=design_free(cell, cp.allowed), prior=cp.prior)
    assert np.trace(fit.tcp_covariance[0]) == pytest.approx(
        np.trace(best.tcp_covariance[0]), rel=1e-3)
    assert np.trace(best.tcp_covariance[0]) / 3 == pytest.approx(best.criteria['kpi'],
                                                                  rel=1e-9)


@pytest.mark.slow
def test_the_drift_state_filter_matches_monte_carlo_of_the_swing_process():
    """The drift state's prediction and update (core.prior) against the process they
    model: the parameters' deviation d and rate ḋ follow the swing's oscillator exactly
    (transition Φ, discrete noise Q), measured every cycle with noise; the posterior
    error of the parameters and of the rates after 12 cycles has the variance the filter
    states (χ²(1) means within 3 std over 400 trials) and no bias."""
    from kpi_calib_ros.core.estimation.drift_state import (
        DriftSwing,
        state_predicted,
        state_updated,
        stationary_state,
    )
    from kpi_calib_ros.core.estimation.prior import Prior
    swing = DriftSwing(10.0, 5e-5, 24.0)
    names = ('a', 'b')
    shape = np.array([[4e-8, 1e-8], [1e-8, 1e-8]])       # swing amplitudes 200, 100 µm
    c0 = np.diag([30e-6, 20e-6]) ** 2                      # the first calibration
    r = np.diag([25e-6, 15e-6]) ** 2                       # each cycle's measurement
    hours, cycles, trials = 1.2, 12, 400
    phi2 = swing.transition(hours)
    p_inf = swing.stationary()
    q = np.kron(p_inf - phi2 @ p_inf @ phi2.T, shape / 2)
    phi = np.kron(phi2, np.eye(2))
    rng = np.random.default_rng(5)
    z_p, z_r, bias = [], [], []
    for _ in range(trials):
        z = np.linalg.cholesky(np.kron(p_inf, shape / 2)) @ rng.normal(size=4)
        p_true = np.array([0.1, -0.2])
        prior = Prior(names, p_true + np.linalg.cholesky(c0) @ rng.normal(size=2), c0)
        state = stationary_state(names, swing, shape)
        for _ in range(cycles):
            z_new = phi @ z + np.linalg.cholesky(q + 1e-30 * np.eye(4)) @ rng.normal(size=4)
            p_true = p_true + z_new[:2] - z[:2]
            z = z_new
            prior, state = state_predicted(prior, state, swing, shape, hours)
            y = p_true + np.linalg.cholesky(r) @ rng.normal(size=2)
            info = np.linalg.inv(prior.covariance) + np.linalg.inv(r)
            post = np.linalg.inv(info)
            mean = post @ (np.linalg.solve(prior.covariance, prior.mean) + np.linalg.solve(r, y))
            state = state_updated(prior, state, names, mean, post)
            prior = Prior(names, mean, post)
        e = prior.mean - p_true
        z_p.append(e ** 2 / np.diag(prior.covariance))
        er = state.rates - z[2:]
        z_r.append(er ** 2 / np.diag(state.covariance)[2:])
        bias.append(e / np.sqrt(np.diag(prior.covariance)))
    tol = 3 * np.sqrt(2 / trials)
    assert np.all(np.abs(np.mean(z_p, axis=0) - 1) < tol)
    assert np.all(np.abs(np.mean(z_r, axis=0) - 1) < tol)
    assert np.all(np.abs(np.mean(bias, axis=0)) < 3 / np.sqrt(trials))


def test_the_stationary_drift_state_stays_stationary_and_bad_states_are_refused():
    from kpi_calib_ros.core.errors import DataError
    from kpi_calib_ros.core.estimation.drift_state import (
        DriftState,
        DriftSwing,
        state_predicted,
        stationary_state,
    )
    from kpi_calib_ros.core.estimation.prior import Prior
    from kpi_calib_ros.io.calibration_file import drift_state_from_dict
    swing = DriftSwing(5.0, 5e-5)
    shape = np.diag([1e-8, 4e-8])
    state = stationary_state(('a', 'b'), swing, shape)
    prior = Prior(('a', 'b'), np.zeros(2), np.eye(2) * 1e-10)
    for hours in (0.5, 1.2, 30.0):
        _, after = state_predicted(prior, state, swing, shape, hours)
        assert np.allclose(after.covariance, state.covariance, rtol=1e-9,
                           atol=1e-12 * np.abs(state.covariance).max())
    # Along the rates: the period's quarter turns a rate into a deviation.
    moving = DriftState(('a', 'b'), np.array([0, 0, 1e-5, 0]), state.covariance, state.cross)
    shifted, _ = state_predicted(prior, moving, swing, shape, 1.0)
    assert shifted.mean[0] == pytest.approx(1e-5 * swing.transition(1.0)[0, 1])
    bad = state.to_dict()
    bad['covariance'] = bad['covariance'][:3]
    with pytest.raises(DataError, match='drift_state.covariance'):
        drift_state_from_dict(bad)
    with pytest.raises(DataError, match='drift_state lacks'):
        drift_state_from_dict({'names': ['a']})
    with pytest.raises(DataError, match='period'):
        DriftSwing(5.0, 5e-5, 0.0)


def test_a_cycle_with_a_drift_state_stores_it_and_the_next_prior_follows_its_rates(
        cell, truth, first_cycle):
    import yaml

    from kpi_calib_ros.app.reidentify import cycle_prior, reidentification_document, reidentify
    from kpi_calib_ros.core.estimation.drift_state import DriftSwing
    from kpi_calib_ros.io.calibration_file import drift_state_from_dict
    p_true, _ = truth
    _, doc = first_cycle
    swing = DriftSwing(8.0, 5e-5)
    data = _cycle_data(cell, p_true, 10, 15)
    # An older calibration without drift_state: the swing's stationary state.
    cp = cycle_prior(cell, doc, data, keep_placement=True, hours=1.0, swing=swing)
    assert 'no drift_state in it: stationary' in cp.description
    assert cp.state is not None and cp.state.names == cp.prior.names
    out = reidentify(cell, data, cp)
    assert out.calibration is not None and out.state is not None
    new = yaml.safe_load(yaml.safe_dump(reidentification_document(cell, out, cp, 'old')))
    stored = drift_state_from_dict(new['drift_state'])
    assert stored.names == cp.prior.names
    assert new['drift_state']['swing']['temperature_k'] == 8.0
    # The next cycle's prior mean is the calibration moved along its state.
    nxt = cycle_prior(cell, new, None, keep_placement=True, hours=2.0, swing=swing,
                      length_rate=0.0, angle_rate=0.0, rotation_rate=0.0, placement_rate=0.0)
    assert 'its drift_state' in nxt.description
    values = {p['name']: p['value'] for p in new['parameters']}
    phi = swing.transition(2.0)
    k = len(stored.names)
    expected = (np.array([values[n] for n in stored.names])
                + (phi[0, 0] - 1) * stored.state[:k] + phi[0, 1] * stored.state[k:])
    assert np.allclose(nxt.prior.mean, expected, rtol=0, atol=1e-12)
    assert all(nxt.values[n] == pytest.approx(m) for n, m in zip(nxt.prior.names,
                                                                 nxt.prior.mean))
    # Without the swing the stored state is not used (random walk only).
    plain = cycle_prior(cell, new, None, keep_placement=True, hours=2.0)
    assert plain.state is None
    assert np.allclose(plain.prior.mean, [values[n] for n in plain.prior.names])


def test_drift_velocity_options_are_validated():
    from kpi_calib_ros.cli import main
    from kpi_calib_ros.core.errors import ConfigError
    from kpi_calib_ros.ros.parameters import PARAMETERS, settings_from_parameters
    for bad in ('5', '5,-1e-5', '5,5e-5,0', 'a,b'):
        with pytest.raises(SystemExit) as exc:
            main(['identify', '--cell', str(DEFAULT_CELL), '--bag', 'x.mcap', '--out', 'o',
                  '--prior', 'c.yaml', f'--drift-velocity={bad}'])
        assert exc.value.code == 2
    values = {k: (v if not hasattr(v, 'name') else []) for k, (v, *_) in PARAMETERS.items()}
    assert settings_from_parameters(values).drift_velocity == ()
    values['drift_velocity'] = [5.0, 5e-5]
    assert settings_from_parameters(values).drift_velocity == (5.0, 5e-5, 24.0)
    values['drift_velocity'] = [5.0]
    with pytest.raises(ConfigError, match='drift_velocity'):
        settings_from_parameters(values)


def test_a_new_station_whose_postures_hardly_turn_the_tool_holds_the_previous_probe():
    """The cell leaves the reflector offset out (registered from the points), the previous
    calibration has it, and the next cycle is measured from a station 0.4 m and 0.3 rad
    away with joint 1 still and the wrist straight: the tool turns about one axis only.
    The start registers the base with the previous calibration's probe held (on the nominal
    robot: within 1 cm), and the cycle predicts the working pose within 4σ; it registered
    the probe from the points as though nothing were known and stopped ("the tip
    orientations hardly vary"), as on the real UR10's Series D."""
    import yaml

    from kpi_calib_ros.app.calibration_document import calibration_document
    from kpi_calib_ros.app.cell_model import build_cell_model
    from kpi_calib_ros.app.identify import calibrate_cell
    from kpi_calib_ros.app.reidentify import cycle_prior, cycle_start, reidentify
    from kpi_calib_ros.io.cell import cell_from_dict
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    del doc['reflector']['offset']
    cm = build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))
    assert cm.needs_registration
    rng = np.random.default_rng(31)
    p_true = true_parameters(cm.model.params, rng)
    p_true[cm.model.params.indices([f'reflector.{c}' for c in 'xyz'])] = [0.004, -0.002, 0.03]
    q = random_configurations(cm.model, p_true, 60, rng)
    cal = calibrate_cell(cm, simulate_measurements(cm.model, p_true, q, SIGMA, rng))
    assert cal.valid
    previous = calibration_document(cm, cal.result)
    moved = p_true.copy()
    moved[:6] += [0.3, -0.25, 0.05, 0.0, 0.0, 0.3]
    q = random_configurations(cm.model, moved, 40, rng)
    q[:, 0] = q[0, 0]
    q[:, 3:] = 0.0
    data = simulate_measurements(cm.model, moved, q, SIGMA, rng)
    cp = cycle_prior(cm, previous, None, hours=0.0)
    start = cycle_start(cm, data, cp)
    names = cm.model.params.names
    reflector = cm.model.params.indices([f'reflector.{c}' for c in 'xyz'])
    assert np.allclose(start[reflector], cal.result.values[reflector])
    assert np.max(np.abs(start[:3] - moved[:3])) < 0.01, (names[:3], start[:3] - moved[:3])
    out = reidentify(cm, data, cp)
    assert out.change.consistent and out.calibration is not None
    tcp = out.calibration.result.tcp[0] - cm.model.predict(moved, cm.q_work)[0]
    assert np.linalg.norm(tcp) < 4 * np.sqrt(np.trace(out.calibration.result.tcp_covariance[0]))

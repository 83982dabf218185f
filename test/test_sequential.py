"""Sequential campaign: σ upper limit, lack-of-fit test, plan and stop rules on the real
identification of the default cell (the Monte Carlo figures are in bench/)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.stats
import yaml

from kpi_calib_ros.app.campaign import campaign_context, new_campaign, simulate_sequential
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.campaigns.plan_order import nested_order, plan_ahead
from kpi_calib_ros.core.campaigns.settings import (
    MAX_MEASUREMENTS,
    MODEL_INADEQUATE,
    TARGET_MET,
    CampaignSettings,
)
from kpi_calib_ros.core.campaigns.statistics import lack_of_fit, pure_error, sigma_upper_limit
from kpi_calib_ros.core.design.exchange import exchange, information
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.simulation import simulate_pose_measurements, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, load_cell, read_cell_document
from kpi_calib_ros.io.cell_settings import hidden_effects
from kpi_calib_ros.io.design_io import read_design_poses

from cell_variants import cell_document


@pytest.fixture(scope='module')
def setup():
    cell_doc = load_cell(DEFAULT_CELL)
    cm = build_cell_model(cell_doc)
    cell, ctx = campaign_context(cm, 3, candidates=1000)
    return cell_doc, cm, cell, ctx


@pytest.mark.slow
def test_sigma_upper_limit_covers_the_true_sigma_at_its_confidence():
    rng = np.random.default_rng(0)
    runs, dof, sigma = 20000, 40, 2e-5
    chi2 = rng.chisquare(dof, size=runs)          # χ² against the true σ
    upper = np.array([sigma_upper_limit(c, dof, sigma, 0.95) for c in chi2])
    coverage = np.mean(upper >= sigma)
    assert abs(coverage - 0.95) < 3 * np.sqrt(0.95 * 0.05 / runs)
    estimate = sigma * np.sqrt(chi2 / dof)
    assert np.all(upper >= estimate)               # never below what the data say
    assert sigma_upper_limit(10.0, 0, sigma, 0.95) == float('inf')


def test_pure_error_is_the_scatter_of_repeated_poses():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(4, 6))
    rows = q[[0, 1, 1, 2, 3, 3, 3]]
    eta = rng.normal(size=(7, 3))
    w = np.array([2.0, 3.0, 4.0])
    ss, dof = pure_error(rows, eta, w)
    expected = sum(np.sum(((eta[idx] - eta[idx].mean(axis=0)) * w) ** 2)
                   for idx in ([1, 2], [4, 5, 6]))
    assert dof == 3 * (1 + 2)
    assert ss == pytest.approx(expected, rel=1e-12)


def test_lack_of_fit_false_alarms_at_its_level_and_detects_a_bias_beyond_the_target():
    """Sums of squares in σ units: pure error χ²(ν_pe); lack of fit χ²(ν_lof) plus a bias
    b per axis that the model cannot absorb (noncentral, λ = ν_lof b²)."""
    rng = np.random.default_rng(2)
    runs, nu_pe, nu_lof, alpha, target = 4000, 15, 60, 0.01, 0.5
    ss_pe = rng.chisquare(nu_pe, size=runs)
    for bias, check in ((0.0, lambda r: r <= alpha + 3 * np.sqrt(alpha / runs)),
                        (target, lambda r: r <= alpha + 3 * np.sqrt(alpha / runs)),
                        (4 * target, lambda r: r >= 0.9)):
        ss_lof = (rng.noncentral_chisquare(nu_lof, nu_lof * bias ** 2, size=runs) if bias
                  else rng.chisquare(nu_lof, size=runs))
        rejects = np.array([lack_of_fit(a + b, nu_pe + nu_lof, b, nu_pe, target,
                                        alpha)['rejects'] for a, b in zip(ss_lof, ss_pe)])
        assert check(rejects.mean()), (bias, rejects.mean())
    assert lack_of_fit(50.0, 40, 0.0, 0, target, alpha) == {}   # no replicates, no test


def test_plan_ahead_keeps_excluded_out_and_beats_the_greedy_sequence(setup):
    _, cm, cell, ctx = setup
    rows, loss = ctx.rows, ctx.problem.loss('kpi')
    start = list(range(10))
    info = information(rows[start])
    plan = plan_ahead(rows, info, 8, loss, np.array(start), max_sweeps=50)
    assert len(set(plan.tolist())) == 8 and not set(plan.tolist()) & set(start)
    greedy, cur = [], info.copy()
    for _ in range(8):
        gain = loss.delta(np.linalg.inv(cur), rows, +1.0)
        gain[start + greedy] = np.inf
        greedy.append(int(np.argmin(gain)))
        cur = cur + rows[greedy[-1]].T @ rows[greedy[-1]]
    planned = loss.value(info + information(rows[plan]))
    assert planned <= loss.value(cur) * (1 + 1e-12)
    # The first pose of the plan is the one whose single addition helps most.
    single = loss.delta(np.linalg.inv(info), rows[plan], +1.0)
    assert single[0] == single.min()


def test_the_plan_does_not_depend_on_how_long_it_takes(setup, monkeypatch):
    """A loaded machine must not change which poses a campaign chooses: with a clock that
    jumps 10 s at every reading (a step-time limit would stop the sweeps at once) the
    plan is the one of an unhurried run."""
    _, _, _, ctx = setup
    rows, loss = ctx.rows, ctx.problem.loss('kpi')
    start = np.arange(10)
    info = information(rows[start])
    calm = plan_ahead(rows, info, 12, loss, start)
    ticks = iter(range(0, 10 ** 9, 10))
    monkeypatch.setattr('time.perf_counter', lambda: float(next(ticks)))
    monkeypatch.setattr('time.monotonic', lambda: float(next(ticks)))
    assert np.array_equal(plan_ahead(rows, info, 12, loss, start), calm)
    # and the sweeps did work: the plan is better than the greedy additions alone
    greedy = plan_ahead(rows, info, 12, loss, start, max_sweeps=0)
    assert loss.value(info + information(rows[calm])) < loss.value(
        info + information(rows[greedy]))


@pytest.mark.slow
def test_nested_order_makes_every_prefix_nearly_as_good_as_the_batch_design(setup):
    """Issue 12, plan nested: the backward-elimination order of a 30-pose KPI design has
    prefixes within 1.15 of the exchange design of each size; the exchange design of the
    smallest size followed by the greedy additions does not (its worst prefix is well
    above), which is why the initial design is a prefix of the larger one."""
    _, _, _, ctx = setup
    rows, loss = ctx.rows, ctx.problem.loss('kpi')
    big = exchange(rows, 30, loss, np.random.default_rng(0))
    order = nested_order(rows, np.asarray(big.selected), loss, 9)
    assert sorted(order.tolist()) == sorted(big.selected)
    worst_nested, worst_greedy = 0.0, 0.0
    small = list(exchange(rows, 11, loss, np.random.default_rng(0)).selected)
    cur = information(rows[small])
    for n in range(11, 31):
        batch = exchange(rows, n, loss, np.random.default_rng(n)).loss
        worst_nested = max(worst_nested, loss.value(information(rows[order[:n]])) / batch)
        worst_greedy = max(worst_greedy, loss.value(cur) / batch)
        gain = loss.delta(np.linalg.inv(cur), rows, +1.0)
        gain[small] = np.inf
        small.append(int(np.argmin(gain)))
        cur = cur + rows[small[-1]].T @ rows[small[-1]]
    assert worst_nested <= 1.15, worst_nested
    assert worst_greedy > worst_nested + 0.05, (worst_greedy, worst_nested)


def test_settings_are_validated_with_the_key():
    with pytest.raises(ConfigError, match='target_tcp_std'):
        CampaignSettings(target_std=-1e-5)
    with pytest.raises(ConfigError, match='max_measurements'):
        CampaignSettings(target_std=1e-5, max_measurements=0)


def test_campaign_meets_the_target_and_the_prediction_holds(setup):
    _, cm, cell, ctx = setup
    target = 10e-6
    campaign = new_campaign(cm, cell, ctx, CampaignSettings(target_std=target), seed=0)
    rng = np.random.default_rng(5)
    p_true = true_parameters(cm.model.params, rng)
    run = simulate_sequential(campaign, cm, p_true, float(cm.cell.sigma[0]), rng)
    final = run.final
    assert final.stop_reason == TARGET_MET
    assert final.statistic <= target < run.history[-2].statistic
    assert final.measurements > run.initial
    # The stop statistic is eq. (19) at the estimate, scaled to the σ upper limit.
    res = campaign.result
    scale = (final.sigma_upper / final.sigma_stated) ** 2
    assert np.allclose(final.tcp_std ** 2,
                       np.diagonal(res.tcp_covariance, axis1=1, axis2=2) * scale)
    assert final.sigma_upper >= final.sigma_hat
    # Every measured pose after the initial design is a feasible candidate, none twice
    # (no χ² rejection here, so no replicates).
    later = run.candidates[run.initial:]
    assert np.all(later >= 0) and len(set(run.candidates.tolist())) == len(run.candidates)
    assert np.allclose(run.configurations, ctx.candidates.configurations[run.candidates])
    # The true TCP error is within 4 std (true σ) on every axis.
    error = run.tcp_estimated - run.tcp_true
    assert np.all(np.abs(error) <= 4 * run.tcp_std_true)


@pytest.mark.slow
def test_hidden_compliance_stops_model_inadequate_before_max(setup):
    cell_doc, cm, cell, ctx = setup
    effects, overrides = hidden_effects({'joint_compliance:joint_2': {'c': 4.0e-7}}, cm.robot)
    truth = build_cell_model(cell_doc, effects=effects)
    settings = CampaignSettings(target_std=10e-6, max_measurements=80)
    campaign = new_campaign(cm, cell, ctx, settings, seed=1)
    rng = np.random.default_rng(7)
    p_true = true_parameters(truth.model.params, rng, overrides=overrides)
    run = simulate_sequential(campaign, truth, p_true, float(cm.cell.sigma[0]), rng)
    assert run.final.stop_reason == MODEL_INADEQUATE
    assert run.final.measurements < settings.max_measurements
    lof = run.final.lack_of_fit
    assert lof['rejects'] == 1.0 and lof['bias_rms_m'] > settings.target_std
    # The replicates were measured again exactly (pure error from them).
    assert lof['pure_error_dof'] >= 3


@pytest.mark.slow
def test_understated_sigma_is_not_called_model_inadequate(setup):
    """True σ 2x the stated one, no missing effect: χ² rejects, replicates are taken, the
    lack-of-fit test stays quiet and the campaign goes on with the σ of the data."""
    _, cm, cell, ctx = setup
    settings = CampaignSettings(target_std=10e-6, max_measurements=30)
    campaign = new_campaign(cm, cell, ctx, settings, seed=2)
    rng = np.random.default_rng(11)
    p_true = true_parameters(cm.model.params, rng)
    sigma = float(cm.cell.sigma[0])
    run = simulate_sequential(campaign, cm, p_true, 2 * sigma, rng)
    final = run.final
    assert final.stop_reason == MAX_MEASUREMENTS
    assert final.lack_of_fit['pure_error_dof'] >= 3 and final.lack_of_fit['rejects'] == 0.0
    # Replicates alternate with new poses (a block of them is the worst prefix).
    seen = [c in run.candidates[:i] for i, c in enumerate(run.candidates)]
    assert any(seen) and not any(a and b for a, b in zip(seen, seen[1:]))
    # σ̂ agrees with the true σ within 3 std of its chi-square spread.
    rel = 3 * np.sqrt(1 / (2 * final.dof))
    assert abs(final.sigma_hat / (2 * sigma) - 1) < rel
    assert final.sigma_upper >= final.sigma_hat


@pytest.mark.slow
def test_cli_plan_and_simulated_campaign(tmp_path):
    assert main(['campaign', '--cell', str(DEFAULT_CELL), '--target-std', '15e-6',
                 '--out', str(tmp_path / 'plan')]) == 0
    names, q = read_design_poses(tmp_path / 'plan' / 'initial_design.yaml')
    assert names == build_cell_model(load_cell(DEFAULT_CELL)).joint_names and len(q) >= 9
    assert main(['campaign', '--cell', str(DEFAULT_CELL), '--target-std', '15e-6',
                 '--simulate', '--seed', '2', '--out', str(tmp_path / 'sim')]) == 0
    doc = yaml.safe_load((tmp_path / 'sim' / 'campaign.yaml').read_text())
    assert doc['status']['stop_reason'] == TARGET_MET
    assert doc['status']['statistic_m'] <= 15e-6
    assert (tmp_path / 'sim' / 'campaign_tcp_std.png').stat().st_size > 10_000
    _, poses = read_design_poses(tmp_path / 'sim' / 'campaign_poses.yaml')
    assert len(poses) == doc['status']['measurements']
    assert main(['campaign', '--cell', str(DEFAULT_CELL), '--target-std', '-1',
                 '--out', str(tmp_path / 'bad')]) == 2


def test_chi2_quantile_used_is_the_lower_tail():
    # σ_u² = σ² χ² / χ²_dof(0.05): at χ² = dof the limit exceeds σ by the known factor.
    dof = 100
    assert sigma_upper_limit(dof, dof, 1.0, 0.95) == pytest.approx(
        np.sqrt(dof / scipy.stats.chi2.ppf(0.05, dof)))


@pytest.mark.parametrize('changes, key', [
    ({'campaign': 'adaptive'}, 'campaign'),
    ({'target_tcp_std': -1e-5}, 'target_tcp_std'),
    ({'target_tcp_std': float('nan')}, 'target_tcp_std'),
    ({'max_measurements': 0}, 'max_measurements'),
])
def test_node_campaign_parameters_are_validated_with_their_name(changes, key):
    from rclpy.parameter import Parameter

    from kpi_calib_ros.ros.parameters import PARAMETERS, settings_from_parameters
    values = {k: ([] if isinstance(v[0], Parameter.Type) else v[0])
              for k, v in PARAMETERS.items()}
    settings = settings_from_parameters(values)
    assert (settings.campaign, settings.target_tcp_std, settings.max_measurements) == (
        'fixed', 1.0e-5, 200)
    values.update(changes)
    with pytest.raises(ConfigError, match=key):
        settings_from_parameters(values)


@pytest.fixture(scope='module', params=['three reflectors', 'tracked pose'])
def several_rows(request):
    """A campaign context on a cell whose poses give several rows."""
    cm = build_cell_model(cell_from_dict(cell_document(request.param), DEFAULT_CELL.parent))
    cell, ctx = campaign_context(cm, 3, candidates=1000)
    return request.param, cm, cell, ctx


@pytest.mark.slow
def test_the_campaign_counts_every_row_a_pose_gives(several_rows):
    """Three reflectors, or a tracked body's rotation: the initial design's predicted TCP
    covariance is the one its identification reports (noise-free at the nominal
    geometry, 1e-3 relative), every row of each pose counted (3 or 2 per pose)."""
    kind, cm, cell, ctx = several_rows
    campaign = new_campaign(cm, cell, ctx, CampaignSettings(target_std=10e-6), seed=0)
    initial = campaign.initial_design()
    q = ctx.candidates.configurations[initial]
    rows = simulate_pose_measurements(cm.model, cm.model.params.nominal, q, 0.0, 0.0,
                                      np.random.default_rng(0))
    status = campaign.add(rows.q, rows.eta, initial, rows.reflector, rows.rotation)
    assert status.measurements == len(initial) == len(campaign.q)
    assert len(campaign.rows) == len(initial) * (cm.model.n_reflectors
                                                 + len(cm.model.orientations))
    problem = ctx.problem
    predicted = problem.tcp_covariance(problem.rows(cell.model, q))
    identified = campaign.result.tcp_covariance
    deviation = np.linalg.norm(predicted - identified) / np.linalg.norm(identified)
    print(f'{kind}: initial design {len(initial)} poses, |C_design - C_identified| / '
          f'|C_identified| = {deviation:.2e}')
    assert deviation < 1e-3


@pytest.mark.slow
def test_a_campaign_with_several_rows_per_pose_meets_the_target(several_rows):
    """The whole loop on a three-reflector and a tracked-pose cell against a true robot:
    the target is met and the true TCP error is within 4 std on every axis."""
    kind, cm, cell, ctx = several_rows
    target = 10e-6
    campaign = new_campaign(cm, cell, ctx, CampaignSettings(target_std=target), seed=0)
    rng = np.random.default_rng(5)
    p_true = true_parameters(cm.model.params, rng)
    run = simulate_sequential(campaign, cm, p_true, float(cm.cell.sigma[0]), rng)
    print(f'{kind}: {run.final.stop_reason} after {run.final.measurements} poses '
          f'({run.initial} initial), statistic {run.final.statistic * 1e6:.2f} µm')
    assert run.final.stop_reason == TARGET_MET and run.final.statistic <= target
    assert np.all(np.abs(run.tcp_estimated - run.tcp_true) <= 4 * run.tcp_std_true)


@pytest.mark.slow
def test_a_campaign_on_a_several_reflector_cell_plans_its_initial_design(tmp_path, capsys):
    """`kpi-calib campaign` on a two-reflector cell writes the initial plan (it was
    refused before: one reflector per pose)."""
    doc = read_cell_document(DEFAULT_CELL)
    doc['reflector'].pop('offset')
    doc['reflectors'] = [{'name': 'a', 'offset': [0.0, 0.0, 0.03]},
                         {'name': 'b', 'offset': [0.06, 0.0, 0.03]}]
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    capsys.readouterr()
    rc = main(['campaign', '--cell', str(cell), '--target-std', '15e-6',
               '--out', str(tmp_path / 'plan')])
    assert rc == 0, capsys.readouterr().err
    assert len(read_design_poses(tmp_path / 'plan' / 'initial_design.yaml')[1]) > 0


def _campaign_with_outlier(campaign, cm, p_true, sigma, rng, outlier: int, offset_m: float):
    """Run ``campaign`` to its stop on the true robot, measurement ``outlier`` of the
    initial design ``offset_m`` off along x (a fault of the tracker reading)."""
    initial = campaign.initial_design()
    q = campaign.candidates[initial]

    def measure(qq):
        return cm.model.predict(p_true, qq) + rng.normal(scale=sigma, size=(len(qq), 3))
    eta = measure(q)
    eta[outlier, 0] += offset_m
    history = [campaign.add(q, eta, initial)]
    while not history[-1].stopped:
        q_next = history[-1].next_configurations[:1]
        history.append(campaign.add(q_next, measure(q_next), history[-1].next_candidates[:1]))
    return history


@pytest.mark.slow
def test_one_outlier_among_the_first_points_is_excluded_and_measured_again(setup):
    """A 1 mm fault among the initial design's points: the campaign applies the batch outlier
    rule, names the point, measures its pose again and meets the target; it never calls the
    model inadequate for one wild point."""
    _, cm, cell, ctx = setup
    target = 10e-6
    campaign = new_campaign(cm, cell, ctx, CampaignSettings(target_std=target,
                                                            max_measurements=60), seed=0)
    rng = np.random.default_rng(5)
    p_true = true_parameters(cm.model.params, rng)
    sigma = float(cm.cell.sigma[0])
    history = _campaign_with_outlier(campaign, cm, p_true, sigma, rng, 3, 1e-3)
    final = history[-1]
    assert all(s.stop_reason != MODEL_INADEQUATE for s in history)
    assert final.stop_reason == TARGET_MET and final.statistic <= target
    assert [e['measurement'] for e in final.excluded] == [3]
    assert final.excluded[0]['distance_m'] > 0.5e-3
    # Its pose was measured again, and the replicate agrees with the fit.
    again = [i for i in range(4, len(campaign.q))
             if np.allclose(campaign.q[i], campaign.q[3], atol=1e-12)]
    assert again and bool(campaign.robust.kept[again[0]])
    # The fit is the one without the fault: the true TCP within 4 std (stop σ).
    error = campaign.result.tcp - cm.model.predict(p_true, cm.q_work)
    assert np.all(np.abs(error) <= 4 * final.tcp_std)


@pytest.mark.slow
def test_a_cap_below_the_initial_design_names_the_cap_and_the_size(tmp_path, capsys):
    capsys.readouterr()
    rc = main(['campaign', '--cell', str(DEFAULT_CELL), '--target-std', '15e-6', '--max', '1',
               '--out', str(tmp_path / 'plan')])
    err = capsys.readouterr().err
    assert rc == 2
    assert 'max_measurements' in err and ' 1 is below the initial design of ' in err, err

"""Measurement design: updates, criteria, exchange, NLP and the independent check."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.collision.capsules import CollisionScene
from kpi_calib_ros.core.collision.matrix import SKIPPED_KINDS
from kpi_calib_ros.core.design.constraints import feasibility_function, flag_pairs, verify_design
from kpi_calib_ros.core.design.exchange import (
    ConditionLoss,
    LogDetLoss,
    TraceLoss,
    exchange,
    information,
)
from kpi_calib_ros.core.design.nlp import solve_design_nlp
from kpi_calib_ros.core.design.optimum import (
    DesignSettings,
    build_problem,
    design_context,
    design_measurements,
    tcp_std_on_drawn_robots,
)
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.covariance import (
    kkt_covariance,
    kpi_jacobians,
    parameter_covariance,
)
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.pose import noisy_rotations
from kpi_calib_ros.core.measurement.pose_rows import with_rotation_rows
from kpi_calib_ros.core.simulation import sampling_bounds, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, load_cell
from kpi_calib_ros.io.cell_settings import design_settings

from cell_variants import KINDS, cell_document

SMALL = DesignSettings(candidates=600, nlp=False)


@pytest.fixture(scope='module')
def cell():
    return build_cell_model(load_cell(DEFAULT_CELL)).design_cell()


@pytest.fixture(scope='module')
def context(cell):
    return design_context(cell, np.random.default_rng(11), SMALL)


def test_woodbury_updates_equal_recomputation():
    rng = np.random.default_rng(0)
    rows = rng.normal(size=(40, 3, 9))
    chosen = list(range(8))
    info = information(rows[chosen])
    inv = np.linalg.inv(info)
    factor = rng.normal(size=(3, 9))
    for loss in (TraceLoss(factor), LogDetLoss(), ConditionLoss(rng.uniform(0.5, 2, 9))):
        base = loss.value(info)
        added = loss.delta(inv, rows[10:20], +1.0)
        removed = loss.delta(inv, rows[chosen], -1.0)
        direct_add = [loss.value(info + r.T @ r) - base for r in rows[10:20]]
        direct_remove = [loss.value(info - r.T @ r) - base for r in rows[chosen]]
        assert np.allclose(added, direct_add, rtol=1e-8, atol=1e-10 * abs(base))
        assert np.allclose(removed, direct_remove, rtol=1e-8, atol=1e-10 * abs(base))


def test_criteria_equal_the_covariance_module(cell, context):
    problem = context.problem
    q = context.candidates.configurations[:40]
    rows = problem.rows(cell.model, q)
    _, jac = cell.model.jacobian(problem.p, q)
    f1_p = (jac[:, :, problem.index] / cell.sigma[None, :, None]).reshape(-1, problem.k)
    tcp_p = problem.kpi_jacobian.reshape(-1, problem.k)
    c_v = kkt_covariance(*kpi_jacobians(f1_p, tcp_p))
    c_s = c_v[problem.k:, problem.k:]
    values = problem.criteria(rows)
    assert np.allclose(problem.tcp_covariance(rows)[0], c_s, rtol=1e-6)
    assert values['kpi'] == pytest.approx(np.trace(c_s) / 3, rel=1e-6)
    c_p = parameter_covariance(f1_p)
    scaled = problem.physical_scale[:, None] * c_p * problem.physical_scale[None, :]
    assert values['A'] == pytest.approx(np.trace(scaled) / problem.k, rel=1e-6)
    assert values['D'] == pytest.approx(np.linalg.det(scaled) ** (1 / problem.k), rel=1e-6)
    j_u = f1_p / problem.physical_scale
    sv = np.linalg.svd(j_u, compute_uv=False)
    assert values['cond'] == pytest.approx(sv[0] / sv[-1], rel=1e-6)
    assert values['O1'] == pytest.approx(np.prod(sv) ** (1 / len(sv)) / np.sqrt(len(j_u)),
                                         rel=1e-6)
    # The exchange losses are the same numbers.
    assert problem.loss('kpi').value(information(rows)) == pytest.approx(values['kpi'], rel=1e-9)


def _measured(model, p, q, sigma, rng):
    """What the tracker reports at configurations ``q``: every reflector's point (noise
    ``sigma`` per axis) and every tracked body's rotation (noise ``sigma`` / rotation
    scale), as the pairing gives them."""
    n_ref = model.n_reflectors
    rows_q, ref = np.repeat(q, n_ref, axis=0), np.tile(np.arange(n_ref), len(q))
    eta = model.predict(p, rows_q, reflector=ref) + rng.normal(size=(len(rows_q), 3)) * sigma
    data = Measurements(q=rows_q, eta=eta, reflector=ref)
    if not model.orientations:
        return data
    rotations = np.full((len(rows_q), 3, 3), np.nan)
    for k in model.orientations:
        sigma_rotation = np.asarray(sigma)[0] / model.rotation_scale[0]
        rotations[ref == k] = noisy_rotations(model.body_rotations(p, rows_q[ref == k], k),
                                              sigma_rotation, rng)
    return with_rotation_rows(model, data, rotations)


@pytest.mark.parametrize('kind', KINDS)
def test_design_covariance_equals_the_identifications_at_the_designed_poses(kind):
    """The TCP covariance a design predicts is the one the identification of its poses
    reports (1e-3 relative) when every row the cell declares is measured there: each
    reflector's point and each tracked body's rotation. Noise-free at the nominal
    geometry, where both linearise (with noise the estimate leaves the nominal geometry's
    degenerate directions and frees more parameters: tcp_std_on_drawn_robots)."""
    model_cell = build_cell_model(cell_from_dict(cell_document(kind), DEFAULT_CELL.parent))
    cell = model_cell.design_cell()
    design = design_measurements(cell, 15, 'kpi', np.random.default_rng(2), SMALL)
    data = _measured(cell.model, cell.model.params.nominal, design.configurations,
                     np.zeros(3), np.random.default_rng(3))
    result = identify(cell.model, data, cell.sigma, cell.q_work)
    assert len(data) == 15 * (cell.model.n_reflectors + len(cell.model.orientations))
    for predicted, identified in zip(design.tcp_covariance, result.tcp_covariance):
        deviation = np.linalg.norm(predicted - identified) / np.linalg.norm(identified)
        print(f'{kind}: {len(result.estimated)} parameters, |C_design - C_identified| / '
              f'|C_identified| = {deviation:.2e}, TCP std {np.sqrt(np.diag(identified)) * 1e6}'
              ' µm')
        assert deviation < 1e-6


def test_a_model_with_a_torque_effect_is_designed_and_predicts_its_identification():
    """A cell whose model has a compliance (``effects: [joint_compliance:joint_2]``, or a
    calibration that added one as the prior of a design) crashed the design with a
    TypeError: the symbolic refinement has no gravity torque. The refinement is skipped and
    said so; the exchange design's predicted TCP covariance is the identification's at its
    poses (noise-free at the nominal geometry, 1e-6 relative)."""
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['effects'] = ['joint_compliance:joint_2']
    model_cell = build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))
    cell = model_cell.design_cell()
    assert cell.model.uses_torque
    design = design_measurements(cell, 15, 'kpi', np.random.default_rng(2),
                                 dataclasses.replace(SMALL, nlp=True))
    assert 'ipopt refinement skipped: an effect of the model reads the gravity torque' \
        in design.status
    assert design.verification.ok
    data = _measured(cell.model, cell.model.params.nominal, design.configurations,
                     np.zeros(3), np.random.default_rng(3))
    result = identify(cell.model, data, cell.sigma, cell.q_work)
    assert 'joint_compliance.joint_2.c' in result.estimated
    for predicted, identified in zip(design.tcp_covariance, result.tcp_covariance):
        assert np.linalg.norm(predicted - identified) / np.linalg.norm(identified) < 1e-6


def test_a_model_with_a_measured_tilt_is_refined_by_the_nlp():
    """A cell whose model holds a measured tilt (``effects: [measured_tilt:joint_2:column]``,
    or a calibration that added one as the prior of the next station's design) crashed the
    symbolic refinement with a TypeError: the effect's joint correction indexed torques the
    refinement does not have. The design is refined; at the reference condition (no tilt
    recorded) the gains move no point, so they are not among its parameters, and its
    predicted TCP covariance is the identification's at its poses."""
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['effects'] = ['measured_tilt:joint_2:column']
    cell = build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent)).design_cell()
    design = design_measurements(cell, 15, 'kpi', np.random.default_rng(2),
                                 dataclasses.replace(SMALL, nlp=True, max_iterations=5))
    assert 'ipopt: ' in design.status and 'skipped' not in design.status, design.status
    assert design.verification.ok
    data = _measured(cell.model, cell.model.params.nominal, design.configurations,
                     np.zeros(3), np.random.default_rng(3))
    result = identify(cell.model, data, cell.sigma, cell.q_work)
    assert not any(n.startswith('measured_tilt.') for n in result.estimated)
    for predicted, identified in zip(design.tcp_covariance, result.tcp_covariance):
        assert np.linalg.norm(predicted - identified) / np.linalg.norm(identified) < 1e-6


def test_the_nlp_counts_the_rotation_rows_of_a_tracked_pose():
    """The IPOPT refinement's KPI criterion at its start is the identification's (the
    weighted mean TCP variance) for a tracked-pose cell: its rotation rows are in it."""
    cell = build_cell_model(cell_from_dict(cell_document('tracked pose'),
                                           DEFAULT_CELL.parent)).design_cell()
    ctx = design_context(cell, np.random.default_rng(1), SMALL)
    start = exchange(ctx.rows, 15, ctx.problem.loss('kpi'), np.random.default_rng(2))
    q0 = ctx.candidates.configurations[start.selected]
    nlp = solve_design_nlp(ctx.problem, cell, ctx.scene, q0, 'kpi', max_iterations=3)
    result = identify(cell.model, _measured(cell.model, cell.model.params.nominal, q0,
                                            np.zeros(3), np.random.default_rng(3)),
                      cell.sigma, cell.q_work)
    kpi = float(ctx.problem.kpi_weights @ np.trace(result.tcp_covariance, axis1=1, axis2=2)) / 3
    assert nlp.loss_start == pytest.approx(kpi, rel=1e-6)


def test_kpi_weights_working_poses(cell, context):
    raw = yaml.safe_load(DEFAULT_CELL.read_text())
    second = {'name': 'side', 'joints': {'joint_1': 0.6, 'joint_2': 0.2, 'joint_3': -0.1,
                                         'joint_4': 0.3, 'joint_5': 0.7, 'joint_6': 0.0}}
    raw['working_poses'].append(second)
    two = build_cell_model(cell_from_dict(raw, DEFAULT_CELL.parent)).design_cell()
    q = context.candidates.configurations
    problem = build_problem(two, q[:300], {'car_roof_edge': 3.0, 'side': 1.0})
    rows = problem.rows(two.model, q[:40])
    traces = np.trace(problem.tcp_covariance(rows), axis1=1, axis2=2)
    assert problem.criteria(rows)['kpi'] == pytest.approx((3 * traces[0] + traces[1]) / 12)
    with pytest.raises(ConfigError, match='design.weights'):
        build_problem(two, q[:300], {'roof': 1.0})


def test_exchange_never_worsens_and_beats_random(context):
    rng = np.random.default_rng(3)
    loss = context.problem.loss('kpi')
    result = exchange(context.rows, 30, loss, rng)
    history = np.array(result.history)
    assert np.all(np.diff(history) <= 1e-12 * history[:-1])
    random_losses = [loss.value(information(context.rows[rng.choice(len(context.rows), 30,
                                                                     replace=False)]))
                     for _ in range(50)]
    print(f'exchange {result.loss:.3e} m², best of 50 random {min(random_losses):.3e} m², '
          f'median {np.median(random_losses):.3e} m²')
    assert result.loss < min(random_losses)
    assert len(set(result.selected.tolist())) == 30


def test_kpi_design_beats_heuristic_on_default_cell(cell, context):
    rng = np.random.default_rng(4)
    heuristic = design_measurements(cell, 30, 'random', rng, SMALL, context=context)
    optimal = design_measurements(cell, 30, 'kpi', rng, SMALL, context=context)
    a_opt = design_measurements(cell, 30, 'A', rng, SMALL, context=context)
    h, s, p = (np.trace(r.tcp_covariance[0]) for r in (heuristic, optimal, a_opt))
    print(f'trace C_s: heuristic {h:.3e}, A-optimal {p:.3e}, KPI-optimal {s:.3e} m² '
          f'({100 * (1 - s / h):.0f} % / {100 * (1 - s / p):.0f} % better)')
    assert s < 0.8 * h and s < p
    for result in (heuristic, optimal, a_opt):
        assert result.verification.ok, result.verification.violations
        assert result.constraint_count == 1 + context.scene.count


def test_verifier_catches_collision_incidence_and_limits(cell, context):
    rng = np.random.default_rng(5)
    lo, hi = sampling_bounds(cell.model)
    q = rng.uniform(lo, hi, size=(4000, 6))
    values = np.array(feasibility_function(cell, context.scene).map(len(q))(q.T)).T
    measurable = values[:, 0] >= np.cos(cell.max_incidence)
    colliding = q[measurable & (values[:, 1:].min(axis=1) < -0.01)][0]
    blind = q[values[:, 0] < np.cos(cell.max_incidence) - 0.1][0]
    good = context.candidates.configurations[0]
    beyond = good.copy()
    beyond[1] = hi[1] + 0.1
    check = verify_design(cell, context.scene, np.array([good, colliding, blind, beyond]))
    print('\n'.join(check.violations[:6]))
    assert not check.ok
    assert not any(v.startswith('configuration 0:') for v in check.violations)
    assert any(v.startswith('configuration 1:') and '~' in v for v in check.violations)
    assert any(v.startswith('configuration 2: incidence') for v in check.violations)
    assert any(v.startswith('configuration 3: joint_2') for v in check.violations)
    assert check.min_margin[1] < -0.01 <= 0.0 <= check.min_margin[0]


def test_nlp_result_passes_the_independent_check(cell, context):
    rng = np.random.default_rng(6)
    q0 = context.candidates.configurations[exchange(context.rows, 12,
                                                    context.problem.loss('kpi'), rng).selected]
    lines = []
    nlp = solve_design_nlp(context.problem, cell, context.scene, q0, 'kpi',
                           max_iterations=60, progress=lines.append, every=20)
    check = verify_design(cell, context.scene, nlp.configurations)
    print(f'{nlp.status}: {nlp.loss_start:.3e} -> {nlp.loss:.3e} m² in {nlp.iterations} '
          f'iterations, {nlp.seconds:.1f} s; min margin {check.min_margin.min() * 1e3:.2f} mm, '
          f'max incidence {check.incidence_deg.max():.2f} deg')
    assert lines and lines[0].startswith('ipopt: iteration 20')
    assert check.ok, check.violations
    assert nlp.loss < nlp.loss_start


def _tcp_mean_square_error(cell, q, p, runs, rng):
    """E|ŝ - s|² (m²) at the first working pose over ``runs`` identifications of the
    poses ``q`` of a robot with parameters ``p``, each with new noise at the cell's σ."""
    model, sigma = cell.model, cell.sigma
    clean = model.predict(p, q)
    truth = model.predict(p, cell.q_work)[0]
    errors = [identify(model, Measurements(q=q, eta=clean + rng.normal(size=clean.shape)
                                           * sigma), sigma, cell.q_work).tcp[0] - truth
              for _ in range(runs)]
    return float(np.mean(np.sum(np.square(errors), axis=1)))


@pytest.mark.slow
def test_predicted_tcp_covariance_matches_monte_carlo(cell, context):
    rng = np.random.default_rng(7)
    design = design_measurements(cell, 30, 'kpi', rng, SMALL, context=context)
    mse = _tcp_mean_square_error(cell, design.configurations, cell.model.params.nominal, 100,
                                 rng)
    ratio = mse / np.trace(design.tcp_covariance[0])
    print(f'Monte Carlo E|ŝ - s|² / predicted trace C_s = {ratio:.3f} over 100 identifications')
    assert abs(ratio - 1) < 0.2


@pytest.mark.slow
def test_tcp_std_on_drawn_robots_matches_monte_carlo_where_the_nominal_one_is_low(cell, context):
    """On the default cell the nominal geometry lacks two directions a real robot has (a
    reflector on the flange axis): the identification of the designed poses frees 27
    parameters, the nominal problem 25. The TCP covariance predicted on drawn robots is
    what 1000 identifications at such a robot scatter by; the nominal one is low."""
    rng = np.random.default_rng(7)
    design = design_measurements(cell, 24, 'kpi', rng, SMALL, context=context)
    drawn = tcp_std_on_drawn_robots(cell, design.configurations, None, np.random.default_rng(3))
    assert len(design.parameter_names) == 25 and set(drawn.parameters) == {27}
    predicted = float(np.median(np.sum(drawn.tcp_std[:, 0] ** 2, axis=1)))
    nominal = float(np.trace(design.tcp_covariance[0]))
    p = true_parameters(cell.model.params, np.random.default_rng(5))
    mse = _tcp_mean_square_error(cell, design.configurations, p, 1000, rng)
    print(f'E|ŝ - s|² over 1000 identifications / predicted trace C_s: drawn robots '
          f'{mse / predicted:.3f}, nominal {mse / nominal:.3f}')
    # 1000 errors in 3 axes: relative std of the mean square about 2.6 %
    assert abs(mse / predicted - 1) < 0.08
    assert predicted > 1.04 * nominal


def test_pairs_violated_almost_always_are_flagged(cell):
    raw = yaml.safe_load(DEFAULT_CELL.read_text())
    raw['collision']['ignore_pairs'] = [p for p in raw['collision']['ignore_pairs']
                                        if 'link_4' not in p]
    cm = build_cell_model(cell_from_dict(raw, DEFAULT_CELL.parent))
    # The sampled collision matrix skips both pairs (they overlap by construction) ...
    skipped = {frozenset(p.links): p.kind for p in cm.robot_geometry().matrix.pairs
               if p.kind in SKIPPED_KINDS}
    assert {frozenset({'link_2', 'link_4'}), frozenset({'link_4', 'link_6'})} <= set(skipped)
    # ... and without it, the design's own screening flags them.
    bare = cm.design_cell()
    bare = dataclasses.replace(bare, scene=CollisionScene(
        bare.scene.robot_capsules, bare.scene.obstacles, bare.scene.chain_links,
        ignore_pairs=set(cm.cell.ignore_pairs), beam_radius=cm.cell.beam_radius))
    flagged = flag_pairs(bare, bare.scene, np.random.default_rng(8), samples=200)
    print(flagged)
    assert set(flagged) == {'link_2~link_4', 'link_4~link_6'}
    with pytest.raises(ConfigError, match='link_2~link_4'):
        design_context(bare, np.random.default_rng(8), SMALL)
    relaxed = dataclasses.replace(SMALL, candidates=50, ignore_flagged=True)
    ctx = design_context(bare, np.random.default_rng(8), relaxed)
    assert set(ctx.flagged) == set(flagged) and 'link_2~link_4' not in ctx.scene.labels


def test_design_settings_are_validated():
    assert design_settings({'candidates': 100, 'weights': {'roof': 2.0}})['candidates'] == 100
    with pytest.raises(ConfigError, match='design.candidates'):
        design_settings({'candidates': 0})
    with pytest.raises(ConfigError, match='design.colision'):
        design_settings({'colision': False})
    with pytest.raises(ConfigError, match='design.nlp'):
        design_settings({'nlp': 'yes'})


def test_design_command_writes_yaml_and_plots(tmp_path):
    from kpi_calib_ros.cli import main
    raw = yaml.safe_load(DEFAULT_CELL.read_text())
    raw['robot']['urdf'] = str((DEFAULT_CELL.parent / raw['robot']['urdf']).resolve())
    raw['design'] = {'candidates': 300, 'nlp': False}
    cell_path = tmp_path / 'cell.yaml'
    cell_path.write_text(yaml.safe_dump(raw))
    out = tmp_path / 'design.yaml'
    assert main(['design', '--cell', str(cell_path), '--n', '15', '--criterion', 'kpi',
                 '--out', str(out), '--seed', '1']) == 0
    doc = yaml.safe_load(out.read_text())
    assert doc['joint_names'] == [f'joint_{i}' for i in range(1, 7)]
    assert np.array(doc['configurations']).shape == (15, 6)
    assert doc['criterion'] == 'kpi' and doc['verification']['ok']
    assert len(doc['working_poses'][0]['tcp_std_m']) == 3
    assert len(doc['constraints']['min_margin_m']) == 15
    drawn = doc['drawn_robots']
    assert drawn['nominal_parameters'] == 25 and drawn['robots'] == len(drawn['parameters'])
    stats = drawn['tcp_std_m'][doc['working_poses'][0]['name']]
    assert len(stats['median']) == 3 and stats['ratio_to_nominal_median'] >= 0.99
    assert (tmp_path / 'design_poses.png').stat().st_size > 10_000
    assert (tmp_path / 'design_ellipsoids.png').stat().st_size > 10_000


@pytest.mark.slow
def test_exchange_at_the_smallest_size_completes_when_a_removal_is_singular(cm):
    """9 poses for 25 parameters: without one pose 24 equations remain, and round-off let
    the loss of that singular information look finite (the inverse then raised); the
    removal is skipped, the design is nonsingular and its loss finite."""
    from kpi_calib_ros.app.campaign import campaign_context
    cell, ctx = campaign_context(cm, 0)
    rows = ctx.problem.rows(cell.model, ctx.candidates.configurations)
    n = int(np.ceil(ctx.problem.k / 3))
    res = exchange(rows, n, ctx.problem.loss('kpi'), np.random.default_rng(21))  # one that hit it
    assert len(set(res.selected)) == n and np.isfinite(res.loss) and res.loss > 0
    info = sum(r.T @ r for r in rows[res.selected])
    assert np.linalg.matrix_rank(info) == ctx.problem.k


def test_a_design_leaves_identify_a_degree_of_freedom():
    """As many equations as parameters (9 poses for 27 parameters of a UR5) was designed,
    called estimable, and refused by identify ("too few measurements"); the exchange now
    asks for one pose more, as identify does."""
    rng = np.random.default_rng(0)
    rows = rng.normal(size=(40, 3, 6))
    with pytest.raises(ValueError, match='2 configurations give 6 equations for 6 parameters; '
                                         'at least 3 are needed'):
        exchange(rows, 2, LogDetLoss(), rng)
    assert len(exchange(rows, 3, LogDetLoss(), rng).selected) == 3


def test_an_incidence_limit_no_pose_meets_is_named_as_such(cm):
    """An incidence limit of 0.002 rad: no drawn pose sees the reflector, and the error names
    reflector.max_incidence, not the number of candidates (which raising would not help)."""
    tight = dataclasses.replace(cm.design_cell(), max_incidence=0.002)
    with pytest.raises(ConfigError, match='reflector.max_incidence') as caught:
        design_context(tight, np.random.default_rng(8), SMALL)
    assert caught.value.key == 'reflector.max_incidence'


def test_a_beam_crossing_an_obstacle_at_every_pose_is_refused_even_when_ignoring(cm):
    """A capsule round the tracker (a stand drawn as an obstacle): the beam crosses it at
    every pose. The design stops naming the obstacle and the tracker's placement, with
    design.ignore_flagged too: dropped as flagged, the design's beam crossed it at 12 of 12
    poses with a warning alone."""
    from kpi_calib_ros.core.collision.capsules import Capsule
    cell = cm.design_cell()
    tracker = cell.tracker_in_base[:3, 3]
    stand = Capsule('stand', 'base', tuple(tracker - [0, 0, 0.3]), tuple(tracker + [0, 0, 0.3]),
                    0.4)
    scene = CollisionScene(cell.scene.robot_capsules, [*cell.scene.obstacles, stand],
                           cell.scene.chain_links, ignore_pairs=set(cm.cell.ignore_pairs),
                           beam_radius=cm.cell.beam_radius)
    for relaxed in (SMALL, dataclasses.replace(SMALL, ignore_flagged=True)):
        with pytest.raises(ConfigError, match='beam crosses obstacle') as caught:
            design_context(dataclasses.replace(cell, scene=scene), np.random.default_rng(8),
                           relaxed)
        assert caught.value.key == 'obstacles' and 'stand' in str(caught.value)


def test_candidates_and_the_refined_design_are_held_to_the_cells_acceptance(cm):
    """A cell whose robot refuses half its joint range beyond the capsules (its meshes):
    every candidate and every designed pose is one it accepts."""
    cell = dataclasses.replace(cm.design_cell(), accept=lambda q: q[:, 0] > 0.0)
    rng = np.random.default_rng(8)
    ctx = design_context(cell, rng, SMALL)
    assert np.all(ctx.candidates.configurations[:, 0] > 0.0)
    result = design_measurements(cell, 12, 'kpi', rng,
                                 dataclasses.replace(SMALL, nlp=True, max_iterations=30))
    assert np.all(result.configurations[:, 0] > 0.0)


@pytest.mark.slow
def test_a_stock_baxter_design_is_free_of_mesh_contact(tmp_path):
    """The stock Baxter's right arm: its capsules overlap their neighbours' in every pose (the
    pairs are skipped), while its meshes touch in some (shoulder and elbow in 62 % of random
    poses). Candidates and the refined design are held to the meshes: none of the 30 poses in
    contact, where every design had 8 of 10 to 25 of 30 in contact, failing its own check."""
    from kpi_calib_ros.cli import main
    out = tmp_path / 'design.yaml'
    assert main(['design', '--cell', str(Path(__file__).parent / 'data' / 'baxter_cell.yaml'),
                 '--n', '30', '--criterion', 'kpi', '--out', str(out)]) == 0
    doc = yaml.safe_load(out.read_text())
    assert doc['geometry']['mesh_check']['in_collision'] == 0

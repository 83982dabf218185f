"""General effects: a periodic joint error at a frequency found from the data, link bending.

Truths asserted: the bending moment's component along each axis is Pinocchio's gravity
torque; a Lomb–Scargle search finds a 17 cycle-per-revolution joint error and the effect
then recovers its amplitude within 3σ; a simulated link bending is proposed by the
diagnosis and brings the error on fresh poses below 1.5× the noise floor; on clean data
the search and the general effects claim nothing.
"""
from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.diagnosis.periodic_search import (
    periodic_candidates,
    periodograms,
    searched_cycles,
)
from kpi_calib_ros.core.diagnosis.screening import screen_effects
from kpi_calib_ros.core.diagnosis.verdict import diagnose
from kpi_calib_ros.core.effects.general import general_candidates, gravity_moment
from kpi_calib_ros.core.effects.registry import parse_effect_spec, resolve_effects, split_specs
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.simulation import random_configurations, simulate_measurements
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict

from hidden_campaigns import FLOOR, SIGMA, campaign


@pytest.fixture(scope='module')
def kr15():
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['reflector']['offset'] = [0.05, 0.0, 0.06]  # off the flange axis
    return build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))


@pytest.fixture(scope='module')
def ur():
    path = Path(DEFAULT_CELL).parent / 'ur_cell.yaml'
    return build_cell_model(cell_from_dict(yaml.safe_load(path.read_text()), path.parent))


def refit(cm, data, result, spec):
    effect = parse_effect_spec(spec, cm.robot)
    richer = augmented_model(cm.model, (effect,))
    p0 = np.concatenate([result.values, np.zeros(len(effect.parameter_names))])
    return effect, richer, identify(richer, data, SIGMA, cm.q_work, p0=p0, max_iterations=25)


@pytest.mark.parametrize('cell', ['kr15', 'ur'])
def test_bending_moment_along_the_axis_is_the_gravity_torque(cell, request):
    robot = request.getfixturevalue(cell).robot
    q = np.random.default_rng(3).uniform(-2.0, 2.0, (6, robot.n_joints))
    tau = robot.gravity_torques(q)
    load = [robot.payload.mass, *robot.payload.com]
    for j, joint in enumerate(robot.joints):
        moment = np.array([np.array(gravity_moment(robot, j)(x, load)).ravel() for x in q])
        np.testing.assert_allclose(moment @ joint.axis, tau[:, j], atol=1e-9 * (1 + abs(tau).max()))


@pytest.mark.parametrize('cell', ['kr15', 'ur'])
def test_bending_moment_is_pinocchios_joint_wrench_with_the_rows_payload(cell, request):
    """The whole moment (3 components) against the wrench Pinocchio's RNEA transmits through
    the joint at rest, with a payload other than the cell's (none, heavier, off centre):
    before, the bending moment took the cell's payload whatever the row carried."""
    import pinocchio as pin

    from kpi_calib_ros.core.model.robot import Payload
    robot = request.getfixturevalue(cell).robot
    q = np.random.default_rng(4).uniform(-2.0, 2.0, (4, robot.n_joints))
    for load in (Payload(0.0, (0.0, 0.0, 0.0)), Payload(7.5, (0.02, -0.01, 0.12))):
        model, data = robot._model_with(load)
        for x in q:
            pin.rnea(model, data, robot.pin_configuration(x), np.zeros(model.nv),
                     np.zeros(model.nv))
            for j in range(robot.n_joints):
                moment = np.array(gravity_moment(robot, j)(x, [load.mass, *load.com])).ravel()
                wrench = data.f[robot._pin_joint_ids[j]].angular
                np.testing.assert_allclose(moment, wrench, atol=1e-9 * (1 + abs(wrench).max()))


def test_specs_name_the_frequency_and_the_bending_axes(kr15):
    robot = kr15.robot
    a = parse_effect_spec('periodic_joint_error:joint_2:k=17', robot)
    b = parse_effect_spec('periodic_joint_error:joint_2:k=3', robot)
    assert a.name == 'periodic_joint_error:joint_2:k=17'
    assert a.parameter_names == ('periodic_joint_error.joint_2.k17.a',
                                 'periodic_joint_error.joint_2.k17.b')
    assert parse_effect_spec(a.name, robot) == a  # the spec round-trips
    assert len(resolve_effects([a, b], robot)) == 2  # two frequencies on one joint
    bend = parse_effect_spec('link_bending:joint_1', robot)  # axis z: bent about x and y
    assert bend.parameter_names == ('link_bending.joint_1.cx', 'link_bending.joint_1.cy')
    for bad in ('periodic_joint_error:joint_2', 'periodic_joint_error:joint_2:k=0',
                'periodic_joint_error:joint_2:k=x', 'periodic_joint_error:joint_9:k=3',
                'link_bending:joint_9'):
        with pytest.raises(ConfigError, match='effects'):
            parse_effect_spec(bad, robot)


def test_frequencies_searched_follow_the_sampling():
    q = np.linspace(-np.pi, np.pi, 40, endpoint=False)
    assert list(searched_cycles(q)) == list(range(2, 21))  # π·40/2π = 20
    assert searched_cycles(q[:10] * 0.1).max() == 64       # narrow span: the cap
    assert len(searched_cycles(np.zeros(5))) == 0          # a joint that never moved


def test_lomb_scargle_finds_17_cpr_and_the_effect_recovers_it(kr15):
    spec = 'periodic_joint_error:joint_3:k=17'
    data, result, p_true, truth, _ = campaign(kr15, {spec: {'a': 2e-4, 'b': -1.5e-4}},
                                              seed=5, n=80)
    grams = {g.joint: g for g in periodograms(kr15.model, data, result)}
    found = grams['joint_3']
    print(f'\njoint_3: peak {found.peak} cpr of {found.cycles[0]}..{found.cycles[-1]}, '
          f'p = {found.p_value:.2g}; other joints: '
          f'{[(g.joint, g.peak, round(g.p_value, 3)) for g in grams.values()]}')
    assert found.peak == 17 and found.p_value < 1e-6
    candidate = next(c for c in periodic_candidates(kr15.model, tuple(grams.values()))
                     if c.joint == 'joint_3')
    assert candidate.name == spec and candidate.searched == len(found.cycles)
    effect, _, after = refit(kr15, data, result, spec)
    z = [(after.value(n) - p_true[truth.params.index(n)]) / after.std_of(n)
         for n in effect.parameter_names]
    richer = augmented_model(kr15.model, (effect,))
    again = periodograms(richer, data, after)  # with the effect in the model
    print(f'z {np.round(z, 2).tolist()}; searched again: '
          f'{[(g.joint, g.peak, round(g.p_value, 3)) for g in again]}')
    assert np.all(np.abs(z) < 3)
    assert after.p_value > 1e-3  # the χ² test passes with the effect
    assert all(g.p_value > 0.01 for g in again)  # and no frequency is left


def test_diagnosis_proposes_link_bending_and_fresh_poses_reach_the_floor(kr15):
    # The forearm bent by the wrist and payload (joint_4's axis along the forearm): no
    # named effect has its signature.
    spec = 'link_bending:joint_4'
    hidden = {spec: {'cy': -1.5e-5, 'cz': -1.2e-5}}
    data, result, p_true, truth, rng = campaign(kr15, hidden, seed=7, n=60)
    diag = diagnose(kr15.model, data, result, folds=5)
    print(f'\n{diag.verdict}\n{diag.best.explanation if diag.best else ""}')
    assert diag.best is not None and diag.best.spec == spec
    effect, richer, after = refit(kr15, data, result, spec)
    z = [(after.value(n) - p_true[truth.params.index(n)]) / after.std_of(n)
         for n in effect.parameter_names]
    q = random_configurations(kr15.model, kr15.model.params.nominal, 100, rng)
    fresh = simulate_measurements(truth, p_true, q, SIGMA, rng)

    def rms(model, p):
        return float(np.sqrt(np.mean(np.sum((fresh.eta - model.predict(p, q)) ** 2, axis=1))))
    before, held_out = rms(kr15.model, result.values), rms(richer, after.values)
    print(f'fresh rms {before * 1e6:.1f} -> {held_out * 1e6:.1f} µm, floor '
          f'{FLOOR * 1e6:.1f} µm; z {np.round(z, 2).tolist()}')
    assert before > 1.5 * FLOOR  # it mattered
    assert held_out <= 1.5 * FLOOR
    assert np.all(np.abs(z) < 3)


def test_clean_data_claims_no_general_effect(kr15):
    claims = []
    for seed in range(30, 33):
        data, result, *_ = campaign(kr15, {}, seed=seed, n=60)
        grams = periodograms(kr15.model, data, result)
        candidates = general_candidates(kr15.robot) + periodic_candidates(kr15.model, grams)
        ranked, _ = screen_effects(kr15.model, data, result, candidates, folds=5)
        claims += [(seed, c.spec, c.p_value) for c in ranked if c.significant]
        # The search's multiplicity is in the p-value: at least the frequencies tried.
        for c in ranked:
            if c.effect == 'periodic_joint_error':
                tried = next(len(g.cycles) for g in grams if g.joint == c.joint)
                assert c.searched == tried > 1
                assert c.p_value_raw == pytest.approx(1.0) or 'search over' in c.explanation
    print(f'\nclaims on clean data: {claims}')
    assert not claims


def test_the_command_line_form_of_the_suggestion_resolves(kr15):
    """``diagnose`` suggests ``--effects <spec>``: the spec of a found frequency and of a
    bending are valid there, also together."""
    effects = resolve_effects(split_specs('periodic_joint_error:joint_2:k=17,'
                                          'link_bending:joint_1'), kr15.robot)
    assert [e.name for e in effects] == ['periodic_joint_error:joint_2:k=17',
                                         'link_bending:joint_1']
    model = augmented_model(kr15.model, effects)
    q = random_configurations(kr15.model, kr15.model.params.nominal, 5,
                              np.random.default_rng(0))
    # At zero effect parameters the model is the geometric one.
    p = np.concatenate([kr15.model.params.nominal, np.zeros(4)])
    np.testing.assert_allclose(model.predict(p, q),
                               kr15.model.predict(kr15.model.params.nominal, q), atol=1e-12)


def test_a_physical_bending_sags_the_arm_along_gravity(kr15):
    """c < 0 (the link turns against the holding moment) tilts the column of a vertical
    first axis under the arm's overhang: the tip goes down in every pose (the tip lies on the
    side of the column where the arm's mass is)."""
    model = kr15.model
    nominal = model.params.nominal
    up = np.array(ca.DM(model.chain.base_in_tracker(ca.DM(nominal))))[:3, 2]
    q = random_configurations(model, nominal, 20, np.random.default_rng(1))
    for spec, c in (('link_bending:joint_1', -1e-6),):
        bent = augmented_model(model, (parse_effect_spec(spec, kr15.robot),))
        moved = bent.predict(np.concatenate([nominal, [c, c]]), q) - model.predict(nominal, q)
        drop = moved @ up
        print(f'\n{spec}: tip height change {np.round(drop * 1e6, 1).tolist()} µm')
        assert np.all(drop <= 1e-9) and np.mean(drop) < -1e-6


@pytest.mark.parametrize('k', ['²', '٣', '3.0', '-3'])
def test_a_frequency_that_is_not_ascii_digits_is_a_config_error_naming_the_spec(kr15, k):
    robot = kr15.robot
    spec = f'periodic_joint_error:joint_2:k={k}'
    with pytest.raises(ConfigError) as err:
        parse_effect_spec(spec, robot)
    assert str(err.value).startswith(f'effects: {spec!r}: periodic_joint_error needs its '
                                     'frequency: write periodic_joint_error:<joint>:k=<k> '
                                     'with k an integer of cycles per revolution in 1..')


def test_link_bending_is_identified_across_payloads_and_predicts_another(kr15):
    """A forearm bent by the load it carries, measured with no payload and with 12 kg: the
    bending read from each row's own payload is recovered within 3σ, and fresh poses under
    6 kg (measured by none of the rows) are predicted at the noise floor."""
    from kpi_calib_ros.core.simulation import true_parameters
    spec = 'link_bending:joint_4'
    effect = parse_effect_spec(spec, kr15.robot)
    truth = augmented_model(kr15.model, (effect,))
    rng = np.random.default_rng(11)
    p_true = np.concatenate([true_parameters(kr15.model.params, rng), [-1.5e-5, -1.2e-5]])

    def measure(n, mass):
        q = random_configurations(kr15.model, kr15.model.params.nominal, n, rng)
        load = {'payload.mass': np.full(n, mass), 'payload.com.x': np.zeros(n),
                'payload.com.y': np.zeros(n), 'payload.com.z': np.full(n, 0.1)}
        return simulate_measurements(truth, p_true, q, SIGMA, rng, covariates=load)
    light, heavy = measure(40, 0.0), measure(40, 12.0)
    data = type(light)(q=np.r_[light.q, heavy.q], eta=np.r_[light.eta, heavy.eta],
                       covariates={k: np.r_[light.covariates[k], heavy.covariates[k]]
                                   for k in light.covariates})
    after = identify(truth, data, SIGMA, kr15.q_work, max_iterations=40)
    z = [(after.value(n) - p_true[truth.params.index(n)]) / after.std_of(n)
         for n in effect.parameter_names]
    fresh = measure(60, 6.0)
    miss = fresh.eta - truth.predict(after.values, fresh.q, covariates=fresh.covariates)
    rms = float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))
    print(f'z {np.round(z, 2).tolist()}, fresh rms at 6 kg {rms * 1e6:.1f} µm '
          f'(floor {FLOOR * 1e6:.1f} µm), χ²/dof {after.chi2 / after.dof:.2f}')
    assert np.all(np.abs(z) < 3)
    assert rms <= 1.3 * FLOOR


def test_a_transmission_error_of_a_prismatic_joint_follows_its_reading_not_an_angle():
    """The screen's explanation of a joint_scale names what the correction follows: the
    joint's reading, an angle or a travel (a lift's k·q "correlated with the angle of
    torso_lift_joint")."""
    from kpi_calib_ros.core.effects.registry import available_effects, bind_effect
    from kpi_calib_ros.core.model.robot import RobotModel
    from kpi_calib_ros.io.resources import resolve_uri
    xml = resolve_uri('package://example-robot-data/robots/tiago_description/robots/'
                      'tiago.urdf').read_text()
    robot = RobotModel(xml, 'base_footprint', 'arm_7_link')
    effect = bind_effect(available_effects()['joint_scale'], robot, 'torso_lift_joint')
    assert effect.joint_kind == 'prismatic'
    assert effect.signature() == 'reading of torso_lift_joint'

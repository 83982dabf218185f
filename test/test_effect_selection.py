"""auto's physical effects (core.effect_selection) and joint_play on simulated robots:
nothing added where the geometric model is the truth, the hidden effect added where it is
there, joint_play's size and transition torque recovered within 3σ."""
from __future__ import annotations

import numpy as np
import pytest

from kpi_calib_ros.app.identify import calibrate_cell, identify_cell, with_effects
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.diagnosis.screening import screen_effects
from kpi_calib_ros.core.effects.registry import available_effects, bind_effect, implausible
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell_settings import hidden_effects

SIGMA = 20e-6  # the default cell's tracker σ
# Joint 3 of the KR15-class cell carries -130 ... +130 N m of gravity torque over random
# poses: a play of 0.5 mrad crossed over ~30 N m shows both its size and its transition.
PLAY = {'joint_play:joint_3': {'b': -5e-4, 'u': float(np.log(30.0))}}



def _campaign(cm, hidden, seed, n=60):
    rng = np.random.default_rng(seed)
    effects, overrides = hidden_effects(hidden, cm.robot)
    truth = augmented_model(cm.model, effects)
    p_true = np.concatenate([true_parameters(cm.model.params, rng),
                             [overrides[n] for e in effects for n in e.parameter_names]])
    q = random_configurations(cm.model, cm.model.params.nominal, n, rng)
    sim = simulate_measurements(truth, p_true, q, SIGMA, rng)
    data = Measurements(q=sim.q, eta=sim.eta, stamps_ns=1_000_000 * (np.arange(n) + 1))
    return data, dict(zip(truth.params.names, p_true))


@pytest.mark.slow
@pytest.mark.parametrize('seed', range(6))
def test_auto_adds_no_effect_to_a_robot_without_hidden_effects(cm, seed):
    data, _ = _campaign(cm, {}, 100 + seed)
    cal = calibrate_cell(cm, data, model='auto')
    assert cal.choice.level == 'geometric'
    assert cal.choice.effects == () and cal.cell is not None and cal.cell.model.effects == ()
    assert cal.choice.effect_selection is not None
    assert 'no effect added' in cal.choice.reason


@pytest.mark.slow
def test_auto_adds_a_hidden_compliance_with_its_value(cm):
    c_true = -8e-7  # rad/(N m): stiffness 1.25e6 N m/rad, an industrial joint
    data, truth = _campaign(cm, {'joint_compliance:joint_2': {'c': c_true}}, 7)
    cal = calibrate_cell(cm, data, model='auto')
    assert cal.choice.effects == ('joint_compliance:joint_2',)
    name = 'joint_compliance.joint_2.c'
    assert abs(cal.result.value(name) - c_true) < 3 * cal.result.std_of(name)
    record = cal.choice.effect_selection
    assert record is not None and record['added'] == ['joint_compliance:joint_2']
    assert record['predicted_rms_after_m'] < 0.95 * record['predicted_rms_before_m']
    # The calibration is written with the model that has the effect.
    assert cal.cell is not None and [e.name for e in cal.cell.model.effects] == \
        ['joint_compliance:joint_2']


@pytest.mark.slow
def test_auto_adds_a_hidden_play_and_recovers_it(cm):
    data, truth = _campaign(cm, PLAY, 3)
    cal = calibrate_cell(cm, data, model='auto')
    assert cal.choice.effects == ('joint_play:joint_3',)
    for name in ('joint_play.joint_3.b', 'joint_play.joint_3.u'):
        assert abs(cal.result.value(name) - truth[name]) < 3 * cal.result.std_of(name), name


@pytest.mark.parametrize('seed', [3, 4, 5])
def test_joint_play_is_recovered_within_3_sigma_from_a_zero_start(cm, seed):
    """Size and transition torque, from b = 0 (where the τ0 column vanishes: it is freed
    once b is fitted) and τ0 = 1 N m."""
    data, truth = _campaign(cm, PLAY, seed)
    rich = with_effects(cm, ('joint_play:joint_3',))
    result = identify_cell(rich, data)
    assert result.converged
    for name in ('joint_play.joint_3.b', 'joint_play.joint_3.u'):
        assert name in result.estimated
        assert abs(result.value(name) - truth[name]) < 3 * result.std_of(name), name


@pytest.mark.slow
def test_screen_tells_a_sharp_backlash_from_a_play_and_a_compliance(cm):
    """joint_play contains backlash (τ0 -> 0) and compliance (τ0 -> ∞): with a hidden
    backlash or compliance the simpler effect is the candidate, the play merged into it or
    not counted; with a hidden play, the play."""
    expected = {'joint_backlash:joint_3': ({'b': -3e-4}, 'joint_backlash:joint_3'),
                'joint_compliance:joint_3': ({'c': -2e-6}, 'joint_compliance:joint_3'),
                'joint_play:joint_3': (PLAY['joint_play:joint_3'], 'joint_play:joint_3')}
    for spec, (values, top) in expected.items():
        data, _ = _campaign(cm, {spec: values}, 11)
        result = identify_cell(cm, data)
        ranked, _ = screen_effects(cm.model, data, result)
        best = ranked[0]
        assert best.spec == top and best.significant and best.plausible, spec
        if top == 'joint_play:joint_3':
            continue
        # The play at its sharpest grid point is the backlash's very column (merged into
        # it), else it is not counted against the simpler effect.
        play = [c for c in ranked if c.spec == 'joint_play:joint_3']
        assert ('joint_play:joint_3' in best.also_explained_by) or (
            not play[0].significant and 'simpler' in play[0].explanation), spec


def test_joint_play_bounds(cm):
    play = available_effects()['joint_play']
    assert play.n_shape == 1 and play.nests == ('joint_backlash', 'joint_compliance')
    bound = bind_effect(play, cm.robot, 'joint_3')
    assert bound.units == ('rad', '1')
    assert implausible(bound, [0.03, 0.0]) == ''          # 30 mrad: a loose service-arm wrist
    assert 'joint_play.joint_3.b' in implausible(bound, [0.2, 0.0])
    assert 'joint_play.joint_3.u' in implausible(bound, [1e-3, 9.0])  # τ0 = 8 kN m

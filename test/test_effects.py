"""Effect library: specs, the user API, and exact effect Jacobians."""
from __future__ import annotations

import importlib.metadata
import textwrap

import casadi as ca
import numpy as np
import pytest

from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.effects import registry as fx
from kpi_calib_ros.core.effects.registry import (
    EffectType,
    candidate_effects,
    implausible,
    parse_effect_spec,
    register_effect,
    resolve_effects,
    split_specs,
)
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.cell_settings import hidden_effects


@pytest.fixture
def clean_registry(monkeypatch):
    """Registry changes made by a test do not leak into others."""
    monkeypatch.setattr(fx, '_REGISTRY', dict(fx._REGISTRY))
    monkeypatch.setattr(fx, '_entry_points_loaded', False)


def _thermal(q_j, tau_j, theta):
    return theta[0] * ca.cos(q_j) ** 2


THERMAL = EffectType('thermal_bend', parameters=('g',), units=('rad',), joint_function=_thermal,
                     typical=(1e-4,), description='bending growing with cos² q')


def test_spec_names_parameters_and_units(cell):
    effect = parse_effect_spec('joint_compliance:joint_2', cell.robot)
    assert effect.name == 'joint_compliance:joint_2'
    assert effect.parameter_names == ('joint_compliance.joint_2.c',)
    assert effect.units == ('rad/(N m)',) and effect.uses_torque
    cyclic = parse_effect_spec(' cyclic_joint_error : joint_3 ', cell.robot)
    assert cyclic.parameter_names == ('cyclic_joint_error.joint_3.a',
                                      'cyclic_joint_error.joint_3.b')
    scale = parse_effect_spec('tracker_scale', cell.robot)
    assert scale.parameter_names == ('tracker_scale.s',) and scale.joint is None
    assert split_specs('joint_compliance:joint_2, joint_scale:joint_1,') == [
        'joint_compliance:joint_2', 'joint_scale:joint_1']


@pytest.mark.parametrize('spec, words', [
    ('joint_complience:joint_2', ['unknown effect', 'joint_compliance', 'joint_6']),
    ('joint_compliance:joint_9', ['joint_9', 'joint_1', 'joint_6']),
    ('joint_compliance', ['acts on one joint', 'joint_2']),
    ('tracker_scale:joint_2', ['global']),
    ('joint_scale:joint_1:x', ['effect:joint']),
    ('', ['non-empty']),
])
def test_bad_specs_name_the_spec_and_the_choices(cell, spec, words):
    with pytest.raises(ConfigError) as err:
        resolve_effects([spec], cell.robot, key='effects')
    message = str(err.value)
    assert message.startswith('effects[0]')
    for word in words:
        assert word in message, message


def test_duplicate_effect_is_an_error(cell):
    with pytest.raises(ConfigError, match='given twice'):
        resolve_effects(['joint_scale:joint_1', 'joint_scale:joint_1'], cell.robot)


@pytest.mark.parametrize('spec', ['joint_compliance:joint_2', 'cyclic_joint_error:joint_3',
                                  'cyclic_joint_error_h2:joint_1', 'joint_backlash:joint_3',
                                  'joint_scale:joint_1', 'tracker_scale'])
def test_effect_jacobian_equals_finite_differences(cell, spec):
    effect = parse_effect_spec(spec, cell.robot)
    model = augmented_model(cell.model, (effect,))
    rng = np.random.default_rng(3)
    k = len(effect.parameter_names)
    p = true_parameters(model.params, rng, overrides={
        n: 3 * t for n, t in zip(effect.parameter_names, effect.typical)})
    q = random_configurations(model, p, 6, rng)
    _, jac = model.jacobian(p, q)
    for i in range(len(p) - k, len(p)):
        eps = 1e-3 * abs(p[i])
        dp = np.zeros(len(p))
        dp[i] = eps
        fd = (model.predict(p + dp, q) - model.predict(p - dp, q)) / (2 * eps)
        assert np.allclose(jac[:, :, i], fd, rtol=1e-6, atol=1e-9), model.params.names[i]


def test_joint_effects_are_the_documented_corrections(cell):
    """h(p, q) with an effect equals the geometric h at the corrected joint values."""
    rng = np.random.default_rng(4)
    q = random_configurations(cell.model, cell.model.params.nominal, 5, rng)
    tau = cell.robot.gravity_torques(q)
    p_geo = true_parameters(cell.model.params, rng)
    cases = {'joint_compliance:joint_2': ([8e-7], 1, lambda qq, tt, th: th[0] * tt[:, 1]),
             'cyclic_joint_error:joint_3': ([2e-4, -1e-4], 2,
                                            lambda qq, tt, th: th[0] * np.sin(qq[:, 2])
                                            + th[1] * np.cos(qq[:, 2])),
             'joint_backlash:joint_2': ([3e-4], 1, lambda qq, tt, th: th[0] * np.sign(tt[:, 1])),
             'joint_play:joint_3': ([3e-4, np.log(50.0)], 2,
                                    lambda qq, tt, th: th[0] * np.tanh(tt[:, 2] / np.exp(th[1]))),
             'joint_scale:joint_1': ([1e-4], 0, lambda qq, tt, th: th[0] * qq[:, 0])}
    for spec, (theta, j, formula) in cases.items():
        model = augmented_model(cell.model, (parse_effect_spec(spec, cell.robot),))
        got = model.predict(np.concatenate([p_geo, theta]), q)
        q_eff = q.copy()
        q_eff[:, j] += formula(q, tau, np.array(theta))
        assert np.allclose(got, cell.model.predict(p_geo, q_eff), atol=1e-12), spec
    model = augmented_model(cell.model, (parse_effect_spec('tracker_scale', cell.robot),))
    got = model.predict(np.concatenate([p_geo, [2e-5]]), q)
    assert np.allclose(got, (1 + 2e-5) * cell.model.predict(p_geo, q), atol=1e-12)


def test_torque_effects_vanish_where_gravity_exerts_no_torque(cell):
    """Joint 1 is vertical: compliance and backlash must not turn numerical noise into signal."""
    rng = np.random.default_rng(5)
    q = random_configurations(cell.model, cell.model.params.nominal, 20, rng)
    p_geo = cell.model.params.nominal
    for spec in ('joint_compliance:joint_1', 'joint_backlash:joint_1'):
        effect = parse_effect_spec(spec, cell.robot)
        model = augmented_model(cell.model, (effect,))
        moved = model.predict(np.concatenate([p_geo, [10 * effect.typical[0]]]), q)
        assert np.max(np.abs(moved - cell.model.predict(p_geo, q))) < 1e-12, spec


def test_candidates_cover_every_screened_effect_and_joint(cell):
    candidates = candidate_effects(cell.robot, exclude=['joint_scale:joint_1'])
    names = {c.name for c in candidates}
    assert len(candidates) == 5 * 6 + 1 - 1  # compliance, cyclic, backlash, play, scale
    assert 'joint_scale:joint_1' not in names and 'tracker_scale' in names
    assert 'cyclic_joint_error_h2:joint_1' not in names  # optional, not screened by default
    with pytest.raises(ConfigError, match='valid effects'):
        candidate_effects(cell.robot, kinds=['nope'])


def test_registered_user_effect_plugs_into_model_and_specs(cell, clean_registry):
    register_effect(THERMAL)
    with pytest.raises(ValueError, match='already registered'):
        register_effect(EffectType('thermal_bend', ('g',), ('rad',), _thermal))
    effect = parse_effect_spec('thermal_bend:joint_3', cell.robot)
    model = augmented_model(cell.model, (effect,))
    q = random_configurations(cell.model, cell.model.params.nominal, 3,
                              np.random.default_rng(6))
    p = np.concatenate([cell.model.params.nominal, [1e-4]])
    q_eff = q.copy()
    q_eff[:, 2] += 1e-4 * np.cos(q[:, 2]) ** 2
    assert np.allclose(model.predict(p, q), cell.model.predict(cell.model.params.nominal, q_eff),
                       atol=1e-12)
    assert 'thermal_bend:joint_3' in {c.name for c in candidate_effects(
        cell.robot, kinds=['thermal_bend'])}


def test_entry_point_discovery(cell, clean_registry, monkeypatch, tmp_path):
    (tmp_path / 'my_effects_plugin.py').write_text(textwrap.dedent('''
        import casadi as ca
        from kpi_calib_ros.core.effects.registry import EffectType
        def make():
            return EffectType('sag', ('s',), ('rad',),
                              joint_function=lambda q, t, th: th[0] * ca.sin(q) ** 2)
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    eps = [importlib.metadata.EntryPoint('sag', 'my_effects_plugin:make', fx.ENTRY_POINT_GROUP),
           importlib.metadata.EntryPoint('bad', 'no_such_module_xyz:X', fx.ENTRY_POINT_GROUP)]
    monkeypatch.setattr(fx.importlib.metadata, 'entry_points',
                        lambda group: [e for e in eps if e.group == group])
    with pytest.warns(UserWarning, match='bad'):
        known = fx.available_effects()
    assert 'sag' in known
    assert parse_effect_spec('sag:joint_2', cell.robot).parameter_names == ('sag.joint_2.s',)


def test_cell_file_names_a_user_effect_file(cell, clean_registry, tmp_path):
    (tmp_path / 'cell_effects.py').write_text(textwrap.dedent('''
        from kpi_calib_ros.core.effects.registry import EffectType
        WARP = EffectType('warp', ('w',), ('rad',), joint_function=lambda q, t, th: th[0] * q ** 2)
    '''))
    effect = parse_effect_spec('cell_effects.py:WARP:joint_2', cell.robot, base_dir=tmp_path,
                               allow_code=True)
    assert effect.parameter_names == ('warp.joint_2.w',)
    with pytest.raises(ConfigError, match='cannot load user effect'):
        parse_effect_spec('missing.py:WARP:joint_2', cell.robot, base_dir=tmp_path,
                          allow_code=True)


EVIL = '''
from pathlib import Path
Path({marker!r}).write_text('the cell file ran this code')
from kpi_calib_ros.core.effects.registry import EffectType
SAG = EffectType('sag', ('g',), ('rad',), joint_function=lambda q, t, th: th[0] * q)
'''


@pytest.mark.parametrize('spec', ['evil.py:SAG:joint_2', 'evil_pkg.evil:SAG:joint_2'])
def test_code_named_by_a_cell_file_does_not_run_without_the_opt_in(cell, clean_registry,
                                                                   tmp_path, monkeypatch, spec):
    code = EVIL.format(marker=str(tmp_path / 'ran.marker'))
    (tmp_path / 'evil.py').write_text(code)
    (tmp_path / 'evil_pkg').mkdir()
    (tmp_path / 'evil_pkg' / '__init__.py').write_text('')
    (tmp_path / 'evil_pkg' / 'evil.py').write_text(code)
    monkeypatch.syspath_prepend(str(tmp_path))  # the module form would import it from here
    for call in (lambda: parse_effect_spec(spec, cell.robot, base_dir=tmp_path),
                 lambda: resolve_effects([spec], cell.robot, base_dir=tmp_path),
                 lambda: hidden_effects({spec: {}}, cell.robot, base_dir=tmp_path)):
        with pytest.raises(ConfigError, match='--allow-code-effects.*allow_code_effects'):
            call()
    assert not (tmp_path / 'ran.marker').exists()
    assert parse_effect_spec(spec, cell.robot, base_dir=tmp_path, allow_code=True).name == \
        'sag:joint_2'
    assert (tmp_path / 'ran.marker').exists()  # the opt-in runs it


def test_built_in_effects_need_no_opt_in(cell):
    assert resolve_effects(['joint_compliance:joint_2', 'tracker_scale'],
                           cell.robot)[1].name == 'tracker_scale'


def test_hidden_effects_for_the_simulator(cell):
    effects, overrides = hidden_effects({'joint_compliance:joint_2': {'c': 8e-7},
                                         'cyclic_joint_error:joint_3': {'a': 1e-4},
                                         'tracker_scale': None}, cell.robot)
    assert [e.name for e in effects] == ['joint_compliance:joint_2', 'cyclic_joint_error:joint_3',
                                         'tracker_scale']
    assert overrides == {'joint_compliance.joint_2.c': 8e-7, 'cyclic_joint_error.joint_3.a': 1e-4,
                         'cyclic_joint_error.joint_3.b': 2e-4, 'tracker_scale.s': 1e-5}
    with pytest.raises(ConfigError, match=r'simulation.hidden_effects.joint_scale:joint_1.x'):
        hidden_effects({'joint_scale:joint_1': {'x': 1.0}}, cell.robot)


def test_a_play_far_above_its_torques_must_be_a_plausible_compliance(cell):
    """joint_play b·tanh(τ/τ0) with every |τ| below τ0/3 is the compliance b/τ0: there it is
    judged by the compliance bound (1e-4 rad/(N m)), in its transition not."""
    play = parse_effect_spec('joint_play:joint_2', cell.robot)
    # (poses, joints) N m: joint_2's torques -40, 20, 50; the other joints' far larger
    tau = np.full((3, cell.robot.n_joints), 500.0)
    tau[:, play.joint_index] = [-40.0, 20.0, 50.0]
    soft = [0.015, np.log(200.0)]          # τ0 200 N m: compliance 7.5e-5 rad/(N m)
    too_soft = [0.045, np.log(200.0)]      # 2.25e-4 rad/(N m): a joint of 4.4e3 N m/rad
    assert implausible(play, soft, tau) == ''
    why = implausible(play, too_soft, tau)
    assert 'compliance b/τ0 = 0.000225' in why
    assert implausible(play, too_soft) == ''                     # no torques: its own bounds
    assert implausible(play, [0.045, np.log(100.0)], tau) == ''  # 50 > 100/3: a play

"""Expected TCP error with the misfit (core.precision.expected_tcp_error): with an effect the
model lacks, the true TCP error at the working poses lies within 2× the stated expected
error, where the parameter covariance alone promises too much; in calibration.yaml, the
summary and the diagnosis report. The full study: bench/expected_tcp_error.py."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from kpi_calib_ros.cli import main
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.effects.registry import parse_effect_spec
from kpi_calib_ros.core.estimation.cross_validation import validation_rms
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.precision import expected_tcp_error, honest_precision
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL

# Hidden effects of several kinds, each at a size χ² rejects with 40 poses.
HIDDEN = (('joint_compliance:joint_2', 1.5e-6), ('cyclic_joint_error:joint_1', 3e-4),
          ('joint_scale:joint_2', 3e-4), ('joint_backlash:joint_2', 3e-4))
EXTRA_WORK = 4



def hidden_run(cm, spec: str, value: float, seed: int):
    """A robot with the hidden effect ``spec`` (its first parameter ``value``), 40 random
    poses, the geometric model identified: the true TCP error at the cell's working pose
    and 4 random ones, and the expected error stated."""
    rng = np.random.default_rng(seed)
    effect = parse_effect_spec(spec, cm.robot)
    truth = augmented_model(cm.model, (effect,))
    p_geo = true_parameters(cm.model.params, rng)
    p_true = np.concatenate([p_geo, np.zeros(len(effect.parameter_names))])
    p_true[len(p_geo)] = value * rng.choice([-1.0, 1.0])
    q = random_configurations(cm.model, p_geo, 40, rng)
    q_work = np.vstack([cm.q_work, random_configurations(cm.model, p_geo, EXTRA_WORK, rng)])
    data = simulate_measurements(truth, p_true, q, cm.cell.sigma, rng)
    result = honest_precision(identify(cm.model, data, cm.cell.sigma, q_work))
    miss = np.linalg.norm(truth.predict(p_true, q_work) - result.tcp, axis=1)
    return miss, expected_tcp_error(cm.model, data, result), result, data


def test_true_tcp_error_within_twice_the_expected_error(cm):
    """4 hidden-effect kinds × 4 runs × 5 working poses: the true error is within 2× the
    expected error in >= 90 % of the poses, where 2× the χ²-scaled std alone covers fewer."""
    by_expected, by_std = [], []
    for k, (spec, value) in enumerate(HIDDEN):
        for seed in range(4):
            miss, expected, result, _ = hidden_run(cm, spec, value, 100 * k + seed)
            assert result.p_value < 0.01 and not expected.adequate
            by_expected += list(miss <= 2 * expected.expected_tcp_error_m)
            by_std += list(miss <= 2 * expected.tcp_std_m)
    assert np.mean(by_expected) >= 0.9, np.mean(by_expected)
    assert np.mean(by_std) < np.mean(by_expected) - 0.1, (np.mean(by_std),
                                                          np.mean(by_expected))


def test_expected_error_is_the_parameter_part_plus_the_held_out_misfit(cm):
    """b² = (held-out rms)² − 3σ², the expected error √(tr C + b²); an adequate model has
    no misfit term and states its parameter part alone."""
    _, expected, result, data = hidden_run(cm, *HIDDEN[0], 7)
    cv = validation_rms(cm.model, data, result)
    std = np.sqrt(np.trace(result.tcp_covariance, axis1=1, axis2=2))
    misfit = np.sqrt(cv ** 2 - np.sum(cm.cell.sigma ** 2))
    assert expected.misfit_m == pytest.approx(misfit)
    np.testing.assert_allclose(expected.expected_tcp_error_m, np.sqrt(std ** 2 + misfit ** 2))
    assert 'tcp_std_m is the parameter part' in expected.basis
    rng = np.random.default_rng(3)
    p_true = true_parameters(cm.model.params, rng)
    clean = simulate_measurements(cm.model, p_true, random_configurations(
        cm.model, p_true, 40, rng), cm.cell.sigma, rng)
    fit = honest_precision(identify(cm.model, clean, cm.cell.sigma, cm.q_work))
    plain = expected_tcp_error(cm.model, clean, fit)
    assert plain.adequate and plain.misfit_m == 0.0
    np.testing.assert_allclose(plain.expected_tcp_error_m, plain.tcp_std_m)


@pytest.mark.slow
def test_identify_and_diagnose_state_both_figures(tmp_path, capsys):
    """calibration.yaml's precision section, the identify summary and the diagnosis report
    carry tcp_std_m (parameter part) and expected_tcp_error_m (with the misfit)."""
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['simulation'] = {'hidden_effects': {'joint_compliance:joint_2': {'c': 1.5e-6}}}
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    bag = tmp_path / 'run.mcap'
    assert main(['simulate', '--cell', str(cell), '--n', '40', '--out', str(bag),
                 '--seed', '3']) == 0
    out = tmp_path / 'out'
    capsys.readouterr()
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out', str(out)]) == 0
    text = capsys.readouterr().out
    precision = yaml.safe_load((out / 'calibration.yaml').read_text())['precision']
    name = doc['working_poses'][0]['name']
    assert precision['expected_tcp_error_m'][name] > 1.5 * precision['tcp_std_m'][name]
    assert precision['misfit_m'] > 0
    assert 'scaled by chi2/dof' in precision['basis']          # the std's own basis kept
    assert 'tcp_std_m is the parameter part' in precision['expected_tcp_error_basis']
    assert f'TCP {name}: expected error' in text and 'parameter part' in text
    assert main(['diagnose', '--cell', str(cell), '--bag', str(bag), '--out',
                 str(tmp_path / 'diag')]) == 0
    report = (tmp_path / 'diag' / 'report.md').read_text()
    assert '## Expected TCP error at the working poses' in report
    assert 'expected_tcp_error_m' in report


@pytest.mark.slow
def test_one_high_leverage_pose_does_not_inflate_the_expected_error(cm):
    """40 poses turn joint_6 by less than 0.05 rad, one more by 1 rad: that pose alone
    determines some parameters (leverage 1 − 1e-5), and its held-out residual, the others'
    extrapolation to it, made the expected TCP error 13 mm against 0.6 mm without it (22×).
    It is left out of the held-out rms and named: the expected error stays within 10 % of
    the design without it, and the true error within twice it."""
    rng = np.random.default_rng(0)
    effect = parse_effect_spec('joint_compliance:joint_2', cm.robot)
    truth = augmented_model(cm.model, (effect,))
    p_geo = true_parameters(cm.model.params, rng)
    p_true = np.concatenate([p_geo, [1.5e-6]])
    q = random_configurations(cm.model, p_geo, 41, rng)
    q[:, 5] = rng.uniform(-0.05, 0.05, 41)
    q[40, 5] += 1.0
    figures = []
    for poses in (q[:40], q):
        data = simulate_measurements(truth, p_true, poses, cm.cell.sigma, rng)
        result = honest_precision(identify(cm.model, data, cm.cell.sigma, cm.q_work))
        figures.append((expected_tcp_error(cm.model, data, result), result))
    (plain, _), (far, result) = figures
    assert abs(far.expected_tcp_error_m[0] / plain.expected_tcp_error_m[0] - 1) < 0.1, (
        far.expected_tcp_error_m[0], plain.expected_tcp_error_m[0])
    assert plain.left_out == () and far.left_out == (40,)
    assert 'leverage >= 0.9 left out' in far.basis and far.to_dict()[
        'high_leverage_left_out'] == [40]
    miss = np.linalg.norm(truth.predict(p_true, cm.q_work) - result.tcp, axis=1)
    assert miss[0] <= 2 * far.expected_tcp_error_m[0]


def test_the_misfit_of_repeated_postures_is_that_of_a_new_pose():
    """40 postures measured in three sessions (readings 0.3 mrad apart), each with an error
    of its own (200 µm per axis, no function of anything): the systematic misfit b of the
    expected TCP error, held out with each posture's repeats, is what a new pose meets
    (0.93-1.09 of the misfit measured at 300 fresh poses); held out one row at a time, the
    repeats predicted each posture and b understated it (0.77-0.91)."""
    from kpi_calib_ros.app.cell_model import build_cell_model
    from kpi_calib_ros.io.cell import load_cell

    from hidden_campaigns import repeated_postures
    cm = build_cell_model(load_cell(DEFAULT_CELL.parent / 'ur_cell.yaml'))
    ratios = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        data, result, p = repeated_postures(cm, rng)
        expected = expected_tcp_error(cm.model, data, honest_precision(result))
        fresh_q = random_configurations(cm.model, p, 300, rng)
        fresh = (cm.model.predict(p, fresh_q) + rng.normal(0, 2e-4, (300, 3))
                 + rng.normal(0, 2e-5, (300, 3)))
        miss = np.mean(np.sum((fresh - cm.model.predict(result.values, fresh_q)) ** 2, axis=1))
        ratios.append(expected.misfit_m / np.sqrt(miss - 3 * 2e-5 ** 2))
    print(np.round(ratios, 3))
    assert np.mean(ratios) >= 0.9 and max(ratios) < 1.3

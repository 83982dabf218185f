"""Model-free residual analysis: the input a hidden deviation depends on comes out first.

Truths asserted: on simulated campaigns of a UR-class arm whose true robot carries a
deviation the effect library does not have (a joint error of 3 cycles per turn, a
deflection in proportion to a gravity torque), the right input is ranked first and
flagged, and its smooth fit recovers the hidden joint error; the F test is exact (its
p-values are uniform on pure noise) and clean campaigns flag nothing; the diagnosis
answers where, what, the command and the held-out error before/after.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import scipy.stats

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.diagnose import with_misfit_answer
from kpi_calib_ros.core.diagnosis.cell_diagnosis import CellDiagnosis
from kpi_calib_ros.core.diagnosis.misfit import GENERAL, NAMED, NONE, SMOOTH, Remedy, answer_misfit
from kpi_calib_ros.core.diagnosis.residual_analysis import (
    _holm,
    analyse_calibration,
    analyse_residuals,
)
from kpi_calib_ros.core.diagnosis.residual_bases import fourier_basis, spline_basis
from kpi_calib_ros.core.diagnosis.residual_inputs import ResidualInput
from kpi_calib_ros.core.diagnosis.verdict import diagnose
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.residuals import LinearizedFit, orthonormal_basis
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.report import write_report

SIGMA = 20e-6
N_POSES = 120
LIFT, ELBOW = 'shoulder_lift_joint', 'elbow_joint'


@pytest.fixture(scope='module')
def ur():
    return build_cell_model(load_cell(DEFAULT_CELL.parent / 'ur_cell.yaml'))


def campaign(cm, seed: int, hidden: str = '', n: int = N_POSES):
    """A true robot with random geometric errors and the ``hidden`` deviation, measured at
    ``n`` random poses over two hours, calibrated with the geometric model. Returns the
    data, the calibration and the hidden elbow error (rad) at each pose."""
    rng = np.random.default_rng(seed)
    model = cm.model
    p_true = true_parameters(model.params, rng)
    q = random_configurations(model, model.params.nominal, n, rng)
    elbow = cm.robot.joint_names.index(ELBOW)
    dq = np.zeros_like(q)
    if hidden == 'periodic':
        dq[:, elbow] = 2e-4 * np.sin(3 * q[:, elbow] + 0.4)
    if hidden == 'map':
        lift = cm.robot.joint_names.index(LIFT)
        dq[:, lift] = 2.5e-4 * np.sin(2 * q[:, lift]) * np.cos(q[:, elbow])
    points = model.predict(p_true, q + dq)
    if hidden == 'bending':
        lift = cm.robot.joint_names.index(LIFT)
        tau = cm.robot.gravity_torques(q)[:, lift]
        lever = model.joint_jacobian(p_true, q)[:, :, lift]
        unit = lever / np.linalg.norm(lever, axis=1, keepdims=True)
        points = points + 2.5e-4 * (tau / np.max(np.abs(tau)))[:, None] * unit
    stamps = np.sort(rng.uniform(0, 7200e9, n)).astype(np.int64)
    data = Measurements(q=q, eta=points + rng.normal(size=points.shape) * SIGMA,
                        stamps_ns=stamps)
    return data, identify(model, data, SIGMA, cm.q_work, max_iterations=25), dq[:, elbow]


def test_a_joint_error_of_three_cycles_per_turn_is_found_on_its_joint(ur):
    data, result, hidden = campaign(ur, 3, 'periodic')
    an = analyse_calibration(ur.model, data, result)
    top = an.scores[0]
    print('\n' + '\n'.join(f'{s.name}: share {s.share:.2f} p {s.p_value:.2g} {s.basis}'
                           for s in an.scores[:4]))
    assert top.name == ELBOW and top.significant and top.kind == 'joint'
    assert top.share > 0.5 and top.held_out_rms_after_m < 0.7 * top.held_out_rms_before_m
    # The fit is the hidden error less what the geometry absorbs (an offset and the first
    # harmonic's share a placement error reproduces): the 3-cycle part comes back.
    q = data.q[:, ur.robot.joint_names.index(ELBOW)]
    fitted = np.interp(q, top.curve_x, top.curve[:, 0])
    three = np.stack([np.cos(3 * q), np.sin(3 * q)], axis=1)
    coef_true = np.linalg.lstsq(three, hidden, rcond=None)[0]
    coef_fit = np.linalg.lstsq(three, fitted, rcond=None)[0]
    assert np.linalg.norm(coef_fit - coef_true) < 0.2 * np.linalg.norm(coef_true)
    assert 'elbow_joint is' in top.region


def test_a_deflection_with_the_gravity_torque_is_found_on_the_torque(ur):
    data, result, _ = campaign(ur, 4, 'bending')
    an = analyse_calibration(ur.model, data, result)
    top = an.scores[0]
    assert top.name == f'gravity torque {LIFT}' and top.significant and top.kind == 'torque'
    assert top.share > 0.5


def test_a_map_of_two_joints_is_found_as_their_interaction(ur):
    """A shoulder error that is a smooth map of shoulder and elbow angles: both joints are
    flagged, and their interaction beyond the sum of one-joint smooths is found and brings
    the held-out error to the noise floor σ√3 (within 20 %)."""
    data, result, _ = campaign(ur, 5, 'map')
    an = analyse_calibration(ur.model, data, result)
    assert an.scores[0].name == LIFT and ELBOW in {s.name for s in an.significant}
    pair = an.pair
    assert pair is not None and set(pair.names) == {LIFT, ELBOW} and pair.significant
    assert pair.held_out_rms_after_m < 0.8 * pair.held_out_rms_additive_m
    floor = SIGMA * np.sqrt(3)
    assert abs(an.combined_after_m - floor) < 0.2 * floor < an.combined_before_m - floor


@pytest.mark.slow
def test_the_f_test_is_exact_on_noise_and_holm_keeps_the_family_level():
    """Pure unit noise projected off a random 'geometry': the raw p-value of one input
    with one basis is uniform (Kolmogorov-Smirnov), and over 100 draws of 4 inputs with
    two bases each the family flags at most what α = 0.05 allows (binomial 99.9 % bound)."""
    rng = np.random.default_rng(0)
    n, k = 60, 8
    q = np.arange(n, dtype=float)[:, None]
    raw, flagged = [], 0
    for _ in range(100):
        jac = rng.normal(size=(3 * n, k))
        basis = orthonormal_basis(jac)
        r = rng.normal(size=3 * n)
        r -= basis @ (basis.T @ r)
        fit = LinearizedFit(r, jac, basis, np.ones(3), None, np.zeros(k))
        inputs = [ResidualInput(f'x{i}', rng.uniform(-1, 1, n), rng.normal(size=(n, 3, 1)),
                                ('f',), ('',), '') for i in range(4)]
        one = analyse_residuals(fit, r.reshape(-1, 3), inputs[:1], q, folds=5, sizes=(6,))
        raw.append(one.scores[0].p_value_raw)
        flagged += bool(analyse_residuals(fit, r.reshape(-1, 3), inputs, q, folds=5,
                                          alpha=0.05, sizes=(4, 8)).significant)
    assert scipy.stats.kstest(raw, 'uniform').pvalue > 0.01
    assert flagged <= scipy.stats.binom.ppf(0.999, 100, 0.05)


@pytest.mark.slow
def test_clean_campaigns_rarely_flag_an_input(ur):
    """At most one of five clean campaigns flags an input (at the family-wise α = 0.01,
    two or more happen with probability 0.1 %; bench/residual_inputs.py counts 100)."""
    flagged = 0
    for seed in range(5):
        data, result, _ = campaign(ur, 100 + seed)
        flagged += bool(analyse_calibration(ur.model, data, result).significant)
    assert flagged <= 1


def test_bases_span_what_they_claim():
    x = np.linspace(-2, 3, 50)
    b = spline_basis(x, 8)
    assert b.shape == (50, 8)
    np.testing.assert_allclose(b.sum(axis=1), 1.0, atol=1e-12)  # partition of unity
    cubic = 0.3 * x ** 3 - x + 2
    assert np.linalg.lstsq(b, cubic, rcond=None)[1][0] < 1e-20  # cubics exactly
    f = fourier_basis(x, 4)
    assert f.shape == (50, 9)
    np.testing.assert_allclose(f[:, 3], np.cos(3 * x))
    np.testing.assert_allclose(_holm(np.array([0.01, 0.04, 0.03, 0.5])),
                               [0.04, 0.09, 0.09, 0.5])


@pytest.mark.slow
def test_diagnose_answers_where_what_command_and_held_out_error(ur, tmp_path):
    """A 3-cycle elbow error, which no named effect of the library has: the answer names
    the elbow as where; the frequency search offers the periodic joint error at 3 cycles
    per revolution as what is missing, with its command; without the general effects the
    answer is a smooth misfit of the elbow with no command. The held-out error falls; the
    report carries the section, the table and the partial-residual plot."""
    data, result, _ = campaign(ur, 3, 'periodic')
    diag = diagnose(ur.model, data, result)
    cd = with_misfit_answer(CellDiagnosis(ur.model, data, result, diag))
    answer = cd.answer
    assert answer is not None and answer.inputs[0] == ELBOW
    spec = f'periodic_joint_error:{ELBOW}:k=3'
    assert diag.best is not None and diag.best.spec == spec
    assert answer.missing.command == f'--effects {spec}'
    before, after = answer.missing.held_out_before_m, answer.missing.held_out_after_m
    assert after < 0.7 * before
    library = diagnose(ur.model, data, result, general=False)
    plain = with_misfit_answer(CellDiagnosis(ur.model, data, result, library)).answer
    assert plain is not None and plain.inputs[0] == ELBOW
    assert plain.missing.kind == SMOOTH and ELBOW in plain.missing.what
    assert plain.missing.command == ''
    # The library's screen names an effect that explains a sliver (a joint scale of the
    # elbow): the answer names it as a partial step, not as what is missing.
    assert library.best is not None and f'--effects {library.best.spec}' in plain.missing.what
    # ... and its command line says so: "none: no effect of the library has this shape"
    # contradicted the verdict's "Add it with" where two library effects were missing
    assert plain.missing.part == f'--effects {library.best.spec}'
    assert any(line.startswith(f'the command that adds it: none answers it alone: --effects '
                               f'{library.best.spec} explains part of it')
               for line in plain.lines()), plain.lines()
    assert plain.missing.held_out_after_m < 0.7 * plain.missing.held_out_before_m
    write_report(tmp_path, cd)
    report = (tmp_path / 'report.md').read_text()
    assert '## Where the model fails' in report and '(partial_residuals.png)' in report
    assert (tmp_path / 'partial_residuals.png').stat().st_size > 10_000
    doc = json.loads((tmp_path / 'diagnosis.json').read_text())
    assert doc['residual_inputs']['inputs'][0]['name'] == ELBOW
    assert doc['misfit']['where'] == answer.where


@pytest.mark.slow
def test_clean_diagnosis_answers_nothing_is_missing(ur):
    data, result, _ = campaign(ur, 101)
    cd = with_misfit_answer(CellDiagnosis(ur.model, data, result,
                                          diagnose(ur.model, data, result)))
    assert cd.answer is not None and cd.answer.inputs == ()
    assert cd.answer.missing.kind == NONE


def test_a_general_remedy_that_gains_more_is_the_answer():
    """The slot for remedies built elsewhere (the learned residual, general effects): the
    one with the smallest held-out error is what is missing, a named effect that gains
    less is not; a remedy that does not lower the error is never offered."""
    named = Remedy(NAMED, 'joint_scale:elbow_joint', '--effects joint_scale:elbow_joint',
                   100e-6, 90e-6)
    learned = Remedy(GENERAL, 'a learned residual', 'kpi-calib identify --learned-residual',
                     100e-6, 40e-6)
    worse = Remedy(GENERAL, 'a worse one', 'kpi-calib x', 100e-6, 120e-6)
    answer = answer_misfit(None, named, (learned, worse))
    assert answer.missing is learned and answer.lines()[2].endswith(learned.command)
    assert answer_misfit(None, named, (worse,)).missing is named
    assert answer_misfit(None, None, (worse,), model_adequate=True).missing.kind == NONE


def test_the_size_where_the_misfit_is_largest_is_read_where_the_fit_is_determined():
    """A joint error of 0.2 mrad · sin 3x over x in [-1, 1], where above x = 0.7 the joint
    barely moves the point (a lever of 1 µm per rad): the implied joint error there is the
    noise over that lever, ~10 rad. The size reported ('up to … µrad') is read only where
    the fitted function is determined (3 standard errors from the stated σ): over 8 seeds it
    stays within 25× of the true 200 µrad, never the 2.6e6 µrad of a spline piece fitted to
    those rows alone, and is the true size within 2× in most."""
    import re
    sizes = []
    for seed in range(8):
        rng = np.random.default_rng(seed)
        n, k, sigma = 200, 4, 1e-5
        x = np.sort(rng.uniform(-1, 1, n))
        lever = np.where(x < 0.7, 1.0, 1e-6)
        direction = rng.normal(size=(n, 3))
        direction /= np.linalg.norm(direction, axis=1)[:, None]
        fields = (direction * lever[:, None])[:, :, None]
        res = fields[:, :, 0] * (2e-4 * np.sin(3 * x))[:, None] + rng.normal(size=(n, 3)) * sigma
        jac = rng.normal(size=(3 * n, k))
        basis = orthonormal_basis(jac)
        r = res.reshape(-1) / sigma
        r -= basis @ (basis.T @ r)
        fit = LinearizedFit(r, jac, basis, np.full(3, 1 / sigma), None, np.zeros(k))
        joint = ResidualInput('joint_x', x, fields, ('joint error',), ('rad',), 'rad',
                              kind='joint')
        score = analyse_residuals(fit, (r * sigma).reshape(-1, 3), [joint],
                                  np.arange(n, dtype=float)[:, None], folds=5,
                                  sizes=(8,)).scores[0]
        assert score.significant
        print(score.region)
        stated = re.match(r'joint error up to (\S+) µrad', score.region)
        # a size the points cannot show (more than twice the largest residual) is not stated
        sizes.append(float(stated.group(1)) if stated else np.inf)
        assert stated or 'not what the points show' in score.region
    assert max(s for s in sizes if np.isfinite(s)) < 25 * 200, sizes
    assert np.sum(np.abs(np.log(np.array(sizes) / 200)) < np.log(2)) >= 6, sizes


def test_a_misfit_over_time_is_placed_where_rows_were_measured_not_between_recordings():
    """Two recordings a day apart (0-1170 s and 86400-87570 s), the second's points drifted
    by 300 µm more at its end than at its start. The region reported for time lies inside the
    recordings' spans: the spline between them, where no row was measured, reached 7.75e4
    µm "where time is 3.147e+04 to 6.732e+04 s" on four recordings whose largest residual was
    416 µm."""
    import re
    rng = np.random.default_rng(3)
    n, k, sigma = 80, 4, 2e-5
    t = np.r_[np.linspace(0, 1170, n // 2), 86400 + np.linspace(0, 1170, n // 2)]
    fields = np.zeros((n, 3, 4))
    fields[:, :, :3] = np.eye(3)
    drift = np.where(t > 4e4, 3e-4 * (t - 86400) / 1170, 0.0)
    res = np.c_[drift, np.zeros(n), np.zeros(n)] + rng.normal(size=(n, 3)) * sigma
    jac = rng.normal(size=(3 * n, k))
    basis = orthonormal_basis(jac)
    r = res.reshape(-1) / sigma
    r -= basis @ (basis.T @ r)
    fit = LinearizedFit(r, jac, basis, np.full(3, 1 / sigma), None, np.zeros(k))
    time = ResidualInput('time', t, fields, ('drift x', 'drift y', 'drift z', 'scale'),
                         ('m', 'm', 'm', ''), 's')
    score = analyse_residuals(fit, (r * sigma).reshape(-1, 3), [time],
                              np.arange(n, dtype=float)[:, None], folds=5).scores[0]
    print(score.region)
    assert score.significant
    size = float(re.match(r'drift x up to (\S+) µm', score.region).group(1))
    assert size < 2 * 300
    where = [float(v) for v in re.findall(r'-?\d[\d.e+]*', score.region.split(' is ')[1])]
    assert all(v <= 1170 or v >= 86400 for v in where), score.region


def test_a_covariate_of_two_values_is_a_level_each_not_a_curve(ur):
    """A recording's one-hot (or a payload changed once) takes two values: the analysis fits
    a level to each, and says where the misfit is by the value, not by a range between the
    two ("where recording.d2A is 0.5377 to 1")."""
    from kpi_calib_ros.core.diagnosis.residual_inputs import residual_inputs
    data, result, _ = campaign(ur, 5, n=40)
    second = (np.arange(len(data)) >= 20).astype(float)
    temperature = 20.0 + np.linspace(0.0, 3.0, len(data))
    inputs = {i.name: i for i in residual_inputs(
        ur.model, data, result, {'recording.b': (second, ''), 'temperature': (temperature,
                                                                            'degC')})}
    assert inputs['recording.b'].categorical and not inputs['temperature'].categorical


def _three_stations(scale: float, every: bool = False):
    """The default cell measured from three stations metres apart, 40 poses each, the third's
    points (``every``: every station's) ``scale`` larger (about its tracker); its cell model
    with the recordings, rows."""
    from kpi_calib_ros.app.measurements import with_recordings
    from kpi_calib_ros.core.measurement import recordings as rec
    from kpi_calib_ros.core.simulation import simulate_measurements
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    rng = np.random.default_rng(8)
    p_robot = true_parameters(cm.model.params, rng)
    moves = {'a': np.zeros(6), 'b': np.array([-1.2, 1.5, 0.1, 0.02, -0.03, 0.6]),
             'c': np.array([0.8, -1.9, -0.2, -0.04, 0.01, -0.5])}
    recordings = [rec.Recording(name) for name in moves]
    parts = []
    for name, move in moves.items():
        placed = p_robot.copy()
        placed[:6] += move
        q = random_configurations(cm.model, placed, 40, rng)
        rows = simulate_measurements(cm.model, placed, q, 2e-5, rng)
        if name == 'c' or every:
            rows = dataclasses.replace(rows, eta=rows.eta * (1 + scale))
        parts.append(rows)
    data = rec.combine(parts, recordings)
    placed_cm = with_recordings(cm, recordings)
    return placed_cm, data


def test_a_stations_scale_is_read_about_its_own_points():
    """Three stations (tracker frames metres apart), the third's points scaled by 150 ppm
    about its tracker: the residual analysis names recording.c and states its scale about
    that station's own points (the shared geometry takes part of it: 0.5-1.1 of the
    truth). About the centroid of every station's points together it read 4.95 ppm for a
    122 ppm misfit (the audit's independent fit)."""
    from kpi_calib_ros.app.identify import calibrate_cell
    from kpi_calib_ros.core.measurement.covariates import measured_covariates
    placed_cm, data = _three_stations(150e-6)
    result = calibrate_cell(placed_cm, data, model='geometric').result
    an = analyse_calibration(placed_cm.model, data, result,
                             measured_covariates(data.covariates))
    top = an.scores[0]
    print(top.name, top.share, top.region)
    assert top.name == 'recording.c' and top.significant
    assert top.region.startswith('scale up to ')
    ppm = float(top.region.split()[3])
    assert 75 <= ppm <= 165, top.region


def test_a_station_that_differs_is_named_first_not_the_joint_readings():
    """Of three stations the third's points are 150 ppm larger (a warmer day): no effect of
    the robot explains it, the residual analysis puts most of the misfit on recording.c,
    and the verdict says so. It told the user that the joint readings may be the cause and
    to state noise.joint_sigma, which would have hidden the station."""
    from kpi_calib_ros.app.diagnose import diagnose_cell
    placed_cm, data = _three_stations(150e-6)
    cd = diagnose_cell(placed_cm, data, recording_names=['a', 'b', 'c'])
    print(cd.diagnosis.verdict)
    assert "Recording 'c' differs from the others" in cd.diagnosis.verdict
    assert 'joint readings may be the cause' not in cd.diagnosis.verdict


def test_a_smooth_function_that_predicts_worse_is_not_what_is_missing(ur):
    """A smooth misfit is named what is missing only when its own held-out figure is lower
    than before: on the real TIAGo the flagged inputs' function took the held-out error
    from 2749 to 7073 µm (repeated postures in other folds) and was named all the same."""
    data, result, _ = campaign(ur, 3, 'periodic')
    an = analyse_calibration(ur.model, data, result)
    assert an.significant and an.combined_after_m < an.combined_before_m
    assert answer_misfit(an, None, ()).missing.kind == SMOOTH
    worse = dataclasses.replace(an, combined_after_m=2.5 * an.combined_before_m)
    answer = answer_misfit(worse, None, ())
    assert answer.missing.kind == NONE and answer.inputs == tuple(s.name for s in an.significant)


def test_repeated_postures_are_held_out_together():
    """40 postures measured in three sessions (readings 0.3 mrad apart), each posture with
    an error of its own (200 µm, no function of any input): held out one row at a time, a
    posture's repeats in the other folds taught its error to the smooth functions, and
    shares up to 0.42 looked like a misfit that carries over to new poses (the real TIAGo's
    0.71). Held out with their repeats, no input explains a quarter of it."""
    from hidden_campaigns import repeated_postures
    cm = build_cell_model(load_cell(DEFAULT_CELL.parent / 'ur_cell.yaml'))
    shares = []
    for seed in range(3):
        data, result, _ = repeated_postures(cm, np.random.default_rng(seed))
        shares += [s.share for s in analyse_calibration(cm.model, data, result).scores]
    print(f'largest share {max(shares):.2f}')
    assert max(shares) < 0.25


def test_a_size_beyond_what_the_points_show_is_not_stated():
    """A joint-error curve of 0.6 rad on a lever of 0.46 m moves a point 278 mm, where no
    point missed by more than 7.1 mm (a real TIAGo's spline nearly one of the geometry's
    directions): the region is named without a size; a size the residuals can show is
    stated, with what it moves at the points."""
    from kpi_calib_ros.core.diagnosis.residual_curves import curve_region
    x = np.linspace(-1.0, 1.0, 50)
    fields = np.zeros((50, 3, 1))
    fields[:, 0, 0] = 0.46
    inp = ResidualInput('arm_3_joint', x, fields, ('joint error',), ('rad',), 'rad',
                        kind='joint', periodic=True)
    grid = np.linspace(-1.0, 1.0, 9)
    big = curve_region(inp, grid, 0.6 * np.exp(-grid[:, None] ** 2), largest_m=7.1e-3)
    assert 'not what the points show' in big and 'µrad' not in big, big
    small = curve_region(inp, grid, 2e-3 * np.exp(-grid[:, None] ** 2), largest_m=7.1e-3)
    assert small.startswith('joint error up to 2e+03 µrad (~920 µm at the points)'), small


def test_what_every_recording_shares_is_no_recordings_own():
    """Two recordings, a misfit along one field (a scale) on every row: the recording's
    one-hot input is judged on how it differs from the other recording, so the shared
    misfit flags it not (on three real TIAGo sessions each later recording was flagged for
    a 367 ppm scale that was one scale shared by all: alone, 1.2-1.4σ); the same misfit on
    the second recording's rows only flags it."""
    found = {}
    for case in ('shared', 'own'):
        rng = np.random.default_rng(2)
        n, k, sigma = 160, 4, 1e-5
        rec = (np.arange(n) >= n // 2).astype(float)
        field = rng.normal(size=(n, 3)) * 0.5
        size = 1e-4 * (np.ones(n) if case == 'shared' else rec)
        res = field * size[:, None] + rng.normal(size=(n, 3)) * sigma
        jac = rng.normal(size=(3 * n, k))
        basis = orthonormal_basis(jac)
        r = res.reshape(-1) / sigma
        r -= basis @ (basis.T @ r)
        fit = LinearizedFit(r, jac, basis, np.full(3, 1 / sigma), None, np.zeros(k))
        one_hot = ResidualInput('recording.b', rec, field[:, :, None], ('scale',), ('',), '',
                                categorical=True)
        score = analyse_residuals(fit, (r * sigma).reshape(-1, 3), [one_hot],
                                  np.arange(n, dtype=float)[:, None], folds=5).scores[0]
        found[case] = score
    assert not found['shared'].significant, found['shared'].p_value
    assert found['own'].significant and found['own'].share > 0.3

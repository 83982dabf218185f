"""Faults, not model misfit (core/estimation/outliers.py): a pose the model misfits is kept and
named, a fault of one reflector is excluded, exclusion runs in batches and diagnose keeps the
points identify keeps. Simulated campaigns on the default cell (three reflectors unless
said)."""
from __future__ import annotations

import copy
import dataclasses
import json

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.calibration_document import add_robust_sections, calibration_document
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.diagnose import diagnose_cell
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.estimation.robust import OutlierSettings
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.replicates import pose_groups
from kpi_calib_ros.core.simulation import (
    one_joint_at_a_time,
    random_configurations,
    true_parameters,
)
from kpi_calib_ros.io.bag_writing import write_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, load_cell, read_cell_document
from kpi_calib_ros.io.names import CALIBRATION_FILE, DIAGNOSIS_FILE

OFFSETS = [[0.0, 0.0, 0.03], [0.06, 0.0, 0.03], [0.0, 0.05, 0.02]]
SWEPT = 1          # the joint whose hidden error grows with the cube of its travel
HIDDEN = 6e-5      # rad / rad³: 0.1-0.3 mm at the sweep ends, 5-15 σ̂


@pytest.fixture(scope='module')
def cm():
    doc = copy.deepcopy(read_cell_document(DEFAULT_CELL))
    del doc['reflector']['offset']
    doc['reflectors'] = [{'name': n, 'offset': o} for n, o in zip('abc', OFFSETS)]
    return build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))


@pytest.fixture(scope='module')
def p_true(cm):
    return true_parameters(cm.model.params, np.random.default_rng(1))


def _hidden(cm, q):
    """Joint values the robot really has: SWEPT is off by HIDDEN·(travel from home)³, an
    effect no parameter of the model describes."""
    q = np.array(q, float)
    q[:, SWEPT] += HIDDEN * (q[:, SWEPT] - cm.q_work[0][SWEPT]) ** 3
    return q


def _three_reflectors(cm, p_true, q, rng):
    rows = np.repeat(q, 3, axis=0)
    ref = np.tile(np.arange(3), len(q))
    eta = cm.model.predict(p_true, _hidden(cm, rows), reflector=ref)
    eta += rng.normal(size=eta.shape) * cm.cell.sigma
    return Measurements(q=rows, eta=eta, reflector=ref, stamps_ns=np.arange(len(rows)) + 1)


def _no_exclusion(cm):
    off = dataclasses.replace(cm.cell.identification, outliers=OutlierSettings(exclude=False))
    return dataclasses.replace(cm, cell=dataclasses.replace(cm.cell, identification=off))


def _held_out_rms(cm, p_true, values):
    q = one_joint_at_a_time(cm.model, cm.q_work[0], 7, np.random.default_rng(5), span=0.9)
    ref = np.zeros(len(q), int)
    err = cm.model.predict(values, q, reflector=ref) - \
        cm.model.predict(p_true, _hidden(cm, q), reflector=ref)
    return float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))


def _sweeps(cm, p_true):
    """24 poses, each joint swept alone over 90 % of its range, three reflectors each."""
    q = one_joint_at_a_time(cm.model, cm.q_work[0], 4, span=0.9)
    return _three_reflectors(cm, p_true, q, np.random.default_rng(1))


def test_misfit_at_the_sweep_ends_is_kept_and_held_out_error_is_the_no_exclusion_one(
        cm, p_true):
    data = _sweeps(cm, p_true)
    cal = calibrate_cell(cm, data)
    plain = calibrate_cell(_no_exclusion(cm), data)
    assert cal.robust.kept.all() and not cal.robust.excluded
    # The points are far off: 11-14 σ̂ at the end of joint 1's sweep, three reflectors alike.
    ends = np.flatnonzero(np.isin(pose_groups(data.q), [4, 7]))
    assert set(cal.robust.misfit) == set(ends) and set(cal.robust.outliers) == set(ends)
    assert any('model misfit at poses 4, 7' in w and 'diagnose' in w
               for w in cal.robust.warnings)
    doc = add_robust_sections(calibration_document(cm, cal.result), cal)
    assert doc['robust']['misfit'] == sorted(ends) and doc['robust']['excluded'] == []
    held, held_plain = (_held_out_rms(cm, p_true, c.result.values) for c in (cal, plain))
    print(f'held-out rms: {held * 1e6:.1f} µm, without exclusion {held_plain * 1e6:.1f} µm')
    assert held == pytest.approx(held_plain, rel=1e-9)


def test_one_reflector_sweep_ends_are_kept_for_their_leverage(p_true):
    single = build_cell_model(load_cell(DEFAULT_CELL))
    p = true_parameters(single.model.params, np.random.default_rng(1))
    q = one_joint_at_a_time(single.model, single.q_work[0], 4, span=0.9)
    eta = single.model.predict(p, _hidden(single, q))
    eta += np.random.default_rng(2).normal(size=eta.shape) * single.cell.sigma
    data = Measurements(q=q, eta=eta, stamps_ns=np.arange(len(q)) + 1)
    cal = calibrate_cell(single, data)
    # Joint 1's sweep ends: 12-15 σ̂ off, the fit leans on each (leverage 0.9 along one
    # direction); excluding one raised the held-out rms from 42.7 to 58.5 µm.
    assert not cal.robust.excluded and set(cal.robust.misfit) == {4, 7}
    plain = calibrate_cell(_no_exclusion(single), data)
    assert _held_out_rms(single, p, cal.result.values) == pytest.approx(
        _held_out_rms(single, p, plain.result.values), rel=1e-9)


def test_a_fault_of_one_reflector_is_excluded_even_at_a_pose_the_model_misfits(cm, p_true):
    data = _sweeps(cm, p_true)
    eta = data.eta.copy()
    rng = np.random.default_rng(7)
    faults = {22: 1e-3, 4: 0.5e-3}  # reflector b at a sweep end, reflector b mid-sweep
    for i, size in faults.items():
        d = rng.normal(size=3)
        eta[i] += size * d / np.linalg.norm(d)
    cal = calibrate_cell(cm, dataclasses.replace(data, eta=eta))
    assert {e.index for e in cal.robust.excluded} == set(faults)
    assert {21, 23} <= set(cal.robust.misfit)  # its pose's other reflectors: kept
    plain = calibrate_cell(_no_exclusion(cm), dataclasses.replace(data, eta=eta))
    assert _held_out_rms(cm, p_true, cal.result.values) < \
        _held_out_rms(cm, p_true, plain.result.values)


def _random_campaign_with_faults(cm, p_true, n_poses, fraction, seed):
    """``n_poses`` random poses, three reflectors each, ``fraction`` of the points moved
    0.5-5 mm in a random direction (a tracker locked on something else)."""
    rng = np.random.default_rng(seed)
    q = random_configurations(cm.model, cm.geometric.nominal, n_poses, rng)
    data = _three_reflectors(cm, p_true, q, rng)
    data = dataclasses.replace(data, eta=cm.model.predict(p_true, data.q,
                                                          reflector=data.reflector)
                               + rng.normal(size=data.eta.shape) * cm.cell.sigma)
    faults = np.sort(rng.choice(len(data), int(fraction * len(data)), replace=False))
    d = rng.normal(size=(len(faults), 3))
    eta = data.eta.copy()
    eta[faults] += rng.uniform(0.5e-3, 5e-3, (len(faults), 1)) * d / \
        np.linalg.norm(d, axis=1, keepdims=True)
    return dataclasses.replace(data, eta=eta), faults


@pytest.mark.slow
def test_identify_and_diagnose_exclude_the_same_points_the_faults_in_batches(cm, p_true):
    # 30 % faults, above the default max_fraction 0.2: that caps only the faults no other
    # reflector of the pose confirms; these the other reflectors confirm.
    data, faults = _random_campaign_with_faults(cm, p_true, 100, 0.3, 11)
    assert cm.cell.identification.outliers == OutlierSettings() and \
        len(faults) > OutlierSettings().max_fraction * len(data)
    rounds: list[str] = []
    cal = calibrate_cell(cm, data, progress=rounds.append)
    excluded = sorted(e.index for e in cal.robust.excluded)
    assert excluded == faults.tolist()
    # Batches: a few rounds for 90 faults, each reported.
    assert 1 < len(rounds) < 20 and all('outliers: round' in r for r in rounds)
    cd = diagnose_cell(cm, data, add_best=False)
    assert np.array_equal(cd.kept, cal.robust.kept) and sorted(cd.excluded) == excluded
    assert len(cd.data) == len(data) - len(faults)
    assert cd.diagnosis.residuals.sigma_robust_m == pytest.approx(cal.robust.sigma_robust,
                                                                 rel=0.05)


@pytest.mark.slow
def test_cli_identify_shows_rounds_and_diagnose_lists_the_same_excluded_points(
        tmp_path, capsys):
    """A bag of 60 random poses (default cell, one reflector) with three 1 mm faults:
    identify prints its exclusion rounds on stderr; diagnose excludes the same points."""
    single = build_cell_model(load_cell(DEFAULT_CELL))
    rng = np.random.default_rng(4)
    p = true_parameters(single.model.params, rng)
    q = random_configurations(single.model, single.model.params.nominal, 60, rng)
    eta = single.model.predict(p, q) + rng.normal(size=(len(q), 3)) * single.cell.sigma
    faults = [7, 21, 44]
    eta[faults] += 1e-3 / np.sqrt(3)
    joints, points = synthesize_streams(q, single.joint_names, eta, single.cell.tracker_frame)
    bag = write_bag(tmp_path / 'faults.mcap', joints, points)
    assert main(['identify', '--cell', str(DEFAULT_CELL), '--bag', str(bag),
                 '--out', str(tmp_path / 'cal')]) == 0
    assert 'outliers: round 1: excluded' in capsys.readouterr().err
    cal = yaml.safe_load((tmp_path / 'cal' / CALIBRATION_FILE).read_text())
    assert sorted(e['index'] for e in cal['robust']['excluded']) == faults
    assert main(['diagnose', '--cell', str(DEFAULT_CELL), '--bag', str(bag),
                 '--out', str(tmp_path / 'diag')]) == 0
    diag = json.loads((tmp_path / 'diag' / DIAGNOSIS_FILE).read_text())
    assert sorted(diag['residuals']['excluded']) == faults
    assert diag['residuals']['measurements'] == 60 - len(faults)
    assert diag['residuals']['sigma_robust_m'] == pytest.approx(
        cal['robust']['sigma_robust_m'], rel=0.05)


def test_a_misfit_everywhere_with_one_point_a_pose_is_kept_not_excluded():
    """One reflector, random poses, an effect the model lacks far above the noise at many
    of them (a real arm's 0.4 mm, the UR10 of shared/data): no replicate tells a fault,
    and more than max_fraction of 'faults' is a misfit. Nothing is excluded (before:
    'more than 20 % ... lie beyond', exit 2, after excluding a fifth of the poses), the
    fit is the no-exclusion one, and the points are named as misfit."""
    single = build_cell_model(load_cell(DEFAULT_CELL))
    p = true_parameters(single.model.params, np.random.default_rng(3))
    q = random_configurations(single.model, p, 60, np.random.default_rng(4))
    lacking = q.copy()
    lacking[:, SWEPT] += 40 * HIDDEN * (q[:, SWEPT] - single.q_work[0][SWEPT]) ** 3
    lacking[:, 2] += 2e-4 * np.sin(3 * q[:, 2])
    eta = single.model.predict(p, lacking)
    eta += np.random.default_rng(5).normal(size=eta.shape) * single.cell.sigma
    data = Measurements(q=q, eta=eta, stamps_ns=np.arange(len(q)) + 1)
    cal = calibrate_cell(single, data)
    assert not cal.robust.excluded
    assert cal.robust.misfit
    assert any(f'more than {OutlierSettings().max_fraction:.0%} of the measurements' in w
               for w in cal.robust.warnings)
    plain = calibrate_cell(_no_exclusion(single), data)
    np.testing.assert_allclose(cal.result.values, plain.result.values, rtol=0, atol=1e-12)


def test_a_backlash_is_not_excluded_as_lone_faults_on_a_stock_xarm7():
    """A stock xArm7 with a 0.2 mrad backlash of joint 2, one reflector, 150 poses of one
    region: the geometric fit left 28 of them (19 %) beyond the threshold with no replicate
    to confirm a fault, and with the former cap of 20 % they were excluded as faults; on the
    76 % left, diagnose judged the backlash not to hold over held-out regions and said to
    keep the model without it (on the held-out other region the geometric model missed by
    208 µm, with the backlash 41 µm). Faults no replicate confirms are few: beyond 5 % of
    the points they are the model's misfit, kept, and the backlash is recommended."""
    from kpi_calib_ros.app.simulate import truth_cell_model
    from kpi_calib_ros.core.simulation import (
        ErrorMagnitudes,
        measurable_batch,
        sampling_bounds,
        simulate_measurements,
    )
    from kpi_calib_ros.io.arm_cell import arm_cell_document
    from kpi_calib_ros.io.cell import cell_from_dict
    doc = arm_cell_document('package://example-robot-data/robots/xarm_description/urdf/'
                            'xarm7.urdf', 'link_base', 'link7', 20e-6)
    cm = build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))
    doc['simulation'] = {'hidden_effects': {'joint_backlash:joint2': {'b': 2e-4}}}
    truth, overrides = truth_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))
    rng = np.random.default_rng(2)
    p_true = true_parameters(truth.model.params, rng, ErrorMagnitudes(
        placement_translation=(2e-4, 8e-4), placement_rotation=(3e-4, 1.5e-3),
        joint_offset=(5e-4, 1.5e-3)), overrides)
    lo, hi = sampling_bounds(truth.model)
    found = []
    while sum(len(f) for f in found) < 150:
        c = measurable_batch(truth.model, truth.model.params.nominal, rng, 4000,
                             np.cos(np.pi * 0.999))
        u = (c - lo) / (hi - lo)
        found.append(c[(u[:, 1] < 0.6) & (u[:, 2] < 0.6)])
    q = np.vstack(found)[:150]
    data = simulate_measurements(truth.model, p_true, q, 20e-6, rng)
    cd = diagnose_cell(cm, data, model='geometric')
    assert cd.excluded == ()
    assert cd.diagnosis.best is not None and cd.diagnosis.best.spec == 'joint_backlash:joint2'
    assert cd.comparison is not None and cd.comparison.holds_elsewhere
    assert 'Add it with --effects joint_backlash:joint2' in cd.diagnosis.verdict
    b = 'joint_backlash.joint2.b'
    assert cd.after is not None
    std = cd.after.std[list(cd.after.estimated).index(b)]
    assert abs(cd.after.value(b) - 2e-4) < 3 * std

"""Several reflectors per pose: cell key, measurement rows, pairing convention,
identification, joint registration, CSV import."""
import copy
import pickle
from pathlib import Path

import numpy as np
import pytest

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import identify_cell
from kpi_calib_ros.app.measurements import measurements_from_bag, print_rejections
from kpi_calib_ros.app.placement import registered_start
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.acquisition.pairing import pair_measurements
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.estimation.registration import register
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document
from kpi_calib_ros.io.csv_import import import_csv, mapping_from_dict

OFFSETS = [[0.0, 0.0, 0.03], [0.06, 0.0, 0.03], [0.0, 0.05, 0.02]]
NAMES = ['a', 'b', 'c']


def _doc(offsets=OFFSETS):
    doc = copy.deepcopy(read_cell_document(DEFAULT_CELL))
    del doc['reflector']['offset']
    doc['reflectors'] = [{'name': n, **({} if o is None else {'offset': o})}
                         for n, o in zip(NAMES, offsets)]
    return doc


@pytest.fixture(scope='module')
def cm():
    return build_cell_model(cell_from_dict(_doc(), DEFAULT_CELL.parent))


def _campaign(cm, n, seed, p_true, sigma=0.0):
    rng = np.random.default_rng(seed)
    q = random_configurations(cm.model, cm.geometric.nominal, n, rng)
    q_rows = np.repeat(q, len(NAMES), axis=0)
    ref = np.tile(np.arange(len(NAMES)), n)
    eta = cm.model.predict(p_true, q_rows, reflector=ref)
    eta = eta + rng.normal(size=eta.shape) * sigma
    return Measurements(q=q_rows, eta=eta, reflector=ref)


def test_cell_reflectors_give_one_named_offset_triple_each(cm):
    names = cm.model.params.names
    for n, o in zip(NAMES, OFFSETS):
        assert [cm.model.params.nominal[names.index(f'reflector.{n}.{c}')]
                for c in 'xyz'] == o
    assert 'reflector.x' not in names and cm.model.n_reflectors == 3
    assert not cm.needs_registration


@pytest.mark.parametrize('change, key', [
    (lambda d: d['reflectors'].append({'name': 'a', 'offset': [0, 0, 0]}), 'reflectors[3].name'),
    (lambda d: d['reflectors'][0].update(offset=[0, 0]), 'reflectors[0].offset'),
    (lambda d: d['reflector'].update(offset=[0, 0, 0.03]), 'reflector.offset'),
    (lambda d: d.update(reflectors=[]), 'reflectors'),
    (lambda d: d['reflectors'][1].update(offset=[0, 0, 30]), 'reflectors[1].offset'),
    (lambda d: d['reflectors'][0].update(offset=[0, 0, 30]), 'reflectors[0].offset'),
    (lambda d: d['reflectors'][2].update(offset=[0, float('nan'), 0]), 'reflectors[2].offset'),
])
def test_bad_reflectors_name_the_key(change, key):
    doc = _doc()
    change(doc)
    with pytest.raises(ConfigError) as err:
        cell_from_dict(doc, DEFAULT_CELL.parent)
    assert err.value.key == key


def test_each_row_is_predicted_with_its_own_reflector(cm):
    p = cm.model.params.nominal
    q = random_configurations(cm.model, p, 4, np.random.default_rng(1))
    tips = np.array([cm.robot.pin_tip_pose(row) for row in q])
    base = np.linalg.inv(cm.tracker_in_base)
    for k, offset in enumerate(OFFSETS):
        expected = (base @ tips @ np.append(offset, 1.0))[:, :3]
        got = cm.model.predict(p, q, reflector=np.full(4, k))
        assert np.allclose(got, expected, atol=1e-12)
    with pytest.raises(ValueError, match='reflector indices'):
        cm.model.predict(p, q, reflector=np.full(4, 3))


def test_noiseless_three_reflector_campaign_is_fitted_exactly_and_gives_the_true_tcp(cm):
    p_true = true_parameters(cm.model.params, np.random.default_rng(3))
    data = _campaign(cm, 25, 4, p_true)
    result = identify_cell(cm, data)
    assert result.converged and result.rms_m < 1e-9
    # The KPI is reflector 0's centre at the working pose: gauge-free, so exact.
    assert np.allclose(result.tcp, cm.model.predict(p_true, cm.q_work), atol=1e-9)
    # Off-axis reflectors observe what one on-axis reflector cannot (the last joint offset).
    single = identify_cell(cm, Measurements(data.q[::3], data.eta[::3],
                                            reflector=data.reflector[::3]))
    assert len(result.estimated) > len(single.estimated)


def test_three_reflectors_shrink_the_tcp_covariance_against_one(cm):
    p_true = true_parameters(cm.model.params, np.random.default_rng(3))
    data = _campaign(cm, 30, 6, p_true, sigma=2e-5)
    three = identify_cell(cm, data)
    one = identify_cell(cm, Measurements(data.q[::3], data.eta[::3],
                                         reflector=data.reflector[::3]))
    assert np.trace(three.tcp_covariance[0]) < np.trace(one.tcp_covariance[0])
    # Truth within 3σ of the stated TCP covariance (3 axes: χ²(3) 99.9 % is 16.3).
    err = three.tcp[0] - cm.model.predict(p_true, cm.q_work)[0]
    assert err @ np.linalg.solve(three.tcp_covariance[0], err) < 16.3


def test_registration_of_base_and_every_offset_jointly(cm):
    p = cm.model.params.nominal.copy()
    base = np.array([1.9, -0.7, 0.4, 0.05, -0.03, -2.6])
    for c, v in zip(('x', 'y', 'z', 'roll', 'pitch', 'yaw'), base):
        p[cm.model.params.index(f'base.{c}')] = v
    data = _campaign(cm, 20, 8, p)
    tips = np.array([cm.robot.pin_tip_pose(q) for q in data.q])
    reg = register(data.eta, tips, reflector=data.reflector)
    assert np.allclose(reg.base_in_tracker, base, atol=1e-9)
    assert np.allclose(reg.reflector_offsets, OFFSETS, atol=1e-9)
    assert reg.rms_m < 1e-10


def test_cell_without_placement_is_registered_then_identified_like_the_known_one(cm):
    p_true = true_parameters(cm.model.params, np.random.default_rng(3))
    data = _campaign(cm, 25, 4, p_true, sigma=1e-5)
    doc = _doc(offsets=[None, None, None])
    del doc['tracker']['base_in_tracker']
    unknown = build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))
    assert unknown.needs_registration
    p0, reg = registered_start(unknown, data)
    assert reg.rms_m < 5e-3
    a, b = identify_cell(cm, data), identify_cell(unknown, data)
    assert b.converged and abs(a.rms_m - b.rms_m) < 1e-9 * a.rms_m + 1e-12
    assert np.allclose(a.tcp, b.tcp, atol=1e-8)


def _streams(points, frame_ids, stamp=5_000_000_000):
    joints = [JointSample(stamp + dt, ('j1',), [0.1], [0.0])
              for dt in range(-300_000_000, 300_000_001, 20_000_000)]
    pts = [PointSample(stamp, f, xyz) for f, xyz in zip(frame_ids, points)]
    return joints, pts


def test_points_of_one_pose_share_a_stamp_and_are_told_apart_by_the_frame_suffix():
    joints, pts = _streams(np.eye(3), ['mocap#a', 'mocap#b', '/mocap#c'])
    res = pair_measurements(joints, pts, ['j1'], 'mocap', reflectors=('a', 'b', 'c'))
    assert len(res) == 3 and res.reflectors == ('a', 'b', 'c')
    assert res.reflector_indices(['c', 'b', 'a']).tolist() == [2, 1, 0]
    joints, pts = _streams(np.eye(3), ['mocap#a', 'mocap#a', 'mocap#z'])
    res = pair_measurements(joints, pts, ['j1'], 'mocap', reflectors=('a', 'b'))
    assert len(res) == 1
    assert res.rejections == {'duplicate_stamp': 1, 'unknown_reflector': 1}
    detail = [r.detail for r in res.rejected if r.reason == 'unknown_reflector'][0]
    assert "'mocap#z'" in detail and 'mocap#b' in detail and '<reflector name>' in detail


def test_a_named_point_for_a_one_reflector_cell_names_its_frame_id_and_the_fix(capsys):
    joints, pts = _streams([[1.0, 2.0, 3.0]], ['laser_tracker#tmac'])
    res = pair_measurements(joints, pts, ['j1'], 'laser_tracker')  # a reflector: cell
    assert res.rejections == {'unknown_reflector': 1}
    print_rejections(res)  # what identify and validate print
    err = capsys.readouterr().err
    assert "frame_id 'laser_tracker#tmac'" in err and 'reflectors: [{name: tmac}]' in err


def test_csv_import_round_trip_through_a_bag(cm, tmp_path: Path):
    p_true = cm.model.params.nominal
    q = random_configurations(cm.model, p_true, 6, np.random.default_rng(2))
    names = cm.joint_names
    header = [f'{c}{k}' for k in (1, 2, 3) for c in 'xyz'] + [f'col_{n}' for n in names]
    lines = [','.join(header)]
    for row in q:
        pts = [cm.model.predict(p_true, row, reflector=[k])[0] * 1e3 for k in range(3)]
        values = list(np.concatenate(pts)) + list(np.degrees(row))
        lines.append(','.join(repr(float(v)) for v in values))
    table = tmp_path / 'postures.csv'
    table.write_text('\n'.join(lines) + '\n')
    mapping = mapping_from_dict({
        'frame_id': cm.cell.tracker_frame, 'joints': {n: f'col_{n}' for n in names},
        'markers': {n: [f'x{k}', f'y{k}', f'z{k}'] for k, n in enumerate(NAMES, 1)},
        'point_unit': 'mm', 'joint_unit': 'deg'})
    summary = import_csv(table, tmp_path / 'p.mcap', mapping)
    assert (summary.postures, summary.points) == (6, 18)
    data, pairing = measurements_from_bag(cm, summary.path)
    assert len(data) == 18 and sum(pairing.rejections.values()) == 0
    assert np.allclose(cm.model.predict(p_true, data.q, reflector=data.reflector), data.eta,
                       atol=1e-12)
    bad = mapping_from_dict({'frame_id': 'f', 'joints': ['nope'],
                             'markers': {'a': ['x1', 'y1', 'z1']}})
    with pytest.raises(DataError, match=r"\['nope'\] are not in the file"):
        import_csv(table, tmp_path / 'q.mcap', bad)


def test_design_rows_hold_every_reflector_of_a_pose(cm):
    from kpi_calib_ros.core.design.criteria import build_problem
    q = random_configurations(cm.model, cm.geometric.nominal, 60, np.random.default_rng(4))
    problem = build_problem(cm.design_cell(), q)
    rows = problem.rows(cm.model, q[:5])
    assert rows.shape == (5, 9, problem.k)
    # Rows 3k..3k+2 are reflector k's weighted, scaled Jacobian.
    _, jac = cm.model.jacobian(problem.p, q[:5], reflector=np.full(5, 2))
    expected = jac[:, :, problem.index] / cm.cell.sigma[None, :, None] * problem.column_scale
    assert np.allclose(rows[:, 6:9], expected, rtol=1e-12, atol=0)


@pytest.mark.slow
def test_a_design_for_three_reflectors_predicts_a_smaller_tcp_covariance(cm):
    from kpi_calib_ros.app.design import design_cell_model
    single = build_cell_model(cell_from_dict(read_cell_document(DEFAULT_CELL),
                                             DEFAULT_CELL.parent))
    one = design_cell_model(single, 30, 'kpi', 0)
    three = design_cell_model(cm, 30, 'kpi', 0)
    assert one.verification.ok and three.verification.ok
    assert three.criteria['kpi'] < 0.75 * one.criteria['kpi']


def test_the_node_store_keeps_every_reflector_of_a_pose_and_restores_them(tmp_path):
    from kpi_calib_ros.ros.measurement_store import MeasurementStore
    joints, pts = _streams(np.eye(3), ['mocap#a', 'mocap#b', 'mocap#a'])
    store = MeasurementStore(tmp_path)
    store.set_chain(['j1'], 'mocap', ('a', 'b'))
    for sample in sorted(joints + pts[:2], key=lambda s: s.stamp_ns):
        store.receive(sample, now_ns=0)
    store.receive(pts[2], now_ns=0)  # the same reflector at the same stamp again
    store.poll(now_ns=10**12)
    data, _ = store.measurements(['j1'], 'mocap', ('a', 'b'))
    assert len(data) == 2 and data.reflector.tolist() == [0, 1]
    assert store.rejections['duplicate_stamp'] == 1
    store.close()
    again, _ = MeasurementStore(tmp_path).measurements(['j1'], 'mocap', ('b', 'a'))
    assert sorted(again.reflector.tolist()) == [0, 1]
    assert np.allclose(sorted(map(tuple, again.eta)), sorted(map(tuple, data.eta)))


def test_a_cell_names_a_pip_installed_urdf_by_package_uri():
    cell_path = Path(__file__).resolve().parent / 'data' / 'tiago_mocap_cell.yaml'
    from kpi_calib_ros.io.cell import load_cell
    tiago = build_cell_model(load_cell(cell_path))
    assert tiago.cell.urdf_path.endswith('robots/tiago_description/robots/tiago_no_hand.urdf')
    assert tiago.joint_names == ['torso_lift_joint'] + [f'arm_{i}_joint' for i in range(1, 8)]
    assert tiago.needs_registration and tiago.model.n_reflectors == 4


@pytest.mark.slow
def test_robust_identification_and_auto_model_keep_each_rows_reflector(cm):
    """The path the CLI and the node publish (calibrate_cell: registration, gross screen,
    model choice by cross-validation over poses, outlier exclusion, estimability) keeps
    every row's reflector: on a three-reflector campaign with one blunder it excludes
    exactly that row, and the fit of the others is at the noise floor."""
    import dataclasses

    from kpi_calib_ros.app.identify import calibrate_cell
    sigma = 2e-5
    p_true = true_parameters(cm.model.params, np.random.default_rng(31))
    data = _campaign(cm, 25, 32, p_true, sigma=sigma)
    eta = data.eta.copy()
    eta[10] += [0.0, 2e-3, 0.0]  # 100 σ off, one reflector of one pose
    data = dataclasses.replace(data, eta=eta, stamps_ns=np.arange(len(eta)) + 1)
    auto = dataclasses.replace(cm.cell.identification, model='auto')
    cal = calibrate_cell(dataclasses.replace(cm, cell=dataclasses.replace(
        cm.cell, identification=auto)), data)
    assert cal.valid and cal.choice.level == 'geometric'
    assert [e.index for e in cal.robust.excluded] == [10]
    kept = data.subset(cal.robust.kept)
    assert kept.reflector.tolist() == np.delete(data.reflector, 10).tolist()
    # rms of the kept rows against σ√3 (dof-corrected: 3N − k of 3N)
    n, k = 3 * len(kept), len(cal.result.estimated)
    assert cal.result.rms_m == pytest.approx(sigma * np.sqrt(3 * (n - k) / n), rel=0.15)


def test_simulate_writes_every_reflector_and_identify_takes_them(tmp_path):
    import yaml

    from kpi_calib_ros.cli import main
    from kpi_calib_ros.io.bag import read_bag
    doc = _doc()
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    bag = tmp_path / 'run.mcap'
    assert main(['simulate', '--cell', str(cell), '--n', '15', '--out', str(bag),
                 '--seed', '4']) == 0
    _, points = read_bag(bag)
    frames = [p.frame_id for p in points]
    assert len(points) == 45 and {f: frames.count(f) for f in set(frames)} == {
        f'laser_tracker#{n}': 15 for n in NAMES}
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out',
                 str(tmp_path / 'out')]) == 0
    result = yaml.safe_load((tmp_path / 'out' / 'calibration.yaml').read_text())
    truth = yaml.safe_load((tmp_path / 'run.truth.yaml').read_text())
    assert result['measurements'] == 45
    error = np.array(result['tcp'][0]['position']) - np.array(truth['tcp_true'][0])
    cov = np.array(result['tcp'][0]['covariance'])
    assert error @ np.linalg.solve(cov, error) < 14.2  # 3σ of χ²₃


def test_the_model_evaluates_each_reflector_exactly_as_its_own_point_expression(cm):
    """The model builds one tool pose for all reflectors, ∂h/∂q and the incidence cosine on
    first use, and each mapped function once per row count: every figure is bit for bit
    what a function of the reflector's own point expression gives, pose by pose."""
    import casadi as ca

    from kpi_calib_ros.core.diagnosis import augmented_model
    from kpi_calib_ros.core.effects import parse_effect_spec
    model = augmented_model(cm.model, tuple(parse_effect_spec(s, cm.robot) for s in (
        'joint_compliance:joint_2', 'cyclic_joint_error:joint_3', 'tracker_scale')))
    rng = np.random.default_rng(4)
    p = model.params.nominal + rng.normal(size=len(model.params)) * 1e-3
    ps, qs, taus = (ca.SX.sym(n, k) for n, k in (('p', len(p)), ('q', cm.robot.n_joints),
                                                 ('tau', cm.robot.n_joints)))
    for n in (5, 8, 5):  # a row count again: the mapped functions kept from the first time
        q = random_configurations(model, model.params.nominal, n, rng)
        tau = model.robot.gravity_torques(q)
        ref = rng.integers(0, len(NAMES), n)
        pts, jac = model.jacobian(p, q, tau, ref)
        jq = model.joint_jacobian(p, q, tau, ref)
        cos = model.incidence_cos(p, q)
        expected_cos = ca.Function('c', [ps, qs], [model.incidence_cos_expression(ps, qs)])
        for i, k in enumerate(ref):
            point = model.point_expression(ps, qs, taus, int(k))
            own = ca.Function('own', [ps, qs, taus],
                              [point, ca.jacobian(point, ps), ca.jacobian(point, qs)])
            h, hp, hq = (np.array(o) for o in own(p, q[i], tau[i]))
            np.testing.assert_array_equal(pts[i], h.ravel())
            np.testing.assert_array_equal(jac[i], hp)
            np.testing.assert_array_equal(jq[i], hq)
            assert cos[i] == float(expected_cos(p, q[i]))
        np.testing.assert_array_equal(model.predict(p, q, tau, ref), pts)
        # A job's result crosses a process boundary pickled, its model with it.
        copy_ = pickle.loads(pickle.dumps(model))
        np.testing.assert_array_equal(copy_.jacobian(p, q, tau, ref)[1], jac)
        np.testing.assert_array_equal(copy_.joint_jacobian(p, q, tau, ref), jq)
        np.testing.assert_array_equal(copy_.incidence_cos(p, q), cos)


def test_a_table_of_two_marker_mounts_gives_each_row_the_markers_it_has(cm, tmp_path: Path,
                                                                         capsys):
    """Two marker mounts in one table (rows of mount 1 carry marker a, rows of mount 2
    markers b and c; the others' fields empty or NaN): import-csv writes each row's points
    only, the bag pairs without a rejection, each row is predicted exactly with its own
    reflector, and the identification from the noisy rows converges with an rms at the
    noise; a row with no marker at all is exit 2 naming the line."""
    rng = np.random.default_rng(4)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, p_true, 40, rng)
    names = cm.joint_names
    header = [f'{c}{k}' for k in (1, 2, 3) for c in 'xyz'] + [f'col_{n}' for n in names]
    lines = [','.join(header)]
    sigma = float(np.max(cm.cell.sigma))
    for i, row in enumerate(q):
        carried = (0,) if i < 20 else (1, 2)
        fields = []
        for k in range(3):
            if k in carried:
                xyz = cm.model.predict(p_true, row, reflector=[k])[0]
                fields += [repr(float(v)) for v in (xyz + rng.normal(size=3) * sigma) * 1e3]
            else:
                fields += ['', '', ''] if i % 2 else ['nan', 'NaN', 'nan']
        lines.append(','.join(fields + [repr(float(v)) for v in np.degrees(row)]))
    table = tmp_path / 'two_mounts.csv'
    table.write_text('\n'.join(lines) + '\n')
    mapping = tmp_path / 'mapping.yaml'
    mapping.write_text(
        f'frame_id: {cm.cell.tracker_frame}\n'
        f'joints: {{{", ".join(f"{n}: col_{n}" for n in names)}}}\n'
        'markers: {a: [x1, y1, z1], b: [x2, y2, z2], c: [x3, y3, z3]}\n'
        'point_unit: mm\njoint_unit: deg\n')
    bag = tmp_path / 'two_mounts.mcap'
    assert main(['import-csv', str(table), '--mapping', str(mapping), '--out', str(bag)]) == 0
    assert '(40 postures, 60 points)' in capsys.readouterr().out
    data, pairing = measurements_from_bag(cm, bag)
    assert len(data) == 60 and sum(pairing.rejections.values()) == 0
    assert np.bincount(data.reflector).tolist() == [20, 20, 20]
    assert np.abs(cm.model.predict(p_true, data.q, reflector=data.reflector)
                  - data.eta).max() < 6 * sigma
    result = identify_cell(cm, data)
    assert result.converged
    assert 0.7 * sigma < result.rms_m / np.sqrt(3) < 1.3 * sigma, result.rms_m
    # A row that carries no marker is refused, naming it.
    lines.append(','.join([''] * 9 + [repr(float(v)) for v in np.degrees(q[0])]))
    table.write_text('\n'.join(lines) + '\n')
    assert main(['import-csv', str(table), '--mapping', str(mapping), '--out',
                 str(tmp_path / 'none.mcap')]) == 2
    err = capsys.readouterr().err
    assert f'{table}: line 42: no marker has a value' in err, err


def test_a_recording_counts_its_poses_and_its_points_apart(cm):
    """Two recordings of 12 poses, three reflectors each: each recording reports 12 poses and
    36 points (the real TIAGo's sessions of 63, 59 and 37 postures were reported as 252,
    236 and 148 poses: its four markers' points)."""
    from kpi_calib_ros.app.calibration_document import recordings_section, recordings_text
    from kpi_calib_ros.app.identify import calibrate_cell
    from kpi_calib_ros.app.measurements import with_recordings
    from kpi_calib_ros.core.measurement import recordings as rec
    p_true = true_parameters(cm.model.params, np.random.default_rng(5))
    recordings = [rec.Recording('a'), rec.Recording('b')]
    data = rec.combine([_campaign(cm, 12, 6, p_true, 2e-5), _campaign(cm, 12, 7, p_true, 2e-5)],
                       recordings)
    placed = with_recordings(cm, recordings)
    cal = calibrate_cell(placed, data, 'geometric')
    section = recordings_section(placed, data, cal, recordings, ['a.mcap', 'b.mcap'])
    assert [(s['poses'], s['points']) for s in section] == [(12, 36), (12, 36)]
    assert 'recording a: 12 poses (36 points), rms' in recordings_text(section)

"""A recording whose placement changed while measured (the tracker knocked half way): named
with the time and the size of the move, against the truth of a simulated move; no jump
named on clean recordings, nor where a hidden compliance leaves a misfit that follows the
poses' order in time."""
from __future__ import annotations

import numpy as np
import pytest

from kpi_calib_ros.app.calibration_document import recording_jumps
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.effects.registry import parse_effect_spec
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)

SIGMA = 20e-6
POSES = 50
STEP_NS = 30 * 10 ** 9  # a pose every 30 s
# The tracker's move half way: 0.4 mm and 0.2 mrad (a knock on the tripod).
MOVE = np.array([3e-4, -2e-4, 1.5e-4, 1e-4, -1.5e-4, 0.8e-4])


def _run(cm, seed: int, move: np.ndarray | None = None, sort_by: int | None = None
         ) -> tuple[Measurements, np.ndarray]:
    """One recording of POSES poses, the base pose in the tracker frame moved by ``move``
    from pose POSES // 2 on; the poses in order of joint ``sort_by`` when given. Returns the
    data and the true displacement of the points after the move."""
    rng = np.random.default_rng(seed)
    p = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, cm.model.params.nominal, POSES, rng)
    if sort_by is not None:
        q = q[np.argsort(q[:, sort_by])]
    stamps = 1_700_000_000 * 10 ** 9 + STEP_NS * np.arange(POSES)
    data = simulate_measurements(cm.model, p, q, SIGMA, rng, stamps_ns=stamps)
    if move is None:
        return data, np.zeros(0)
    moved = p.copy()
    moved[:6] += move
    half = POSES // 2
    shift = cm.model.predict(moved, q[half:]) - cm.model.predict(p, q[half:])
    eta = np.array(data.eta)
    eta[half:] += shift
    return Measurements(q=data.q, eta=eta, stamps_ns=data.stamps_ns), shift


@pytest.mark.parametrize('seed', [1, 2])
def test_a_tracker_moved_half_way_is_named_with_its_time_and_size(cm, seed):
    data, shift = _run(cm, seed, MOVE)
    cal = calibrate_cell(cm, data, model='geometric')
    jumps = recording_jumps(cm, data, cal, ['run'])
    assert len(jumps) == 1, [j.text() for j in jumps]
    jump = jumps[0]
    assert jump.recording == 'run' and jump.before == POSES // 2
    assert jump.at_s == pytest.approx((POSES // 2 - 0.5) * STEP_NS * 1e-9)
    moved = float(np.linalg.norm(shift.mean(axis=0)))
    print(jump.text(), f'true move at the centroid {moved * 1e3:.3f} mm')
    assert 0.7 * moved < jump.translation_m < 1.3 * moved
    assert jump.chi2_split < 0.2 * jump.chi2
    assert 'split_at: [735.0]' in jump.text() and not jump.drift


def test_a_move_is_found_between_poses_of_several_points(cm):
    """Every pose measured by two points at one stamp (several markers or reflectors): the
    splits fall between poses. Before, a recording whose stamps repeat was not judged at all
    (the real TIAGo's four markers per posture)."""
    data, _ = _run(cm, 1, MOVE)
    rng = np.random.default_rng(3)
    twice = Measurements(q=np.repeat(data.q, 2, axis=0),
                         eta=np.repeat(data.eta, 2, axis=0) + rng.normal(0, SIGMA, (2 * POSES, 3)),
                         stamps_ns=np.repeat(data.stamps_ns, 2))
    jumps = recording_jumps(cm, twice, calibrate_cell(cm, twice, model='geometric'), ['run'])
    assert len(jumps) == 1 and jumps[0].before == POSES  # rows: 2 per pose
    assert jumps[0].at_s == pytest.approx((POSES // 2 - 0.5) * STEP_NS * 1e-9)


def test_diagnose_names_the_move_before_the_robot(cm):
    """``diagnose`` says what identify says about the recording, first: its effects are
    screened on a fit the move bends (it ranked a joint-reading noise and a link bending)."""
    from kpi_calib_ros.app.diagnose import diagnose_cell
    from kpi_calib_ros.io.report import diagnosis_text
    data, _ = _run(cm, 1, MOVE)
    cd = diagnose_cell(cm, data, model='geometric', add_best=False, recording_names=['run'])
    assert len(cd.set_up) == 1 and cd.set_up[0].startswith(
        'recording run: its placement changed while it was measured, at 735.0 s')
    assert diagnosis_text(cd).startswith('WARNING: recording run: its placement changed')


def test_a_tracker_drifting_through_the_recording_is_named_a_drift(cm):
    """The tracker drifting steadily (0.4 mm over the recording, a warm-up) is a change of
    placement too, but no step at one time: named a drift, its fix another."""
    rng = np.random.default_rng(6)
    p = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, cm.model.params.nominal, POSES, rng)
    stamps = 1_700_000_000 * 10 ** 9 + STEP_NS * np.arange(POSES)
    data = simulate_measurements(cm.model, p, q, SIGMA, rng, stamps_ns=stamps)
    eta = np.array(data.eta)
    for i in range(POSES):
        moved = p.copy()
        moved[:6] += i / (POSES - 1) * MOVE
        eta[i] += (cm.model.predict(moved, q[i:i + 1]) - cm.model.predict(p, q[i:i + 1]))[0]
    data = Measurements(q=data.q, eta=eta, stamps_ns=data.stamps_ns)
    jumps = recording_jumps(cm, data, calibrate_cell(cm, data, model='geometric'), ['run'])
    assert len(jumps) == 1 and jumps[0].drift and jumps[0].chi2_drift < jumps[0].chi2_split
    assert 'it drifted steadily' in jumps[0].text()


def test_clean_recordings_name_no_jump(cm):
    found = []
    for seed in range(10):
        data, _ = _run(cm, 100 + seed)
        found += recording_jumps(cm, data, calibrate_cell(cm, data, model='geometric'),
                                 ['run'])
    assert found == []


def test_a_misfit_that_follows_the_poses_order_is_no_jump(cm):
    """A joint 2 compliance the geometric model lacks, the poses measured in order of joint
    2: the residuals change with time, but not by a rigid move."""
    effect = parse_effect_spec('joint_compliance:joint_2', cm.robot)
    truth = augmented_model(cm.model, (effect,))
    found, misfit = [], []
    for seed in range(5):
        rng = np.random.default_rng(200 + seed)
        p = np.concatenate([true_parameters(cm.model.params, rng), [4e-7]])
        q = random_configurations(cm.model, cm.model.params.nominal, POSES, rng)
        q = q[np.argsort(q[:, 1])]
        stamps = 1_700_000_000 * 10 ** 9 + STEP_NS * np.arange(POSES)
        data = simulate_measurements(truth, p, q, SIGMA, rng, stamps_ns=stamps)
        cal = calibrate_cell(cm, data, model='geometric')
        misfit.append(cal.result.chi2 / cal.result.dof)
        found += recording_jumps(cm, data, cal, ['run'])
    print('χ²/dof of the geometric fits', np.round(misfit, 1))
    assert min(misfit) > 2.0  # the misfit is there
    assert found == [], [j.text() for j in found]


MAPPING = """frame_id: laser_tracker
joints: [joint_1, joint_2, joint_3, joint_4, joint_5, joint_6]
markers: {reflector: [x, y, z]}
stamp_columns: [t]
stamp_format: unix
point_unit: m
joint_unit: rad
"""


def _csv(path, data: Measurements) -> None:
    rows = ['t,joint_1,joint_2,joint_3,joint_4,joint_5,joint_6,x,y,z']
    for stamp, q, eta in zip(data.stamps_ns, data.q, data.eta):
        rows.append(','.join([str(int(stamp) // 10 ** 9)] + [f'{v:.12g}' for v in (*q, *eta)]))
    path.write_text('\n'.join(rows) + '\n')


def test_identify_names_the_move_and_a_manifest_split_at_it_holds(cm, tmp_path, capsys):
    """From a table, as a user brings a campaign: ``identify`` warns with the time and writes
    it to calibration.yaml (read back); the manifest's ``split_at`` at that time makes the
    bag two recordings of 25 poses, each with its own placement, fitted to the noise with no
    move left to name."""
    import yaml

    from kpi_calib_ros.cli import main
    from kpi_calib_ros.io.calibration_file import read_calibration_document
    from kpi_calib_ros.io.cell import DEFAULT_CELL

    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    # the reflector named as the table's marker
    doc['reflectors'] = [{'name': 'reflector', 'offset': doc.pop('reflector')['offset']}]
    (tmp_path / 'cell.yaml').write_text(yaml.safe_dump(doc))
    data, _ = _run(cm, 3, MOVE)
    _csv(tmp_path / 'run.csv', data)
    (tmp_path / 'mapping.yaml').write_text(MAPPING)
    assert main(['import-csv', str(tmp_path / 'run.csv'), '--mapping',
                 str(tmp_path / 'mapping.yaml'), '--out', str(tmp_path / 'run.mcap')]) == 0
    (tmp_path / 'one.yaml').write_text('recordings:\n  - {bag: run.mcap, name: run}\n')
    cell = ['--cell', str(tmp_path / 'cell.yaml'), '--model', 'geometric']
    capsys.readouterr()
    main(['identify', *cell, '--recordings', str(tmp_path / 'one.yaml'),
          '--out', str(tmp_path / 'one')])
    text = capsys.readouterr().out
    assert ('WARNING: recording run: its placement changed while it was measured, at 735.0 s'
            in text), text
    doc = read_calibration_document(tmp_path / 'one' / 'calibration.yaml')
    assert [j['at_s'] for j in doc['placement_jumps']] == [735.0]
    (tmp_path / 'split.yaml').write_text(
        'recordings:\n  - {bag: run.mcap, name: run, split_at: [735.0]}\n')
    assert main(['identify', *cell, '--recordings', str(tmp_path / 'split.yaml'),
                 '--out', str(tmp_path / 'split')]) == 0
    text = capsys.readouterr().out
    assert 'placement changed' not in text
    doc = read_calibration_document(tmp_path / 'split' / 'calibration.yaml')
    assert doc['placement_jumps'] == [] and doc['valid'] is True
    assert [(r['name'], r['poses']) for r in doc['recordings']] == [('run_1', 25),
                                                                    ('run_2', 25)]
    for entry in doc['recordings']:
        assert entry['rms_m'] < 1.5 * np.sqrt(3) * SIGMA
    # a split after the last row leaves a part without a measurement: named, exit 2
    (tmp_path / 'late.yaml').write_text(
        'recordings:\n  - {bag: run.mcap, name: run, split_at: [5000]}\n')
    assert main(['identify', *cell, '--recordings', str(tmp_path / 'late.yaml'),
                 '--out', str(tmp_path / 'late')]) == 2
    err = capsys.readouterr().err
    assert "recording 'run_2'" in err and 'check split_at' in err, err

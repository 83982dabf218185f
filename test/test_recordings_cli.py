"""``kpi-calib identify --bag a.mcap --bag b.mcap`` on bags the tool's own writer makes (one
robot, set-ups metres and tens of degrees apart), the calibration read back by validate and
``--prior``; ``validate --register reflector``; a learned residual carried into a registered
set-up."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from kpi_calib_ros.app.simulate import simulate_campaign, truth_cell_model
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.model.kinematics import pose6
from kpi_calib_ros.core.simulation import true_parameters
from kpi_calib_ros.io.calibration_file import calibration_recordings, read_calibration_document
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell

# Each set-up: the base moved against the tracker (m, rad), the probe offset moved (m).
SET_UPS = {'a': (np.zeros(6), np.zeros(3)),
           'b': (np.array([-1.2, 1.5, 0.1, 0.02, -0.03, 0.6]), np.zeros(3)),
           'c': (np.array([0.8, -1.9, -0.2, -0.04, 0.01, -0.5]), np.zeros(3)),
           'a_remounted': (np.zeros(6), np.array([0.004, -0.003, 0.01]))}
POSES = {'a': 40, 'b': 40, 'c': 30, 'a_remounted': 30}


def _cell_document(hidden: dict | None = None) -> dict:
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc.setdefault('identification', {})['model'] = 'geometric'
    if hidden:
        doc['simulation'] = {'hidden_effects': hidden}
    return doc


def _set_ups(folder: Path, doc: dict, poses: dict[str, int], seed: int,
             built_to_urdf: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """One robot measured in each set-up of ``poses`` into ``folder/<name>.mcap``; the cell
    of set-up A is ``folder/cell.yaml``. Returns each set-up's true parameter vector. The
    set-ups ``built_to_urdf`` measure a robot built to its URDF instead (another unit of
    the type), placed and probed as the others."""
    folder.mkdir(parents=True, exist_ok=True)
    cell = folder / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    cm, overrides = truth_cell_model(load_cell(cell))
    robot = true_parameters(cm.model.params, np.random.default_rng(seed), overrides=overrides)
    n_geo = len(cm.geometric)
    truths = {}
    for i, (name, n) in enumerate(poses.items()):
        moved, remount = SET_UPS[name]
        here = dict(doc, tracker=dict(doc['tracker']))
        here['tracker']['base_in_tracker'] = (np.array(doc['tracker']['base_in_tracker'])
                                              + moved).tolist()
        here['reflector'] = dict(doc['reflector'])
        here['reflector']['offset'] = (np.array(doc['reflector']['offset']) + remount).tolist()
        path = folder / f'cell_{name}.yaml'
        path.write_text(yaml.safe_dump(here))
        cm_here, _ = truth_cell_model(load_cell(path))
        truth = robot.copy()
        if name in built_to_urdf:
            truth[6:n_geo - 3] = cm.model.params.nominal[6:n_geo - 3]
        truth[:6] += moved
        truth[n_geo - 3:n_geo] += remount
        simulate_campaign(path, n, folder / f'{name}.mcap', seed + 1 + i, cm=cm_here,
                          p_true=truth)
        truths[name] = truth
    return truths


@pytest.fixture(scope='module')
def set_ups(tmp_path_factory):
    folder = tmp_path_factory.mktemp('set_ups')
    return folder, _set_ups(folder, _cell_document(), POSES, 3)


def _placement(doc: dict, name: str) -> np.ndarray:
    entry = next(r for r in doc['recordings'] if r['name'] == name)
    return np.array([v['value'] for n, v in entry['placement'].items()
                     if '.reflector' not in n and not n.startswith('reflector')])


@pytest.mark.slow
def test_identify_two_set_ups_with_repeated_bag_and_read_it_back(set_ups, capsys):
    """Two bags of one robot from stations metres and 35° apart: exit 0, each recording's
    placement and contribution in calibration.yaml, the station-to-station transform
    recovered (gauge-free) and the TCP within 3σ; the file loads back in validate (a third
    set-up, --register base: holds) and as --prior."""
    folder, truths = set_ups
    out = folder / 'joint'
    argv = ['identify', '--cell', str(folder / 'cell.yaml'), '--bag', str(folder / 'a.mcap'),
            '--bag', str(folder / 'b.mcap'), '--out', str(out)]
    assert main(argv) == 0, capsys.readouterr()
    text = capsys.readouterr().out
    assert 'recording a: 40 poses' in text and 'recording b: 40 poses' in text
    doc = yaml.safe_load((out / 'calibration.yaml').read_text())
    assert [r['name'] for r in doc['recordings']] == ['a', 'b']
    assert doc['pairing']['accepted'] == 80 and doc['valid'] is True
    for entry in doc['recordings']:
        assert entry['poses'] == 40 and entry['rms_m'] < 3 * np.sqrt(3) * 2e-5
        assert entry['tcp_variance_ratio_without'] > 1.0
        # never worse than nominal on its own rows: held-out rms near σ√3, the nominal
        # robot's (its placement registered) millimetres
        versus = entry['against_nominal']
        assert versus['worse_than_nominal'] is False and versus['rows'] == 40
        assert versus['in_region_rms_m'] < 1.5 * np.sqrt(3) * 2e-5
        assert versus['nominal_in_region_rms_m'] > 10 * versus['in_region_rms_m']
        assert f"held-out rms {versus['in_region_rms_m'] * 1e6:.1f} µm against the " \
            f"nominal robot's {versus['nominal_in_region_rms_m'] * 1e6:.1f} µm" in text
    # the transform from station A's frame to B's: the same whatever gauge the fit chose
    def pose(v: np.ndarray) -> np.ndarray:
        return np.array(pose6(v), float)
    found = pose(_placement(doc, 'b')) @ np.linalg.inv(pose(_placement(doc, 'a')))
    true = pose(truths['b'][:6]) @ np.linalg.inv(pose(truths['a'][:6]))
    assert np.linalg.norm(found[:3, 3] - true[:3, 3]) < 1e-4
    assert np.linalg.norm(found[:3, :3] - true[:3, :3]) < 5e-5
    truth_tcp = yaml.safe_load((folder / 'a.truth.yaml').read_text())['tcp_true'][0]
    tcp = doc['tcp'][0]
    assert np.all(np.abs(np.array(tcp['position']) - truth_tcp) < 3 * np.array(tcp['std']))
    # read back: validate a third set-up registered, and the calibration as --prior
    calibration = str(out / 'calibration.yaml')
    assert main(['validate', '--cell', str(folder / 'cell.yaml'), '--calibration', calibration,
                 '--bag', str(folder / 'c.mcap'), '--out', str(folder / 'val_c'),
                 '--register', 'base']) == 0, capsys.readouterr()
    assert main(['identify', '--cell', str(folder / 'cell.yaml'), '--bag',
                 str(folder / 'a.mcap'), '--prior', calibration, '--out',
                 str(folder / 'again')]) in (0, 1), capsys.readouterr()
    assert 'Traceback' not in capsys.readouterr().err


@pytest.mark.slow
def test_identify_refuses_a_set_up_it_predicts_worse_than_nominal(tmp_path, capsys):
    """The first bag measures a robot built to its URDF (20 poses), the second the robot
    with geometric errors (40 poses): better than nominal over all rows, several times worse
    on the first set-up. Exit 1, calibration.failed.yaml names that set-up (the first, by
    its bag's name) with both figures and the fix, its ``recordings:`` entry says so; the
    file reads back."""
    _set_ups(tmp_path, _cell_document(), {'b': 20, 'a': 40}, 5, built_to_urdf=('b',))
    out = tmp_path / 'joint'
    argv = ['identify', '--cell', str(tmp_path / 'cell.yaml'), '--bag', str(tmp_path / 'b.mcap'),
            '--bag', str(tmp_path / 'a.mcap'), '--out', str(out)]
    assert main(argv) == 1, capsys.readouterr()
    text = capsys.readouterr().out
    doc = yaml.safe_load((out / 'calibration.failed.yaml').read_text())
    assert not (out / 'calibration.yaml').exists() and doc['valid'] is False
    assert doc['against_nominal']['better'] is True  # the overall verdict alone holds
    harmed, kept = doc['recordings']
    assert harmed['against_nominal']['worse_than_nominal'] is True
    assert kept['against_nominal']['worse_than_nominal'] is False
    figures = harmed['against_nominal']
    assert figures['in_region_rms_m'] > 3 * figures['nominal_in_region_rms_m']
    reasons = [r for r in doc['invalid_reasons'] if 'set-up' in r]
    assert len(reasons) == 1 and "recording 'b'" in reasons[0], doc['invalid_reasons']
    assert f"{figures['in_region_rms_m'] * 1e6:.1f} µm" in reasons[0]
    assert 'register it separately' in reasons[0] and reasons[0] in text
    assert '(WORSE than nominal beyond the noise)' in text
    # read back as validate and --prior read a calibration document
    back = read_calibration_document(out / 'calibration.failed.yaml')
    assert [r.name for r in calibration_recordings(back, 'test')] == ['b', 'a']


@pytest.mark.slow
def test_diagnose_and_a_manifest_take_several_recordings(set_ups, capsys):
    """diagnose with --bag repeated and identify with a manifest (the probe remounted, a
    constant payload per recording): exit 0, the manifest's statements in calibration.yaml."""
    folder, truths = set_ups
    assert main(['diagnose', '--cell', str(folder / 'cell.yaml'), '--bag',
                 str(folder / 'a.mcap'), '--bag', str(folder / 'b.mcap'), '--out',
                 str(folder / 'diag')]) == 0, capsys.readouterr()
    assert (folder / 'diag' / 'diagnosis.json').is_file()
    manifest = folder / 'manifest.yaml'
    manifest.write_text(yaml.safe_dump({'recordings': [
        {'bag': 'a.mcap', 'name': 'first', 'covariates': {'payload.mass': 5.0}},
        {'bag': 'a_remounted.mcap', 'name': 'probe_again', 'reflector_remounted': True,
         'covariates': {'payload.mass': 5.0}}]}))
    out = folder / 'manifest_out'
    assert main(['identify', '--cell', str(folder / 'cell.yaml'), '--recordings',
                 str(manifest), '--out', str(out)]) == 0, capsys.readouterr()
    doc = yaml.safe_load((out / 'calibration.yaml').read_text())
    first, again = doc['recordings']
    assert first['covariates'] == {'payload.mass': 5.0} and again['reflector_remounted']
    # the remounted probe's offset relative to the first's, as it was moved
    offset = np.array([again['placement'][f'recording.probe_again.reflector.{c}']['value']
                       for c in 'xyz'])
    first_offset = np.array([first['placement'][f'reflector.{c}']['value'] for c in 'xyz'])
    moved = offset - first_offset
    assert np.linalg.norm(moved - SET_UPS['a_remounted'][1]) < 2e-4, moved


def test_validate_says_when_a_miss_is_the_set_up_moved(set_ups, capsys):
    """Calibrated on set-up A and validated on B without --register: the miss (metres) is
    a rigid move of the tracker frame, and validate says so and names --register base
    (before: 'does not hold', rms 1761 mm, no hint). A probe remounted is no rigid move of
    the points: no such hint."""
    folder, _ = set_ups
    cal = folder / 'single_hint'
    assert main(['identify', '--cell', str(folder / 'cell.yaml'), '--bag',
                 str(folder / 'a.mcap'), '--out', str(cal)]) == 0, capsys.readouterr()
    args = ['validate', '--cell', str(folder / 'cell.yaml'), '--calibration',
            str(cal / 'calibration.yaml')]
    assert main(args + ['--bag', str(folder / 'b.mcap'), '--out', str(folder / 'v_b')]) == 1
    printed = capsys.readouterr().out
    assert 'set up again since the calibration; validate with --register base' in printed
    moved = json.loads((folder / 'v_b' / 'validation.json').read_text())['set_up_moved']
    roll, pitch, yaw = SET_UPS['b'][0][3:]
    turn = pin.rpy.rpyToMatrix(roll, pitch, yaw)
    angle = np.arccos((np.trace(turn) - 1) / 2)
    assert abs(moved['rotation_rad'] - angle) < 1e-3, (moved, angle)
    assert moved['rms_after_m'] < 0.01 * moved['rms_before_m']
    assert main(args + ['--bag', str(folder / 'a_remounted.mcap'), '--out',
                        str(folder / 'v_probe')]) == 1
    doc = json.loads((folder / 'v_probe' / 'validation.json').read_text())
    assert 'set_up_moved' not in doc and 'set up again' not in capsys.readouterr().out


def test_a_recording_with_the_wrong_joint_names_is_named(set_ups, capsys):
    """Of several recordings, the one whose joint states name other joints is named with its
    bag; the error named neither."""
    from kpi_calib_ros.app.cell_model import build_cell_model
    from kpi_calib_ros.app.measurements import measurements_from_bag
    from kpi_calib_ros.core.acquisition.streams import synthesize_streams
    from kpi_calib_ros.io.bag_writing import write_bag
    folder, _ = set_ups
    cm = build_cell_model(load_cell(folder / 'cell.yaml'))
    data, _ = measurements_from_bag(cm, folder / 'b.mcap')
    names = ['elbow' if n == cm.joint_names[2] else n for n in cm.joint_names]
    joints, points = synthesize_streams(data.q, names, data.eta, cm.cell.tracker_frame)
    (folder / 'typo').mkdir(exist_ok=True)
    typo = write_bag(folder / 'typo' / 'b_typo.mcap', joints, points)
    code = main(['identify', '--cell', str(folder / 'cell.yaml'), '--bag',
                 str(folder / 'a.mcap'), '--bag', str(typo), '--out', str(folder / 'typo_out')])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"recording 'b_typo' ({typo}): the joint states name joints" in err, err


def test_a_copy_of_a_bag_under_another_name_is_refused(set_ups, capsys):
    """The same measurements under two names were two set-ups, their rows counted twice
    (the TCP std 17.0 µm instead of 22.7 µm): refused, naming both files, by identify and
    diagnose."""
    folder, _ = set_ups
    copy = folder / 'copies' / 'b_again.mcap'
    copy.parent.mkdir(exist_ok=True)
    copy.write_bytes((folder / 'b.mcap').read_bytes())
    for command in ('identify', 'diagnose'):
        code = main([command, '--cell', str(folder / 'cell.yaml'), '--bag',
                     str(folder / 'a.mcap'), '--bag', str(folder / 'b.mcap'), '--bag',
                     str(copy), '--out', str(folder / f'copy_{command}')])
        err = capsys.readouterr().err
        assert code == 2, err
        assert "recording 'b_again'" in err and "from recording 'b'" in err, err


@pytest.mark.slow
def test_validate_register_reflector_refits_the_probe_alone(set_ups, capsys):
    """Calibrated on set-up A, the probe remounted (tracker where it was): --register
    reflector re-fits the offsets alone (3 dof) and the calibration holds; without it, it
    does not."""
    folder, truths = set_ups
    cal = folder / 'single'
    assert main(['identify', '--cell', str(folder / 'cell.yaml'), '--bag',
                 str(folder / 'a.mcap'), '--out', str(cal)]) == 0, capsys.readouterr()
    args = ['validate', '--cell', str(folder / 'cell.yaml'), '--calibration',
            str(cal / 'calibration.yaml'), '--bag', str(folder / 'a_remounted.mcap')]
    assert main(args + ['--out', str(folder / 'v_none')]) == 1
    assert main(args + ['--out', str(folder / 'v_ref'), '--register', 'reflector']) == 0, \
        capsys.readouterr()
    out = json.loads((folder / 'v_ref' / 'validation.json').read_text())
    assert out['registration']['parameters'] == ['reflector.x', 'reflector.y', 'reflector.z']
    assert out['dof'] == 3 * POSES['a_remounted'] - 3
    assert out['rms_m'] < 2 * np.sqrt(3) * 2e-5
    assert out['registration']['valid']  # a remount of 11 mm is one
    # From another station (the tracker 1.9 m away) the offsets alone take up the move,
    # metres: that registration was called valid; it is no remount.
    capsys.readouterr()
    far = args[:-1] + [str(folder / 'b.mcap'), '--out', str(folder / 'v_far'),
                       '--register', 'reflector']
    assert main(far) == 1
    out = json.loads((folder / 'v_far' / 'validation.json').read_text())
    assert not out['registration']['valid']
    moved = next(v for v in out['registration']['violations'] if v.startswith('reflector'))
    assert 'from the calibration' in moved and '--register base+reflector' in moved, moved
    assert 'NOT VALID: the re-registered placement fails the gate' in capsys.readouterr().out


@pytest.mark.slow
def test_a_learned_residual_is_carried_into_a_registered_set_up(tmp_path, capsys):
    """A joint-2 error at twice per turn the geometric model lacks: the learned residual of
    set-up A, carried into set-up B (35° and metres away, --register base), predicts B better
    than the physical model alone, within its stated uncertainty."""
    doc = _cell_document({'cyclic_joint_error_h2:joint_2': {'a': 4e-4, 'b': 2e-4}})
    _set_ups(tmp_path, doc, {'a': 150, 'b': 40}, 11)
    assert main(['identify', '--cell', str(tmp_path / 'cell.yaml'), '--bag',
                 str(tmp_path / 'a.mcap'), '--out', str(tmp_path / 'cal'),
                 '--learned-residual']) == 0, capsys.readouterr()
    assert (tmp_path / 'cal' / 'learned_residual.yaml').is_file()
    assert main(['validate', '--cell', str(tmp_path / 'cell.yaml'), '--calibration',
                 str(tmp_path / 'cal' / 'calibration.yaml'), '--bag', str(tmp_path / 'b.mcap'),
                 '--out', str(tmp_path / 'val'), '--register', 'base']) in (0, 1)
    text = capsys.readouterr().out
    learned = json.loads((tmp_path / 'val' / 'validation.json').read_text())['learned_residual']
    print(text)
    assert 'skipped' not in learned
    assert learned['rms_m'] < 0.7 * learned['rms_physical_m'], learned
    assert learned['holds'], learned


@pytest.mark.slow
def test_validate_recording_places_a_later_bag_of_a_known_set_up_as_the_calibration_did(
        set_ups, capsys):
    """Calibrated from set-ups A and B together, a later recording from B (30 new poses,
    nothing moved): ``--recording b`` places it with B's stored placement and its covariance
    and the calibration holds (χ² within its dof's acceptance, rms near the noise); without
    it the bag is placed by the first set-up's base pose, 2 m and 35° away, and it does not
    hold. An unknown name exits 2 naming --recording and the calibration's recordings."""
    folder, truths = set_ups
    cal = folder / 'joint_for_later'
    assert main(['identify', '--cell', str(folder / 'cell.yaml'), '--bag',
                 str(folder / 'a.mcap'), '--bag', str(folder / 'b.mcap'), '--out',
                 str(cal)]) == 0, capsys.readouterr()
    cm_b, _ = truth_cell_model(load_cell(folder / 'cell_b.yaml'))
    simulate_campaign(folder / 'cell_b.yaml', 30, folder / 'b_later.mcap', 41, cm=cm_b,
                      p_true=truths['b'])
    args = ['validate', '--cell', str(folder / 'cell.yaml'), '--calibration',
            str(cal / 'calibration.yaml'), '--bag', str(folder / 'b_later.mcap')]
    capsys.readouterr()
    assert main(args + ['--out', str(folder / 'v_b'), '--recording', 'b']) == 0, \
        capsys.readouterr()
    assert 'placed as recording b of the calibration' in capsys.readouterr().out
    out = json.loads((folder / 'v_b' / 'validation.json').read_text())
    with capsys.disabled():
        print(f"--recording b: chi2/dof {out['chi2']:.1f}/{out['dof']}, p "
              f"{out['p_value']:.3g}, rms {out['rms_m'] * 1e6:.1f} µm")
    assert out['holds'] is True and out['recording'] == 'b' and out['dof'] == 90
    assert out['rms_m'] < 2 * np.sqrt(3) * 2e-5
    # combined with --register: B's stored placement is the start, re-fitted on the bag
    assert main(args + ['--out', str(folder / 'v_b_reg'), '--recording', 'b',
                        '--register', 'base']) == 0, capsys.readouterr()
    again = json.loads((folder / 'v_b_reg' / 'validation.json').read_text())
    assert again['dof'] == 84 and again['registration']['parameters'][0] == 'base.x'
    stored = _placement(yaml.safe_load((cal / 'calibration.yaml').read_text()), 'b')
    moved = np.array(list(again['registration']['values'].values()))[:3] - stored[:3]
    with capsys.disabled():
        print(f'--recording b --register base: chi2/dof {again["chi2"]:.1f}/84, base moved '
              f'{np.linalg.norm(moved) * 1e6:.1f} µm from B\'s stored placement')
    assert np.linalg.norm(moved) < 1e-3  # nothing moved: B's, not A's 2 m away
    assert main(args + ['--out', str(folder / 'v_first')]) == 1
    first = json.loads((folder / 'v_first' / 'validation.json').read_text())
    with capsys.disabled():
        print(f"without: chi2/dof {first['chi2']:.3g}/{first['dof']}, rms "
              f"{first['rms_m'] * 1e3:.0f} mm")
    assert first['holds'] is False and first['rms_m'] > 0.5
    assert main(args + ['--out', str(folder / 'v_c'), '--recording', 'c']) == 2
    err = capsys.readouterr().err
    assert "--recording: the calibration has no recording 'c'; its recordings: ['a', 'b']" \
        in err and 'Traceback' not in err


@pytest.mark.slow
def test_validate_recording_carries_the_learned_residual_into_that_set_up(tmp_path, capsys):
    """A joint-2 error at twice per turn the geometric model lacks, learned from set-ups A and
    B together (100 poses each): a later bag from B validated with ``--recording b`` has the
    field carried into B's frame; it predicts B better than the physical model alone, within
    its stated uncertainty."""
    doc = _cell_document({'cyclic_joint_error_h2:joint_2': {'a': 4e-4, 'b': 2e-4}})
    truths = _set_ups(tmp_path, doc, {'a': 100, 'b': 100}, 11)
    assert main(['identify', '--cell', str(tmp_path / 'cell.yaml'), '--bag',
                 str(tmp_path / 'a.mcap'), '--bag', str(tmp_path / 'b.mcap'), '--out',
                 str(tmp_path / 'cal'), '--learned-residual']) == 0, capsys.readouterr()
    assert (tmp_path / 'cal' / 'learned_residual.yaml').is_file()
    cm_b, _ = truth_cell_model(load_cell(tmp_path / 'cell_b.yaml'))
    simulate_campaign(tmp_path / 'cell_b.yaml', 40, tmp_path / 'b_later.mcap', 77, cm=cm_b,
                      p_true=truths['b'])
    assert main(['validate', '--cell', str(tmp_path / 'cell.yaml'), '--calibration',
                 str(tmp_path / 'cal' / 'calibration.yaml'), '--bag',
                 str(tmp_path / 'b_later.mcap'), '--out', str(tmp_path / 'val'),
                 '--recording', 'b']) == 0, capsys.readouterr()
    learned = json.loads((tmp_path / 'val' / 'validation.json').read_text())['learned_residual']
    with capsys.disabled():
        print(f"learned residual in B: rms {learned['rms_m'] * 1e6:.1f} µm, physical "
              f"{learned['rms_physical_m'] * 1e6:.1f} µm, p {learned['p_value']:.3g}")
    assert 'skipped' not in learned
    assert learned['rms_m'] < 0.7 * learned['rms_physical_m'], learned
    assert learned['holds'], learned


def _as_node_logs(folder: Path, bags: dict[str, tuple[str, bool]]) -> list[Path]:
    """Each bag's paired measurements written as the node writes its measurement log, one
    log per station (``{bag: (station, reflector_remounted)}``), in order."""
    from kpi_calib_ros.app.cell_model import build_cell_model
    from kpi_calib_ros.app.measurements import measurements_from_bag
    from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
    from kpi_calib_ros.io.measurement_log import MeasurementLog
    cm = build_cell_model(load_cell(folder / 'cell.yaml'))
    logs = folder / 'data_dir'
    for i, (bag, (station, remounted)) in enumerate(bags.items()):
        data = measurements_from_bag(cm, folder / bag)[0]
        with MeasurementLog(logs, station=station, reflector_remounted=remounted) as log:
            for k in range(len(data)):
                t = int(data.stamps_ns[k]) + i * 10 ** 12
                log.append(JointSample(t, tuple(cm.joint_names), np.asarray(data.q[k], float)),
                           PointSample(t, cm.cell.tracker_frame, np.asarray(data.eta[k], float)))
    return sorted(logs.glob('measurements_*.mcap'))


@pytest.mark.slow
def test_node_logs_given_as_bags_keep_their_stations_remounted_probe(set_ups, capsys):
    """The node's logs of station A and of A with the probe remounted (its log says so),
    given as ``--bag`` once per log or in a manifest that does not state
    ``reflector_remounted``: identified as the node identifies them, the second log with its
    own probe offset, at the noise. Before, the remount was read from the command line only:
    both logs shared one offset, rms 3 mm, and it exited 0."""
    folder, _ = set_ups
    logs = _as_node_logs(folder, {'a.mcap': ('station_a', False),
                                  'a_remounted.mcap': ('station_r', True)})
    assert [p.name for p in logs] == ['measurements_1.mcap', 'measurements_2.mcap']
    (folder / 'logs.yaml').write_text(yaml.safe_dump({'recordings': [
        {'bag': str(p)} for p in logs]}))
    for tag, given in (('bags', ['--bag', str(logs[0]), '--bag', str(logs[1])]),
                       ('manifest', ['--recordings', str(folder / 'logs.yaml')])):
        out = folder / f'from_logs_{tag}'
        assert main(['identify', '--cell', str(folder / 'cell.yaml'), *given, '--out',
                     str(out)]) == 0, capsys.readouterr()
        doc = yaml.safe_load((out / 'calibration.yaml').read_text())
        assert [r['reflector_remounted'] for r in doc['recordings']] == [False, True], tag
        assert doc['rms_m'] < 2 * np.sqrt(3) * 2e-5, (tag, doc['rms_m'])


@pytest.mark.slow
def test_validate_refuses_a_placement_the_new_poses_cannot_register(set_ups, capsys):
    """The probe remounted, then 20 poses turning joint 1 alone: re-registering base and
    probe together trades one against the other (the tool would report a base and an offset
    that are guesses), so validate exits 1 naming both and the fix; the probe alone
    (the tracker where it was) is determined by the same poses and holds."""
    folder, truths = set_ups
    cal = folder / 'for_gate'
    assert main(['identify', '--cell', str(folder / 'cell.yaml'), '--bag',
                 str(folder / 'a.mcap'), '--out', str(cal)]) == 0, capsys.readouterr()
    cm, _ = truth_cell_model(load_cell(folder / 'cell_a_remounted.yaml'))
    q = np.tile([0.1, 0.3, -0.4, 0.2, 0.5, 0.3], (20, 1))
    q[:, 0] = np.linspace(-1.0, 1.0, len(q))
    simulate_campaign(folder / 'cell_a_remounted.yaml', len(q), folder / 'joint_1.mcap', 77,
                      poses=(cm.robot.joint_names, q), cm=cm, p_true=truths['a_remounted'])
    args = ['validate', '--cell', str(folder / 'cell.yaml'), '--calibration',
            str(cal / 'calibration.yaml'), '--bag', str(folder / 'joint_1.mcap')]
    capsys.readouterr()
    assert main(args + ['--out', str(folder / 'v_both'), '--register', 'base+reflector']) == 1
    text = capsys.readouterr().out
    assert 'NOT VALID' in text and 'cannot place the probe' in text \
        and 'joint_4 (measured over 0 rad)' in text, text
    out = json.loads((folder / 'v_both' / 'validation.json').read_text())
    assert out['registration']['valid'] is False and out['registration']['std']['reflector.z'] \
        is None
    assert main(args + ['--out', str(folder / 'v_probe'), '--register', 'reflector']) == 0
    out = json.loads((folder / 'v_probe' / 'validation.json').read_text())
    assert out['registration']['valid'] is True
    std = np.array([out['registration']['std'][f'reflector.{c}'] for c in 'xyz'])
    assert np.all(std < 1e-4), std

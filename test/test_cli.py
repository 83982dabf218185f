"""kpi-calib simulate/identify end to end, and every kind of bad input the issue names."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from kpi_calib_ros.cli import main
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
from kpi_calib_ros.io.bag import read_bag, write_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL

CELL = str(DEFAULT_CELL)


@pytest.fixture(scope='module')
def run_bag(tmp_path_factory) -> Path:
    bag = tmp_path_factory.mktemp('run') / 'run.mcap'
    assert main(['simulate', '--cell', CELL, '--n', '40', '--out', str(bag), '--seed', '11']) == 0
    return bag


def _cell_copy(tmp_path: Path, **changes) -> Path:
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    for dotted, value in changes.items():
        node = doc
        *path, last = dotted.split('.')
        for key in path:
            node = node[key]
        node[last] = value
    path = tmp_path / 'cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def test_identify_recovers_truth_from_a_simulated_bag(run_bag, tmp_path, capsys):
    assert main(['identify', '--cell', CELL, '--bag', str(run_bag), '--out', str(tmp_path)]) == 0
    doc = yaml.safe_load((tmp_path / 'calibration.yaml').read_text())
    truth = yaml.safe_load(run_bag.with_name('run.truth.yaml').read_text())
    assert doc['pairing'] == {'accepted': 40, 'rejected': {}}
    tcp = doc['tcp'][0]
    error = np.array(tcp['position']) - np.array(truth['tcp_true'][0])
    assert np.all(np.abs(error) < 3 * np.array(tcp['std']))
    names = {p['name'] for p in doc['parameters'] if p['estimated']}
    assert 'reflector.z' in {p['name'] for p in doc['parameters']}
    assert len(names) + len(doc['dropped_parameters']) == len(doc['parameters'])
    assert 'rms residual' in capsys.readouterr().out
    # Its picture: the residuals and the TCP's 95 % region (first tutorial).
    assert (tmp_path / 'identification.png').stat().st_size > 10_000


def _identify_error(cell: Path | str, bag: Path, out: Path, capsys) -> str:
    code = main(['identify', '--cell', str(cell), '--bag', str(bag), '--out', str(out)])
    assert code == 2
    return capsys.readouterr().err


def test_malformed_urdf(tmp_path, run_bag, capsys):
    urdf = tmp_path / 'bad.urdf'
    urdf.write_text('<robot name="x"><link name="a"/><joint name="j"/></robot>')
    err = _identify_error(_cell_copy(tmp_path, **{'robot.urdf': str(urdf)}), run_bag, tmp_path,
                          capsys)
    assert 'robot.urdf' in err and 'not a valid URDF' in err


def test_unknown_frame(tmp_path, run_bag, capsys):
    err = _identify_error(_cell_copy(tmp_path, **{'robot.tip_frame': 'flange_x'}), run_bag,
                          tmp_path, capsys)
    assert 'robot.tip_frame' in err and 'flange_x' in err and 'tool0' in err


def test_bad_cell_value_names_the_key(tmp_path, run_bag, capsys):
    err = _identify_error(_cell_copy(tmp_path, **{'noise.sigma': 20}), run_bag, tmp_path, capsys)
    assert 'noise.sigma' in err and 'metres' in err


def test_wrong_joint_names_in_the_bag(tmp_path, run_bag, capsys):
    joints, points = read_bag(run_bag)
    renamed = [JointSample(s.stamp_ns, tuple(f'a{i + 1}' for i in range(len(s.names))),
                           s.positions, s.velocities) for s in joints]
    bag = tmp_path / 'renamed.mcap'
    write_bag(bag, renamed, points)
    err = _identify_error(CELL, bag, tmp_path, capsys)
    assert "'a1'" in err and "'joint_1'" in err


def test_bad_points_are_rejected_and_counted(tmp_path, run_bag, capsys):
    joints, points = read_bag(run_bag)
    bad = list(points)
    bad[0] = PointSample(points[0].stamp_ns, points[0].frame_id, [np.nan, 0.0, 1.0])
    bad[1] = PointSample(points[1].stamp_ns, points[1].frame_id, [np.inf, 0.0, 1.0])
    bad[2] = PointSample(points[2].stamp_ns, 'world', points[2].xyz)
    # A point stamped while the robot moves between two poses.
    moving = (points[3].stamp_ns + points[4].stamp_ns) // 2
    bad.append(PointSample(moving, points[3].frame_id, points[3].xyz))
    # A point long after the last joint state: no still joint state around it.
    bad.append(PointSample(joints[-1].stamp_ns + 10**10, points[3].frame_id, points[3].xyz))
    bag = tmp_path / 'bad_points.mcap'
    write_bag(bag, joints, bad)
    out = tmp_path / 'out'
    assert main(['identify', '--cell', CELL, '--bag', str(bag), '--out', str(out)]) == 0
    doc = yaml.safe_load((out / 'calibration.yaml').read_text())
    assert doc['pairing'] == {'accepted': 37, 'rejected': {
        'no_joint_state': 1, 'non_finite_point': 2, 'robot_moving': 1, 'wrong_frame': 1}}
    assert 'rejected 2 sample(s): non_finite_point' in capsys.readouterr().err


def test_too_few_measurements(tmp_path, run_bag, capsys):
    joints, points = read_bag(run_bag)
    bag = tmp_path / 'few.mcap'
    write_bag(bag, joints, points[:5])
    err = _identify_error(CELL, bag, tmp_path, capsys)
    assert 'too few measurements' in err and '5 points' in err


@pytest.mark.slow
def test_cli_errors_have_no_traceback(tmp_path):
    exe = Path(sys.executable).with_name('kpi-calib')
    proc = subprocess.run([str(exe), 'identify', '--cell', CELL, '--bag',
                           str(tmp_path / 'missing.mcap'), '--out', str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert 'Traceback' not in proc.stderr
    assert 'missing.mcap' in proc.stderr


@pytest.fixture(scope='module')
def renamed_bag(run_bag, tmp_path_factory) -> Path:
    """The campaign of ``run_bag`` recorded on a robot's own topic names."""
    joints, points = read_bag(run_bag)
    bag = tmp_path_factory.mktemp('renamed') / 'renamed.mcap'
    write_bag(bag, joints, points, joint_topic='/arm/joint_states', point_topic='/tracker/pt')
    return bag


@pytest.mark.parametrize('command', ['identify', 'diagnose'])
def test_renamed_topics_error_names_the_options_that_exist(command, renamed_bag, tmp_path,
                                                           capsys):
    code = main([command, '--cell', CELL, '--bag', str(renamed_bag), '--out', str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2
    assert "'/arm/joint_states'" in err and '--joint-topic' in err and 'topics.' in err


@pytest.mark.slow
def test_identify_reads_renamed_topics_from_options_or_cell(renamed_bag, tmp_path, capsys):
    assert main(['identify', '--cell', CELL, '--bag', str(renamed_bag), '--out',
                 str(tmp_path / 'a'), '--joint-topic', '/arm/joint_states',
                 '--point-topic', '/tracker/pt']) == 0
    cell = _cell_copy(tmp_path, topics={'joint_states': '/arm/joint_states',
                                        'point': '/tracker/pt'})
    assert main(['identify', '--cell', str(cell), '--bag', str(renamed_bag), '--out',
                 str(tmp_path / 'b')]) == 0
    a, b = (yaml.safe_load((tmp_path / d / 'calibration.yaml').read_text()) for d in 'ab')
    assert a['pairing'] == b['pairing'] == {'accepted': 40, 'rejected': {}}
    assert a['parameters'] == b['parameters']


@pytest.mark.parametrize('command', ['identify', 'diagnose'])
def test_an_unwritable_out_fails_before_computing(command, run_bag, tmp_path, capsys,
                                                  monkeypatch):
    from kpi_calib_ros.app import measurements as app_measurements

    def no_computing(*args, **kwargs):
        raise AssertionError('the bag was read before --out was checked')
    monkeypatch.setattr(app_measurements, 'measurements_from_bag', no_computing)
    blocker = tmp_path / 'a_file'
    blocker.write_text('in the way')
    for out in (blocker / 'result', Path('/proc/kpi_calib_result')):
        code = main([command, '--cell', CELL, '--bag', str(run_bag), '--out', str(out)])
        err = capsys.readouterr().err
        assert code == 2
        assert '--out' in err and str(out) in err and 'writable' in err


def test_a_cell_file_cannot_run_code_without_the_flag(run_bag, tmp_path, capsys):
    marker = tmp_path / 'ran.marker'
    (tmp_path / 'evil.py').write_text(
        f'from pathlib import Path\nPath({str(marker)!r}).write_text("ran")\n'
        'from kpi_calib_ros.core.effects.registry import EffectType\n'
        "SAG = EffectType('sag', ('g',), ('rad',), joint_function=lambda q, t, th: th[0] * q)\n")
    cell = _cell_copy(tmp_path, effects=['evil.py:SAG:joint_2'])
    for command in (['identify', '--bag', str(run_bag)], ['diagnose', '--bag', str(run_bag)],
                    ['design', '--n', '3'], ['simulate', '--n', '3']):
        code = main(command + ['--cell', str(cell), '--out', str(tmp_path / f'{command[0]}.x')])
        err = capsys.readouterr().err
        assert code == 2 and '--allow-code-effects' in err and 'effects[0]' in err, command
        assert not marker.exists(), command
    code = main(['identify', '--bag', str(run_bag), '--cell', str(cell), '--out',
                 str(tmp_path / 'ok'), '--allow-code-effects'])
    assert marker.exists() and code in (0, 1)  # ran: the opt-in was given


def test_the_iteration_limit_is_a_cell_setting_and_a_flag(run_bag, tmp_path, capsys):
    """identification.max_iterations / --max-iterations reach every fit: one iteration from
    the nominal start (millimetres off) is no convergence, and the calibration says so."""
    limited = _cell_copy(tmp_path, **{'identification': {'max_iterations': 1}})
    for cell, extra in ((limited, []), (CELL, ['--max-iterations', '1'])):
        out = tmp_path / ('cell' if extra == [] else 'flag')
        assert main(['identify', '--cell', str(cell), '--bag', str(run_bag), '--out', str(out),
                     *extra]) == 1
        doc = yaml.safe_load((out / 'calibration.failed.yaml').read_text())
        assert 'maximum number of iterations (1)' in ' '.join(doc['invalid_reasons'])
    capsys.readouterr()
    bad = _cell_copy(tmp_path, **{'identification': {'max_iterations': 0}})
    err = _identify_error(bad, run_bag, tmp_path, capsys)
    assert 'identification.max_iterations' in err and 'positive integer' in err
    with pytest.raises(SystemExit) as info:
        main(['identify', '--cell', CELL, '--bag', str(run_bag), '--out', str(tmp_path),
              '--max-iterations', '0'])
    assert info.value.code == 2 and 'positive integer' in capsys.readouterr().err


def test_identify_needs_no_working_poses_and_design_says_it_does(run_bag, tmp_path, capsys):
    """Identification does not need the KPI points: without working_poses it calibrates and
    reports no TCP; a design optimises the TCP precision and refuses, naming the key."""
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    del doc['working_poses']
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    assert main(['identify', '--cell', str(cell), '--bag', str(run_bag), '--out',
                 str(tmp_path / 'cal')]) == 0
    out = capsys.readouterr().out
    assert 'TCP: none reported' in out and 'TCP estimable' not in out
    cal = yaml.safe_load((tmp_path / 'cal' / 'calibration.yaml').read_text())
    assert cal['valid'] and cal['tcp'] == []
    # The KPI points enter only the constraint s = h(p, q_work): the estimate is the same.
    assert main(['identify', '--cell', CELL, '--bag', str(run_bag), '--out',
                 str(tmp_path / 'ref')]) == 0
    ref = yaml.safe_load((tmp_path / 'ref' / 'calibration.yaml').read_text())
    assert len(ref['tcp']) == 1 and cal['measurements'] == ref['measurements'] == 40
    assert [p['value'] for p in cal['parameters']] == pytest.approx(
        [p['value'] for p in ref['parameters']], rel=0, abs=1e-12)
    capsys.readouterr()
    assert main(['design', '--cell', str(cell), '--n', '10', '--out',
                 str(tmp_path / 'design.yaml')]) == 2
    err = capsys.readouterr().err
    assert 'working_poses' in err and 'identify needs none' in err


def test_identify_help_says_how_auto_chooses(capsys):
    """auto takes a larger level by a test of its held-out gain (core.model_selection), not
    by a margin on a figure."""
    with pytest.raises(SystemExit):
        main(['identify', '--help'])
    text = ' '.join(capsys.readouterr().out.split())
    assert '5%' not in text
    assert 'larger level only when it lowers the misfit beyond noise (F-test)' in text
    assert '--max-iterations' in text


@pytest.mark.slow
def test_a_reader_that_closes_the_pipe_early_loses_no_result(run_bag, tmp_path):
    """``kpi-calib identify … | true``: the reader leaves before the first line; the
    command still writes its whole result, exits 0 and prints no traceback."""
    out = tmp_path / 'out'
    with subprocess.Popen(
            [sys.executable, '-m', 'kpi_calib_ros.cli', 'identify', '--cell', CELL,
             '--bag', str(run_bag), '--out', str(out)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE) as proc:
        assert proc.stdout is not None and proc.stderr is not None
        proc.stdout.close()  # as `true` does, or `head` once it has its lines
        stderr = proc.stderr.read().decode()
        code = proc.wait(timeout=300)
    assert code == 0, stderr
    assert 'Traceback' not in stderr and 'BrokenPipeError' not in stderr, stderr
    assert yaml.safe_load((out / 'calibration.yaml').read_text())['valid'] is True


@pytest.mark.parametrize('alpha', ['5', '0', '1', 'nan', '-0.01', 'one'])
def test_a_false_alarm_level_outside_0_1_is_refused(alpha, tmp_path, capsys):
    """Before, ``--alpha 5`` ran a diagnosis that tested nothing and exited 0, and ``nan``
    failed on writing its JSON."""
    with pytest.raises(SystemExit) as info:
        main(['diagnose', '--cell', CELL, '--bag', str(tmp_path / 'b.mcap'), '--out',
              str(tmp_path / 'd'), '--alpha', alpha])
    err = capsys.readouterr().err
    assert info.value.code == 2 and '--alpha' in err and 'between 0 and 1' in err

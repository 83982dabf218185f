"""Every subcommand's --out is checked before anything is computed (one check,
cli.check_output): a file-system root or an existing folder given for a file is exit 2
naming --out, and nothing is written there; a write that fails, and a SIGTERM or SIGINT
while writing, leave no hidden .partial or temporary file behind."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kpi_calib_ros.cli import OUTPUTS, main
from kpi_calib_ros.io.bag_writing import BagStream
from kpi_calib_ros.io.cell import DEFAULT_CELL

CELL = str(DEFAULT_CELL)


def _command(name: str, out: str, tmp_path: Path) -> list[str]:
    """``name`` with every required input, ``--out out``."""
    table = tmp_path / 't.csv'
    table.write_text('j1,x,y,z\n0.1,1,2,3\n')
    bag, cal = str(tmp_path / 'in.mcap'), str(tmp_path / 'calibration.yaml')
    return {'identify': ['identify', '--cell', CELL, '--bag', bag],
            'diagnose': ['diagnose', '--cell', CELL, '--bag', bag],
            'validate': ['validate', '--cell', CELL, '--calibration', cal, '--bag', bag],
            'campaign': ['campaign', '--cell', CELL, '--target-std', '1e-4'],
            'demo': ['demo'], 'robots': ['robots'],
            'simulate': ['simulate', '--cell', CELL, '--n', '5'],
            'import-csv': ['import-csv', str(table), '--frame', 'laser_tracker',
                           '--joints', 'j1', '--marker', 'm=x,y,z'],
            'design': ['design', '--cell', CELL, '--n', '8']}[name] + ['--out', out]


def _root_entries() -> set[str]:
    return set(os.listdir('/'))


@pytest.mark.parametrize('command', sorted(OUTPUTS))
def test_out_at_the_root_is_refused_before_computing(command, tmp_path, capsys, monkeypatch):
    """``--out /``: exit 2 naming --out, before any input is read or anything computed
    (campaign wrote /initial_design.yaml, simulate and design computed and failed with
    EBUSY, simulate leaving /..XXXX.partial)."""
    from kpi_calib_ros.io import cell as io_cell

    def no_computing(*args, **kwargs):
        raise AssertionError('an input was read before --out was checked')
    monkeypatch.setattr(io_cell, 'read_yaml_file', no_computing)
    before = _root_entries()
    code = main(_command(command, '/', tmp_path))
    err = capsys.readouterr().err
    assert code == 2, err
    assert f'kpi-calib {command}: error: --out: \'/\'' in err, err
    assert 'Traceback' not in err
    assert _root_entries() == before


@pytest.mark.parametrize('command', sorted(c for c, example in OUTPUTS.items() if example))
def test_a_folder_given_for_a_file_is_refused_before_computing(command, tmp_path, capsys):
    folder = tmp_path / 'existing'
    folder.mkdir()
    code = main(_command(command, str(folder), tmp_path))
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"--out: '{folder}' is a folder: give the file to write, e.g. " \
        f"'{folder / OUTPUTS[command]}'" in err, err
    assert list(folder.iterdir()) == []


def test_a_bag_that_cannot_be_renamed_into_place_leaves_no_partial(tmp_path):
    """The rename at the end fails (the target is a folder): the .partial is removed
    (it stayed, 265 kB for simulate)."""
    target = tmp_path / 'a_folder'
    target.mkdir()
    with pytest.raises(IsADirectoryError):
        with BagStream(target) as bag:
            bag.write_joint  # noqa: B018  (nothing to write: the header alone)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['a_folder']


def _table(path: Path, rows: int) -> Path:
    lines = ['j1,j2,j3,j4,j5,j6,x,y,z']
    for i in range(rows):
        lines.append(','.join([f'{0.001 * (i % 997):.4f}'] * 6 + ['1.5', '0.2', '0.9']))
    path.write_text('\n'.join(lines) + '\n')
    return path


@pytest.mark.slow
@pytest.mark.parametrize('signum', [signal.SIGTERM, signal.SIGINT])
def test_a_stopped_import_leaves_no_partial_bag(signum, tmp_path):
    """import-csv stopped while it writes the bag: exit 128 + signal with a line saying
    so, no traceback, and neither the bag nor its hidden .partial left (a SIGTERM left a
    1.6 GB .partial)."""
    table = _table(tmp_path / 'big.csv', 20000)
    out = tmp_path / 'out'
    out.mkdir()
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join(
        [str(Path(__file__).parent.parent)] + os.environ.get('PYTHONPATH', '').split(
            os.pathsep))}
    process = subprocess.Popen(
        [sys.executable, '-m', 'kpi_calib_ros.cli', 'import-csv', str(table), '--out',
         str(out / 'bag.mcap'), '--frame', 'laser_tracker', '--joints',
         'j1,j2,j3,j4,j5,j6', '--marker', 'm=x,y,z'],
        env=env, stderr=subprocess.PIPE, text=True,
        # A user's terminal delivers SIGINT to a command that handles it; a test worker may
        # run with SIGINT ignored at the C level (a library's handler left behind), which a
        # child would inherit and never see the signal: start it as a terminal would.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        # Polls for the file the import writes into (a condition, not a fixed wait).
        while not any(p.name.endswith('.partial') for p in out.iterdir()):
            assert process.poll() is None, process.communicate()[1]
            assert time.monotonic() < deadline, 'no .partial appeared'
            time.sleep(0.01)
        process.send_signal(signum)
        _, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 128 + signum, err
    assert f'stopped by {signal.Signals(signum).name}' in err and 'Traceback' not in err, err
    assert list(out.iterdir()) == []

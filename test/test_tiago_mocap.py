"""Real data: the TIAGo mocap campaign (four markers per posture, unknown placements).

Calibrate on the three 2021-11-30 sessions, validate on the 2021-11-26 one with
``kpi-calib validate`` (the held-out day). The shared data folder is part of the
test environment (it is not copied into the repository); the cell and column mapping are
in test/data/.
"""
import json
import os
from pathlib import Path

import pytest
import yaml

from kpi_calib_ros.cli import main

# Beside the repository (../shared/data/tiago_mocap), or where TIAGO_MOCAP_DIR says.
_BESIDE = Path(__file__).resolve().parents[2] / 'shared' / 'data' / 'tiago_mocap'
DATA = Path(os.environ.get('TIAGO_MOCAP_DIR') or (
    _BESIDE if _BESIDE.is_dir() else '/work/shared/data/tiago_mocap'))
HERE = Path(__file__).resolve().parent / 'data'
CELL = HERE / 'tiago_mocap_cell.yaml'
MAPPING = HERE / 'tiago_mocap_mapping.yaml'
TRAIN = ['2021-11-30', '2021-11-30-1403', '2021-11-30-1504']
# The full geometric model calibrated on the 37-posture session alone predicted the
# other day with this rms before several points per pose were used together.
FULL_MODEL_BEFORE_M = 4.2e-3


def _table(session):
    return str(DATA / f'qualisys_{session}_static_postures.csv')


@pytest.mark.slow
def test_calibrated_on_one_day_predicts_the_other_day_better_than_before(tmp_path):
    assert main(['import-csv', *map(_table, TRAIN), '--mapping', str(MAPPING),
                 '--out', str(tmp_path / 'train.mcap')]) == 0
    assert main(['import-csv', _table('2021-11-26'), '--mapping', str(MAPPING),
                 '--out', str(tmp_path / 'new.mcap')]) == 0
    assert main(['identify', '--cell', str(CELL), '--bag', str(tmp_path / 'train.mcap'),
                 '--out', str(tmp_path / 'cal')]) == 0
    cal = yaml.safe_load((tmp_path / 'cal' / 'calibration.yaml').read_text())
    assert cal['pairing']['accepted'] == 4 * (37 + 63 + 59)
    # Outlier exclusion (identification.outliers) leaves the rest in the fit.
    assert cal['measurements'] == 4 * (37 + 63 + 59) - len(cal['robust']['excluded'])
    rc = main(['validate', '--cell', str(CELL), '--calibration',
               str(tmp_path / 'cal' / 'calibration.yaml'), '--bag', str(tmp_path / 'new.mcap'),
               '--out', str(tmp_path / 'val')])
    out = json.loads((tmp_path / 'val' / 'validation.json').read_text())
    assert out['measurements'] == 4 * 62
    assert out['rms_m'] < FULL_MODEL_BEFORE_M
    # Millimetre errors (arm_6 play, the README says) against a stated 0.2 mm σ: the
    # calibration's own prediction is far too optimistic, and validate says so.
    assert rc == 1 and not out['holds']

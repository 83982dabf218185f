"""Real data: where the geometric model of the UR10 and the TIAGo fails, model-free.

UR10 (../shared/data/ipa_ur10, Series A, every ``STEP``-th posture of the grid (four days),
with the cell temperature as a covariate: ``import-csv`` records it, the cell's
``temperature:`` section reads it and pairs it to the measurements as ``kpi-calib
diagnose`` does, :func:`kpi_calib_ros.app.measurements.with_readings`) and TIAGo
(../shared/data/tiago_mocap, the 2021-11-30 session): ``kpi-calib diagnose``'s
calibration, its named-effect screen, the residual analysis (core.diagnosis.residual_analysis) and
the learned residual's decision; the four answers, the ranked inputs and the
partial-residual plot. Writes bench/results/residual_inputs_real.md and the plots beside it.

    .venv/bin/python bench/residual_inputs_real.py [DATA_DIR]   # default ../shared/data
"""
from __future__ import annotations

import contextlib
import io
import shutil
import sys
import tempfile
import time
from pathlib import Path

import yaml

from kpi_calib_ros.app.cell_model import CellModel, build_cell_model
from kpi_calib_ros.app.diagnose import diagnose_cell, learned_remedy, with_remedies
from kpi_calib_ros.app.learned_residual import choose_residual
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.cli import main
from kpi_calib_ros.io.cell import cell_from_dict
from kpi_calib_ros.io.names import DEFAULT_TEMPERATURE_TOPIC
from kpi_calib_ros.io.report import write_report
from kpi_calib_ros.io.residual_plots import analysis_lines

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / 'bench' / 'results'
STEP = 40   # every 40th of the 11911 Series A postures: 298 poses over Series A's four days


def _subset(source: Path, target: Path, step: int) -> Path:
    lines = source.read_bytes().split(b'\r\n')
    body = [line for line in lines[1:] if line][::step]
    target.write_bytes(b'\r\n'.join([lines[0], *body]) + b'\r\n')
    return target


def _cell(path: Path, temperature: dict | None = None) -> CellModel:
    """The cell file's model, with ``temperature`` as its ``temperature:`` section."""
    doc = yaml.safe_load(path.read_text())
    if temperature is not None:
        doc['temperature'] = temperature
    return build_cell_model(cell_from_dict(doc, path.parent))


def _run(name: str, cm: CellModel, bag: Path, out: Path) -> list[str]:
    # The temperatures of the cell's temperature: section paired to every measurement
    # (app.measurements.with_readings); diagnose_cell analyses the recorded ones.
    data, _ = measurements_from_bag(cm, bag)
    start = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()):
        cd = diagnose_cell(cm, data, add_best=False)
    took = time.perf_counter() - start
    # As kpi-calib diagnose does: the learned residual, when chosen, is one more remedy.
    choice = choose_residual(cm, cd.data, cd.result)
    learned = learned_remedy(choice)
    if learned is not None:
        cd = with_remedies(cd, (learned,))
    folder = out / name
    write_report(folder, cd)
    shutil.copy(folder / 'partial_residuals.png', RESULTS / f'residual_inputs_{name}.png')
    assert cd.residual_analysis is not None
    lines = [f'## {name}', '',
             f'{len(cd.data)} measurement rows, rms {cd.result.rms_m * 1e6:.1f} µm, '
             f'validation rms {cd.diagnosis.validation_rms_m * 1e6:.1f} µm; diagnose '
             f'(calibration, screen, residual analysis) {took:.0f} s. Verdict of the '
             f'named-effect screen: {cd.diagnosis.verdict}', '',
             f'Learned residual: {choice.reason}.', '',
             f'Plot: `residual_inputs_{name}.png`.']
    lines += analysis_lines(cd.residual_analysis, cd.answer)[1:]
    return lines + ['']


def main_(argv: list[str]) -> int:
    data = Path(argv[0]) if argv else ROOT.parent / 'shared' / 'data'
    if not data.is_dir():
        data = Path('/work/shared/data')
    lines = ['# Where the geometric model fails on real robots (model-free)', '',
             'Command: `.venv/bin/python bench/residual_inputs_real.py`.', '']
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        table = _subset(data / 'ipa_ur10' / 'Series_A' / 'measurements_grid.csv',
                        tmp_path / 'grid.csv', STEP)
        bag = tmp_path / 'grid.mcap'
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(['import-csv', str(table), '--mapping',
                         str(ROOT / 'test' / 'data' / 'ipa_ur10_mapping.yaml'),
                         '--out', str(bag)]) == 0
        # import-csv writes the table's temperature column on the default topic, frame id
        # of the tracker: that sensor is the cell's temperature.
        ur10 = _cell(ROOT / 'test' / 'data' / 'ipa_ur10_cell.yaml',
                     {'topic': DEFAULT_TEMPERATURE_TOPIC, 'sensors': ['laser_tracker'],
                      'reference': 20.0})
        lines += _run('ur10_series_a', ur10, bag, tmp_path)
        print('\n'.join(lines), flush=True)
        tiago = data / 'tiago_mocap' / 'qualisys_2021-11-30_static_postures.csv'
        tbag = tmp_path / 'tiago.mcap'
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(['import-csv', str(tiago), '--mapping',
                         str(ROOT / 'test' / 'data' / 'tiago_mocap_mapping.yaml'),
                         '--out', str(tbag)]) == 0
        lines += _run('tiago_2021_11_30', _cell(ROOT / 'test' / 'data' /
                                                'tiago_mocap_cell.yaml'), tbag, tmp_path)
    text = '\n'.join(lines) + '\n'
    (RESULTS / 'residual_inputs_real.md').write_text(text)
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main_(sys.argv[1:]))

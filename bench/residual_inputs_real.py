"""Real data: where the geometric model of the UR10 and the TIAGo fails, model-free.

UR10 (../shared/data/ipa_ur10, Series A, every ``STEP``-th posture of the overnight grid,
with the cell temperature as a covariate) and TIAGo (../shared/data/tiago_mocap, the
2021-11-30 session): ``kpi-calib diagnose``'s calibration, its named-effect screen, the
residual analysis (core.residual_analysis) and the learned residual's decision; the four
answers, the ranked inputs and the
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

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from kpi_calib_ros.app.diagnose import diagnose_cell, learned_remedy, with_remedies
from kpi_calib_ros.app.learned_residual import choose_residual
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.cli import main
from kpi_calib_ros.io.cell import build_cell_model, load_cell
from kpi_calib_ros.io.names import DEFAULT_TEMPERATURE_TOPIC
from kpi_calib_ros.io.report import write_report
from kpi_calib_ros.io.residual_plots import analysis_lines

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / 'bench' / 'results'
STEP = 40   # every 40th of the 11911 Series A postures: 298 poses over the night


def _subset(source: Path, target: Path, step: int) -> Path:
    lines = source.read_bytes().split(b'\r\n')
    body = [line for line in lines[1:] if line][::step]
    target.write_bytes(b'\r\n'.join([lines[0], *body]) + b'\r\n')
    return target


def _temperatures(bag: Path, stamps_ns: np.ndarray) -> np.ndarray:
    """The cell temperature (°C) of each measurement: the message nearest its stamp."""
    with open(bag, 'rb') as f:
        msgs = [m for _, _, _, m in make_reader(f, decoder_factories=[DecoderFactory()])
                .iter_decoded_messages(topics=[DEFAULT_TEMPERATURE_TOPIC])]
    t = np.array([m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec for m in msgs])
    value = np.array([m.temperature for m in msgs])
    order = np.argsort(t)
    t, value = t[order], value[order]
    idx = np.clip(np.searchsorted(t, stamps_ns), 1, len(t) - 1)
    nearer = np.where(np.abs(stamps_ns - t[idx - 1]) <= np.abs(t[idx] - stamps_ns), idx - 1, idx)
    return value[nearer]


def _run(name: str, cell: Path, bag: Path, covariates: bool, out: Path) -> list[str]:
    cm = build_cell_model(load_cell(cell))
    data, _ = measurements_from_bag(cm, bag)
    cov = None
    if covariates:
        cov = {'temperature': (_temperatures(bag, np.asarray(data.stamps_ns)), '°C')}
    start = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()):
        cd = diagnose_cell(cm, data, add_best=False, covariates=cov)
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
        lines += _run('ur10_series_a', ROOT / 'test' / 'data' / 'ipa_ur10_cell.yaml', bag,
                      True, tmp_path)
        print('\n'.join(lines), flush=True)
        tiago = data / 'tiago_mocap' / 'qualisys_2021-11-30_static_postures.csv'
        tbag = tmp_path / 'tiago.mcap'
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(['import-csv', str(tiago), '--mapping',
                         str(ROOT / 'test' / 'data' / 'tiago_mocap_mapping.yaml'),
                         '--out', str(tbag)]) == 0
        lines += _run('tiago_2021_11_30', ROOT / 'test' / 'data' / 'tiago_mocap_cell.yaml',
                      tbag, False, tmp_path)
    text = '\n'.join(lines) + '\n'
    (RESULTS / 'residual_inputs_real.md').write_text(text)
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main_(sys.argv[1:]))

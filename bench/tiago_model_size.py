"""Real data: can a smaller geometric model of the TIAGo arm predict another day better?

Backward elimination on the 37-posture session (2021-11-30, four markers per posture),
with the rule fixed before any held-out figure was looked at: start from the full geometric
model; at each step drop the geometric parameter (not the base or reflector placement) with
the smallest |value / std|, refit; score every model by its leave-one-posture-out error
(core.estimation.cross_validation.validation_rms: PRESS over posture blocks of the linearised
fit, all four markers of a posture held out together) and choose the smallest PRESS. Every
step's error on the 2021-11-26 session and on the two other 2021-11-30 sessions (which none of the
choices uses) is printed beside it.

    .venv/bin/python bench/tiago_model_size.py

Writes bench/results/tiago_model_size.md. Needs ../shared/data/tiago_mocap (or
TIAGO_MOCAP_DIR). Plain least squares on every point (no outlier exclusion), so the first
row differs slightly from `identify`'s 4.30 mm (which excludes 4 of 148 points).
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.identify import identify_cell
from kpi_calib_ros.app.measurements import load_measurements
from kpi_calib_ros.app.placement import registered_start
from kpi_calib_ros.cli import main as cli
from kpi_calib_ros.core.diagnosis.model_selection import level_free
from kpi_calib_ros.core.estimation.cross_validation import validation_rms

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get('TIAGO_MOCAP_DIR') or ROOT.parent / 'shared' / 'data' / 'tiago_mocap')
CELL = ROOT / 'test' / 'data' / 'tiago_mocap_cell.yaml'
MAPPING = ROOT / 'test' / 'data' / 'tiago_mocap_mapping.yaml'
TRAIN = '2021-11-30'
HELD_OUT = ('2021-11-26', '2021-11-30-1403', '2021-11-30-1504')
OUT = ROOT / 'bench' / 'results' / 'tiago_model_size.md'
PLACEMENT = ('base.', 'reflector.')


def _bag(session: str, folder: Path) -> Path:
    out = folder / f'{session}.mcap'
    table = DATA / f'qualisys_{session}_static_postures.csv'
    if cli(['import-csv', str(table), '--mapping', str(MAPPING), '--out', str(out)]) != 0:
        raise SystemExit(f'import-csv failed for {table}')
    return out


def _rms(cm, values, data) -> float:
    e = data.eta - cm.model.predict(values, data.q, data.tau, data.reflector, data.rotation)
    return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))


def main() -> None:
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        bags = {s: _bag(s, Path(tmp)) for s in (TRAIN,) + HELD_OUT}
        cm, data, _ = load_measurements(CELL, bags[TRAIN])
        held = {s: load_measurements(CELL, bags[s])[1] for s in HELD_OUT}
    start, _ = registered_start(cm, data)
    free = level_free(cm.model.params, 'geometric', len(cm.geometric))
    names = list(cm.model.params.names)
    rows = []
    while True:
        result = identify_cell(cm, data, p0=start, free=free)
        row = {'n': len(result.estimated), 'train': result.rms_m,
               'press': validation_rms(cm.model, data, result),
               **{s: _rms(cm, result.values, d) for s, d in held.items()}}
        t = {n: abs(result.values[names.index(n)]) / s
             for n, s in zip(result.estimated, result.std) if not n.startswith(PLACEMENT)}
        row['drop'] = min(t, key=t.get) if t else ''
        row['t'] = t[row['drop']] if t else float('nan')
        rows.append(row)
        print(f"{row['n']:3d} parameters  train {1e3 * row['train']:.3f}  PRESS "
              f"{1e3 * row['press']:.3f}  " + '  '.join(f'{s} {1e3 * row[s]:.3f}'
                                                     for s in HELD_OUT) + ' mm', flush=True)
        if not t:
            break
        free = [n for n in free if n != row['drop'] and
                (n in result.estimated or n.startswith(PLACEMENT))]
    best = min(range(len(rows)), key=lambda i: rows[i]['press'])
    lines = ['# TIAGo: model size by backward elimination (37-posture session)', '',
             'Command: `.venv/bin/python bench/tiago_model_size.py` '
             f'({time.perf_counter() - t0:.0f} s). Rule (fixed before the held-out columns '
             'were read): drop the geometric parameter with the smallest |value/std|, refit, '
             'choose the smallest leave-one-posture-out PRESS. rms over all four markers, mm; '
             'plain least squares on all 148 training points.', '',
             '| identified | training | PRESS (leave one posture out) | '
             + ' | '.join(HELD_OUT) + ' | dropped next (|value/std|) |',
             '|---|---|---|' + '---|' * len(HELD_OUT) + '---|']
    for i, r in enumerate(rows):
        mark = ' **chosen**' if i == best else ''
        lines.append(f"| {r['n']}{mark} | {1e3 * r['train']:.2f} | {1e3 * r['press']:.2f} | "
                     + ' | '.join(f'{1e3 * r[s]:.2f}' for s in HELD_OUT)
                     + f" | {r['drop']} ({r['t']:.2f}) |")
    b, full = rows[best], rows[0]
    lines += ['', f"Chosen by PRESS: {b['n']} parameters; 2021-11-26 {1e3 * b[HELD_OUT[0]]:.2f} mm "
              f"against {1e3 * full[HELD_OUT[0]]:.2f} mm for the full model "
              f"({full['n']} parameters); the confirmation sessions "
              + ', '.join(f'{1e3 * b[s]:.2f} (full {1e3 * full[s]:.2f})' for s in HELD_OUT[1:])
              + ' mm.', '']
    OUT.write_text('\n'.join(lines))
    print(f'written: {OUT}')


if __name__ == '__main__':
    sys.exit(main())

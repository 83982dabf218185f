"""Outlier exclusion at scale: 900 poses, three reflectors, 30 % of the points far off.

A simulated campaign on the default cell with three reflectors per pose (the offsets of
test_multipoint), σ = 20 µm, and 30 % of its 2700 points moved 0.5-5 mm in a random
direction (faults; none is gross, so every one is found by the fits), with the cell's
default outlier settings: ``max_fraction`` 0.2 caps only the faults no other reflector of
the pose confirms. Times ``calibrate_cell`` (what ``kpi-calib identify`` runs) with its
progress lines, then ``diagnose_cell`` (no effect added), and checks that both keep the
same points and that the excluded points are the faults. Writes
bench/results/outlier_scale.md.
"""
from __future__ import annotations

import copy
import sys
import time
from pathlib import Path

import numpy as np

import kpi_calib_ros  # noqa: F401  (sets single-threaded BLAS before numpy loads)
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.diagnose import diagnose_cell
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.core.estimation.robust import OutlierSettings
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document

OFFSETS = [[0.0, 0.0, 0.03], [0.06, 0.0, 0.03], [0.0, 0.05, 0.02]]
POSES = 900
FRACTION = 0.3
SEED = 1


def main() -> int:
    doc = copy.deepcopy(read_cell_document(DEFAULT_CELL))
    del doc['reflector']['offset']
    doc['reflectors'] = [{'name': n, 'offset': o} for n, o in zip('abc', OFFSETS)]
    cm = build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))
    assert cm.cell.identification.outliers == OutlierSettings()
    rng = np.random.default_rng(SEED)
    p_true = true_parameters(cm.model.params, rng)
    q = np.repeat(random_configurations(cm.model, cm.geometric.nominal, POSES, rng), 3, axis=0)
    ref = np.tile(np.arange(3), POSES)
    eta = cm.model.predict(p_true, q, reflector=ref) + rng.normal(size=(len(q), 3)) * 20e-6
    faults = np.sort(rng.choice(len(q), int(FRACTION * len(q)), replace=False))
    d = rng.normal(size=(len(faults), 3))
    eta[faults] += rng.uniform(0.5e-3, 5e-3, (len(faults), 1)) * d / \
        np.linalg.norm(d, axis=1, keepdims=True)
    data = Measurements(q=q, eta=eta, reflector=ref, stamps_ns=np.arange(len(q)) + 1)

    lines_seen: list[str] = []

    def progress(line: str) -> None:
        lines_seen.append(line)
        print(f'  [{time.perf_counter() - t0:6.1f} s] {line}', flush=True)
    print(f'{POSES} poses x 3 reflectors = {len(q)} points, {len(faults)} faults', flush=True)
    t0 = time.perf_counter()
    cal = calibrate_cell(cm, data, progress=progress)
    t_identify = time.perf_counter() - t0
    rounds = len(lines_seen)
    excluded = sorted(e.index for e in cal.robust.excluded)
    t0 = time.perf_counter()
    cd = diagnose_cell(cm, data, add_best=False, progress=progress)
    t_diagnose = time.perf_counter() - t0
    same = bool(np.array_equal(cd.kept, cal.robust.kept))
    missed = sorted(set(faults.tolist()) - set(excluded))
    extra = sorted(set(excluded) - set(faults.tolist()))
    rows = [('points / faults', f'{len(q)} / {len(faults)}'),
            ('identify (calibrate_cell) wall time', f'{t_identify:.1f} s'),
            ('exclusion rounds', str(rounds)),
            ('excluded', str(len(excluded))),
            ('faults not excluded / good points excluded', f'{len(missed)} / {len(extra)}'),
            ('misfit points kept', str(len(cal.robust.misfit))),
            ('identify rms / σ̂ (calibration.yaml)', f'{cal.result.rms_m * 1e6:.1f} µm / '
                                                    f'{cal.robust.sigma_robust * 1e6:.1f} µm'),
            ('diagnose (diagnose_cell, no effect added) wall time', f'{t_diagnose:.1f} s'),
            ('diagnose keeps the points identify keeps', str(same)),
            ('diagnose rms / σ̂', f'{cd.diagnosis.rms_m * 1e6:.1f} µm / '
                                 f'{cd.diagnosis.residuals.sigma_robust_m * 1e6:.1f} µm')]
    for k, v in rows:
        print(f'{k}: {v}')
    lines = ['# Outlier exclusion at scale', '',
             f'{POSES} random poses of the default cell, three reflectors each (σ = 20 µm), '
             f'{FRACTION:.0%} of the points moved 0.5-5 mm in a random direction '
             f'(seed {SEED}); default outlier settings (`max_fraction` 0.2, which caps only '
             'the faults no other reflector of the pose confirms). One run on the '
             'shared 2-core machine, command: `.venv/bin/python bench/outlier_scale.py`.', '',
             '| figure | value |', '|---|---|'] + [f'| {k} | {v} |' for k, v in rows]
    out = Path(__file__).resolve().parent / 'results' / 'outlier_scale.md'
    out.write_text('\n'.join(lines) + '\n')
    print(f'written {out}')
    return 0 if same and not missed and not extra else 1


if __name__ == '__main__':
    sys.exit(main())

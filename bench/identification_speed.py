"""Identification time on the KR15-class default cell: 60 poses, and growth over 30-500 poses.

Times one `identify` call (QR identifiability, Gauss-Newton, eq. (19) covariance)
after the model is built; model build time is reported separately. Median of
repeats with perf_counter. Writes bench/results/identification_speed.md.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

import kpi_calib_ros  # noqa: F401  (sets single-threaded BLAS before numpy loads)
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell

SIGMA = 20e-6
SIZES = (30, 60, 120, 250, 500)
REPEATS = 7


def main() -> int:
    t0 = time.perf_counter()
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    build = time.perf_counter() - t0
    rng = np.random.default_rng(1)
    p_true = true_parameters(cm.model.params, rng)
    rows = []
    for n in SIZES:
        q = random_configurations(cm.model, cm.model.params.nominal, n, rng)
        data = simulate_measurements(cm.model, p_true, q, SIGMA, rng)
        times, iterations = [], []
        for _ in range(REPEATS):
            t0 = time.perf_counter()
            result = identify(cm.model, data, SIGMA, cm.q_work)
            times.append(time.perf_counter() - t0)
            iterations.append(result.iterations)
        rows.append((n, float(np.median(times)), float(np.min(times)), iterations[0],
                     result.rms_m))
        print(f'{n:4d} poses: median {rows[-1][1] * 1e3:7.1f} ms '
              f'(min {rows[-1][2] * 1e3:7.1f} ms), '
              f'{iterations[0]} GN iterations, rms {result.rms_m * 1e6:.1f} µm', flush=True)
    lines = ['# Identification time (KR15-class default cell)', '',
             f'Model build (URDF -> CasADi eq. (3) with Jacobians): {build * 1e3:.0f} ms.', '',
             f'`identify` after build, median of {REPEATS} runs, σ = 20 µm, '
             f'command: `.venv/bin/python bench/identification_speed.py`', '',
             '| poses | median ms | min ms | GN iterations | rms µm |', '|---|---|---|---|---|']
    lines += [f'| {n} | {m * 1e3:.1f} | {mn * 1e3:.1f} | {it} | {rms * 1e6:.1f} |'
              for n, m, mn, it, rms in rows]
    out = Path(__file__).resolve().parent / 'results' / 'identification_speed.md'
    out.write_text('\n'.join(lines) + '\n')
    print(f'model build {build * 1e3:.0f} ms; written {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

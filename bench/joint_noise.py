"""Joint-reading noise stated in the cell (noise.joint_sigma) against left out.

Default cell, random measurable poses, σ = 20 µm, joint readings with 0.03° of noise on
every joint. Stated, the fit whitens every point with σ²I + J_q Σ_q J_qᵀ; left out, it
weighs by 1/σ alone:

* χ² p-values over ``seeds`` campaigns of 30 poses (KS test for uniformity);
* the diagnosis over ``diag_seeds`` campaigns of 40 poses: adequate, an effect suggested;
* the TCP sqrt(trace) against the Monte Carlo spread over 100 noise draws of one robot.

Writes bench/results/joint_noise.md.

    .venv/bin/python bench/joint_noise.py [seeds] [diag_seeds]
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import scipy.stats

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.diagnosis.verdict import diagnose, equivalent_joint_sigma
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.precision import honest_precision
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell

JOINT_SIGMA = float(np.deg2rad(0.03))


def campaign(cm, seed: int, poses: int):
    rng = np.random.default_rng(seed)
    p_true = true_parameters(cm.model.params, rng)
    return p_true, random_configurations(cm.model, p_true, poses, rng), rng


def main() -> None:
    seeds = int(sys.argv[1]) if len(sys.argv) > 1 else 100
    diag_seeds = int(sys.argv[2]) if len(sys.argv) > 2 else 20
    cell = load_cell(DEFAULT_CELL)
    exact = build_cell_model(cell)
    stated = build_cell_model(dataclasses.replace(cell, joint_sigma=JOINT_SIGMA))
    start = time.time()
    p_stated, p_unstated = [], []
    for seed in range(seeds):
        p_true, q, rng = campaign(exact, seed, 30)
        data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng, JOINT_SIGMA)
        p_stated.append(identify(stated.model, data, cell.sigma, stated.q_work).p_value)
        p_unstated.append(identify(exact.model, data, cell.sigma, exact.q_work).p_value)
    ks = scipy.stats.kstest(p_stated, 'uniform').pvalue
    counts = {'stated': [0, 0], 'unstated': [0, 0]}
    equivalent = []
    for seed in range(diag_seeds):
        p_true, q, rng = campaign(exact, 200 + seed, 40)
        data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng, JOINT_SIGMA)
        for name, cm in (('stated', stated), ('unstated', exact)):
            result = identify(cm.model, data, cell.sigma, cm.q_work)
            d = diagnose(cm.model, data, result)
            counts[name][0] += d.model_adequate
            counts[name][1] += d.best is not None
            if name == 'unstated':
                equivalent.append(np.rad2deg(equivalent_joint_sigma(cm.model, data, result)))
    p_true, q, _ = campaign(exact, 11, 30)
    rng = np.random.default_rng(12)
    tcp, trace = [], []
    for _ in range(100):
        data = simulate_measurements(exact.model, p_true, q, cell.sigma, rng, JOINT_SIGMA)
        result = honest_precision(identify(stated.model, data, cell.sigma, stated.q_work))
        tcp.append(result.tcp)
        trace.append(np.trace(result.tcp_covariance, axis1=1, axis2=2))
    monte_carlo = np.sqrt(np.sum(np.var(np.array(tcp), axis=0, ddof=1), axis=1))
    predicted = np.sqrt(np.mean(trace, axis=0))
    elapsed = time.time() - start
    lines = [
        '# Joint-reading noise stated (noise.joint_sigma) against left out',
        '',
        f'`.venv/bin/python bench/joint_noise.py {seeds} {diag_seeds}`: default cell, '
        f'σ = 20 µm, 0.03° on every joint; {elapsed:.0f} s.',
        '',
        '| figure | joint noise stated | left out |',
        '|---|---|---|',
        f'| χ² p-values, {seeds} campaigns of 30 poses: KS p (uniform) | {ks:.3g} | '
        f'largest p {max(p_unstated):.3g} |',
        f'| share of p < 0.01 | {np.mean(np.array(p_stated) < 0.01):.0%} | '
        f'{np.mean(np.array(p_unstated) < 0.01):.0%} |',
        f'| diagnosis, {diag_seeds} campaigns of 40 poses: adequate | '
        f'{counts["stated"][0]}/{diag_seeds} | {counts["unstated"][0]}/{diag_seeds} |',
        f'| an effect suggested | {counts["stated"][1]}/{diag_seeds} | '
        f'{counts["unstated"][1]}/{diag_seeds} |',
        f'| joint noise that explains the residuals (verdict, left out) | | '
        f'{np.min(equivalent):.4f}–{np.max(equivalent):.4f}° |',
        f'| TCP sqrt(trace) / Monte Carlo (100 draws, 30 poses) | '
        f'{predicted[0] * 1e6:.1f} / {monte_carlo[0] * 1e6:.1f} µm = '
        f'{predicted[0] / monte_carlo[0]:.3f} | |',
    ]
    text = '\n'.join(lines) + '\n'
    print(text)
    (Path(__file__).resolve().parent / 'results' / 'joint_noise.md').write_text(text)


if __name__ == '__main__':
    main()

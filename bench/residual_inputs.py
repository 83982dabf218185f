"""Which input explains the misfit: the residual analysis on simulated hidden effects.

A UR-class arm (``ur_cell.yaml``), random geometric errors, tracker noise σ = 20 µm,
``N_POSES`` random poses measured in random order over eight hours; the true robot carries
one deviation the effect library does not have, added to the simulated points:

- ``periodic_3``: elbow_joint angle error 0.2 mrad · sin(3 q + 0.4) (3 cycles per turn);
- ``periodic_20``: shoulder_lift_joint angle error 0.2 mrad · sin(20 q + 1) (20 per turn);
- ``periodic_40``: the same at 40 cycles per turn;
- ``bending``: a deflection 0.25 mm · τ_2/max|τ_2| along the direction shoulder_lift moves
  the point, of the same size at every reach (a link bending, not a joint compliance);
- ``map_2_3``: shoulder_lift_joint angle error 0.25 mrad · sin(2 q2) · cos(q3), a smooth
  map of two joints;
- ``thermal``: every link grows by α·ΔT(t), α = 23e-6/K, ΔT a 4 K warm-up over the eight
  hours plus a ±1 K air-conditioning cycle of 20 minutes, recorded as the covariate
  ``temperature`` (the points scaled about the robot base).

For each, over the seeds: how often the right input is ranked first and flagged (an input
of the right joint for the two-joint map; temperature for the thermal growth), the
held-out rms before/after the top input, how often the interaction of the top two
joint angles is flagged, and the held-out rms with all flagged inputs (and the
interaction when flagged). Clean data (no deviation): how often any input is
flagged (family-wise α = 0.01, Holm). Writes bench/results/residual_inputs.md.

    .venv/bin/python bench/residual_inputs.py [n_seeds] [n_clean]
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.diagnosis.residual_analysis import analyse_calibration
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell

SIGMA = 20e-6
N_POSES = 300
HOURS = 8.0
UR_CELL = DEFAULT_CELL.parent / 'ur_cell.yaml'
LIFT, ELBOW = 'shoulder_lift_joint', 'elbow_joint'


def temperature_k(t_s: np.ndarray) -> np.ndarray:
    """ΔT (K) of the links at ``t_s``: a 4 K warm-up and a ±1 K, 20-minute cycle."""
    return 4.0 * (1 - np.exp(-t_s / 7200.0)) + 1.0 * np.sin(2 * np.pi * t_s / 1200.0)


def campaign(cm, scenario: str, seed: int, n: int = N_POSES):
    """Measurements of a true robot with the hidden deviation ``scenario`` (or none:
    'clean'), its geometric calibration, and the temperature covariate."""
    rng = np.random.default_rng(seed)
    model = cm.model
    p_true = true_parameters(model.params, rng)
    q = random_configurations(model, model.params.nominal, n, rng)
    t = np.sort(rng.uniform(0, HOURS * 3600, n))
    lift, elbow = (cm.robot.joint_names.index(x) for x in (LIFT, ELBOW))
    dq = np.zeros_like(q)
    if scenario == 'periodic_3':
        dq[:, elbow] = 2e-4 * np.sin(3 * q[:, elbow] + 0.4)
    elif scenario in ('periodic_20', 'periodic_40'):
        dq[:, lift] = 2e-4 * np.sin(int(scenario[-2:]) * q[:, lift] + 1.0)
    elif scenario == 'map_2_3':
        dq[:, lift] = 2.5e-4 * np.sin(2 * q[:, lift]) * np.cos(q[:, elbow])
    points = model.predict(p_true, q + dq)
    if scenario == 'bending':
        tau = cm.robot.gravity_torques(q)[:, lift]
        lever = model.joint_jacobian(p_true, q)[:, :, lift]
        unit = lever / np.linalg.norm(lever, axis=1, keepdims=True)
        points = points + 2.5e-4 * (tau / np.max(np.abs(tau)))[:, None] * unit
    temperature = 22.9 + temperature_k(t)
    if scenario == 'thermal':
        base = np.array([p_true[model.params.index(f'base.{a}')] for a in 'xyz'])
        points = base + (points - base) * (1 + 23e-6 * temperature_k(t))[:, None]
    eta = points + rng.normal(size=points.shape) * SIGMA
    data = Measurements(q=q, eta=eta, stamps_ns=(t * 1e9).astype(np.int64))
    result = identify(model, data, SIGMA, cm.q_work, max_iterations=25)
    return data, result, {'temperature': (temperature, '°C')}


RIGHT = {'periodic_3': {ELBOW}, 'periodic_20': {LIFT}, 'periodic_40': {LIFT},
         'bending': {f'gravity torque {LIFT}'}, 'map_2_3': {LIFT, ELBOW},
         'thermal': {'temperature'}}


def main(argv: list[str]) -> int:
    n_seeds = int(argv[0]) if argv else 10
    n_clean = int(argv[1]) if len(argv) > 1 else 100
    cm = build_cell_model(load_cell(UR_CELL))
    lines = ['# Residual analysis: the input that explains a hidden deviation', '',
             f'UR-class cell, σ = {SIGMA * 1e6:.0f} µm, {N_POSES} random poses over '
             f'{HOURS:g} h, geometric calibration, inputs ranked by '
             '`core.diagnosis.residual_analysis` (10 pose folds, Holm over the inputs, α = 0.01). '
             'Command: `.venv/bin/python bench/residual_inputs.py '
             f'{n_seeds} {n_clean}`.', '',
             '| hidden deviation | right input first and flagged | top inputs (seed 0) | '
             'share of the top input (median) | held-out rms before -> after (median, µm) '
             '| interaction of two inputs flagged | held-out rms, all flagged (median, µm) '
             '| s per analysis |', '|---|---|---|---|---|---|---|---|']
    for scenario, right in RIGHT.items():
        hits, shares, before, after, secs, tops = 0, [], [], [], [], ''
        pairs, combined = 0, []
        for seed in range(n_seeds):
            data, result, cov = campaign(cm, scenario, 1000 + seed)
            start = time.perf_counter()
            an = analyse_calibration(cm.model, data, result, cov)
            secs.append(time.perf_counter() - start)
            top = an.scores[0]
            hits += top.significant and top.name in right
            shares.append(top.share)
            before.append(top.held_out_rms_before_m * 1e6)
            after.append(top.held_out_rms_after_m * 1e6)
            pairs += bool(an.pair and an.pair.significant)
            combined.append(an.combined_after_m * 1e6)
            if seed == 0:
                tops = '; '.join(f'{s.name} ({s.share:.2f}, p {s.p_value:.1g})'
                                 for s in an.scores[:3])
            print(f'{scenario} seed {seed}: top {top.name} share {top.share:.2f} '
                  f'p {top.p_value:.2g} sig {top.significant}', flush=True)
        lines.append(f'| {scenario} | {hits}/{n_seeds} | {tops} | {np.median(shares):.2f} | '
                     f'{np.median(before):.1f} -> {np.median(after):.1f} | '
                     f'{pairs}/{n_seeds} | {np.median(combined):.1f} | '
                     f'{np.median(secs):.2f} |')
    flagged, secs = 0, []
    p_min = []
    for seed in range(n_clean):
        data, result, cov = campaign(cm, 'clean', 5000 + seed)
        start = time.perf_counter()
        an = analyse_calibration(cm.model, data, result, cov)
        secs.append(time.perf_counter() - start)
        flagged += bool(an.significant)
        p_min.append(min(s.p_value for s in an.scores))
        if an.significant:
            print(f'clean seed {seed}: flagged {[s.name for s in an.significant]}', flush=True)
    lines += ['', f'Clean data (no deviation), {n_clean} seeds: any input flagged in '
              f'**{flagged}/{n_clean}** (family-wise α = 0.01; expected at most '
              f'{0.01 * n_clean:.0f}); median smallest Holm p {np.median(p_min):.2g}; '
              f'{np.median(secs):.2f} s per analysis (median).']
    text = '\n'.join(lines) + '\n'
    out = Path(__file__).resolve().parent / 'results' / 'residual_inputs.md'
    out.write_text(text)
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

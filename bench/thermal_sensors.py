"""A sensor per link against the mean of the sensors: links that warm differently.

Simulated KR15-class default cell, tracker σ = 20 µm per axis, 60 random poses over an 8 h
shift and 40 fresh poses at fresh times of it. The upper arm (joint_3's origin, 0.68 m,
aluminium α = 23e-6 /K) warms by 10 K (``shift_temperature``, 95 % after 4 h); the forearm
(joint_4's origin, 0.67 m, steel α = 12e-6 /K) swings ±3 K over the shift and warms by 2 K in
its first hour; each link grows with its own sensor. Both cells hold
``thermal_link_growth:joint_3`` and ``thermal_link_growth:joint_4``; one maps the sensors to
their joints (``temperature.sensors: {upper_arm: [joint_3], forearm: [joint_4, joint_5]}``),
the other lists them (their mean for every joint). Per seed: ``identify_cell``
with each; the α's against the truth in units of their reported σ, the χ² test, and the
fresh poses' rms (predicted with their temperatures); and ``calibrate_cell(model='auto')`` on
each cell without effects: what it adds, its χ² test and fresh rms.
``test/test_thermal_sensors.py`` asserts seeds 0 and 3 of the same scenario (and ``auto`` on
seed 0). Slow (~5 min). Writes bench/results/thermal_sensors.md.

    .venv/bin/python bench/thermal_sensors.py [n_seeds]
"""
from __future__ import annotations

import copy
import sys
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell, identify_cell
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA
from kpi_calib_ros.core.simulation import simulate_two_sensor_shift, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document

SIGMA = 20e-6
EFFECTS = ['thermal_link_growth:joint_3', 'thermal_link_growth:joint_4']
TRUTH = {'thermal_link_growth.joint_3.alpha': 23e-6, 'thermal_link_growth.joint_4.alpha': 12e-6}
BY_LINK = {'upper_arm': ['joint_3'], 'forearm': ['joint_4', 'joint_5']}


def cell_model(sensors, effects=tuple(EFFECTS)):
    doc = read_cell_document(DEFAULT_CELL)
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['temperature'] = {'sensors': copy.deepcopy(sensors)}
    doc['effects'] = list(effects)
    return build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))


def shift(truth_cm, seed, n=60, n_fresh=40):
    rng = np.random.default_rng(seed)
    p_true = np.concatenate([true_parameters(truth_cm.geometric, rng), list(TRUTH.values())])
    return (simulate_two_sensor_shift(truth_cm.model, p_true, n, SIGMA, rng),
            simulate_two_sensor_shift(truth_cm.model, p_true, n_fresh, SIGMA, rng))


def fresh_rms(cm, result, fresh):
    miss = fresh.eta - cm.model.predict(result.values, fresh.q, covariates=fresh.covariates)
    return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))


def main(n_seeds: int = 10) -> str:
    sensors = {'per sensor': BY_LINK, 'mean': ['upper_arm', 'forearm']}
    cells = {name: cell_model(v) for name, v in sensors.items()}
    plain = {name: cell_model(v, ()) for name, v in sensors.items()}
    floor = np.sqrt(3) * SIGMA
    rows = {name: {'z': [], 'p': [], 'fresh': [], 's': [], 'both': 0, 'auto_ok': 0,
                   'auto_fresh': []} for name in cells}
    details = []
    for seed in range(n_seeds):
        data, fresh = shift(cells['per sensor'], seed)
        line = [f'- seed {seed}:']
        for name, cm in cells.items():
            t0 = time.perf_counter()
            result = identify_cell(cm, data)
            rows[name]['s'].append(time.perf_counter() - t0)
            z = [abs(result.value(k) - v) / result.std_of(k) for k, v in TRUTH.items()]
            rows[name]['z'].append(max(z))
            rows[name]['p'].append(result.p_value)
            rows[name]['fresh'].append(fresh_rms(cm, result, fresh))
            line.append(f'{name}: α3 {result.value(EFFECTS[0].replace(":", ".") + ".alpha"):.3g},'
                        f' α4 {result.value(EFFECTS[1].replace(":", ".") + ".alpha"):.3g} '
                        f'(largest {max(z):.1f}σ), χ²/dof {result.chi2:.1f}/{result.dof} '
                        f'(p {result.p_value:.2g}), fresh {rows[name]["fresh"][-1] * 1e6:.1f} µm')
            auto = calibrate_cell(plain[name], data, model='auto')
            rows[name]['both'] += set(auto.choice.effects) == set(EFFECTS)
            rows[name]['auto_ok'] += auto.result.p_value > ADEQUACY_ALPHA
            auto_cm = auto.cell or plain[name]
            rows[name]['auto_fresh'].append(fresh_rms(auto_cm, auto.result, fresh))
            line.append(f'(auto adds {", ".join(auto.choice.effects) or "none"}: p '
                        f'{auto.result.p_value:.2g}, fresh '
                        f'{rows[name]["auto_fresh"][-1] * 1e6:.1f} µm);')
        details.append(' '.join(line))
        print(details[-1], flush=True)
    ratio = np.array(rows['mean']['fresh']) / np.array(rows['per sensor']['fresh'])
    lines = ['# A sensor per link against the mean of the sensors', '',
             __doc__.split('\n\n')[1].replace('\n', ' '), '',
             f'{n_seeds} seeds (0..{n_seeds - 1}); noise floor √3 σ = {floor * 1e6:.1f} µm.', '',
             '| ΔT each link reads | both α within 3σ | largest error / σ | χ² p (min, max) | '
             'fresh rms / floor (median, max) | s per fit | auto adds both growths | '
             f'auto χ² passed (p > {ADEQUACY_ALPHA:g}) | auto fresh rms / floor (median) |',
             '|---|---|---|---|---|---|---|---|---|']
    for name, r in rows.items():
        z, p, f = np.array(r['z']), np.array(r['p']), np.array(r['fresh']) / floor
        lines.append(f'| {name} | {int(np.sum(z < 3))}/{n_seeds} | {z.max():.2f} | '
                     f'{p.min():.2g}, {p.max():.2g} | {np.median(f):.2f}, {f.max():.2f} | '
                     f'{np.median(r["s"]):.1f} | {r["both"]}/{n_seeds} | '
                     f'{r["auto_ok"]}/{n_seeds} | '
                     f'{np.median(np.array(r["auto_fresh"]) / floor):.2f} |')
    lines += ['', f'Fresh rms of the mean over the per-sensor one: {ratio.min():.2f}–'
              f'{ratio.max():.2f} (median {np.median(ratio):.2f}). The α of the mean fit are '
              'reported with σ scaled by χ²/dof (the model rejected), which is why they can '
              'still fall within 3σ.', '', 'Per seed:', ''] + details
    text = '\n'.join(lines) + '\n'
    out = Path(__file__).parent / 'results' / 'thermal_sensors.md'
    out.write_text(text)
    print(text)
    return text


if __name__ == '__main__':
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 10)

"""Joint compliance from two payloads: identified from the difference between the loads and
a third load predicted, against the same data read with the cell's one payload.

Simulated KR15-class default cell (payload 5 kg at 5 cm), tracker σ = 20 µm per axis; truth
``joint_compliance`` of joint_2 (c = -2e-6 rad/(N m)) and joint_3 (-3e-6). The same 40 random
poses measured unloaded (``payload.mass`` = 0 on their rows) and with 5 kg; 40 fresh poses
measured with 2.5 kg. Per seed: ``calibrate_cell`` of the geometric level with both
compliances (``with_effects``), the rows' torques each with its own payload; the fresh poses
predicted with their 2.5 kg give the held-out rms in units of the noise floor √3 σ. "One
payload": the same fit with the payload covariates dropped (every row with the cell's 5 kg,
as before per-row payloads), the fresh poses predicted with 5 kg. The working pose of the
cell with ``payload: {mass: 2.5}``: the calibration's TCP against the true one (Mahalanobis
distance d² with its stated covariance, χ²₃). Writes bench/results/payload_compliance.md.

    .venv/bin/python bench/payload_compliance.py [n_seeds]
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell, with_effects
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.effects.registry import parse_effect_spec
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document

SIGMA = 20e-6
COMPLIANCE = {'joint_2': -2e-6, 'joint_3': -3e-6}


def loaded_cell():
    doc = read_cell_document(DEFAULT_CELL)
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['working_poses'] = [{'name': 'half_load', 'payload': {'mass': 2.5},
                             'joints': {'joint_1': 0.0, 'joint_2': 0.45, 'joint_3': -0.35,
                                        'joint_4': 0.0, 'joint_5': 0.9, 'joint_6': 0.0}}]
    return build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))


def two_loads(cm, seed):
    rng = np.random.default_rng(seed)
    effects = tuple(parse_effect_spec(f'joint_compliance:{j}', cm.robot) for j in COMPLIANCE)
    truth = augmented_model(cm.model, effects)
    p_true = np.concatenate([true_parameters(cm.model.params, rng), list(COMPLIANCE.values())])

    def measure(q, mass):
        cov = {'payload.mass': np.full(len(q), mass)}
        clean = truth.predict(p_true, q, covariates=cov)
        return Measurements(q=q, eta=clean + rng.normal(0.0, SIGMA, clean.shape), covariates=cov)
    q = random_configurations(cm.model, cm.model.params.nominal, 40, rng)
    a, b = measure(q, 0.0), measure(q, 5.0)
    data = Measurements(q=np.vstack([a.q, b.q]), eta=np.vstack([a.eta, b.eta]),
                        covariates={'payload.mass': np.r_[a.covariates['payload.mass'],
                                                          b.covariates['payload.mass']]})
    fresh = measure(random_configurations(cm.model, cm.model.params.nominal, 40, rng), 2.5)
    tcp = truth.predict(p_true, cm.q_work, covariates={'payload.mass': np.array([2.5])})[0]
    truth_miss = fresh.eta - truth.predict(p_true, fresh.q, covariates=fresh.covariates)
    truth_rms = float(np.sqrt(np.mean(np.sum(truth_miss ** 2, axis=1))))
    return data, fresh, effects, tcp, truth_rms


def rms(cm, cal, fresh, covariates):
    miss = fresh.eta - cm.model.predict(cal.result.values, fresh.q, covariates=covariates)
    return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))


def main(n_seeds: int = 10) -> str:
    base = loaded_cell()
    floor = np.sqrt(3) * SIGMA
    within = 0
    per_row, one, true, d2, seconds, details = [], [], [], [], [], []
    for seed in range(4000, 4000 + n_seeds):
        data, fresh, effects, tcp, truth_rms = two_loads(base, seed)
        true.append(truth_rms / floor)
        cm = with_effects(base, effects)
        t0 = time.perf_counter()
        cal = calibrate_cell(cm, data, model='geometric')
        seconds.append(time.perf_counter() - t0)
        errs = {j: (cal.result.value(f'joint_compliance.{j}.c') - c)
                / cal.result.std_of(f'joint_compliance.{j}.c') for j, c in COMPLIANCE.items()}
        within += all(abs(e) < 3 for e in errs.values())
        per_row.append(rms(cm, cal, fresh, fresh.covariates) / floor)
        plain = calibrate_cell(cm, dataclasses.replace(data, covariates=None), model='geometric')
        one.append(rms(cm, plain, fresh, None) / floor)
        e = cal.result.tcp[0] - tcp
        d2.append(float(e @ np.linalg.solve(cal.result.tcp_covariance[0], e)))
        details.append(f'- seed {seed}: ' + ', '.join(
            f'{j} c = {cal.result.value(f"joint_compliance.{j}.c"):.3g} ± '
            f'{cal.result.std_of(f"joint_compliance.{j}.c"):.2g} ({v:+.1f}σ)'
            for j, v in errs.items()) + f'; fresh 2.5 kg {per_row[-1]:.2f} (one payload '
            f'{one[-1]:.2f}, the true robot {true[-1]:.2f}); TCP d² {d2[-1]:.2f}')
        print(details[-1], flush=True)
    lines = ['# Joint compliance from two payloads', '',
             __doc__.split('\n\n')[1].replace('\n', ' '), '',
             f'{n_seeds} seeds (4000..{3999 + n_seeds}); noise floor √3 σ = {floor * 1e6:.1f} µm. '
             f'Command: `.venv/bin/python bench/payload_compliance.py {n_seeds}`. "The true '
             'robot": the same fresh poses, their noise included, predicted by the true model: '
             'what the noise of 40 poses alone puts on the ratio.',
             '', '| compliances within 3σ | fresh 2.5 kg rms / floor, per-row payload (median, '
             'max) | fresh rms / floor, one payload (median, max) | fresh rms / floor, the true '
             'robot (median, max) | seeds above 1.2: per-row payload, the true robot | '
             'working-pose TCP d² (median, max; χ²₃ 99 % = 11.3) | s per seed |',
             '|---|---|---|---|---|---|---|',
             f'| {within}/{n_seeds} | {np.median(per_row):.2f}, {np.max(per_row):.2f} | '
             f'{np.median(one):.2f}, {np.max(one):.2f} | {np.median(true):.2f}, '
             f'{np.max(true):.2f} | {sum(v > 1.2 for v in per_row)}, '
             f'{sum(v > 1.2 for v in true)} | {np.median(d2):.2f}, {np.max(d2):.2f} '
             f'| {np.median(seconds):.0f} |', '', 'Per seed:', ''] + details
    text = '\n'.join(lines) + '\n'
    (Path(__file__).parent / 'results' / 'payload_compliance.md').write_text(text)
    print(text)
    return text


if __name__ == '__main__':
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 10)

"""Thermal effects under a shift's warm-up: how often ``auto`` proposes the hidden one, its
value against the truth, the error on fresh poses, and false alarms on clean seeds.

Simulated KR15-class default cell, tracker σ = 20 µm per axis, 60 random poses over an 8 h
shift whose arm warms by 8 K (``shift_temperature``: 95 % of the rise after 4 h), the
temperature recorded with every point (``delta_temperature``, reference 20 °C). Per seed:
``calibrate_cell(model='auto')``; 40 fresh poses at fresh times of the same shift predicted
by the calibration (with their temperatures) give the held-out rms, in units of the noise
rms √3 σ. Scenarios: a hidden link growth of joint 3's link (aluminium, α = 23e-6 /K), a
hidden joint-zero drift of joint 2 (d = 1e-5 rad/K), and clean (no hidden effect).
Slow (minutes): not part of ``make test``. Writes bench/results/thermal_effects.md.

    .venv/bin/python bench/thermal_effects.py [n_seeds]
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.measurement.covariates import DELTA_TEMPERATURE, shift_temperature
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.cell_settings import hidden_effects

SIGMA = 20e-6
S = 10**9
SCENARIOS = {
    'link growth joint_3, α = 23e-6 /K': {'thermal_link_growth:joint_3': {'alpha': 23e-6}},
    'zero drift joint_2, d = 1e-5 rad/K': {'thermal_zero_drift:joint_2': {'d': 1e-5}},
    'clean (no hidden effect)': {},
}


def shift(cm, hidden, seed, n=60, n_fresh=40, rise=8.0):
    rng = np.random.default_rng(seed)
    effects, overrides = hidden_effects(hidden, cm.robot)
    truth = augmented_model(cm.model, effects)
    p_true = np.concatenate([true_parameters(cm.model.params, rng),
                             [overrides[k] for e in effects for k in e.parameter_names]])

    def measure(count):
        q = random_configurations(cm.model, cm.model.params.nominal, count, rng)
        stamps = (np.sort(rng.uniform(0, 8, count)) * 3600 * S).astype(np.int64)
        celsius = shift_temperature(stamps, 20.0, rise, 4.0, start_ns=0)
        cov = {'temperature.arm': celsius, DELTA_TEMPERATURE: celsius - 20.0}
        return simulate_measurements(truth, p_true, q, SIGMA, rng, covariates=cov,
                                     stamps_ns=stamps)
    return measure(n), measure(n_fresh), overrides


def fresh_rms(cal, fresh):
    model = cal.cell.model
    miss = fresh.eta - model.predict(cal.result.values, fresh.q, covariates=fresh.covariates)
    return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))


def main(n_seeds: int = 10) -> str:
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    floor = np.sqrt(3) * SIGMA
    lines = ['# Thermal effects under a warm-up: proposal, recovery, fresh-pose error', '',
             __doc__.split('\n\n')[1].replace('\n', ' '), '',
             f'{n_seeds} seeds per scenario (seeds 0..{n_seeds - 1}); noise floor '
             f'√3 σ = {floor * 1e6:.1f} µm.', '',
             '| scenario | hidden proposed | any thermal proposed | value within 3σ | '
             'fresh rms / floor, auto (median, max) | fresh rms / floor, geometric (median) '
             '| s per seed |',
             '|---|---|---|---|---|---|---|']
    details = []
    for title, hidden in SCENARIOS.items():
        spec = next(iter(hidden), None)
        proposed = thermal = within = 0
        auto_ratio, plain_ratio, seconds = [], [], []
        for seed in range(n_seeds):
            data, fresh, truth = shift(cm, hidden, 1000 + seed)
            t0 = time.perf_counter()
            cal = calibrate_cell(cm, data, model='auto')
            seconds.append(time.perf_counter() - t0)
            plain = calibrate_cell(cm, data, model='geometric')
            added = cal.choice.effects
            thermal += any(e.startswith('thermal') for e in added)
            hit = spec is not None and spec in added
            proposed += hit
            if hit:
                name = next(iter(truth))
                err = abs(cal.result.value(name) - truth[name]) / cal.result.std_of(name)
                within += err < 3
                details.append(f'- {title}, seed {seed}: {name} = '
                               f'{cal.result.value(name):.3g} ± {cal.result.std_of(name):.2g} '
                               f'(true {truth[name]:.3g}, {err:.1f}σ)')
            elif added:
                details.append(f'- {title}, seed {seed}: added {", ".join(added)}')
            auto_ratio.append(fresh_rms(cal, fresh) / floor)
            plain_ratio.append(fresh_rms(plain, fresh) / floor)
            print(f'{title} seed {seed}: {added} fresh {auto_ratio[-1]:.2f} / plain '
                  f'{plain_ratio[-1]:.2f} ({seconds[-1]:.0f} s)', flush=True)
        lines.append(f'| {title} | {proposed if spec else "-"}/{n_seeds} | {thermal}/{n_seeds} | '
                     f'{f"{within}/{proposed}" if spec else "-"} | '
                     f'{np.median(auto_ratio):.2f}, {np.max(auto_ratio):.2f} | '
                     f'{np.median(plain_ratio):.2f} | {np.median(seconds):.0f} |')
    text = '\n'.join(lines + ['', 'Per seed (effects added, fitted values):', ''] + details) + '\n'
    out = Path(__file__).parent / 'results' / 'thermal_effects.md'
    out.write_text(text)
    print(text)
    return text


if __name__ == '__main__':
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 10)

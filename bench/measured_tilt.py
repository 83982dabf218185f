"""A measured tilt: a column that leans by a recorded angle, found, recovered and predicted;
false alarms where the tilt is recorded but the truth has none.

Simulated KR15-class default cell, tracker σ = 20 µm per axis, 60 random poses; at every
pose the frame of ``joint_1`` (the column on its footing) leans by an angle about the base's
x and y axes drawn uniformly in ±2 mrad, recorded by an inclinometer as the covariates
``tilt.column.x`` / ``tilt.column.y`` with a reading noise of 2 µrad. Truth
``measured_tilt:joint_1:column`` with gains (1.0, 0.8) (the sensor reads the x tilt fully,
80 % of the y tilt). Per seed: ``calibrate_cell(model='auto')``; 40 fresh poses with their
recorded tilts predicted by the calibration give the held-out rms, in units of the noise
floor √3 σ. Clean: the same tilts recorded, none in the truth; a false alarm is any effect
``auto`` adds. Slow (minutes): not part of ``make test``. Writes
bench/results/measured_tilt.md.

    .venv/bin/python bench/measured_tilt.py [n_seeds_tilt] [n_seeds_clean]
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.effects.registry import parse_effect_spec
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell

SIGMA = 20e-6
SPEC = 'measured_tilt:joint_1:column'
GAINS = (1.0, 0.8)
TILT_RAD = 2e-3
READING_RAD = 2e-6


def recording(cm, seed, tilted, n=60, n_fresh=40):
    """(data, fresh, truth {name: value}) of a campaign with recorded tilts."""
    rng = np.random.default_rng(seed)
    effect = parse_effect_spec(SPEC, cm.robot)
    truth = augmented_model(cm.model, (effect,))
    gains = GAINS if tilted else (0.0, 0.0)
    p_true = np.concatenate([true_parameters(cm.model.params, rng), gains])

    def measure(count):
        q = random_configurations(cm.model, cm.model.params.nominal, count, rng)
        lean = rng.uniform(-TILT_RAD, TILT_RAD, (count, 2))
        actual = {'tilt.column.x': lean[:, 0], 'tilt.column.y': lean[:, 1]}
        data = simulate_measurements(truth, p_true, q, SIGMA, rng, covariates=actual)
        recorded = {k: v + rng.normal(0.0, READING_RAD, count) for k, v in actual.items()}
        return dataclasses.replace(data, covariates=recorded)
    return measure(n), measure(n_fresh), dict(zip(effect.parameter_names, gains))


def fresh_rms(cal, fresh):
    miss = fresh.eta - cal.cell.model.predict(cal.result.values, fresh.q,
                                              covariates=fresh.covariates)
    return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))


def main(n_tilt: int = 10, n_clean: int = 100) -> str:
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    floor = np.sqrt(3) * SIGMA
    lines = ['# A measured tilt: proposal, recovery, fresh-pose error, false alarms', '',
             __doc__.split('\n\n')[1].replace('\n', ' '), '',
             f'Noise floor √3 σ = {floor * 1e6:.1f} µm. Command: `.venv/bin/python '
             f'bench/measured_tilt.py {n_tilt} {n_clean}` (seeds 2000.. tilted, 3000.. clean).',
             '',
             '| scenario | seeds | tilt proposed | any effect added | gains within 3σ | '
             'fresh rms / floor, auto (median, max) | seeds above 1.2 × floor, auto | '
             'fresh rms / floor, geometric (median) | s per seed |',
             '|---|---|---|---|---|---|---|---|---|']
    details = []
    for title, tilted, n_seeds, first in (('tilted column', True, n_tilt, 2000),
                                          ('clean, tilts recorded', False, n_clean, 3000)):
        proposed = added_any = within = 0
        auto_ratio, plain_ratio, seconds = [], [], []
        for seed in range(first, first + n_seeds):
            data, fresh, truth = recording(cm, seed, tilted)
            t0 = time.perf_counter()
            cal = calibrate_cell(cm, data, model='auto')
            seconds.append(time.perf_counter() - t0)
            added = cal.choice.effects
            added_any += bool(added)
            hit = SPEC in added
            proposed += hit
            if tilted and hit:
                errs = [abs(cal.result.value(k) - v) / cal.result.std_of(k)
                        for k, v in truth.items()]
                within += all(e < 3 for e in errs)
                details.append(f'- {title}, seed {seed}: ' + ', '.join(
                    f'{k} = {cal.result.value(k):.4f} ± {cal.result.std_of(k):.2g} '
                    f'(true {v:g}, {e:.1f}σ)' for (k, v), e in zip(truth.items(), errs)))
            elif added:
                details.append(f'- {title}, seed {seed}: added {", ".join(added)}')
            auto_ratio.append(fresh_rms(cal, fresh) / floor)
            if tilted:
                plain = calibrate_cell(cm, data, model='geometric')
                plain_ratio.append(fresh_rms(plain, fresh) / floor)
            print(f'{title} seed {seed}: {added} fresh {auto_ratio[-1]:.2f} '
                  f'({seconds[-1]:.0f} s)', flush=True)
        lines.append(f'| {title} | {n_seeds} | {proposed}/{n_seeds} | {added_any}/{n_seeds} | '
                     f'{f"{within}/{proposed}" if tilted else "-"} | '
                     f'{np.median(auto_ratio):.2f}, {np.max(auto_ratio):.2f} | '
                     f'{int(np.sum(np.array(auto_ratio) > 1.2))}/{n_seeds} | '
                     f'{f"{np.median(plain_ratio):.2f}" if plain_ratio else "-"} | '
                     f'{np.median(seconds):.0f} |')
    text = '\n'.join(lines + ['', 'Per seed (effects added, fitted values):', ''] + details) + '\n'
    out = Path(__file__).parent / 'results' / 'measured_tilt.md'
    out.write_text(text)
    print(text)
    return text


if __name__ == '__main__':
    main(*(int(a) for a in sys.argv[1:3]))

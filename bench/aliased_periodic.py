"""An aliased periodic error: poses too few for its frequency. Does ``auto`` add a second one?

Simulated KR15-class cell of bench/general_effects.py (σ = 20 µm, random geometric
errors), a periodic error of joint_2 at k = 40 cycles per revolution, 0.25 mrad, random
phase, measured on ``N_POSES`` random poses: over joint_2's sampled range (about 3.3 rad,
21 periods) that is under two poses per period, so the error is seen at an alias. Two
designs: ``full`` (joint_2 over its whole sampled range) and ``narrow`` (joint_2 within
0.6 rad, resolution 2π/Δq ≈ 10 cycles per revolution). Per seed, ``calibrate_cell(model=
'auto')``: the periodic effects it adds on joint_2, whether a second one is within the
resolution 2π/Δq of the first (one aliased peak counted twice: the rule refuses it), any
second frequency on joint_2 at all, and the rms on ``N_FRESH`` fresh poses over the full
range (with noise) over the noise floor σ√3, against the geometric level's
(``calibrate_cell(model='geometric')``: the same prior and outlier exclusion).
Writes bench/results/aliased_periodic.md.

    .venv/bin/python bench/aliased_periodic.py [n_seeds]
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from general_effects import AMPLITUDE, FLOOR, SIGMA, cell

from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.effects.general import frequency_resolution
from kpi_calib_ros.core.simulation import (
    random_configurations,
    sampling_bounds,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell_settings import hidden_effects

N_POSES = 40
N_FRESH = 200
K = 40
JOINT = 'joint_2'
NARROW = 0.6  # rad


def run(cm, design: str, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi)
    spec = f'periodic_joint_error:{JOINT}:k={K}'
    effects, overrides = hidden_effects(
        {spec: {'a': AMPLITUDE * np.cos(phase), 'b': AMPLITUDE * np.sin(phase)}}, cm.robot)
    truth = augmented_model(cm.model, effects)
    p_true = true_parameters(truth.params, rng, overrides=overrides)
    j = cm.robot.joint_names.index(JOINT)
    lower, upper = sampling_bounds(cm.model)
    mid = 0.5 * (lower[j] + upper[j])
    accept = None if design == 'full' else (lambda c: np.abs(c[:, j] - mid) < NARROW / 2)
    q = random_configurations(cm.model, cm.model.params.nominal, N_POSES, rng, accept=accept)
    q_fresh = random_configurations(cm.model, cm.model.params.nominal, N_FRESH, rng)
    data = simulate_measurements(truth, p_true, q, SIGMA, rng)
    fresh = simulate_measurements(truth, p_true, q_fresh, SIGMA, rng)

    def fresh_rms(model, values) -> float:
        miss = fresh.eta - model.predict(values, q_fresh)
        return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1)))) / FLOOR
    # The geometric level as auto fits it (the cell's prior, outlier exclusion): what the
    # effects auto adds are judged against.
    geo = calibrate_cell(cm, data, 'geometric').result
    t0 = time.perf_counter()
    auto = calibrate_cell(cm, data, 'auto')
    seconds = time.perf_counter() - t0
    on_joint = [e for e in auto.choice.effects if e.startswith('periodic_joint_error:')
                and e.split(':')[1] == JOINT]
    ks = [int(e.split('k=')[1]) for e in on_joint]
    resolution = frequency_resolution(q[:, j])
    within = any(abs(a - b) < resolution for i, a in enumerate(ks) for b in ks[i + 1:])
    model = (auto.cell or cm).model
    return {'design': design, 'seed': seed, 'resolution': resolution, 'added': tuple(ks),
            'effects': tuple(auto.choice.effects), 'level': auto.choice.level,
            'second': len(ks) > 1, 'within': within, 'valid': auto.valid,
            'geometric': fresh_rms(cm.model, geo.values),
            'auto': fresh_rms(model, auto.result.values), 's': seconds}


def write(path: Path, rows: list[dict], seeds: int, seconds: float) -> None:
    text = ['# An aliased periodic error: poses too few for its frequency', '',
            f'KR15-class cell, σ = {SIGMA * 1e6:.0f} µm, periodic error of {JOINT} at k = '
            f'{K}, {AMPLITUDE * 1e3:.2f} mrad, {N_POSES} random poses (under two per period); '
            f'`full`: {JOINT} over its sampled range, `narrow`: within {NARROW} rad. '
            f'`calibrate_cell(model=\'auto\')` per seed; fresh rms over {N_FRESH} poses over '
            'the full range / the noise floor σ√3. Command: '
            f'`.venv/bin/python bench/aliased_periodic.py {seeds}` ({seconds:.0f} s).', '',
            '| design | seeds | a second frequency on the joint | within the resolution '
            '| the true k among those added | fresh rms / floor, geometric level (median) | auto '
            '(median) | auto worse than geometric (> 0.5 %) |',
            '|---|---|---|---|---|---|---|---|']
    for design in ('full', 'narrow'):
        got = [r for r in rows if r['design'] == design]
        if not got:
            continue
        text.append(
            f"| {design} | {len(got)} | {sum(r['second'] for r in got)}/{len(got)} | "
            f"{sum(r['within'] for r in got)}/{len(got)} | "
            f"{sum(K in r['added'] for r in got)}/{len(got)} | "
            f"{np.median([r['geometric'] for r in got]):.2f} | "
            f"{np.median([r['auto'] for r in got]):.2f} | "
            f"{sum(r['auto'] > 1.005 * r['geometric'] for r in got)}/{len(got)} |")
    text += ['', '## Per seed', '']
    text += [f"- {r['design']} {r['seed']}: resolution {r['resolution']:.3g} cycles/rev, "
             f"auto {r['level']} {list(r['effects'])}, valid {r['valid']}, fresh "
             f"{r['geometric']:.2f} -> {r['auto']:.2f} ({r['s']:.0f} s)" for r in rows]
    path.write_text('\n'.join(text) + '\n')


def main(argv: list[str]) -> int:
    seeds = int(argv[0]) if argv else 10
    cm = cell()
    rows: list[dict] = []
    out = Path(__file__).resolve().parent / 'results' / 'aliased_periodic.md'
    t0 = time.perf_counter()
    for i in range(seeds):
        for design in ('full', 'narrow'):
            r = run(cm, design, 4000 + i)
            rows.append(r)
            print(f"{design} {r['seed']}: added k {list(r['added'])} of {list(r['effects'])}, "
                  f"fresh {r['geometric']:.2f} -> {r['auto']:.2f}", flush=True)
            write(out, rows, seeds, time.perf_counter() - t0)
    print(out.read_text())
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

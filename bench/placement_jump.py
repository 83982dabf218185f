"""A recording whose placement changed while measured: how often is a move found, how often
is one named where there was none?

Simulated KR15-class cell (σ = 20 µm, random geometric errors), one recording of
``N_POSES`` random poses 30 s apart, identified with the geometric model; the check of
:mod:`kpi_calib_ros.core.diagnosis.placement_jump` (through
:func:`kpi_calib_ros.app.calibration_document.recording_jumps`, as identify runs it). Cases:

- ``clean``: nothing moved;
- ``move <size>``: the tracker frame moved half way (after pose 25) by ``size`` in a random
  direction and ``size`` / 1 m in rotation about a random axis (a knock on the tripod);
- ``order``: nothing moved, a hidden joint 2 compliance of 4e-7 rad/(N m) the geometric model
  lacks, the poses measured in order of joint 2 (a misfit that follows time);
- ``drift``: nothing knocked, the tracker drifting linearly over the recording by 0.5 mm (a
  thermal drift: not a move at one time).

Per case the share named, how many of those as a steady drift rather than a step, and for
the moves the time found (exact: the split between poses
25 and 26) and the size found over the true size at the points' centroid. Writes
bench/results/placement_jump.md.

    .venv/bin/python bench/placement_jump.py [n_seeds]
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from general_effects import SIGMA, cell

from kpi_calib_ros.app.calibration_document import recording_jumps
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.effects.registry import parse_effect_spec
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)

N_POSES = 50
STEP_NS = 30 * 10 ** 9
SIZES = (5e-5, 1e-4, 2e-4, 5e-4)  # m (and that / 1 m in rad)
HALF = N_POSES // 2


def run(cm, case: str, seed: int, size: float = 0.0) -> dict:
    rng = np.random.default_rng(seed)
    model = cm.model
    stamps = 1_700_000_000 * 10 ** 9 + STEP_NS * np.arange(N_POSES)
    if case == 'order':
        effect = parse_effect_spec('joint_compliance:joint_2', cm.robot)
        truth = augmented_model(model, (effect,))
        p = np.concatenate([true_parameters(model.params, rng), [4e-7]])
        q = random_configurations(model, model.params.nominal, N_POSES, rng)
        q = q[np.argsort(q[:, 1])]
        data = simulate_measurements(truth, p, q, SIGMA, rng, stamps_ns=stamps)
        true_move = 0.0
    else:
        p = true_parameters(model.params, rng)
        q = random_configurations(model, model.params.nominal, N_POSES, rng)
        data = simulate_measurements(model, p, q, SIGMA, rng, stamps_ns=stamps)
        eta = np.array(data.eta)
        true_move = 0.0
        if case in ('move', 'drift'):
            direction = rng.normal(size=3)
            axis = rng.normal(size=3)
            move = np.r_[size * direction / np.linalg.norm(direction),
                         size / 1.0 * axis / np.linalg.norm(axis)]
            for i in range(N_POSES):
                share = (float(i >= HALF) if case == 'move' else i / (N_POSES - 1))
                moved = p.copy()
                moved[:6] += share * move
                eta[i] += (model.predict(moved, q[i:i + 1]) - model.predict(p, q[i:i + 1]))[0]
            if case == 'move':
                later = model.predict(p, q[HALF:])
                moved = p.copy()
                moved[:6] += move
                true_move = float(np.linalg.norm(
                    (model.predict(moved, q[HALF:]) - later).mean(axis=0)))
        data = Measurements(q=data.q, eta=eta, stamps_ns=data.stamps_ns)
    cal = calibrate_cell(cm, data, 'geometric')
    jumps = recording_jumps(cm, data, cal, ['run'])
    found = jumps[0] if jumps else None
    return {'case': case, 'size': size, 'seed': seed, 'named': found is not None,
            'as_drift': found is not None and found.drift,
            'at_right_time': found is not None and found.before == HALF,
            'ratio': (found.translation_m / true_move if found is not None and true_move > 0
                      else float('nan')),
            'chi2_dof': cal.result.chi2 / cal.result.dof}


def write(path: Path, rows: list[dict], seeds: int, seconds: float) -> None:
    text = ['# A recording whose placement changed while measured', '',
            f'KR15-class cell, σ = {SIGMA * 1e6:.0f} µm, one recording of {N_POSES} random '
            f'poses 30 s apart, geometric model; a move after pose {HALF} of the given size '
            '(m, and that over 1 m in rad, random directions); `order`: a hidden joint 2 '
            'compliance (4e-7 rad/(N m)), the poses in order of joint 2; `drift`: the tracker '
            'drifting linearly by 0.5 mm over the recording. Command: '
            f'`.venv/bin/python bench/placement_jump.py {seeds}` ({seconds:.0f} s).', '',
            '| case | seeds | named | as a drift | at the true time | size found / true '
            '(median) | χ²/dof of the fit (median) |', '|---|---|---|---|---|---|---|']
    keys = sorted({(r['case'], r['size']) for r in rows}, key=lambda k: (k[0] != 'clean', k))
    for case, size in keys:
        got = [r for r in rows if r['case'] == case and r['size'] == size]
        label = f'{case} {size * 1e3:g} mm' if case == 'move' else case
        named = [r for r in got if r['named']]
        ratio = [r['ratio'] for r in named if np.isfinite(r['ratio'])]
        text.append(f"| {label} | {len(got)} | {len(named)}/{len(got)} | "
                    + f"{sum(r['as_drift'] for r in named)}/{len(named)} | "
                    + (f"{sum(r['at_right_time'] for r in named)}/{len(named)} | "
                       if case == 'move' else '– | ')
                    + (f'{np.median(ratio):.2f} | ' if ratio else '– | ')
                    + f"{np.median([r['chi2_dof'] for r in got]):.2f} |")
    path.write_text('\n'.join(text) + '\n')


def main(argv: list[str]) -> int:
    seeds = int(argv[0]) if argv else 20
    cm = cell()
    out = Path(__file__).resolve().parent / 'results' / 'placement_jump.md'
    rows: list[dict] = []
    t0 = time.perf_counter()
    plan = ([('clean', 0.0, 5 * seeds)] + [('move', s, seeds) for s in SIZES]
            + [('order', 0.0, seeds), ('drift', 5e-4, seeds)])
    for case, size, n in plan:
        for i in range(n):
            rows.append(run(cm, case, 7000 + i, size))
        got = [r for r in rows if r['case'] == case and r['size'] == size]
        print(f"{case} {size}: named {sum(r['named'] for r in got)}/{len(got)}", flush=True)
        write(out, rows, seeds, time.perf_counter() - t0)
    print(out.read_text())
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

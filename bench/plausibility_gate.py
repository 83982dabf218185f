"""The plausibility gate on simulated campaigns of the built-in cell: false alarms and refusals.

1. False alarms: clean data (random geometric errors, σ = 20 µm, 60 random measurable poses,
   the correct geometric model), 20 seeds, identified as `kpi-calib identify` does
   (`app.identify.calibrate_cell`); counted: calibrations the gate calls not plausible. Once
   with the cell as shipped, once with the base pose and the reflector offset left out
   (registered from the points, the reflector judged by whether the poses observe it).
2. A reflector offset the poses do not observe (the wrist, joints 4-6, never turns; base and
   offset left out, no working pose so the TCP check cannot catch it): refused or not, and
   the same cell with the wrist turning: valid, offset against the truth in the identified
   gauge (`core.simulation.equivalent_parameters`) in units of its std.
3. A servo-stiff wrist (joint_compliance:joint_5, c = −1e-3 rad/(N m), 1/kp of a position
   servo): default bound, then the bound widened by identification.bounds.
4. joint_play:joint_5 measured where its gravity torque never changes sign (> 4 N m).

Writes bench/results/plausibility_gate.md.

    .venv/bin/python bench/plausibility_gate.py [n_seeds]
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.core.estimation.plausibility import Tolerances
from kpi_calib_ros.core.simulation import (
    equivalent_parameters,
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell

SIGMA = 20e-6
N_POSES = 60


def false_alarms(seeds: int, left_out: bool) -> tuple[int, int, list[str]]:
    cell = load_cell(DEFAULT_CELL)
    if left_out:
        cell = dataclasses.replace(cell, base_in_tracker_given=False,
                                   reflector_offset_given=False)
    cm = build_cell_model(cell)
    flagged, invalid, reasons = 0, 0, []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        p_true = true_parameters(cm.model.params, rng)
        q = random_configurations(cm.model, p_true, N_POSES, rng)
        cal = calibrate_cell(cm, simulate_measurements(cm.model, p_true, q, SIGMA, rng))
        flagged += bool(cal.implausible)
        invalid += not cal.valid
        reasons += [f'{seed}: {r[:120]}' for r in cal.implausible]
    return flagged, invalid, reasons


def reflector_case() -> list[str]:
    cell = load_cell(DEFAULT_CELL)
    cm = build_cell_model(cell)
    rng = np.random.default_rng(3)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, p_true, N_POSES, rng)
    blind = dataclasses.replace(cell, base_in_tracker_given=False, reflector_offset_given=False,
                                working_poses=())
    cb = build_cell_model(blind)
    lines = []
    for label, poses in (('wrist never turns', np.where(np.arange(6) >= 3, q[0], q)),
                         ('wrist turns', q)):
        data = simulate_measurements(cm.model, p_true, poses, SIGMA, np.random.default_rng(1))
        cal = calibrate_cell(cb, data)
        r = cal.result
        names = [f'reflector.{c}' for c in 'xyz']
        std = dict(zip(r.estimated, r.std))
        equiv, _ = equivalent_parameters(cb.model, p_true, r.estimated, r.values, q)
        z = {n: (r.value(n) - equiv[cb.model.params.index(n)]) / std[n]
             for n in names if n in std}
        lines.append(f'| {label} | {cal.valid} | '
                     + (', '.join(f'{n} {v:+.2f} σ' for n, v in z.items()) or '–') + ' | '
                     + ('; '.join(p[:160] for p in cal.implausible) or '–') + ' |')
    return lines


def compliance_case() -> list[str]:
    cell = load_cell(DEFAULT_CELL)
    model = build_cell_model(cell).model
    q = random_configurations(model, model.params.nominal, N_POSES, np.random.default_rng(3))
    lines = []
    for bounds in ({}, {'joint_compliance:joint_5': (2e-3,)}):
        ident = dataclasses.replace(cell.identification, tolerances=Tolerances(bounds=bounds))
        cm = build_cell_model(dataclasses.replace(cell, effects=('joint_compliance:joint_5',),
                                                  identification=ident))
        name = 'joint_compliance.joint_5.c'
        p_true = true_parameters(cm.model.params, np.random.default_rng(4),
                                 overrides={name: -1e-3})
        cal = calibrate_cell(cm, simulate_measurements(cm.model, p_true, q, SIGMA,
                                                       np.random.default_rng(5)))
        r = cal.result
        std = dict(zip(r.estimated, r.std))[name]
        lines.append(f"| {bounds or 'default (2e-4)'} | {cal.valid} | {r.value(name):.4g} ± "
                     f'{std:.2g} ({(r.value(name) + 1e-3) / std:+.2f} σ) | '
                     + ('; '.join(p[:160] for p in cal.implausible) or '–') + ' |')
    return lines


def play_case() -> list[str]:
    cell = dataclasses.replace(load_cell(DEFAULT_CELL), effects=('joint_play:joint_5',))
    cm = build_cell_model(cell)
    q = random_configurations(cm.model, cm.model.params.nominal, 600, np.random.default_rng(3))
    tau = cm.robot.gravity_torques(q)
    lines = []
    for label, keep in (('torque of one sign (> 4 N m)', tau[:, 4] > 4.0),
                        ('torque of both signs', np.ones(len(q), bool))):
        p_true = true_parameters(cm.model.params, np.random.default_rng(4))
        poses = q[keep][:N_POSES]
        cal = calibrate_cell(cm, simulate_measurements(cm.model, p_true, poses, SIGMA,
                                                       np.random.default_rng(5)))
        lines.append(f'| {label} | {cal.valid} | '
                     + ('; '.join(p[:200] for p in cal.implausible) or '–') + ' |')
    return lines


def main(argv: list[str]) -> int:
    seeds = int(argv[0]) if argv else 20
    t0 = time.perf_counter()
    rows = []
    for left_out in (False, True):
        flagged, invalid, reasons = false_alarms(seeds, left_out)
        what = 'base and offset left out (registered)' if left_out else 'as shipped'
        print(f'clean data, cell {what}: gate flagged {flagged}/{seeds}, not valid '
              f'{invalid}/{seeds} {reasons}', flush=True)
        rows.append(f'| {what} | {flagged}/{seeds} | {invalid}/{seeds} |')
    reflector, compliance, play = reflector_case(), compliance_case(), play_case()
    for line in reflector + compliance + play:
        print(line, flush=True)
    lines = ['# Plausibility gate', '',
             f'Built-in cell, σ = 20 µm, {N_POSES} random measurable poses, identified as '
             '`kpi-calib identify` does. Command: `.venv/bin/python bench/plausibility_gate.py`',
             '', f'## False alarms: clean data, correct model, seeds 0..{seeds - 1}', '',
             '| cell | gate flagged | not valid (any reason) |', '|---|---|---|', *rows, '',
             '## Reflector offset left out of the cell, no working pose', '',
             '| poses | valid | reflector − truth (identified gauge) | gate |', '|---|---|---|---|',
             *reflector, '', '## Servo-stiff wrist: joint_compliance:joint_5, truth c = −1e-3',
             '', '| identification.bounds | valid | c identified | gate |', '|---|---|---|---|',
             *compliance, '', '## joint_play:joint_5 (truth: no play)', '',
             '| poses | valid | gate |', '|---|---|---|', *play, '',
             f'{time.perf_counter() - t0:.0f} s']
    out = Path(__file__).resolve().parent / 'results' / 'plausibility_gate.md'
    out.parent.mkdir(exist_ok=True)
    out.write_text('\n'.join(lines) + '\n')
    print(f'written {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

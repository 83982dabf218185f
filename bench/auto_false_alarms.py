"""False alarms of ``identification.model: auto``'s effect selection on clean simulated data.

Clean data: random geometric errors, tracker noise σ = 20 µm, 80 random poses, no hidden
effect (as bench/diagnosis_false_alarms.py). Each seed is calibrated as the CLI and the node
do (``calibrate_cell`` with ``model='auto'``: the level chosen, then
``choose_effects`` with the general effects: the effect library, link bending and each
joint's periodic error at its periodogram peak). Its stated level: a round's screen passes a
candidate with probability at most α = 0.01 (family-wise, Bonferroni over the candidates, the
frequency search counted), and an added effect must then predict held-out regions of joint
space better beyond the held-out noise (core.diagnosis.model_selection.held_out_gain: z above
the normal quantile at HELD_OUT_ALPHA = 0.01, Bonferroni over the round's trials) and be
worse beyond noise in no held-out fold (region blocks and each joint's range ends).
Counts the seeds where the screen passes a candidate and where an effect is added (which),
with an exact one-sided 95 % upper bound (Clopper-Pearson) and the binomial probability of
at least as many at α. Cells: the built-in cell (DEFAULT_CELL, KR15-class) and the stock UR10
of example-robot-data in the tracker cell of bench/general_effects_stock.py (poses at every
incidence). Writes bench/results/auto_false_alarms.md (about 1 s per seed and cell: 500 seeds
~18 min).

    .venv/bin/python bench/auto_false_alarms.py [n_seeds] [cell ...]
"""
from __future__ import annotations

import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import scipy.stats
import yaml

from kpi_calib_ros.app.cell_model import CellModel, build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict

from general_effects_stock import stock_cell

SIGMA = 20e-6
N_POSES = 80
FIRST_SEED = 1000
CELLS = ('default', 'ur10')


def cell(name: str) -> tuple[CellModel, float | None]:
    """The cell model and the largest incidence of its random poses (None: the cell's)."""
    if name == 'default':
        doc = yaml.safe_load(DEFAULT_CELL.read_text())
        return build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent)), None
    return stock_cell(name), np.pi


def upper_bound(k: int, n: int) -> float:
    """Exact one-sided 95 % upper bound on a rate seen k times in n (Clopper-Pearson)."""
    return 1.0 if k == n else float(scipy.stats.beta.ppf(0.95, k + 1, n - k))


def _gain(record: dict) -> str:
    """Round 1's best trial: rms over held-out regions, the level's → its, and its gain z."""
    trials = [t for t in record.get('trials', []) if t['round'] == 1
              and (t.get('cross_validated_before') or {}).get('other_region_rms_m') is not None
              and (t.get('cross_validated_after') or {}).get('other_region_rms_m') is not None]
    if not trials:
        return ''

    def z(t: dict) -> float:
        value = (t.get('held_out_gain') or {}).get('z')
        return -np.inf if value is None else value
    t = max(trials, key=z)
    before = t['cross_validated_before']['other_region_rms_m']
    after = t['cross_validated_after']['other_region_rms_m']
    gain = t.get('held_out_gain') or {}
    zs = ('' if gain.get('z') is None else
          f', z = {gain["z"]:.2f} (needed > {gain["z_needed"]:.2f}), worse in '
          f'{gain["folds_worse"]} of {gain["folds_compared"]} folds')
    return f'{before * 1e6:.1f} → {after * 1e6:.1f} µm ({1 - after / before:.1%}{zs})'


def study(name: str, seeds: int) -> dict:
    cm, incidence = cell(name)
    added, passed, levels, seconds = [], [], Counter(), []
    for seed in range(FIRST_SEED, FIRST_SEED + seeds):
        t0 = time.perf_counter()
        rng = np.random.default_rng(seed)
        p_true = true_parameters(cm.model.params, rng)
        kw = {} if incidence is None else {'max_incidence': incidence}
        q = random_configurations(cm.model, cm.model.params.nominal, N_POSES, rng, **kw)
        data = simulate_measurements(cm.model, p_true, q, SIGMA, rng)
        choice = calibrate_cell(cm, data, model='auto').choice
        seconds.append(time.perf_counter() - t0)
        levels[choice.level] += 1
        record = choice.effect_selection or {}
        # The candidates the first round's screen passed (significant and plausible) are
        # the ones refitted as trials in round 1.
        first = [t['spec'] for t in record.get('trials', []) if t['round'] == 1]
        if first:
            passed.append((seed, first, _gain(record)))
        if choice.effects:
            added.append((seed, list(choice.effects), _gain(record)))
            print(f'{name} seed {seed}: added {list(choice.effects)} ({choice.reason})',
                  flush=True)
        elif first:
            print(f'{name} seed {seed}: screen passed {first}, nothing added '
                  f'({record.get("reason", "")})', flush=True)
    out = {'cell': name, 'seeds': seeds, 'added': added, 'passed': passed,
           'levels': dict(levels), 'median_s': float(np.median(seconds)),
           'total_s': float(np.sum(seconds))}
    for key in ('added', 'passed'):
        k = len(out[key])
        out[f'{key}_upper'] = upper_bound(k, seeds)
        out[f'{key}_p'] = float(scipy.stats.binom.sf(k - 1, seeds, ADEQUACY_ALPHA))
    print(f"{name}: effect added in {len(added)}/{seeds} clean seeds (95 % upper bound "
          f"{100 * out['added_upper']:.1f} %), screen passed a candidate in "
          f"{len(passed)}/{seeds} ({100 * out['passed_upper']:.1f} %); levels "
          f"{out['levels']}; {out['median_s']:.1f} s per seed (median)", flush=True)
    return out


def families(rows: list[dict], key: str) -> str:
    """How often each candidate family (the spec before its first ':') appears."""
    count = Counter(spec.split(':', 1)[0] for r in rows for _, specs, _ in r[key]
                    for spec in specs)
    return ', '.join(f'{f} {n}' for f, n in count.most_common()) or '–'


def main(argv: list[str]) -> int:
    seeds = int(argv[0]) if argv else 100
    names = argv[1:] or list(CELLS)
    load = os.getloadavg()[0]
    rows = [study(name, seeds) for name in names]
    load = max(load, os.getloadavg()[0])
    alpha = ADEQUACY_ALPHA
    lines = ['# False alarms of `auto`\'s effect selection on clean data', '',
             f'{N_POSES} random poses, σ = 20 µm, random geometric errors, no hidden effect, '
             f'seeds {FIRST_SEED}..{FIRST_SEED + seeds - 1}; `calibrate_cell(model=\'auto\')` '
             '(the level, then `choose_effects` with the general effects). Stated level: '
             f'a round\'s screen passes a candidate with probability ≤ α = {alpha} '
             '(family-wise), and an added effect must predict held-out regions of joint '
             'space better beyond the held-out noise (`held_out_gain`: z above the normal '
             'quantile at 0.01, Bonferroni over the round\'s trials) and '
             'be worse beyond noise in no held-out fold (region blocks and each joint\'s '
             'range ends). Upper bound: '
             'exact one-sided 95 % (Clopper-Pearson); P(≥ k | α): the binomial probability '
             f'of at least as many at α. `default`: {DEFAULT_CELL.name} (KR15-class); `ur10`: '
             'the stock UR10 of example-robot-data in the cell of '
             'bench/general_effects_stock.py, poses at every incidence. Command: '
             f'`.venv/bin/python bench/auto_false_alarms.py {seeds}` (load average up to '
             f'{load:.1f} on 2 cores, at its start and end). Round 1\'s cross-validated '
             'rms over held-out regions of joint space: the level\'s → its best trial\'s '
             '(improvement; its gain z and the z needed).', '',
             '| cell | effect added | 95 % upper | P(≥ k \\| α) | screen passed | 95 % upper '
             '| P(≥ k \\| α) | level chosen | s per seed (median) | s total |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(
            f"| {r['cell']} | {len(r['added'])}/{r['seeds']} | {100 * r['added_upper']:.1f} % "
            f"| {r['added_p']:.3g} | {len(r['passed'])}/{r['seeds']} "
            f"| {100 * r['passed_upper']:.1f} % | {r['passed_p']:.3g} "
            f"| {', '.join(f'{k} {v}' for k, v in r['levels'].items())} "
            f"| {r['median_s']:.1f} | {r['total_s']:.0f} |")
    lines += ['', f"Families added: {families(rows, 'added')}; passed by the first round's "
              f"screen: {families(rows, 'passed')}.", '']
    for r in rows:
        for key, what in (('added', 'added'), ('passed', 'passed by the screen')):
            for seed, specs, gain in r[key]:
                lines.append(f"- {r['cell']} seed {seed}: {what} "
                             + ', '.join(f'`{s}`' for s in specs)
                             + (f'; cross-validated rms over held-out regions {gain}'
                                if gain else ''))
    out = Path(__file__).resolve().parent / 'results' / 'auto_false_alarms.md'
    out.parent.mkdir(exist_ok=True)
    out.write_text('\n'.join(lines) + '\n')
    print('\n'.join(lines))
    print(f'written {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

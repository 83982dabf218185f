"""False alarms and power of ``auto``'s model level on simulated data whose level is known.

``auto`` takes a larger level only when it lowers the misfit of the measured poses beyond
noise (core.diagnosis.model_selection, ``level_test``: the nested F-test of the two fits,
one-sided, α = 0.01, Bonferroni over the larger levels compared).
Robots: "offsets" -- random placements and joint offsets, the rest of the geometry nominal
(the true level is ``joint_offsets``: taking ``geometric`` is a false alarm); "0.5 %" -- the
same plus 0.5 % of the usual errors of the rest of the geometry (``geometric`` is the truth,
and its gain is small). Built-in cell (KR15-class), σ of the cell, random poses. Beside it,
the former rule on the same fits: the smallest level whose predicted out-of-sample rms is
within 5 % of the best. The error of fresh poses' points (without noise) of the level each
rule takes. Writes bench/results/level_false_alarms.md.

    .venv/bin/python bench/level_false_alarms.py [n_seeds] [n_poses ...]
"""
from __future__ import annotations

import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import scipy.stats
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import _fit_function
from kpi_calib_ros.core.diagnosis.model_selection import LEVELS, choose_model, level_free
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict

FIRST_SEED = 4000
ROBOTS = {'offsets': 0.0, '0.5 %': 0.005}
FRESH = 400


def robot(cm, rng: np.random.Generator, fraction: float) -> np.ndarray:
    """Placements and joint offsets drawn whole, ``fraction`` of the rest of the geometry."""
    nominal = np.array(cm.model.params.nominal, float)
    full = np.array(true_parameters(cm.model.params, rng), float)
    whole = np.array([n.startswith(('base.', 'reflector.')) or n.endswith('.offset')
                      for n in cm.model.params.names])
    return np.where(whole, full, nominal + fraction * (full - nominal))


def old_rule(predicted: dict) -> str:
    """The former choice: the smallest level within 5 % of the best predicted rms."""
    finite = {k: v for k, v in predicted.items() if v is not None}
    best = min(finite.values())
    return next(k for k in LEVELS if k in finite and finite[k] <= 1.05 * best)


def study(cm, name: str, n_poses: int, seeds: int) -> dict:
    fraction = ROBOTS[name]
    fit = _fit_function(cm)
    new, old, miss_new, miss_old, seconds = Counter(), Counter(), [], [], []
    for seed in range(FIRST_SEED, FIRST_SEED + seeds):
        t0 = time.perf_counter()
        rng = np.random.default_rng(seed)
        p_true = robot(cm, rng, fraction)
        q = random_configurations(cm.model, cm.model.params.nominal, n_poses, rng)
        data = simulate_measurements(cm.model, p_true, q, cm.cell.sigma, rng)
        choice = choose_model(cm.model, data, fit, 'auto', len(cm.geometric))
        before = old_rule(choice.predicted_rms_m)
        new[choice.level] += 1
        old[before] += 1
        fresh = random_configurations(cm.model, cm.model.params.nominal, FRESH, rng)
        errors = {}
        for level in {choice.level, before}:
            values = fit(data, level_free(cm.model.params, level, len(cm.geometric))).values
            d = cm.model.predict(p_true, fresh) - cm.model.predict(values, fresh)
            errors[level] = float(np.sqrt(np.mean(np.sum(d ** 2, axis=1))))
        miss_new.append(errors[choice.level])
        miss_old.append(errors[before])
        seconds.append(time.perf_counter() - t0)
        print(f'{name} {n_poses} seed {seed}: test {choice.level} ({errors[choice.level] * 1e6:.1f}'
              f' µm), 5 % rule {before} ({errors[before] * 1e6:.1f} µm); z '
              f'{choice.level_z}', flush=True)
    return {'robot': name, 'poses': n_poses, 'seeds': seeds, 'new': dict(new), 'old': dict(old),
            'miss_new_um': 1e6 * float(np.median(miss_new)),
            'miss_old_um': 1e6 * float(np.median(miss_old)),
            'median_s': float(np.median(seconds))}


def upper_bound(k: int, n: int) -> float:
    """Exact one-sided 95 % upper bound on a rate seen k times in n (Clopper-Pearson)."""
    return 1.0 if k == n else float(scipy.stats.beta.ppf(0.95, k + 1, n - k))


def main(argv: list[str]) -> int:
    seeds = int(argv[0]) if argv else 100
    sizes = [int(a) for a in argv[1:]] or [80, 300]
    cm = build_cell_model(cell_from_dict(yaml.safe_load(DEFAULT_CELL.read_text()),
                                         DEFAULT_CELL.parent))
    rows = [study(cm, name, n, seeds) for n in sizes for name in ROBOTS]

    def counts(c: dict) -> str:
        return ', '.join(f'{k} {c[k]}' for k in LEVELS if c.get(k))
    lines = ['# `auto`\'s model level on robots whose level is known', '',
             'Built-in cell (KR15-class), σ of the cell, random poses, seeds from '
             f'{FIRST_SEED}. "offsets": placements and joint offsets only (true level '
             '`joint_offsets`; `geometric` is a false alarm); "0.5 %": plus 0.5 % of the '
             'usual errors of the rest of the geometry (true level `geometric`, a small '
             'gain). Test: a larger level when it lowers the misfit beyond noise (the nested '
             'F-test of the two fits, one-sided α = 0.01, Bonferroni over the larger '
             'levels). 5 % rule: the former choice on the same fits. Fresh error: '
             f'median over seeds of the rms point error on {FRESH} fresh poses (no noise) of '
             'the level taken. Command: `.venv/bin/python bench/level_false_alarms.py '
             f'{seeds} {" ".join(map(str, sizes))}`.', '',
             '| robot | poses | seeds | test: levels taken | false alarms (95 % upper) | '
             '5 % rule: levels taken | fresh error µm, test / 5 % rule | s per seed |',
             '|---|---|---|---|---|---|---|---|']
    for r in rows:
        false = r['new'].get('geometric', 0) if r['robot'] == 'offsets' else None
        alarm = ('–' if false is None else
                 f'{false}/{r["seeds"]} ({100 * upper_bound(false, r["seeds"]):.1f} %)')
        lines.append(f'| {r["robot"]} | {r["poses"]} | {r["seeds"]} | {counts(r["new"])} | '
                     f'{alarm} | {counts(r["old"])} | {r["miss_new_um"]:.1f} / '
                     f'{r["miss_old_um"]:.1f} | {r["median_s"]:.1f} |')
    out = Path(__file__).parent / 'results' / 'level_false_alarms.md'
    out.write_text('\n'.join(lines) + '\n')
    print('\n'.join(lines))
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

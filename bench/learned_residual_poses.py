"""How many poses the learned residual needs for an honest statement, through the CLI.

The built-in KR15 cell with a second-harmonic error of joint_2 (a = 0.4 mrad, b = 0.2 mrad)
the geometric model lacks. Per seed: ``kpi-calib simulate`` N training poses, ``identify
--model geometric --learned-residual``, then 200 fresh poses of the same robot and
``kpi-calib validate``, which predicts them with the learned residual and tests them against
its statement. Reported per N: how often it was chosen, the rms with it / without it, the
share of fresh points inside their stated 95 % ellipsoid, χ²/dof, how often χ² holds at
0.01 as if the points were independent, and how often validate's test holds (χ² under the
joint statement, in which the points share the parameters' error and the learned field),
with the independent points the 200 are worth.

    .venv/bin/python bench/learned_residual_poses.py [n_seeds]

Writes bench/results/learned_residual_poses.md.
"""
from __future__ import annotations

import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from kpi_calib_ros.app.simulate import simulate_campaign, truth_cell_model
from kpi_calib_ros.cli import main as cli
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.results import read_truth

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / 'bench' / 'results' / 'learned_residual_poses.md'
HIDDEN = {'cyclic_joint_error_h2:joint_2': {'a': 4e-4, 'b': 2e-4}}
SIZES = (90, 150, 300)
N_FRESH = 200


def cell(folder: Path) -> Path:
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['simulation'] = {'hidden_effects': HIDDEN}
    path = folder / 'misfit.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def run(folder: Path, n: int, seed: int) -> dict | None:
    """One seed: the learned residual's validation on fresh poses (None: not chosen)."""
    misfit = cell(folder)
    train, out = folder / 'train.mcap', folder / 'out'
    with contextlib.redirect_stdout(io.StringIO()):
        assert cli(['simulate', '--cell', str(misfit), '--n', str(n), '--out', str(train),
                    '--seed', str(seed)]) == 0
        cli(['identify', '--cell', str(misfit), '--bag', str(train), '--out', str(out),
             '--model', 'geometric', '--learned-residual'])
        if not (out / 'learned_residual.yaml').is_file():
            return None
        cm, _ = truth_cell_model(load_cell(misfit))
        truth = read_truth(train)['parameters']
        p_true = np.array([truth[k] for k in cm.model.params.names])
        fresh = folder / 'fresh.mcap'
        simulate_campaign(misfit, N_FRESH, fresh, 10_000 + seed, cm=cm, p_true=p_true)
        cli(['validate', '--cell', str(misfit), '--calibration', str(out / 'calibration.yaml'),
             '--bag', str(fresh), '--out', str(folder / 'val')])
    return json.loads((folder / 'val' / 'validation.json').read_text())['learned_residual']


def main() -> None:
    n_seeds = int(sys.argv[1]) if len(sys.argv) > 1 else 10
    lines = ['# How many poses the learned residual needs for an honest statement', '',
             f'`.venv/bin/python bench/learned_residual_poses.py {n_seeds}`; built-in KR15 '
             'cell, hidden `cyclic_joint_error_h2:joint_2` (a 0.4, b 0.2 mrad), geometric '
             f'model with `--learned-residual`, {N_FRESH} fresh poses of the same robot '
             f'validated with `kpi-calib validate`, seeds 0..{n_seeds - 1}.', '',
             '| training poses | chosen | rms with / without (median) | inside 95 % (median, '
             'min-max) | χ²/dof (median, max) | χ² holds at 0.01 (as if independent) | '
             'validate holds at 0.01 (joint statement) | worth (independent points, median) '
             '| s per seed |',
             '|---|---|---|---|---|---|---|---|---|']
    for n in SIZES:
        rows, t0 = [], time.perf_counter()
        for seed in range(n_seeds):
            with tempfile.TemporaryDirectory() as tmp:
                found = run(Path(tmp), n, seed)
            if found is not None:
                rows.append(found)
        seconds = (time.perf_counter() - t0) / n_seeds
        if not rows:
            lines.append(f'| {n} | 0/{n_seeds} | | | | | | | {seconds:.0f} |')
            continue
        ratio = [r['rms_m'] / r['rms_physical_m'] for r in rows]
        share = [r['inside_95_share'] for r in rows]
        chi2 = [r['chi2'] / r['dof'] for r in rows]
        lines.append(f'| {n} | {len(rows)}/{n_seeds} | {np.median(ratio):.2f} | '
                     f'{np.median(share):.3f} ({min(share):.3f}-{max(share):.3f}) | '
                     f'{np.median(chi2):.2f} ({max(chi2):.2f}) | '
                     f'{sum(r["p_value_independent"] >= 0.01 for r in rows)}/{len(rows)} | '
                     f'{sum(r["holds"] for r in rows)}/{len(rows)} | '
                     f'{np.median([r["effective_points"] for r in rows]):.0f} | '
                     f'{seconds:.0f} |')
        print(lines[-1], flush=True)
    OUT.write_text('\n'.join(lines) + '\n')
    print(f'written: {OUT}')


if __name__ == '__main__':
    main()

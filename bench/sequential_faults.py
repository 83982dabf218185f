"""Sequential campaign with one faulty tracker reading: the same true robots with and without it.

Default cell (stated σ 20 µm), 1000 candidates, target 10 µm on the largest per-axis TCP
std, cap 60. Per run: a new true robot (random geometric errors), the campaign to its
stop; in the faulty case one point of the initial design, chosen at random, is moved by
``--fault`` (m, random direction) — a wrong reflector reading, not a model error. Counts
the stop reasons, whether the fault is the one excluded measurement, false exclusions in
the clean runs, and the number of measurements.

Usage: .venv/bin/python bench/sequential_faults.py [--runs 20] [--fault 1e-3]
Writes bench/results/sequential_faults.md.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.campaign import campaign_context, new_campaign
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.campaigns.settings import TARGET_MET, CampaignSettings
from kpi_calib_ros.core.simulation import true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell


def run(cm, cell, ctx, seed: int, fault: float) -> tuple[str, int, list[int], int]:
    """(stop reason, measurements, excluded indices, faulty index or -1) of one campaign."""
    sigma = float(cm.cell.sigma[0])
    campaign = new_campaign(cm, cell, ctx, CampaignSettings(target_std=10e-6,
                                                            max_measurements=60), seed=seed)
    rng = np.random.default_rng(100 + seed)
    p_true = true_parameters(cm.model.params, rng)
    initial = campaign.initial_design()
    q = campaign.candidates[initial]
    eta = cm.model.predict(p_true, q) + rng.normal(scale=sigma, size=(len(q), 3))
    bad = int(rng.integers(len(q))) if fault > 0 else -1
    if bad >= 0:
        eta[bad] += fault * rng.normal(size=3) / np.sqrt(3)
    status = campaign.add(q, eta, initial)
    while not status.stopped:
        q_next = status.next_configurations[:1]
        eta_next = cm.model.predict(p_true, q_next) + rng.normal(scale=sigma, size=(1, 3))
        status = campaign.add(q_next, eta_next, status.next_candidates[:1])
    return (status.stop_reason, status.measurements,
            [int(e['measurement']) for e in status.excluded], bad)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument('--runs', type=int, default=20)
    ap.add_argument('--fault', type=float, default=1e-3)
    ap.add_argument('--out', default=str(Path(__file__).parent / 'results' /
                                         'sequential_faults.md'))
    args = ap.parse_args()
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    cell, ctx = campaign_context(cm, 3, candidates=1000)
    start = time.perf_counter()
    rows = []
    for case, fault in (('clean', 0.0), (f'fault {args.fault * 1e3:g} mm', args.fault)):
        out = [run(cm, cell, ctx, seed, fault) for seed in range(args.runs)]
        met = sum(o[0] == TARGET_MET for o in out)
        named = sum(o[2] == [o[3]] for o in out) if fault else 0
        wrong = sum(any(i != o[3] for i in o[2]) for o in out)
        others = sorted({o[0] for o in out if o[0] != TARGET_MET})
        rows.append(f'| {case} | {args.runs} | {met} | {", ".join(others) or "-"} | '
                    f'{named if fault else "-"} | {wrong} | '
                    f'{np.mean([o[1] for o in out]):.2f} |')
        print(rows[-1], flush=True)
    text = '\n'.join([
        '# Sequential campaign with one faulty reading', '',
        f'`.venv/bin/python bench/sequential_faults.py --runs {args.runs} --fault '
        f'{args.fault:g}`: default cell, target 10 µm, cap 60, the same true robots '
        '(seeds 0..runs-1) in both cases.', '',
        '| case | runs | target met | other stops | fault the one excluded | '
        'other points excluded | mean measurements |',
        '|---|---|---|---|---|---|---|', *rows, '',
        f'{time.perf_counter() - start:.0f} s.', ''])
    Path(args.out).write_text(text)
    print(f'written: {args.out}')


if __name__ == '__main__':
    main()

"""A sequential campaign at a second station, with the first stations' calibration as prior.

Simulated default cell (σ 20 µm), one true robot per seed measured from a near station
(30 random poses) and a far one (8 random poses; the tracker 3.2 m and 0.7 rad away, the
ground tilted), identified together (``calibrate_cell`` with both as recordings). Then the
sequential campaign at the far station to a target TCP std, run twice on the same true
robot: with that calibration, seen from the far station, as prior
(:func:`kpi_calib_ros.ros.job_work.station_campaign`, as the node runs it) and without
(the far placement known, nothing else). Each starts from the far station's 8 poses and
measures its initial design, then the first pose of every plan. Per seed: the far
measurements each needs to stop, whether the target was met, and the true TCP error at the
working pose in the far station's frame over the std the campaign states (|error|/std per
axis; a right std gives |z| ≤ 3 in 99.7 %). Writes bench/results/station_campaign.md.

    .venv/bin/python bench/station_campaign.py [n_seeds]
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import yaml

from kpi_calib_ros.app.calibration_document import (
    add_robust_sections,
    calibration_document,
    recordings_section,
    with_recording_names,
)
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.app.measurements import with_recordings
from kpi_calib_ros.core.campaigns.settings import TARGET_MET, CampaignSettings
from kpi_calib_ros.core.measurement import recordings as rec
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.ros import job_work

MOVE = np.array([2.5, -2.0, 0.15, 0.03, -0.02, 0.7])
TARGET = 9e-6
CAP = 120
STATIONS = [rec.Recording('near'), rec.Recording('far')]


def run(cm, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    sigma = float(np.max(cm.cell.sigma))
    p_robot = true_parameters(cm.model.params, rng)
    far_truth = p_robot.copy()
    far_truth[:6] += MOVE

    def measure(p: np.ndarray, q: np.ndarray):
        return simulate_measurements(cm.model, p, q, sigma, rng)
    near = measure(p_robot, random_configurations(cm.model, p_robot, 30, rng))
    far = measure(far_truth, random_configurations(cm.model, far_truth, 8, rng))
    placed = with_recordings(cm, STATIONS)
    data = rec.combine([near, far], STATIONS)
    cal = with_recording_names(calibrate_cell(placed, data), STATIONS)
    model_cm = cal.cell or placed
    doc = add_robust_sections(calibration_document(model_cm, cal.result), cal)
    doc['recordings'] = recordings_section(model_cm, data, cal, STATIONS,
                                           ['near.mcap', 'far.mcap'])
    at_far, base, cp = job_work.station_campaign(cm, yaml.safe_dump(doc), 'far')
    settings = CampaignSettings(target_std=TARGET, max_measurements=CAP)
    true_tcp = cm.model.predict(far_truth, cm.q_work)[0]
    out = {'seed': seed, 'valid': cal.valid}
    for key, prior in (('prior', cp), ('alone', None)):
        campaign, initial = job_work.new_sequential(
            at_far if prior is not None else job_work.at_placement(cm, base), settings, 0,
            prior)
        step_rng = np.random.default_rng([seed, 1])
        q = np.vstack([far.q, initial])
        eta = np.vstack([far.eta, simulate_measurements(cm.model, far_truth, initial, sigma,
                                                        step_rng).eta])
        status = campaign.add(q, eta)
        while not status.stopped:
            nxt = status.next_configurations[:1]
            status = campaign.add(nxt, simulate_measurements(cm.model, far_truth, nxt, sigma,
                                                             step_rng).eta)
        res = campaign.result
        assert res is not None
        error = res.tcp[0] - true_tcp
        z = error / status.tcp_std[0]
        out[key] = {'measurements': int(status.measurements), 'initial': len(initial),
                    'met': status.stop_reason == TARGET_MET, 'z': z.tolist(),
                    'statistic_um': float(status.statistic * 1e6)}
    return out


def main(argv: list[str]) -> int:
    seeds = int(argv[0]) if argv else 10
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    start = time.perf_counter()
    rows = []
    for i in range(seeds):
        r = run(cm, 5000 + i)
        rows.append(r)
        print(f"seed {r['seed']}: prior {r['prior']['measurements']} "
              f"({r['prior']['initial']} initial), alone {r['alone']['measurements']} "
              f"({r['alone']['initial']} initial)", flush=True)
    text = ['# A sequential campaign at a second station, with the first stations as prior',
            '', f'Default cell, σ 20 µm; near station 30 random poses, far station 8 '
            f'(3.2 m and 0.7 rad away), identified together; then the far campaign to a '
            f'TCP std of {TARGET * 1e6:g} µm (at most {CAP} far measurements), with the '
            'joint calibration as prior and without. Command: '
            f'`.venv/bin/python bench/station_campaign.py {seeds}` '
            f'({time.perf_counter() - start:.0f} s).', '',
            '| campaign | seeds | far measurements to stop (median, max) | initial design '
            '(median) | target met | true TCP error / stated std: max |z|, share within 3 |',
            '|---|---|---|---|---|---|']
    for key, name in (('prior', 'with the joint calibration as prior'),
                      ('alone', 'alone (far placement known)')):
        n = [r[key]['measurements'] for r in rows]
        z = np.abs(np.array([r[key]['z'] for r in rows]))
        text.append(f"| {name} | {len(rows)} | {np.median(n):.0f}, {max(n)} | "
                    f"{np.median([r[key]['initial'] for r in rows]):.0f} | "
                    f"{sum(r[key]['met'] for r in rows)}/{len(rows)} | "
                    f"{z.max():.2f}, {np.mean(z <= 3):.2f} |")
    text += ['', 'The far station\'s 8 poses measured before are counted in both.', '',
             '## Per seed', '']
    text += [f"- seed {r['seed']}: joint calibration valid {r['valid']}; prior "
             f"{r['prior']['measurements']} measurements, {r['prior']['statistic_um']:.2f} µm, "
             f"z {np.round(r['prior']['z'], 2).tolist()}; alone {r['alone']['measurements']}, "
             f"{r['alone']['statistic_um']:.2f} µm, z {np.round(r['alone']['z'], 2).tolist()}"
             for r in rows]
    path = Path(__file__).resolve().parent / 'results' / 'station_campaign.md'
    path.write_text('\n'.join(text) + '\n')
    print(path.read_text())
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

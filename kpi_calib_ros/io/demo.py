"""`kpi-calib demo`: the main job on the built-in simulated cell, end to end.

Simulates a measurement campaign on the default KR15-class cell, writes it as
an MCAP bag, identifies the robot from the bag and prints a readable report
comparing the result with the simulated truth.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from kpi_calib_ros.io.bag import read_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL, build_cell_model, load_cell
from kpi_calib_ros.io.results import calibration_to_dict, summary_text, write_calibration
from kpi_calib_ros.io.simulate import simulate_campaign, truth_path
from kpi_calib_ros.pipeline import identify_cell, measurements_from_samples


def run_demo(out: str | Path, seed: int) -> int:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    bag = out / 'campaign.mcap'
    print(f'== simulate: 60 random measurable, collision-free poses on {DEFAULT_CELL.name}')
    print(simulate_campaign(DEFAULT_CELL, 60, bag, seed, cm=cm))
    print('\n== identify from the bag')
    joints, points = read_bag(bag)
    data, pairing = measurements_from_samples(cm, joints, points)
    result = identify_cell(cm, data)
    doc = calibration_to_dict(result, pairing)
    write_calibration(out, doc)
    print(summary_text(doc))
    truth = yaml.safe_load(truth_path(bag).read_text())
    tcp_true = np.array(truth['tcp_true'])
    print('\n== against the simulated truth')
    for name, est, true, cov in zip(result.working_pose_names, result.tcp, tcp_true,
                                    result.tcp_covariance):
        err = est - true
        std = np.sqrt(np.diag(cov))
        print(f'TCP {name}: error [{", ".join(f"{e * 1e6:+.1f}" for e in err)}] µm '
              f'= [{", ".join(f"{z:+.2f}" for z in err / std)}] σ')
    print(f'\nresults in {out.resolve()}')
    return 0

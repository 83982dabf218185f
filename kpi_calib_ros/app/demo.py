"""`kpi-calib demo`: the main job on the built-in simulated cell, end to end.

Simulates a measurement campaign on the default KR15-class cell, writes it as
an MCAP bag, identifies the robot from the bag and prints a readable report
comparing the result with the simulated truth. Ends with the model diagnosis
of a simulated cell whose robot has a hidden joint compliance: the error
before and after adding the effect the diagnosis suggests.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from kpi_calib_ros.app.calibration_document import calibration_document
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.diagnose import diagnose_cell
from kpi_calib_ros.app.identify import identify_cell
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.app.simulate import simulate_campaign
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell, read_cell_document, write_cell_document
from kpi_calib_ros.io.report import diagnosis_text, write_report
from kpi_calib_ros.io.results import read_truth, summary_text, write_calibration


def run_demo(out: str | Path, seed: int) -> int:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    bag = out / 'campaign.mcap'
    print(f'== simulate: 60 random measurable, collision-free poses on {DEFAULT_CELL.name}')
    print(simulate_campaign(DEFAULT_CELL, 60, bag, seed, cm=cm))
    print('\n== identify from the bag')
    data, pairing = measurements_from_bag(cm, bag)
    result = identify_cell(cm, data)
    doc = calibration_document(cm, result, pairing)
    write_calibration(out, doc)
    print(summary_text(doc))
    truth = read_truth(bag)
    tcp_true = np.array(truth['tcp_true'])
    print('\n== against the simulated truth')
    for name, est, true, cov in zip(result.working_pose_names, result.tcp, tcp_true,
                                    result.tcp_covariance):
        err = est - true
        std = np.sqrt(np.diag(cov))
        print(f'TCP {name}: error [{", ".join(f"{e * 1e6:+.1f}" for e in err)}] µm '
              f'= [{", ".join(f"{z:+.2f}" for z in err / std)}] σ')
    run_diagnosis_demo(out / 'diagnosis', seed)
    print(f'\nresults in {out.resolve()}')
    return 0


# The hidden effect of the diagnosis demo: joint 2 bends by c·τ, 0.3 mrad at its
# largest gravity torque (~700 N m) -- a real KR15-class gear stiffness.
HIDDEN_EFFECT = {'joint_compliance:joint_2': {'c': 4.0e-7}}


def run_diagnosis_demo(out: str | Path, seed: int, n: int = 80) -> Path:
    """Diagnose a simulated cell whose robot has an effect the model lacks.

    Writes a cell file with ``simulation.hidden_effects``, simulates a
    campaign from it, diagnoses the geometric calibration, adds the suggested
    effect and prints the error before and after, also against the truth.
    Returns the report path.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    doc = read_cell_document(DEFAULT_CELL)
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    # On an adapter, off the flange axis: joint 6 then moves the reflector and the
    # wrist placement errors stay linear (on the axis they leave ~10 µm residuals).
    doc['reflector']['offset'] = [0.05, 0.0, 0.06]
    doc['simulation'] = {'hidden_effects': HIDDEN_EFFECT}
    cell_path = write_cell_document(out / 'hidden_effect_cell.yaml', doc)
    bag = out / 'campaign.mcap'
    spec = next(iter(HIDDEN_EFFECT))
    print(f'\n== diagnosis: the simulated robot has a hidden {spec} '
          f'({HIDDEN_EFFECT[spec]}), the model does not')
    print(simulate_campaign(cell_path, n, bag, seed + 1))
    cm = build_cell_model(load_cell(cell_path))  # geometric model: the cell lists no effects
    data, _ = measurements_from_bag(cm, bag)
    cd = diagnose_cell(cm, data)
    report = write_report(out, cd)
    print(diagnosis_text(cd))
    if cd.after is not None and cd.added is not None:  # set together
        tcp_true = np.array(read_truth(bag)['tcp_true'])
        print(f'\n== TCP error against the simulated truth, before -> after adding {cd.added.name}')
        for i, name in enumerate(cd.result.working_pose_names):
            before = np.linalg.norm(cd.result.tcp[i] - tcp_true[i])
            after = np.linalg.norm(cd.after.tcp[i] - tcp_true[i])
            print(f'TCP {name}: |error| {before * 1e6:.1f} -> {after * 1e6:.1f} µm')
    print(f'report: {report}')
    return report

"""Your first calibration, from Python: simulate a campaign on the built-in cell,
identify the robot and compare the TCP with the simulated truth.

Run: ``python examples/first_calibration.py``. Prints, per working pose, the TCP error
against the truth in µm and in units of the std that eq. (19) predicts for it.
"""
from __future__ import annotations

import numpy as np

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import identify_cell
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell


def main(seed: int = 7, n: int = 60) -> dict[str, np.ndarray]:
    cm = build_cell_model(load_cell(DEFAULT_CELL))         # robot, tracker, working poses
    rng = np.random.default_rng(seed)
    p_true = true_parameters(cm.model.params, rng)          # a "true" robot near the URDF
    q = random_configurations(cm.model, cm.model.params.nominal, n, rng,
                              cm.cell.max_incidence)        # measurable poses (rad)
    data = simulate_measurements(cm.model, p_true, q, cm.cell.sigma, rng)  # tracker points
    result = identify_cell(cm, data)                        # constrained least squares
    tcp_true = cm.model.predict(p_true, cm.q_work)          # (t, 3) m, tracker frame
    print(f'{n} poses, {len(result.estimated)} parameters identified, '
          f'rms {result.rms_m * 1e6:.1f} µm')
    z_all = []
    for name, est, true, cov in zip(result.working_pose_names, result.tcp, tcp_true,
                                    result.tcp_covariance):
        err = est - true
        std = np.sqrt(np.diag(cov))
        z_all.append(err / std)
        print(f'TCP {name}: error [{", ".join(f"{e * 1e6:+.1f}" for e in err)}] µm, '
              f'std [{", ".join(f"{s * 1e6:.1f}" for s in std)}] µm, '
              f'z [{", ".join(f"{z:+.2f}" for z in err / std)}]')
    return {'error': result.tcp - tcp_true, 'std': np.sqrt(np.diagonal(
        result.tcp_covariance, axis1=1, axis2=2)), 'z': np.array(z_all)}


if __name__ == '__main__':
    main()

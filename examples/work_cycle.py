"""A work cycle: recalibrate with 10 poses and the last calibration as prior, and refuse
to blend a change.

Run: ``python examples/work_cycle.py``. A robot is calibrated from 60 poses; one hour
later 10 new poses are identified with that calibration as prior (widened by the default
drift model for 1 h); then its joint_2 placement is bent by 1 mm and 10 more poses are
tested: the change test refuses them and names what moved most.
"""
from __future__ import annotations

import numpy as np

from kpi_calib_ros.app.calibration_document import calibration_document
from kpi_calib_ros.app.identify import identify_cell
from kpi_calib_ros.app.reidentify import cycle_prior, reidentify
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, build_cell_model, load_cell

BENT = 'joint_2.placement.tx'
BEND_M = 1.0e-3


def main(seed: int = 5) -> dict[str, object]:
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    rng = np.random.default_rng(seed)
    p_true = true_parameters(cm.model.params, rng)

    def measure(p: np.ndarray, n: int):
        q = random_configurations(cm.model, cm.model.params.nominal, n, rng,
                                  cm.cell.max_incidence)
        return simulate_measurements(cm.model, p, q, cm.cell.sigma, rng)

    first = identify_cell(cm, measure(p_true, 60))                 # the full campaign
    doc = calibration_document(cm, first)                           # as calibration.yaml
    tcp_true = cm.model.predict(p_true, cm.q_work)
    print(f'cycle 0: 60 poses, TCP std {_worst_std(first.tcp_covariance) * 1e6:.1f} µm')

    data = measure(p_true, 10)                                      # same robot, 1 h later
    cycle = reidentify(cm, data, cycle_prior(cm, doc, data, hours=1.0))
    fit = cycle.calibration.result if cycle.calibration is not None else cycle.fit
    z = (fit.tcp - tcp_true) / np.sqrt(np.diagonal(fit.tcp_covariance, axis1=1, axis2=2))
    print(f'cycle 1: 10 poses, consistent: {cycle.change.consistent}, '
          f'TCP std {_worst_std(fit.tcp_covariance) * 1e6:.1f} µm, '
          f'TCP error z [{", ".join(f"{v:+.2f}" for v in z.ravel())}]')

    p_bent = p_true.copy()
    p_bent[cm.model.params.names.index(BENT)] += BEND_M             # a collision bent a link
    data = measure(p_bent, 10)
    bent = reidentify(cm, data, cycle_prior(cm, doc, data, hours=2.0))
    moved = bent.change.moved                                       # largest LR first
    print(f'cycle 2: 10 poses after a {BEND_M * 1e3:g} mm bend of {BENT}, consistent: '
          f'{bent.change.consistent}')
    if moved:
        print(f'moved most: {moved[0].name} by {moved[0].shift * 1e3:+.2f} ± '
              f'{moved[0].shift_std * 1e3:.2f} mm (LR {moved[0].lr:.0f}); '
              f'{len(moved) - 1} more beyond the threshold; not blended')
    return {'consistent': cycle.change.consistent, 'z': z, 'bent_consistent':
            bent.change.consistent, 'moved': [m.name for m in moved]}


def _worst_std(covariance: np.ndarray) -> float:
    """Largest per-axis TCP std over the working poses (m)."""
    return float(np.sqrt(np.diagonal(covariance, axis1=1, axis2=2)).max())


if __name__ == '__main__':
    main()

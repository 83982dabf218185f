"""A work cycle: recalibrate with 10 poses and the last calibration as prior, and refuse
to blend a change.

Run: ``python examples/work_cycle.py``. A robot is calibrated from 60 poses; one hour
later 10 new poses are identified with that calibration as prior (widened by the default
drift model for 1 h); then its joint_2 placement is bent by 1 mm and 10 more poses are
tested: the change test refuses them and names what moved most.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from kpi_calib_ros import api

BENT = 'joint_2.placement.tx'
BEND_M = 1.0e-3


def main(seed: int = 5) -> dict[str, object]:
    cell = api.load_cell()
    campaign = api.simulate(cell, 60, seed=seed)                    # the full campaign
    first = api.calibrate(cell, campaign.data)
    print(f'cycle 0: 60 poses, TCP std {_worst_std(first.result.tcp_covariance) * 1e6:.1f} µm')

    data = api.simulate(cell, 10, seed + 1, truth=campaign).data    # same robot, 1 h later
    cycle = api.recalibrate(cell, first, data, hours=1.0)
    fit = cycle.calibration.result if cycle.calibration is not None else cycle.fit
    z = (fit.tcp - campaign.true_tcp) / np.sqrt(
        np.diagonal(fit.tcp_covariance, axis1=1, axis2=2))
    print(f'cycle 1: 10 poses, consistent: {cycle.change.consistent}, '
          f'TCP std {_worst_std(fit.tcp_covariance) * 1e6:.1f} µm, '
          f'TCP error z [{", ".join(f"{v:+.2f}" for v in z.ravel())}]')

    p_bent = campaign.true_values.copy()
    p_bent[cell.model.params.index(BENT)] += BEND_M                 # a collision bent a link
    bent_robot = replace(campaign, true_values=p_bent)
    bent = api.recalibrate(cell, first, api.simulate(cell, 10, seed + 2, truth=bent_robot).data,
                           hours=2.0)
    moved = bent.change.moved                                       # largest LR first
    print(f'cycle 2: 10 poses after a {BEND_M * 1e3:g} mm bend of {BENT}, consistent: '
          f'{bent.change.consistent}')
    if moved:
        print(f'moved most: {moved[0].name} by {moved[0].shift * 1e3:+.2f} ± '
              f'{moved[0].shift_std * 1e3:.2f} mm (LR {moved[0].lr:.0f}); '
              f'{len(moved) - 1} more beyond the threshold; not blended')
    assert cycle.change.consistent and np.abs(z).max() < 3.0
    assert not bent.change.consistent and moved and moved[0].name == BENT
    return {'consistent': cycle.change.consistent, 'z': z, 'bent_consistent':
            bent.change.consistent, 'moved': [m.name for m in moved]}


def _worst_std(covariance: np.ndarray) -> float:
    """Largest per-axis TCP std over the working poses (m)."""
    return float(np.sqrt(np.diagonal(covariance, axis1=1, axis2=2)).max())


if __name__ == '__main__':
    main()

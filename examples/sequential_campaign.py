"""The sequential campaign: measure pose by pose until the TCP is known well enough.

Run: ``python examples/sequential_campaign.py``. An initial KPI design is measured on a
simulated robot, then each next pose is the candidate that lowers the TCP variance at
the working poses most; the campaign stops once the largest per-axis TCP std (at the
upper confidence limit of the noise) is below 15 µm, as ``kpi-calib campaign
--simulate`` does.
"""
from __future__ import annotations

import numpy as np

from kpi_calib_ros import api

TARGET_STD = 15e-6   # m


def main(seed: int = 61) -> dict[str, float]:
    cell = api.load_cell()
    truth = api.simulate(cell, 1, seed=seed)                  # the robot to measure
    run = api.sequential_campaign(cell, TARGET_STD, truth, seed=seed, candidates=300)
    final = run.history[-1]
    error = run.tcp_estimated - run.tcp_true
    z = np.abs(error) / run.tcp_std_true
    print(f'{final.measurements} poses ({run.initial} initial), stopped: '
          f'{final.stop_reason}; largest TCP std {final.tcp_std.max() * 1e6:.2f} µm')
    print(f'TCP error [{", ".join(f"{e * 1e6:+.1f}" for e in error.ravel())}] µm, '
          f'largest |z| {z.max():.2f}')
    assert final.stop_reason == 'target met' and final.tcp_std.max() < TARGET_STD
    assert z.max() < 3.0
    return {'poses': float(final.measurements), 'z': float(z.max())}


if __name__ == '__main__':
    main()

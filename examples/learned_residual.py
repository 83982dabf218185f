"""The learned residual: what no physical effect explains, learned over the joints.

Run: ``python examples/learned_residual.py``. The simulated robot's points carry a smooth
error of joints 2 and 3 (0.2 mm, products of sines) that no effect of the library
describes. The geometric calibration leaves it in its residuals; ``api.learn_residual``
fits a Gaussian process to them, keeps it only if it predicts held-out poses better,
and then corrects 100 fresh poses of the same robot.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from kpi_calib_ros import api
from kpi_calib_ros.core.simulation import smooth_joint_map

JOINTS = (1, 2)          # joint_2 and joint_3 (column indices)
AMPLITUDE_M = 2e-4


def main(seed: int = 51, n: int = 150) -> dict[str, float]:
    cell = api.load_cell()
    phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, 6)

    def with_misfit(campaign: api.Campaign) -> api.Campaign:
        data = campaign.data
        eta = data.eta + smooth_joint_map(data.q, JOINTS, AMPLITUDE_M, phase)
        return replace(campaign, data=replace(data, eta=eta))
    train = with_misfit(api.simulate(cell, n, seed=seed))
    fresh = with_misfit(api.simulate(cell, 100, seed + 1, truth=train))
    cal = api.calibrate(cell, train.data, model='geometric')
    choice = api.learn_residual(cell, cal, train.data)
    print(choice.reason)
    physical = (cal.cell or cell).model.predict(cal.result.values, fresh.data.q)
    miss = fresh.data.eta - physical
    corrected = miss - choice.model.predict(fresh.data.q).mean

    def rms(e: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))
    print(f'fresh poses: rms {rms(miss) * 1e6:.1f} µm physical, '
          f'{rms(corrected) * 1e6:.1f} µm with the learned residual')
    noise = np.sqrt(3) * float(cell.cell.sigma[0])       # a point's rms at σ per axis
    assert choice.chosen and rms(corrected) < 0.5 * rms(miss) and rms(corrected) < 2 * noise
    return {'physical': rms(miss), 'learned': rms(corrected)}


if __name__ == '__main__':
    main()

"""Measured inputs per row: a payload recorded with each measurement.

Run: ``python examples/measured_inputs.py``. Joint 2 of the simulated robot bends under
gravity (a joint compliance); half of its 60 poses are measured without a load, half
with 20 kg, and each row records its ``payload.mass``, as the cell's ``inputs:`` or a
manifest's ``covariates`` record it. The compliance is identified from the rows' own
gravity torques; taken with the cell's one payload for every row, the fit fails.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from kpi_calib_ros import api

C_NAME = 'joint_compliance.joint_2.c'
C_TRUE = -1.0e-6                                   # rad/(N m)


def main(seed: int = 41, n: int = 60) -> dict[str, float]:
    cell = api.load_cell(effects='joint_compliance:joint_2')
    mass = np.where(np.arange(n) % 2 == 0, 0.0, 20.0)  # kg, recorded per row
    campaign = api.simulate(cell, n, seed=seed, values={C_NAME: C_TRUE},
                            inputs={'payload.mass': mass})
    cal = api.calibrate(cell, campaign.data, model='geometric')
    c, c_std = cal.result.value(C_NAME), cal.result.std_of(C_NAME)
    print(f'with the recorded payloads: c = {c:.3e} ± {c_std:.1e} rad/(N m), '
          f'true {C_TRUE:.1e}; rms {cal.result.rms_m * 1e6:.1f} µm')
    unrecorded = replace(campaign.data, covariates=None)   # every row the cell's 5 kg
    blind = api.calibrate(cell, unrecorded, model='geometric')
    print(f'with the cell\'s one payload: rms {blind.result.rms_m * 1e6:.1f} µm')
    assert abs(c - C_TRUE) < 3 * c_std and blind.result.rms_m > 2 * cal.result.rms_m
    return {'c': c, 'c_std': c_std, 'rms': cal.result.rms_m, 'rms_blind': blind.result.rms_m}


if __name__ == '__main__':
    main()

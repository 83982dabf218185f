"""Find the effect the geometric model misses: a simulated robot whose joint 2 bends
under gravity (a joint compliance the model lacks) is calibrated, diagnosed, and the
effect the diagnosis ranks first is added.

Run: ``python examples/find_missing_effect.py``. Prints the model adequacy, the top
candidate effect and the rms before and after adding it.
"""
from __future__ import annotations

from kpi_calib_ros import api

HIDDEN = 'joint_compliance:joint_2'
C_NAME = 'joint_compliance.joint_2.c'
C_TRUE = -1.0e-6   # rad/(N m): joint 2 sags along gravity, stiffness 1e6 N m/rad


def main(seed: int = 3, n: int = 60) -> dict[str, object]:
    cell = api.load_cell()                                           # geometric model
    campaign = api.simulate(cell, n, seed=seed, hidden=HIDDEN, values={C_NAME: C_TRUE})
    cd = api.diagnose(cell, campaign.data)                           # calibrate + diagnose
    best = cd.diagnosis.best
    print(f'geometric model adequate: {cd.diagnosis.model_adequate}, '
          f'rms {cd.result.rms_m * 1e6:.1f} µm')
    if best is None or cd.after is None:
        print('no significant effect')
        return {'best': None, 'adequate': cd.diagnosis.model_adequate}
    print(f'top candidate: {best.spec} (p = {best.p_value:.1e})')
    print(f'rms after adding it: {cd.after.rms_m * 1e6:.1f} µm')
    result: dict[str, object] = {'best': best.spec, 'adequate': cd.diagnosis.model_adequate,
                                 'rms_before': cd.result.rms_m, 'rms_after': cd.after.rms_m}
    if best.spec == HIDDEN:
        result.update(c=cd.after.value(C_NAME), c_std=cd.after.std_of(C_NAME))
        print(f'identified c = {result["c"]:.3e} ± {result["c_std"]:.1e} rad/(N m), '
              f'true {C_TRUE:.1e}')
    return result


if __name__ == '__main__':
    main()

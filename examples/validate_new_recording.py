"""Validate a calibration on a new recording, and on one made after the tracker was set
up again (re-registration).

Run: ``python examples/validate_new_recording.py``. A robot calibrated from 60 poses is
checked on 40 new poses of the same set-up (it holds), then on 40 poses measured with the
robot 0.4 m and 0.15 rad away from the tracker: taken as they are they contradict the
calibration; with ``register='base'`` the base pose is re-fitted on them first and the
calibration holds again.
"""
from __future__ import annotations

from dataclasses import replace

from kpi_calib_ros import api

MOVE = {'base.x': 0.4, 'base.y': -0.2, 'base.yaw': 0.15}  # m, m, rad


def main(seed: int = 21) -> dict[str, bool]:
    cell = api.load_cell()
    campaign = api.simulate(cell, 60, seed=seed)
    cal = api.calibrate(cell, campaign.data)
    same = api.validate(cell, cal, api.simulate(cell, 40, seed + 1, truth=campaign).data)
    moved_values = campaign.true_values.copy()
    for name, step in MOVE.items():
        moved_values[cell.model.params.index(name)] += step
    moved = replace(campaign, true_values=moved_values)      # the tracker set up again
    new = api.simulate(cell, 40, seed + 2, truth=moved).data
    as_is = api.validate(cell, cal, new)
    registered = api.validate(cell, cal, new, register='base')
    for label, v in (('same set-up', same), ('set up again, as is', as_is),
                     ('set up again, registered', registered)):
        print(f'{label:>26}: holds {v.holds}, rms {v.rms_m * 1e6:.1f} µm, '
              f'p = {v.p_value:.3g}')
    verdicts = {'same': bool(same.holds), 'as_is': bool(as_is.holds),
                'registered': bool(registered.holds)}
    assert verdicts == {'same': True, 'as_is': False, 'registered': True}, verdicts
    return verdicts


if __name__ == '__main__':
    main()

"""Several recordings (tracker set-ups) in one calibration: one robot measured from two
tracker stations, the robot shared and each station's placement identified.

Run: ``python examples/several_recordings.py``. Station ``b`` is 1.2 m and 0.5 rad
away from station ``a``; each has 30 poses. ``api.calibrate`` takes them as
``{name: measurements}``, as ``kpi-calib identify --bag a.mcap --bag b.mcap`` does, and
identifies ``recording.b.base.*`` beside the robot's parameters. The TCP (in station
``a``'s frame) is within 3σ of the truth, and known better than from station ``a`` alone.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from kpi_calib_ros import api

MOVE = {'base.x': 1.2, 'base.y': -0.6, 'base.yaw': 0.5}  # station b against a (m, rad)


def main(seed: int = 31, n: int = 30) -> float:
    cell = api.load_cell()
    a = api.simulate(cell, n, seed=seed)
    b_values = a.true_values.copy()
    for name, step in MOVE.items():
        b_values[cell.model.params.index(name)] += step
    b = api.simulate(cell, n, seed + 1, truth=replace(a, true_values=b_values))
    cal = api.calibrate(cell, {'a': a.data, 'b': b.data}, model='geometric')
    res = cal.result
    print(f'{len(a.data)} + {len(b.data)} poses, valid: {cal.valid}, '
          f'rms {res.rms_m * 1e6:.1f} µm')
    for name in MOVE:
        print(f'recording.b.{name} = {res.value(f"recording.b.{name}"):+.6f} '
              f'± {res.std_of(f"recording.b.{name}"):.1e}')
    std = np.sqrt(np.diagonal(res.tcp_covariance, axis1=1, axis2=2))
    z_tcp = np.abs(res.tcp - a.true_tcp) / std    # the TCP in station a's frame
    alone = api.calibrate(cell, a.data, model='geometric').result
    std_alone = np.sqrt(np.diagonal(alone.tcp_covariance, axis1=1, axis2=2))
    print(f'TCP error within {z_tcp.max():.2f}σ; largest TCP std {std.max() * 1e6:.1f} µm '
          f'(station a alone: {std_alone.max() * 1e6:.1f} µm)')
    assert cal.valid and z_tcp.max() < 3.0 and std.max() < std_alone.max()
    return float(z_tcp.max())


if __name__ == '__main__':
    main()

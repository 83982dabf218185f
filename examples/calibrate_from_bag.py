"""Calibrate from a recording: write a simulated campaign as an MCAP bag, read it back as
the command line reads a bag, calibrate, and compare the TCP with the simulated truth.

Run: ``python examples/calibrate_from_bag.py [BAG]`` (default: a temporary file). The
bag holds joint states held still around each tracker point, as a cell records them;
``api.read_bag`` pairs them (topics from the cell's ``topics:``).
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from kpi_calib_ros import api


def main(bag: str | None = None, seed: int = 11) -> float:
    cell = api.load_cell()
    campaign = api.simulate(cell, 50, seed=seed)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(bag) if bag else Path(tmp) / 'run.mcap'
        print(api.write_bag(campaign, path, seed=seed).splitlines()[0])
        data = api.read_bag(cell, path)
    cal = api.calibrate(cell, data)
    std = np.sqrt(np.diagonal(cal.result.tcp_covariance, axis1=1, axis2=2))
    z = (cal.result.tcp - campaign.true_tcp) / std
    print(f'{len(data)} measurements paired, valid: {cal.valid}, '
          f'rms {cal.result.rms_m * 1e6:.1f} µm')
    print(f'TCP error / predicted std: largest |z| {np.abs(z).max():.2f}')
    assert cal.valid and np.abs(z).max() < 3.0, 'the TCP is not within 3σ of the truth'
    return float(np.abs(z).max())


if __name__ == '__main__':
    args = sys.argv[1:]
    if len(args) > 1 or (args and args[0].startswith('-')):
        sys.exit(f'usage: python {sys.argv[0]} [BAG.mcap]  (the bag to write; '
                 f'default a temporary file)')
    main(*args)

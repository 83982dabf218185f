"""Reading a campaign bag for pairing: time and peak memory, 50 Hz / 1 kHz / 2000 poses.

Bags come from :func:`kpi_calib_ros.core.acquisition.streams.synthesize_streams` (6 joints, 2 s
move + 2 s hold per pose, one tracker point per hold, joint noise 1e-5 rad) written
with :func:`kpi_calib_ros.io.bag.write_bag` as ``ros2 bag record`` writes them. Each
case is measured in a fresh process, so peak RSS (``ru_maxrss``) is that of reading
and pairing alone:

- ``read``: :func:`read_for_pairing` (points first, then the joint states around them);
- ``pair``: :func:`pair_measurements` on what was read;
- ``read_all``: :func:`read_bag` of every message, for comparison.

Usage: ``python bench/bag_reading.py [--cases 50hz,1khz,2000poses] [--keep DIR]`` (bags
already in DIR from an earlier run are reused).
Writes bench/results/bag_reading.md.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import kpi_calib_ros  # noqa: F401  (sets single-threaded BLAS before numpy loads)

NAMES = tuple(f'joint_{i}' for i in range(1, 7))
FRAME = 'laser_tracker'
CASES = {'50hz': (60, 50.0), '1khz': (60, 1000.0), '2000poses': (2000, 50.0)}


def make_bag(path: Path, poses: int, rate_hz: float) -> dict:
    from kpi_calib_ros.core.acquisition.streams import synthesize_streams
    from kpi_calib_ros.io.bag import write_bag
    rng = np.random.default_rng(7)
    q = rng.uniform(-2.0, 2.0, (poses, len(NAMES)))
    eta = rng.uniform(-1.5, 1.5, (poses, 3))
    joints, points = synthesize_streams(q, NAMES, eta, FRAME, rate_hz=rate_hz,
                                        joint_noise_rad=1e-5, rng=rng)
    write_bag(path, joints, points)
    return {'joint_states': len(joints), 'points': len(points),
            'bytes': path.stat().st_size}


def measure(path: Path, mode: str) -> dict:
    """One measurement in this (fresh) process."""
    from kpi_calib_ros.core.acquisition.pairing import pair_measurements
    from kpi_calib_ros.io.bag import read_bag, read_for_pairing
    t0 = time.perf_counter()
    if mode == 'read_all':
        joints, points = read_bag(path)
    else:
        contents = read_for_pairing(path)
        joints, points = contents.joints, contents.points
    t1 = time.perf_counter()
    pairing = pair_measurements(joints, points, NAMES, FRAME)
    t2 = time.perf_counter()
    return {'read_s': t1 - t0, 'pair_s': t2 - t1, 'decoded_joint_states': len(joints),
            'accepted': len(pairing), 'rejected': pairing.rejections,
            'peak_rss_mb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--cases', default=','.join(CASES))
    parser.add_argument('--keep', help='directory for the generated bags (kept, reused)')
    parser.add_argument('--measure', nargs=2, metavar=('BAG', 'MODE'), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.measure:
        print(json.dumps(measure(Path(args.measure[0]), args.measure[1]), allow_nan=False))
        return 0
    directory = Path(args.keep or tempfile.mkdtemp(prefix='bag_reading_'))
    directory.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in args.cases.split(','):
        poses, rate = CASES[case]
        path = directory / f'{case}.mcap'
        info_path = path.with_suffix('.json')
        t0 = time.perf_counter()
        if args.keep and path.exists() and info_path.exists():  # made by an earlier run
            info = json.loads(info_path.read_text())
        else:
            info = make_bag(path, poses, rate)
            info_path.write_text(json.dumps(info, allow_nan=False))
        print(f'{case}: {poses} poses, joint states at {rate:g} Hz: {info} '
              f'(ready in {time.perf_counter() - t0:.1f} s)', flush=True)
        for mode in ('for_pairing', 'read_all'):
            out = subprocess.run([sys.executable, __file__, '--measure', str(path), mode],
                                 check=True, capture_output=True, text=True).stdout
            r = json.loads(out.strip().splitlines()[-1])
            print(f'  {mode:12s} read {r["read_s"]:.2f} s + pair {r["pair_s"]:.2f} s = '
                  f'{r["read_s"] + r["pair_s"]:.2f} s, peak RSS {r["peak_rss_mb"]:.0f} MB, '
                  f'decoded {r["decoded_joint_states"]} joint states, accepted '
                  f'{r["accepted"]}, rejected {r["rejected"]}', flush=True)
            rows.append((case, poses, rate, info, mode, r))
    lines = ['# Reading a bag for pairing', '',
             f'`python bench/bag_reading.py --cases {args.cases}`; each row a fresh process.', '',
             '| case | poses | joint rate (Hz) | joint states | bag (MB) | mode | read (s) | '
             'pair (s) | total (s) | peak RSS (MB) | decoded | accepted |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|']
    for case, poses, rate, info, mode, r in rows:
        lines.append(f'| {case} | {poses} | {rate:g} | {info["joint_states"]} | '
                     f'{info["bytes"] / 1e6:.1f} | {mode} | {r["read_s"]:.2f} | '
                     f'{r["pair_s"]:.2f} | {r["read_s"] + r["pair_s"]:.2f} | '
                     f'{r["peak_rss_mb"]:.0f} | {r["decoded_joint_states"]} | {r["accepted"]} |')
    out = Path(__file__).parent / 'results' / 'bag_reading.md'
    out.write_text('\n'.join(lines) + '\n')
    print(f'written: {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

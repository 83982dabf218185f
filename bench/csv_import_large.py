"""import-csv of large posture tables: peak memory and time against the number of rows.

Writes tables of 1e4, 1e5 and 1e6 rows (two joints, one point, Unix stamps 5 s apart;
written row by row), imports each in its own process and reads that process's peak
resident set size (``os.wait4``: ru_maxrss) and wall time. Joint states are held at 2 Hz
(three per posture, ±0.5 s) rather than the default 50 Hz so that the 1e6-row bag stays
under a GB and the run under ten minutes; the rows, not the messages per row, are what
this bench scales.

    .venv/bin/python bench/csv_import_large.py [--rows 10000,100000,1000000]

Writes bench/results/csv_import_large.md.
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / 'bench' / 'results' / 'csv_import_large.md'
RATE_HZ = 2.0


def write_table(path: Path, rows: int) -> None:
    rng = np.random.default_rng(0)
    with open(path, 'w') as f:
        f.write('stamp,joint_1,joint_2,x,y,z\n')
        for start in range(0, rows, 10_000):
            n = min(10_000, rows - start)
            values = np.column_stack([1.6e9 + 5.0 * np.arange(start, start + n),
                                      rng.uniform(-1, 1, (n, 5))])
            np.savetxt(f, values, fmt=['%.1f'] + ['%.9f'] * 5, delimiter=',')


def child(table: str, bag: str) -> None:
    from kpi_calib_ros.io.csv_import import import_csv, mapping_from_dict
    mapping = mapping_from_dict({'frame_id': 'laser_tracker', 'joints': ['joint_1', 'joint_2'],
                                 'markers': {'r': ['x', 'y', 'z']},
                                 'stamp_columns': ['stamp']})
    summary = import_csv(table, bag, mapping, rate_hz=RATE_HZ)
    print(summary.postures, summary.points)


def measure(table: Path, bag: Path) -> tuple[float, float, str]:
    """(wall s, peak RSS MiB, child's stdout) of one import in its own process."""
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, __file__, '--child', str(table), str(bag)],
                            stdout=subprocess.PIPE, text=True,
                            env={**os.environ, 'OPENBLAS_NUM_THREADS': '1',
                                 'OMP_NUM_THREADS': '1'})
    assert proc.stdout is not None
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f'import of {table} failed with exit code {proc.returncode}')
    return time.perf_counter() - start, usage.ru_maxrss / 1024, out.strip()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--rows', default='10000,100000,1000000')
    parser.add_argument('--child', nargs=2, metavar=('TABLE', 'BAG'), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(*args.child)
        return
    lines = ['# import-csv of large tables: peak memory and time', '',
             f'`.venv/bin/python bench/csv_import_large.py --rows {args.rows}` on '
             f'{platform.node()} ({os.cpu_count()} cores, shared), Python '
             f'{platform.python_version()}; joint states held at {RATE_HZ:g} Hz (3 per '
             'posture), one point per posture.', '',
             '| rows | table MB | bag MB | wall s | µs per row | peak RSS MiB |',
             '|---:|---:|---:|---:|---:|---:|']
    with tempfile.TemporaryDirectory(prefix='csv_import_large_') as tmp:
        for rows in (int(r) for r in args.rows.split(',')):
            table, bag = Path(tmp) / f'{rows}.csv', Path(tmp) / f'{rows}.mcap'
            write_table(table, rows)
            wall, rss, out = measure(table, bag)
            assert out == f'{rows} {rows}', out
            row = (f'| {rows} | {table.stat().st_size / 1e6:.1f} | {bag.stat().st_size / 1e6:.1f} '
                   f'| {wall:.1f} | {wall / rows * 1e6:.0f} | {rss:.0f} |')
            print(row, flush=True)
            lines.append(row)
            table.unlink()
            bag.unlink()
    lines += ['', 'Peak RSS is that of the importing process alone (os.wait4 ru_maxrss). '
              'What grows with the rows is the stamp index (16 bytes a row, about three '
              'times that while it is sorted at the end to check for overlapping holds).']
    OUT.write_text('\n'.join(lines) + '\n')
    print(f'written: {OUT}')


if __name__ == '__main__':
    main()

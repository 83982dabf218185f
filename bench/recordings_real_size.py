"""Several recordings of the real UR10 at full size, through the command line as a user runs it.

../shared/data/ipa_ur10: all 11 911 poses of Series A and half of Series D (316 poses, random,
seed 0; months later, the tracker set up again and the probe remounted) identified together
(``identify --bag A.mcap --bag D.mcap --remounted D``); the other 316 poses of D held out
and predicted after registration (``validate --register base`` and ``base+reflector``),
against the same prediction from A alone. Each command runs in its own process: wall time
and peak resident memory (os.wait4 ru_maxrss). Every figure the tool writes is then
recomputed without it, as test/test_recordings_real_size.py does at 2000 poses: the
residuals of calibration.yaml from the written URDF (Pinocchio) and its placements, the
held-out rms by a registration done here.

Writes bench/results/recordings_real_size.md.

    nice -n 19 /work/main/.venv/bin/python bench/recordings_real_size.py [DATA_DIR] [A_POSES]
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
NOTES = '## Measured beside the script'
sys.path.insert(0, str(ROOT / 'test'))
from test_recordings_real_size import (  # noqa: E402  (the independent evaluation)
    BASE,
    CELL,
    MAPPING,
    PROBE,
    _flange,
    _misses,
    _registered_rms,
    _rows,
    _table,
)


def run(args: list[str], log: Path) -> tuple[int, float, float]:
    """Exit code, wall time (s) and peak RSS (MiB) of ``kpi-calib args`` in its own process;
    its output into ``log``."""
    start = time.perf_counter()
    with open(log, 'w') as out:
        proc = subprocess.Popen([sys.executable, '-m', 'kpi_calib_ros.cli', *args], stdout=out,
                                stderr=subprocess.STDOUT,
                                env={**os.environ, 'OMP_NUM_THREADS': '1',
                                     'OPENBLAS_NUM_THREADS': '1'})
        _, status, usage = os.wait4(proc.pid, 0)
    return os.waitstatus_to_exitcode(status), time.perf_counter() - start, usage.ru_maxrss / 1024


def independent(folder: Path, tables: dict[str, Path], prefixes: dict[str, str]) -> float:
    """Largest difference (m) between the residuals of ``folder``'s calibration.yaml and
    those recomputed from its URDF and placements, row for row."""
    doc = yaml.safe_load((folder / 'calibration.yaml').read_text())
    value = {p['name']: p['value'] for p in doc['parameters']}
    urdf = (folder / 'robot_description_calibrated.urdf').read_text()
    points, angles = [], []
    for name, prefix in prefixes.items():
        q, eta, rotations = _table(tables[name])
        p, a = _misses({n: value[prefix + n] for n in BASE + PROBE}, _flange(urdf, q), eta,
                       rotations)
        points.append(p)
        angles.append(a)
    tool = np.array(doc['residuals_m'])
    worst = 0.0
    for rows, mine in ((tool[0::2], np.concatenate(points)), (tool[1::2], np.concatenate(angles))):
        distance, index = cKDTree(mine).query(rows)
        if len(set(index.tolist())) != len(rows) or len(rows) != len(mine):
            return float('inf')
        worst = max(worst, float(distance.max()))
    return worst


def main(argv: list[str]) -> int:
    data = Path(argv[0]) if argv else Path('/work/shared/data/ipa_ur10')
    series_a = data / 'Series_A' / 'measurements_grid.csv'
    series_d = data / 'Series_D' / 'measurements_iso_cubes.csv'
    rows_a = sum(1 for line in series_a.read_bytes().split(b'\r\n')[1:] if line)
    a_poses = int(argv[1]) if len(argv) > 1 else rows_a
    folder = Path(tempfile.mkdtemp(prefix='recordings_real_size_'))
    order = np.random.default_rng(0).permutation(632)
    tables = {'A': series_a if a_poses == rows_a else _rows(
                  series_a, folder / 'A.csv',
                  np.random.default_rng(0).choice(rows_a, a_poses, replace=False)),
              'D': _rows(series_d, folder / 'D.csv', order[:316]),
              'D_heldout': _rows(series_d, folder / 'D_heldout.csv', order[316:])}
    rows_only = yaml.safe_load(MAPPING.read_text())
    for key in ('stamp_columns', 'stamp_format', 'stamp_timezone'):
        rows_only.pop(key)
    (folder / 'rows.yaml').write_text(yaml.safe_dump(rows_only))
    steps: list[tuple[str, list[str]]] = []
    for name, table in tables.items():
        mapping = MAPPING if name == 'A' else folder / 'rows.yaml'
        steps.append((f'import-csv {name}', ['import-csv', str(table), '--mapping', str(mapping),
                                             '--out', str(folder / f'{name}.mcap')]))
    cell = ['--cell', str(CELL)]
    steps += [('identify A + D (remounted)',
               ['identify', *cell, '--bag', str(folder / 'A.mcap'), '--bag',
                str(folder / 'D.mcap'), '--remounted', 'D', '--out', str(folder / 'joint')]),
              ('identify A alone', ['identify', *cell, '--bag', str(folder / 'A.mcap'), '--out',
                                    str(folder / 'alone')])]
    for cal in ('joint', 'alone'):
        for register in ('base', 'base+reflector'):
            steps.append((f'validate D held out, {cal}, --register {register}',
                          ['validate', *cell, '--calibration',
                           str(folder / cal / 'calibration.yaml'), '--bag',
                           str(folder / 'D_heldout.mcap'), '--register', register, '--out',
                           str(folder / f'val_{cal}_{register}')]))
    measured = []
    for label, args in steps:
        code, seconds, mib = run(args, folder / f'{label.replace(" ", "_")}.log')
        measured.append((label, code, seconds, mib))
        print(label, code, f'{seconds:.1f} s', f'{mib:.0f} MiB', flush=True)
    joint = yaml.safe_load((folder / 'joint' / 'calibration.yaml').read_text())
    figures = {}
    for cal in ('joint', 'alone'):
        for register, names in (('base', BASE), ('base+reflector', BASE + PROBE)):
            v = json.loads((folder / f'val_{cal}_{register}' / 'validation.json').read_text())
            mine = _registered_rms(folder / cal, tables['D_heldout'], names)
            figures[(cal, register)] = (v['rms_m'], mine, v['verdict'])
    worst = {'joint': independent(folder / 'joint', tables, {'A': '', 'D': 'recording.D.'}),
             'alone': independent(folder / 'alone', tables, {'A': ''})}
    rec_a, rec_d = joint['recordings']
    lines = ['# Several recordings of the real UR10 at full size', '',
             f'Command: `nice -n 19 /work/main/.venv/bin/python bench/recordings_real_size.py`'
             f' (figures exactly as measured; see the module docstring). {a_poses} poses of '
             'Series A and 316 of Series D identified together; the other 316 of D held out. '
             'A shared 2-core machine: other work ran beside it.', '',
             '| command | exit | wall (s) | peak RSS (MiB) |', '|---|---|---|---|']
    lines += [f'| {label} | {code} | {seconds:.1f} | {mib:.0f} |'
              for label, code, seconds, mib in measured]
    lines += ['', '## calibration.yaml of A and D together', '',
              f"valid {joint['valid']}, {joint['pairing']['accepted']} poses, rms "
              f"{joint['rms_m'] * 1e6:.1f} µm. Largest difference between its residuals and "
              'those recomputed from the written URDF and its placements (Pinocchio, the CSV '
              f"read without the tool): {worst['joint']:.1e} m (A alone: "
              f"{worst['alone']:.1e} m).", '',
              '| recording | poses | rms (µm) | base x, y, z (m) | base roll, pitch, yaw (rad) | '
              'probe offset (mm) | TCP variance without it | held-out rms (µm) | nominal '
              '(µm) | worse than nominal |', '|---|---|---|---|---|---|---|---|---|---|']
    for rec in (rec_a, rec_d):
        place = list(rec['placement'].values())
        ago = rec['against_nominal']
        where = ', '.join(f"{p['value']:.4f}" for p in place[:3])
        turn = ', '.join(f"{p['value']:.4f}" for p in place[3:6])
        probe = ', '.join(f"{p['value'] * 1e3:.1f} ± {p['std'] * 1e3:.1f}" for p in place[6:9])
        lines.append(
            f"| {rec['name']} | {rec['poses']} | {rec['rms_m'] * 1e6:.1f} | {where} | {turn} | "
            f"{probe} | {rec['tcp_variance_ratio_without']:.2f} | "
            f"{ago['in_region_rms_m'] * 1e6:.1f} | {ago['nominal_in_region_rms_m'] * 1e6:.1f} | "
            f"{ago['worse_than_nominal']} |")
    lines += ['', '## D held out, registered (316 poses)', '',
              '| calibrated on | --register | rms (µm) | recomputed here (µm) | verdict |',
              '|---|---|---|---|---|']
    for (cal, register), (rms, mine, verdict) in figures.items():
        lines.append(f"| {'A and D' if cal == 'joint' else 'A alone'} | {register} | "
                     f'{rms * 1e6:.2f} | {mine * 1e6:.2f} | {verdict} |')
    result = ROOT / 'bench' / 'results' / 'recordings_real_size.md'
    # the notes measured beside the script (before the fix, diagnose, open findings) stay
    kept = result.read_text().partition(NOTES)[1:] if result.exists() else ('', '')
    result.write_text('\n'.join(lines) + '\n' + ('\n' + ''.join(kept) if kept[0] else ''))
    print('\n'.join(lines))
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

"""Real data: model choice on the smallest TIAGo session, validated on the other sessions.

Calibrates on the 37-posture session (2021-11-30) with ``--model geometric``, ``--model
auto`` (auto chooses the level and the physical effects on that session alone) and ``--model
auto`` with the cell's tolerances (tiago_mocap_cell_tolerances.yaml), validates
each calibration with ``kpi-calib validate`` on the other day (2021-11-26) and on the two
later sessions of the same afternoon (2021-11-30-1403, -1504; never used for a choice),
and writes bench/results/tiago_auto.md: rms over all markers, inside / outside the
training joint ranges (inside: training poses measured again / new poses, as
`kpi-calib validate` reports them), per marker. The last two rows follow the peer toolbox's held-out
protocol (FIGAROH, figaroh-examples docs/development/tiago-mocap-heldout-protocol.md): one
marker (m1) observed in training and in validation, norm rms of its position in mm.

    .venv/bin/python bench/tiago_auto.py [DATA_DIR]   # default ../shared/data/tiago_mocap
"""
from __future__ import annotations

import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.cli import main
from kpi_calib_ros.io.cell import load_cell

ROOT = Path(__file__).resolve().parents[1]
CELL = ROOT / 'test' / 'data' / 'tiago_mocap_cell.yaml'
TOLERANCES = ROOT / 'test' / 'data' / 'tiago_mocap_cell_tolerances.yaml'
# (row name, cell, --model, markers): the full model, auto, auto with the cell's
# tolerances on the four markers; the full model and auto with tolerances on m1 alone
RUNS = (('geometric', CELL, 'geometric', 'all'), ('auto', CELL, 'auto', 'all'),
        ('auto, tolerances', TOLERANCES, 'auto', 'all'),
        ('geometric, m1 only', CELL, 'geometric', 'm1'),
        ('auto, tolerances, m1 only', TOLERANCES, 'auto', 'm1'))
MAPPING = ROOT / 'test' / 'data' / 'tiago_mocap_mapping.yaml'
TRAIN = '2021-11-30'
VALIDATE = ('2021-11-26', '2021-11-30-1403', '2021-11-30-1504')


def _quiet(argv: list[str]) -> int:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return main(argv)


def one_marker(path: Path, out: Path) -> Path:
    """The mapping or cell at ``path`` with its first marker (m1) alone, written to ``out``."""
    doc = yaml.safe_load(path.read_text())
    if 'markers' in doc:
        doc['markers'] = {'m1': doc['markers']['m1']}
    else:
        doc['reflectors'] = [r for r in doc['reflectors'] if r['name'] == 'm1']
    out.write_text(yaml.safe_dump(doc))
    return out


def poses(cell: Path, bag: Path) -> dict[int, np.ndarray]:
    """Joint values (URDF, chain order) of every measured point of ``bag``, by stamp."""
    data, _ = measurements_from_bag(build_cell_model(load_cell(cell)), bag)
    return {int(s): q for s, q in zip(data.stamps_ns, data.q)}


def peer_groups(doc: dict, q_new: dict[int, np.ndarray], q_train: np.ndarray) -> str:
    """rms (mm) and postures per posture group of the peer's protocol: out of range (a
    joint beyond the training range ± 0.05), repeated (every joint within 0.01 of a
    training posture), new (the rest)."""
    lo, hi = q_train.min(axis=0) - 0.05, q_train.max(axis=0) + 0.05
    groups: dict[str, list[float]] = {'repeated': [], 'new': [], 'out of range': []}
    stamps: dict[str, set[int]] = {g: set() for g in groups}
    for point in doc['points']:
        q = q_new[point['stamp_ns']]
        group = ('out of range' if np.any((q < lo) | (q > hi)) else 'repeated'
                 if np.any(np.all(np.abs(q_train - q) <= 0.01, axis=1)) else 'new')
        groups[group].append(float(np.sum(np.square(point['residual_m']))))
        stamps[group].add(point['stamp_ns'])
    return ' | '.join(f'{np.sqrt(np.mean(v)) * 1e3:.2f} ({len(stamps[g])})' if v else '-'
                      for g, v in groups.items())


def main_bench(data_dir: Path) -> str:
    t0 = time.time()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        mappings = {'all': MAPPING, 'm1': one_marker(MAPPING, out / 'mapping_m1.yaml')}
        cells = {(c, 'm1'): one_marker(c, out / f'{c.stem}_m1.yaml') for c in (CELL, TOLERANCES)}
        # The full model on one marker tilts arm_7's placement by 0.11 rad to fit it: the
        # plausibility gate refuses it (exit 1); as the baseline it is fitted with the
        # rotation tolerance widened, as test/test_tiago_mocap.py does.
        wide = yaml.safe_load(cells[CELL, 'm1'].read_text())
        wide.setdefault('identification', {})['tolerances'] = {'rotation': 0.2}
        cells[CELL, 'm1'] = out / 'tiago_mocap_cell_m1_wide.yaml'
        cells[CELL, 'm1'].write_text(yaml.safe_dump(wide))
        for markers, mapping in mappings.items():
            for session in (TRAIN, *VALIDATE):
                table = data_dir / f'qualisys_{session}_static_postures.csv'
                assert _quiet(['import-csv', str(table), '--mapping', str(mapping),
                               '--out', str(out / f'{session}-{markers}.mcap')]) == 0
        reasons, group_rows = [], []
        # Joint values by stamp, read once per session (the m1 bags have the same stamps).
        q_by_stamp = {s: poses(CELL, out / f'{s}-all.mcap') for s in (TRAIN, *VALIDATE)}
        q_train = np.array(list(q_by_stamp[TRAIN].values()))
        for name, cell_path, model, markers in RUNS:
            run = name.replace(', ', '-').replace(' ', '_')
            cell = cells.get((cell_path, markers), cell_path)
            code = _quiet(['identify', '--cell', str(cell), '--bag',
                           str(out / f'{TRAIN}-{markers}.mcap'),
                           '--out', str(out / run), '--model', model])
            assert code == 0, f'{name}: identify exited {code}'
            cal = yaml.safe_load((out / run / 'calibration.yaml').read_text())
            values = {p['name']: p for p in cal['parameters']}
            effects = '; '.join(
                f"{spec} ("
                + ', '.join(f"{n.rsplit('.', 1)[1]} = {values[n]['value']:.4g}"
                            + (f" ± {values[n]['std']:.2g}" if 'std' in values[n] else ' held')
                            for n in values if n.startswith(spec.replace(':', '.') + '.'))
                + ')' for spec in cal['effects']) or 'none'
            for session in VALIDATE:
                _quiet(['validate', '--cell', str(cell), '--calibration',
                        str(out / run / 'calibration.yaml'), '--bag',
                        str(out / f'{session}-{markers}.mcap'), '--out',
                        str(out / f'{run}-{session}')])
                doc = json.loads((out / f'{run}-{session}' / 'validation.json').read_text())
                group_rows.append(f"| `{name}` | {session} | " + peer_groups(
                    doc, q_by_stamp[session], q_train) + ' |')
                marker = doc['rms_per_reflector_m']
                outside = doc['outside_training_range']
                rows.append(
                    f"| `{name}` | {effects} | {cal['rms_m'] * 1e3:.2f} | {session} | "
                    f"{doc['rms_m'] * 1e3:.3f} | {doc['rms_inside_training_range_m'] * 1e3:.3f} "
                    f"({doc['rms_repeated_from_training_m'] * 1e3:.2f} / "
                    f"{doc['rms_new_inside_training_range_m'] * 1e3:.2f}) | "
                    f"{doc['rms_outside_training_range_m'] * 1e3:.3f} ({outside} of "
                    f"{doc['measurements']}) | {marker['m1'] * 1e3:.3f} | "
                    + (' / '.join(f'{marker[k] * 1e3:.2f}' for k in ('m2', 'm3', 'm4'))
                       if markers == 'all' else 'not observed') + ' |')
            if model == 'auto':
                reasons.append(f"{name}: {cal['model']['reason']}"
                               + (f" ({cal['prior']['description']})" if 'prior' in cal else ''))
    header = (
        '# Model choice on the smallest TIAGo session, validated on the other sessions\n\n'
        f'Calibrated on {TRAIN} (37 postures, 4 markers each, outlier exclusion on), validated '
        'with `kpi-calib validate` (rms in mm). auto chose on the training session alone; '
        + '; '.join(reasons) + '.\n\n'
        '`m1 only`: the peer toolbox\'s protocol, one marker observed in training and '
        'validation; its published figures (FIGAROH `full_params`, 31 parameters, macOS; 30 '
        'on Linux): 3.07 / 2.83 / 2.44 mm (Linux 3.22 / 3.00 / 2.56) on 2021-11-26 / '
        '-1403 / -1504.\n\n'
        '`tolerances`: test/data/tiago_mocap_cell_tolerances.yaml (identification.prior 1 mm, '
        '5 mrad, 50 mrad, weighed against the noise the residuals show).\n\n'
        f'Command: `.venv/bin/python bench/tiago_auto.py` ({time.time() - t0:.0f} s)\n\n'
        '| model | effects (fitted) | training rms | validated on | rms | inside training '
        'ranges (repeated / new poses) | outside (points) | m1 | m2 / m3 / m4 |\n'
        '|---|---|---|---|---|---|---|---|---|\n')
    groups = ('\n\nBy the posture groups of the peer\'s protocol (its definition: out of range '
              'when a joint is beyond the training range ± 0.05 rad or m, repeated when every '
              'joint is within 0.01 of a training posture, new otherwise; validate\'s own '
              'groups use the exact ranges), rms in mm over the observed markers (postures). '
              'The peer\'s `full_params` on 2021-11-26 / -1403 / -1504: repeated 2.34 / 2.03 / '
              '1.91, new 2.84 / 2.75 / 2.64, out of range 5.31 / 5.01 / 3.77.\n\n'
              '| model | validated on | repeated | new | out of range |\n|---|---|---|---|---|\n')
    return header + '\n'.join(rows) + groups + '\n'.join(group_rows) + '\n'


if __name__ == '__main__':
    beside = ROOT.parents[1] / 'shared' / 'data' / 'tiago_mocap'
    data = Path(sys.argv[1]) if len(sys.argv) > 1 else beside
    if not data.is_dir():
        data = Path('/work/shared/data/tiago_mocap')
    text = main_bench(data)
    (ROOT / 'bench' / 'results' / 'tiago_auto.md').write_text(text)
    print(text)

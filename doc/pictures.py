"""The pictures of the documentation, drawn by the tool itself (``make pictures``).

Runs ``kpi-calib`` (in this process, :func:`kpi_calib_ros.cli.main`) on the built-in
simulated cell and on the real data beside the repository (``../shared/data``: the UR10
laser-tracker Series A and the TIAGo motion-capture sessions), and copies the PNGs the
commands write into ``doc/_static/pictures/`` with ``manifest.json``: for every picture the
command that drew it, the data and their licence, and the sha256 of the source files of
the code that drew it (the plotting module and this script). ``test/test_doc_pictures.py``
fails when one of those files changed after the pictures were made, when a page shows a
picture that does not exist, or when a picture exists that no page shows.

    make pictures          # or: .venv/bin/python doc/pictures.py [DATA_DIR]

A few minutes on one free core; not part of ``make test``. ``make test-slow`` draws every
picture again into a temporary folder and compares it with the committed one.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.simulate import simulate_campaign, truth_cell_model
from kpi_calib_ros.cli import main as kpi_calib
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell, read_cell_document, write_cell_document
from kpi_calib_ros.io.design_io import read_design_poses
from kpi_calib_ros.io.results import read_truth

DOC = Path(__file__).resolve().parent
ROOT = DOC.parent
OUT = DOC / '_static' / 'pictures'
MANIFEST = OUT / 'manifest.json'
SCRIPT = 'doc/pictures.py'
# The plotting module of each kind of picture (repository paths).
REPORT_PLOTS = 'kpi_calib_ros/io/report_plots.py'
RESIDUAL_PLOTS = 'kpi_calib_ros/io/residual_plots.py'
DESIGN_IO = 'kpi_calib_ros/io/design_io.py'
CAMPAIGN_IO = 'kpi_calib_ros/io/campaign_io.py'
DRAWN_BY = {'identification.png': REPORT_PLOTS, 'validation_residuals.png': REPORT_PLOTS,
            'before_after.png': REPORT_PLOTS, 'periodogram.png': REPORT_PLOTS,
            'residuals_vs_joints.png': REPORT_PLOTS, 'residuals_vs_torque.png': REPORT_PLOTS,
            'joint_errors.png': REPORT_PLOTS, 'partial_residuals.png': RESIDUAL_PLOTS,
            'learned_residual.png': RESIDUAL_PLOTS, 'campaign_tcp_std.png': CAMPAIGN_IO,
            'change_test.png': CAMPAIGN_IO}
SIMULATED = 'the built-in simulated cell (kpi_calib_ros/data/cells/default_cell.yaml)'
UR10 = ('UR10 laser-tracker measurements, ipa_ur10 Series A (../shared/data/ipa_ur10, '
        'Christian Landgraf, MIT licence), every 40th of the 11911 postures')
TIAGO = ('TIAGo motion capture, {session} (../shared/data/tiago_mocap, Thanh Nguyen / CNRS '
         '/ Toward, FIGAROH data, Apache-2.0 licence)')
UR10_STEP = 40


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


class Pictures:
    """Runs the commands and collects their pictures into ``OUT``."""

    def __init__(self, work: Path) -> None:
        self.work = work
        self.entries: dict[str, dict] = {}

    def run(self, *argv: str, expect: tuple[int, ...] = (0,)) -> str:
        """``kpi-calib argv``; its stdout (kept in the work folder's log)."""
        buffer = io.StringIO()
        start = time.perf_counter()
        with contextlib.redirect_stdout(buffer), contextlib.redirect_stderr(io.StringIO()):
            code = kpi_calib(list(argv))
        text = buffer.getvalue()
        print(f'kpi-calib {argv[0]} ({time.perf_counter() - start:.0f} s, exit {code})',
              flush=True)
        with open(self.work / 'commands.log', 'a') as log:
            log.write(f'$ kpi-calib {" ".join(argv)}\n{text}\n')
        if code not in expect:
            raise SystemExit(f'kpi-calib {" ".join(argv)} exited {code}:\n{text}')
        return text

    def keep(self, folder: Path, png: str, name: str, command: str, data: str,
             drawn_by: str | None = None) -> None:
        """Copy ``folder/png`` to ``OUT/name.png`` and record it."""
        shutil.copyfile(folder / png, OUT / f'{name}.png')
        module = drawn_by or DRAWN_BY[png]
        self.entries[f'{name}.png'] = {
            'written_by_the_tool_as': png, 'command': command, 'data': data,
            'sources': {p: sha256(ROOT / p) for p in (module, SCRIPT)},
            'png_sha256': sha256(OUT / f'{name}.png')}


def cells(work: Path) -> tuple[Path, Path]:
    """The built-in cell with a quick design (300 candidates, no IPOPT refinement), and
    the same with the reflector on an adapter and a hidden joint-2 compliance (as
    ``kpi-calib demo``)."""
    doc = read_cell_document(DEFAULT_CELL)
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['design'] = {'candidates': 300, 'nlp': False}
    cell = write_cell_document(work / 'cell.yaml', doc)
    doc['reflector']['offset'] = [0.05, 0.0, 0.06]
    doc['simulation'] = {'hidden_effects': {'joint_compliance:joint_2': {'c': 4.0e-7}}}
    return cell, write_cell_document(work / 'hidden.yaml', doc)


def simulated(p: Pictures) -> None:
    w = p.work
    cell, hidden = cells(w)
    c, h = str(cell), str(hidden)
    p.run('simulate', '--cell', c, '--n', '60', '--seed', '7', '--out', str(w / 'run.mcap'))
    p.run('identify', '--cell', c, '--bag', str(w / 'run.mcap'), '--out', str(w / 'result'))
    p.keep(w / 'result', 'identification.png', 'sim_identification',
           'kpi-calib identify --cell CELL.yaml --bag run.mcap --out result/', SIMULATED)
    p.run('design', '--cell', c, '--n', '20', '--criterion', 'kpi',
          '--out', str(w / 'design.yaml'))
    p.keep(w, 'design_poses.png', 'sim_design_poses',
           'kpi-calib design --cell CELL.yaml --n 20 --criterion kpi --out design.yaml',
           SIMULATED, DESIGN_IO)
    p.keep(w, 'design_ellipsoids.png', 'sim_design_ellipsoids',
           'kpi-calib design --cell CELL.yaml --n 20 --criterion kpi --out design.yaml',
           SIMULATED, DESIGN_IO)
    # The same robot (same seed) measured again at the designed poses.
    p.run('simulate', '--cell', c, '--seed', '7', '--poses', str(w / 'design.yaml'),
          '--n', '20', '--out', str(w / 'new.mcap'))
    p.run('validate', '--cell', c, '--calibration', str(w / 'result' / 'calibration.yaml'),
          '--bag', str(w / 'new.mcap'), '--out', str(w / 'val'), expect=(0, 1))
    p.keep(w / 'val', 'validation_residuals.png', 'sim_validation_residuals',
           'kpi-calib validate --cell CELL.yaml --calibration result/calibration.yaml '
           '--bag new.mcap --out val/', SIMULATED)
    # The missing effect: the robot's joint 2 bends, the model does not know it.
    p.run('simulate', '--cell', h, '--n', '80', '--seed', '8', '--out', str(w / 'hidden.mcap'))
    p.run('diagnose', '--cell', h, '--bag', str(w / 'hidden.mcap'), '--out', str(w / 'diag'))
    command = 'kpi-calib diagnose --cell hidden.yaml --bag run.mcap --out diag/'
    data = SIMULATED + ' with a hidden joint_compliance:joint_2'
    for png in ('before_after.png', 'partial_residuals.png', 'periodogram.png',
                'residuals_vs_joints.png', 'residuals_vs_torque.png', 'joint_errors.png',
                'learned_residual.png'):
        p.keep(w / 'diag', png, 'sim_diagnose_' + png[:-4], command, data)
    # A sequential campaign against a simulated robot.
    p.run('campaign', '--cell', c, '--target-std', '1e-5', '--simulate', '--seed', '0',
          '--out', str(w / 'campaign'), expect=(0, 1))
    p.keep(w / 'campaign', 'campaign_tcp_std.png', 'sim_campaign_tcp_std',
           'kpi-calib campaign --cell CELL.yaml --target-std 1e-5 --simulate --out camp/',
           SIMULATED)
    # A work cycle: ten poses designed with the calibration as prior, the same robot an
    # hour later.
    prior = str(w / 'result' / 'calibration.yaml')
    p.run('design', '--cell', c, '--n', '10', '--prior', prior, '--hours', '1',
          '--out', str(w / 'design10.yaml'))
    p.keep(w, 'design10_ellipsoids.png', 'sim_cycle_design_ellipsoids',
           'kpi-calib design --cell CELL.yaml --n 10 --prior result/calibration.yaml '
           '--hours 1 --out design10.yaml', SIMULATED, DESIGN_IO)
    p.run('simulate', '--cell', c, '--seed', '7', '--poses', str(w / 'design10.yaml'),
          '--n', '10', '--out', str(w / 'cycle.mcap'))
    p.run('identify', '--cell', c, '--bag', str(w / 'cycle.mcap'), '--prior', prior,
          '--out', str(w / 'cycle'), expect=(0, 1, 3))
    p.keep(w / 'cycle', 'change_test.png', 'sim_cycle_change_test',
           'kpi-calib identify --cell CELL.yaml --bag cycle2.mcap --out result2/ '
           '--prior result/calibration.yaml', SIMULATED)
    # The same robot after a collision bent joint 2's placement by 1 mm (as
    # examples/work_cycle.py): simulated as kpi-calib simulate does, with that robot.
    cm, _ = truth_cell_model(load_cell(cell))
    truth = read_truth(w / 'run.mcap')['parameters']
    bent = np.array([truth[name] for name in cm.model.params.names])
    bent[cm.model.params.names.index('joint_2.placement.tx')] += 1.0e-3
    simulate_campaign(cell, 10, w / 'bent.mcap', 9, poses=read_design_poses(
        w / 'design10.yaml'), cm=cm, p_true=bent)
    p.run('identify', '--cell', c, '--bag', str(w / 'bent.mcap'), '--prior', prior,
          '--out', str(w / 'bent'), expect=(3,))
    p.keep(w / 'bent', 'change_test.png', 'sim_cycle_change_bent',
           'kpi-calib identify --cell CELL.yaml --bag cycle3.mcap --out result3/ '
           '--prior result/calibration.yaml',
           SIMULATED + ', joint_2.placement.tx bent by 1 mm')


def _every(source: Path, target: Path, step: int, start: int) -> Path:
    """Every ``step``-th row of a table from row ``start`` (header kept)."""
    lines = source.read_bytes().split(b'\r\n')
    body = [line for line in lines[1:] if line][start::step]
    target.write_bytes(b'\r\n'.join([lines[0], *body]) + b'\r\n')
    return target


def ur10(p: Pictures, data: Path) -> None:
    w = p.work
    grid = data / 'ipa_ur10' / 'Series_A' / 'measurements_grid.csv'
    mapping = str(ROOT / 'test' / 'data' / 'ipa_ur10_mapping.yaml')
    cell = str(ROOT / 'test' / 'data' / 'ipa_ur10_cell.yaml')
    for part, start in (('a', 0), ('b', UR10_STEP // 2)):
        table = _every(grid, w / f'ur10_{part}.csv', UR10_STEP, start)
        p.run('import-csv', str(table), '--mapping', mapping, '--out', str(w / f'ur10_{part}.mcap'))
    p.run('diagnose', '--cell', cell, '--bag', str(w / 'ur10_a.mcap'),
          '--out', str(w / 'ur10_diag'))
    command = 'kpi-calib diagnose --cell test/data/ipa_ur10_cell.yaml --bag ur10.mcap --out diag/'
    for png in ('before_after.png', 'partial_residuals.png', 'periodogram.png'):
        p.keep(w / 'ur10_diag', png, 'ur10_diagnose_' + png[:-4], command, UR10)
    p.run('identify', '--cell', cell, '--bag', str(w / 'ur10_a.mcap'), '--out', str(w / 'ur10_cal'),
          expect=(0, 1))
    p.keep(w / 'ur10_cal', 'identification.png', 'ur10_identification',
           'kpi-calib identify --cell test/data/ipa_ur10_cell.yaml --bag ur10.mcap --out result/',
           UR10)
    p.run('validate', '--cell', cell, '--calibration', str(w / 'ur10_cal' / 'calibration.yaml'),
          '--bag', str(w / 'ur10_b.mcap'), '--out', str(w / 'ur10_val'), expect=(0, 1))
    p.keep(w / 'ur10_val', 'validation_residuals.png', 'ur10_validation_residuals',
           'kpi-calib validate --cell test/data/ipa_ur10_cell.yaml --calibration '
           'result/calibration.yaml --bag other_postures.mcap --out val/',
           UR10 + '; validated on the postures half-way between')


def tiago(p: Pictures, data: Path) -> None:
    w = p.work
    mapping = str(ROOT / 'test' / 'data' / 'tiago_mocap_mapping.yaml')
    cell = str(ROOT / 'test' / 'data' / 'tiago_mocap_cell_tolerances.yaml')
    for day in ('2021-11-30', '2021-11-26'):
        p.run('import-csv', str(data / 'tiago_mocap' / f'qualisys_{day}_static_postures.csv'),
              '--mapping', mapping, '--out', str(w / f'tiago_{day}.mcap'))
    train = str(w / 'tiago_2021-11-30.mcap')
    p.run('diagnose', '--cell', cell, '--bag', train, '--out', str(w / 'tiago_diag'))
    command = ('kpi-calib diagnose --cell test/data/tiago_mocap_cell_tolerances.yaml '
               '--bag tiago.mcap --out diag/')
    session = TIAGO.format(session='the 37 postures of 2021-11-30')
    for png in ('before_after.png', 'partial_residuals.png', 'learned_residual.png'):
        p.keep(w / 'tiago_diag', png, 'tiago_diagnose_' + png[:-4], command, session)
    # The cell's model (geometric with the nominal tolerances); --model auto takes
    # minutes more and is measured in doc/guide/real_data.md.
    p.run('identify', '--cell', cell, '--bag', train, '--out', str(w / 'tiago_cal'),
          expect=(0, 1))
    p.keep(w / 'tiago_cal', 'identification.png', 'tiago_identification',
           'kpi-calib identify --cell test/data/tiago_mocap_cell_tolerances.yaml '
           '--bag tiago.mcap --out result/', session)
    p.run('validate', '--cell', cell, '--calibration', str(w / 'tiago_cal' / 'calibration.yaml'),
          '--bag', str(w / 'tiago_2021-11-26.mcap'), '--out', str(w / 'tiago_val'), expect=(0, 1))
    p.keep(w / 'tiago_val', 'validation_residuals.png', 'tiago_validation_residuals',
           'kpi-calib validate --cell test/data/tiago_mocap_cell_tolerances.yaml '
           '--calibration result/calibration.yaml --bag other_session.mcap --out val/',
           session + '; validated on the 62 postures of 2021-11-26')


def main(argv: list[str]) -> int:
    data = Path(argv[0]) if argv else ROOT.parent / 'shared' / 'data'
    if not data.is_dir():
        data = Path('/work/shared/data')
    if not (data / 'ipa_ur10').is_dir() or not (data / 'tiago_mocap').is_dir():
        print(f'error: {data} holds no ipa_ur10/ and tiago_mocap/ (the real data); give '
              'their folder: python doc/pictures.py DATA_DIR', file=sys.stderr)
        return 2
    OUT.mkdir(parents=True, exist_ok=True)
    for old in OUT.glob('*.png'):
        old.unlink()
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        p = Pictures(Path(tmp))
        simulated(p)
        ur10(p, data)
        tiago(p, data)
        (ROOT / 'build').mkdir(exist_ok=True)  # what each command printed, to read
        shutil.copyfile(Path(tmp) / 'commands.log', ROOT / 'build' / 'pictures_commands.log')
    MANIFEST.write_text(json.dumps(dict(sorted(p.entries.items())), indent=1,
                                   ensure_ascii=False) + '\n')
    size = sum(f.stat().st_size for f in OUT.glob('*.png'))
    print(f'{len(p.entries)} pictures, {size / 1e6:.2f} MB, in {OUT} '
          f'({time.perf_counter() - start:.0f} s)')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

"""Design time with stock mesh URDFs (UR10 and Panda from example-robot-data).

``kpi-calib design`` on the test cells test/data/{ur10,panda}_mesh_cell.yaml (no
capsules, no ignore_pairs; N = 24, criterion kpi, seed 0) and on the hand-capsule
cells beside them, timed stage by stage with perf_counter: cell model, geometry
(mesh resolution + capsule fitting + 2000-sample collision matrix, first call;
cached afterwards), the design itself (candidates, exchange, IPOPT, coal check) and
the mesh check of the result. Writes bench/results/design_mesh.md.

Usage: .venv/bin/python bench/design_mesh.py
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app import robot_geometry
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.design import mesh_verified
from kpi_calib_ros.core.design.optimum import design_measurements
from kpi_calib_ros.io.cell import load_cell

DATA = Path(__file__).resolve().parents[1] / 'test' / 'data'
N = 24


def run(cell_file: Path) -> dict:
    robot_geometry._CACHE.clear()  # time the geometry from scratch
    t0 = time.perf_counter()
    cm = build_cell_model(load_cell(cell_file))
    t1 = time.perf_counter()
    geometry = cm.robot_geometry()
    t2 = time.perf_counter()
    result = design_measurements(cm.design_cell(), N, 'kpi', np.random.default_rng(0),
                                 cm.design_settings)
    t3 = time.perf_counter()
    result, doc = mesh_verified(cm, result)
    t4 = time.perf_counter()
    return {'model': t1 - t0, 'geometry': t2 - t1, 'design': t3 - t2, 'mesh': t4 - t3,
            'total': t4 - t0, 'objective': result.objective, 'ok': result.verification.ok,
            'collisions': doc['mesh_check']['in_collision'], 'capsules': len(geometry.capsules),
            'skipped': len(geometry.skip_pairs()), 'stages': result.timings}


def main() -> int:
    lines = ['# Design time with stock mesh URDFs (example-robot-data)', '',
             'Command: `.venv/bin/python bench/design_mesh.py`; '
             f'{os.cpu_count()} cores shared with other work; one run per cell, N = {N}, '
             'criterion kpi, seed 0, cell `design:` settings (1500 candidates, 150 IPOPT '
             'iterations).', '',
             '| cell | capsules | skipped pairs | model s | geometry s (resolve + fit + '
             'matrix) | design s (candidates / exchange / nlp / verify) | mesh check s | '
             'total s | KPI trace m² | mesh collisions | verified |',
             '|---|---|---|---|---|---|---|---|---|---|---|']
    for cell in ('ur10_mesh_cell', 'ur10_hand_cell', 'panda_mesh_cell', 'panda_hand_cell'):
        r = run(DATA / f'{cell}.yaml')
        s = r['stages']
        stages = ' / '.join(f"{s.get(k, 0.0):.1f}" for k in ('candidates', 'exchange', 'nlp',
                                                              'verify'))
        print(f"{cell}: total {r['total']:.1f} s (geometry {r['geometry']:.1f} s, design "
              f"{r['design']:.1f} s, mesh {r['mesh']:.2f} s), KPI {r['objective']:.4e}, "
              f"{r['collisions']}/{N} in mesh collision", flush=True)
        lines.append(f"| {cell} | {r['capsules']} | {r['skipped']} | {r['model']:.2f} | "
                     f"{r['geometry']:.2f} | {r['design']:.1f} ({stages}) | {r['mesh']:.2f} | "
                     f"{r['total']:.1f} | {r['objective']:.4e} | {r['collisions']}/{N} | "
                     f"{'yes' if r['ok'] else 'NO'} |")
    lines += ['', 'Stage figures in brackets are DesignResult.timings. Geometry is built once '
              'per cell and cached; with hand-given capsules only the carried links (hand, '
              'fingers, ee_link) are fitted. The machine load varies between rows.']
    out = Path(__file__).resolve().parent / 'results' / 'design_mesh.md'
    out.write_text('\n'.join(lines) + '\n')
    print(f'written: {out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())

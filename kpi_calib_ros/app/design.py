"""Measurement design for a cell: the ``kpi-calib design`` command and the node's ``~/design``.

Builds the typed design problem from the cell (:meth:`CellModel.design_cell`),
uses the cell file's ``design:`` settings, and writes design.yaml and its plots.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from kpi_calib_ros.core.design import DesignResult, design_context, design_measurements
from kpi_calib_ros.io.cell import CellModel, build_cell_model, load_cell
from kpi_calib_ros.io.design_io import plot_design, plot_ellipsoids, summary_text, write_design


def design_cell_model(cm: CellModel, n: int, criterion: str, seed: int,
                      progress: Callable[[str], None] | None = None) -> DesignResult:
    """N configurations optimal for ``criterion`` in the cell of ``cm`` (its ``design:``
    settings), drawn with ``numpy.random.default_rng(seed)``."""
    return design_measurements(cm.design_cell(), n, criterion, np.random.default_rng(seed),
                               cm.cell.design, progress=progress)


def run_design(cell_path: str | Path, n: int, criterion: str, out: str | Path,
               seed: int = 0, allow_code_effects: bool = False) -> int:
    """``kpi-calib design``: design.yaml, ``<stem>_poses.png`` and ``<stem>_ellipsoids.png``
    (heuristic vs this design) and a summary on stdout.

    Returns 0, or 1 when the independent verification failed.
    """
    cm = build_cell_model(load_cell(cell_path, allow_code_effects=allow_code_effects))
    cell, settings = cm.design_cell(), cm.cell.design
    rng = np.random.default_rng(seed)
    context = design_context(cell, rng, settings)
    print(f'{context.candidates.configurations.shape[0]} feasible candidates from '
          f'{context.candidates.draws} draws ({context.seconds:.1f} s)')
    result = design_measurements(cell, n, criterion, rng, settings, context=context,
                                 progress=print)
    baseline = result if criterion == 'random' else design_measurements(
        cell, n, 'random', rng, settings, context=context)
    out = Path(out)
    write_design(out, result)
    stem = out.with_suffix('')
    poses_png = plot_design(cell, context.check_scene, result, f'{stem}_poses.png')
    shown = [baseline] if result is baseline else [baseline, result]
    names = ['heuristic'] if result is baseline else ['heuristic', f'{criterion}-optimal']
    ell_png = plot_ellipsoids(shown, names, f'{stem}_ellipsoids.png')
    print(summary_text(result, None if result is baseline else baseline))
    print(f'written: {out}, {poses_png}, {ell_png}')
    return 0 if result.verification.ok else 1

"""An effect's shape parameters the data leave undetermined, held on its grid.

An effect nonlinear in a shape parameter (``joint_play``'s transition torque τ0 = e^u) has
a size the data determine and a shape they may not: a true backlash is a play whose τ0 lies
below every measured torque, and any τ0 there fits alike. ``auto`` and ``diagnose`` hold such
a shape at the best plausible point of its grid (the screen's); a calibration with the effect
named by the user (``--effects``, the cell's ``effects``) was refused instead ("u not
determined"), though ``diagnose`` had told the user to add it.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from kpi_calib_ros.app.calibration_document import CellCalibration
from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.core.diagnosis.model_selection import ModelChoice
from kpi_calib_ros.core.effects.registry import BoundEffect

__all__ = ['hold_undetermined_shapes']


def hold_undetermined_shapes(cal: CellCalibration, cm: CellModel, choice: ModelChoice,
                             start: np.ndarray,
                             refit: Callable[[ModelChoice, np.ndarray], CellCalibration]
                             ) -> CellCalibration:
    """Return ``cal`` refitted with the refused effects' shape parameters held on their grid.

    ``cal``: a calibration the gate refused; the effects of ``cm`` whose shape parameters it
    names (undetermined, beyond their bound), and none of their size parameters, are
    refitted with those held at each point of their grid (``refit(choice, start)``, the
    same final fit); the valid one with the lowest χ² is returned, its ``model.held`` and
    reason saying so. ``cal`` itself when no effect with a shape is named or no grid point
    gives a valid calibration.
    """
    names = list(cm.model.params.names)

    def named(which: set[str]) -> bool:
        return any(n in problem for problem in cal.problems for n in which)
    # Only a shape the data leave free while its size is determined (a backlash's τ0): a
    # play whose size the poses cannot see either (its joint's torque never changes sign)
    # is refused, as it was; held, its size came out at 2.4 mrad from no evidence.
    effects = [e for e in cm.model.effects if isinstance(e, BoundEffect) and e.shape_names
               and named(set(e.shape_names))
               and not named(set(e.parameter_names) - set(e.shape_names))]
    if not effects:
        return cal
    best: tuple[CellCalibration, list[str], tuple[float, ...]] | None = None
    for effect in effects:
        shape = list(effect.shape_names)
        for point in effect.kind.shape_grid:
            p0 = np.array(start, float)
            p0[[names.index(n) for n in shape]] = point
            trial = refit(dataclasses.replace(
                choice, held=tuple(choice.held) + tuple(shape)), p0)
            if trial.valid and (best is None or trial.result.chi2 < best[0].result.chi2):
                best = (trial, shape, point)
    if best is None:
        return cal
    trial, shape, point = best
    values = ', '.join(f'{n} = {v:.3g}' for n, v in zip(shape, point))
    why = next(p for p in cal.problems if any(n in p for n in shape))
    return dataclasses.replace(trial, choice=dataclasses.replace(trial.choice, reason=(
        f'{trial.choice.reason}; {", ".join(shape)} held at the point of its grid that fits '
        f'best ({values}): with it free the calibration was refused ({why})')))

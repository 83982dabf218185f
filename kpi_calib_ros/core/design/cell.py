"""The typed problem a measurement design is computed for: one cell, numerically.

Built by :meth:`kpi_calib_ros.app.cell_model.CellModel.design_cell` from a validated
cell file; the design modules take this object and nothing from the YAML.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from kpi_calib_ros.core.collision.capsules import CollisionScene
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.model.robot import RobotModel

__all__ = ['DesignCell']


@dataclass(frozen=True)
class DesignCell:
    """Everything eq. (24) needs about a cell (SI units, robot base frame).

    Attributes
    ----------
    model : MeasurementModel
        Measurement model at the nominal parameters ``model.params.nominal``.
    q_work : (t, n) ndarray
        Working poses in chain order (rad); their TCP points are the KPI.
    working_pose_names : tuple of str
    tracker_in_base : (4, 4) ndarray
        Nominal tracker pose in the robot base frame.
    reflector_offset : (3,) ndarray
        Nominal reflector centre in the tip frame (m).
    max_incidence : float
        Largest admissible angle between beam and reflector axis (rad, eq. 4).
    sigma : (3,) ndarray
        Tracker noise per axis (m).
    identification_method : {'pivoted', 'priority'}
    identification_priority : tuple of str
        Parameter order of the ``'priority'`` selection.
    scene : CollisionScene
        Robot capsules and obstacles (all pairs; the design may ignore some).
    tau_work : (t, n) ndarray or None
        Torques at the working poses, each with the payload it carries there (N m); None:
        the gravity torques with the cell's payload.
    accept : callable or None
        Which configurations the robot can take beyond the capsules (its meshes in no
        contact): candidates and the refined design are held to it. Capsules fitted to a
        link overlap their neighbour's in every pose, so the pair is skipped, while the
        meshes touch in some (a Baxter's shoulder and elbow in 62 % of random poses).
    """

    model: MeasurementModel
    q_work: np.ndarray
    working_pose_names: tuple[str, ...]
    tracker_in_base: np.ndarray
    reflector_offset: np.ndarray
    max_incidence: float
    sigma: np.ndarray
    identification_method: str
    identification_priority: tuple[str, ...]
    scene: CollisionScene
    tau_work: np.ndarray | None = None
    # (N, n) configurations -> (N,) bool: those the robot can take beyond the capsules'
    # judgement (its collision meshes); None: the capsules decide alone.
    accept: Callable[[np.ndarray], np.ndarray] | None = field(default=None, compare=False)

    @property
    def robot(self) -> RobotModel:
        """The kinematic chain of the measurement model."""
        return self.model.robot

    @property
    def reflector_axis(self) -> np.ndarray:
        """Reflector axis (3,) in the tip frame."""
        return self.model.reflector_axis

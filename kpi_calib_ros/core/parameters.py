"""Error parameters: the named vector p that calibration estimates.

Every parameter has a stable string name that appears in outputs, plots and
reports. The geometric set is general for any URDF chain:

* ``base.{x,y,z,roll,pitch,yaw}`` -- pose of the robot base frame in the
  tracker frame (full values; URDF roll-pitch-yaw convention), 6;
* ``<joint>.placement.{tx,ty,tz,rx,ry,rz}`` -- a small 6-DoF error applied to
  every joint placement after the nominal URDF origin, 6 per joint;
* ``<joint>.offset`` -- joint zero offset, 1 per joint;
* ``reflector.{x,y,z}`` -- reflector centre in the tip frame (full values), 3.

Many of these are redundant for position-only tracker data; the identifiable
subset is chosen by :mod:`kpi_calib_ros.core.identifiability`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kpi_calib_ros.core.robot import RobotModel

PLACEMENT_COMPONENTS = ('tx', 'ty', 'tz', 'rx', 'ry', 'rz')
BASE_COMPONENTS = ('x', 'y', 'z', 'roll', 'pitch', 'yaw')


@dataclass(frozen=True)
class ParameterSet:
    """Names, nominal values and units of a parameter vector.

    Attributes
    ----------
    names : tuple of str
        Stable parameter names, in vector order.
    nominal : (n_p,) ndarray
        Nominal (prior) values.
    units : tuple of str
        ``'m'``, ``'rad'`` or the unit of an effect parameter.
    """

    names: tuple[str, ...]
    nominal: np.ndarray
    units: tuple[str, ...]

    def __post_init__(self) -> None:
        if len(set(self.names)) != len(self.names):
            raise ValueError('parameter names must be unique')
        if not (len(self.names) == len(self.nominal) == len(self.units)):
            raise ValueError('names, nominal and units must have equal length')

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Position of ``name`` in the vector; KeyError naming the parameter."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f'unknown parameter {name!r}') from None

    def indices(self, names: list[str] | tuple[str, ...]) -> np.ndarray:
        return np.array([self.index(n) for n in names], dtype=int)

    def extended(self, names: list[str], nominal: np.ndarray,
                 units: list[str]) -> 'ParameterSet':
        """A new set with extra parameters appended (e.g. a physical effect's)."""
        return ParameterSet(self.names + tuple(names),
                            np.concatenate([self.nominal, np.asarray(nominal, float)]),
                            self.units + tuple(units))

    def with_values(self, values: dict[str, float]) -> np.ndarray:
        """Nominal vector with the named entries replaced."""
        p = self.nominal.copy()
        for name, value in values.items():
            p[self.index(name)] = value
        return p


def geometric_parameters(robot: RobotModel, base_in_tracker: np.ndarray,
                         reflector_offset: np.ndarray) -> ParameterSet:
    """The full geometric parameter set of ``robot`` in a laser-tracker cell.

    Parameters
    ----------
    robot : RobotModel
    base_in_tracker : (6,) array
        Nominal [x, y, z, roll, pitch, yaw] of the base frame in the tracker
        frame (m, rad).
    reflector_offset : (3,) array
        Nominal reflector centre in the tip frame (m).
    """
    names: list[str] = [f'base.{c}' for c in BASE_COMPONENTS]
    nominal: list[float] = list(np.asarray(base_in_tracker, float))
    units: list[str] = ['m'] * 3 + ['rad'] * 3
    for joint in robot.joints:
        names += [f'{joint.name}.placement.{c}' for c in PLACEMENT_COMPONENTS]
        nominal += [0.0] * 6
        units += ['m'] * 3 + ['rad'] * 3
        names.append(f'{joint.name}.offset')
        nominal.append(0.0)
        units.append('m' if joint.kind == 'prismatic' else 'rad')
    names += ['reflector.x', 'reflector.y', 'reflector.z']
    nominal += list(np.asarray(reflector_offset, float))
    units += ['m'] * 3
    return ParameterSet(tuple(names), np.array(nominal), tuple(units))

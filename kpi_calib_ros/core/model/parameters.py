"""Error parameters: the named vector p that calibration estimates.

Every parameter has a stable string name that appears in outputs, plots and
reports. The geometric set is general for any URDF chain:

* ``base.{x,y,z,roll,pitch,yaw}`` -- pose of the robot base frame in the
  tracker frame (full values; URDF roll-pitch-yaw convention), 6;
* ``<joint>.placement.{tx,ty,tz,rx,ry,rz}`` -- a small 6-DoF error applied to
  every joint placement after the nominal URDF origin, 6 per joint;
* ``<joint>.offset`` -- joint zero offset, 1 per joint;
* ``reflector.{x,y,z}`` -- reflector centre in the tip frame (full values), 3;
  with several reflectors (or mocap markers) on the tool, one triple per
  reflector: ``reflector.<name>.{x,y,z}``, in the cell's order;
* ``recording.<name>.base.*`` (and ``recording.<name>.<reflector prefix>.*``) -- the
  placement of a further recording (tracker set-up) identified with the first
  (:mod:`kpi_calib_ros.core.measurement.recordings`), appended after the reflectors.

Many of these are redundant for position-only tracker data; the identifiable
subset is chosen by :mod:`kpi_calib_ros.core.estimation.identifiability`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kpi_calib_ros.core.model.robot import RobotModel

__all__ = [
    'PLACEMENT_COMPONENTS', 'BASE_COMPONENTS', 'RECORDING_PREFIX', 'ParameterSet',
    'reflector_prefixes', 'recording_names', 'geometric_parameters',
]

PLACEMENT_COMPONENTS = ('tx', 'ty', 'tz', 'rx', 'ry', 'rz')
BASE_COMPONENTS = ('x', 'y', 'z', 'roll', 'pitch', 'yaw')
# Parameters of the recordings after the first (kpi_calib_ros.core.measurement.recordings).
RECORDING_PREFIX = 'recording.'


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
        """Check that the names are unique and names, nominal and units have one length."""
        if len(set(self.names)) != len(self.names):
            raise ValueError('parameter names must be unique')
        if not (len(self.names) == len(self.nominal) == len(self.units)):
            raise ValueError('names, nominal and units must have equal length')

    def __len__(self) -> int:
        """Return the number of parameters."""
        return len(self.names)

    def index(self, name: str) -> int:
        """Position of ``name`` in the vector; KeyError naming the parameter."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f'unknown parameter {name!r}') from None

    def indices(self, names: list[str] | tuple[str, ...]) -> np.ndarray:
        """Positions (len(names),) of ``names`` in the vector; KeyError naming an unknown one."""
        return np.array([self.index(n) for n in names], dtype=int)

    def extended(self, names: list[str], nominal: np.ndarray,
                 units: list[str]) -> 'ParameterSet':
        """Return a new set with extra parameters appended (e.g. a physical effect's)."""
        return ParameterSet(self.names + tuple(names),
                            np.concatenate([self.nominal, np.asarray(nominal, float)]),
                            self.units + tuple(units))

    def with_values(self, values: dict[str, float]) -> np.ndarray:
        """Nominal vector with the named entries replaced."""
        p = self.nominal.copy()
        for name, value in values.items():
            p[self.index(name)] = value
        return p


def reflector_prefixes(params: ParameterSet) -> list[str]:
    """Name prefixes of the reflector triples of ``params``, in vector order.

    ``['reflector']`` for the single-reflector form, ``['reflector.a', 'reflector.b']``
    for named reflectors; reflector index ``k`` everywhere is position ``k`` here.
    """
    return [n[:-2] for n in params.names if n.startswith('reflector.') and n.endswith('.x')]


def recording_names(params: ParameterSet) -> list[str]:
    """Names of the recordings after the first that ``params`` places, in vector order."""
    suffix = '.base.x'
    return [n[len(RECORDING_PREFIX):-len(suffix)] for n in params.names
            if n.startswith(RECORDING_PREFIX) and n.endswith(suffix)]


def geometric_parameters(robot: RobotModel, base_in_tracker: np.ndarray,
                         reflector_offset: np.ndarray,
                         reflector_names: tuple[str, ...] | None = None) -> ParameterSet:
    """Return the full geometric parameter set of ``robot`` in a laser-tracker cell.

    Parameters
    ----------
    robot : RobotModel
    base_in_tracker : (6,) array
        Nominal [x, y, z, roll, pitch, yaw] of the base frame in the tracker
        frame (m, rad).
    reflector_offset : (3,) or (R, 3) array
        Nominal reflector centre(s) in the tip frame (m).
    reflector_names : tuple of str, optional
        Names of the R reflectors (``reflector.<name>.x`` …); None: one unnamed
        reflector (``reflector.x`` …).
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
    offsets = np.asarray(reflector_offset, float).reshape(-1, 3)
    if reflector_names is None:
        if len(offsets) != 1:
            raise ValueError('several reflector offsets need reflector_names')
        prefixes = ['reflector']
    else:
        if len(reflector_names) != len(offsets) or len(set(reflector_names)) != len(offsets):
            raise ValueError('reflector_names must be unique, one per offset')
        prefixes = [f'reflector.{n}' for n in reflector_names]
    for prefix, offset in zip(prefixes, offsets):
        names += [f'{prefix}.x', f'{prefix}.y', f'{prefix}.z']
        nominal += list(offset)
        units += ['m'] * 3
    return ParameterSet(tuple(names), np.array(nominal), tuple(units))

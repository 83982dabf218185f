"""A measured tilt: the frame of a joint turned by an angle an inclinometer recorded.

A column, a gantry or a mobile base leans against its footing by an angle that changes
from stop to stop (the load moves, the ground gives, the sun warms one side); an
accelerometer or inclinometer on it records that angle at every stop. The effect reads
the two recorded angles as covariates (:mod:`kpi_calib_ros.core.measurement.covariates`)::

    measured_tilt:<joint>[:<sensor>]   joint j's frame, as placed and before its motion,
                                       turned about its origin by g_x·t_x about the base's
                                       x axis and g_y·t_y about its y axis     g_x, g_y  1

``t_x``, ``t_y`` (rad) are the covariates ``tilt.<sensor>.x`` and ``tilt.<sensor>.y`` (the
tilt about the base frame's x and y axes; ``tilt.x``, ``tilt.y`` without a sensor name).
The turn is R = R_x(g_x·t_x)·R_y(g_y·t_y) in the base axes, the x turn applied last: the
other order differs by t_x·t_y (1.5e-3 rad at 50 and 30 mrad, a millimetre at a metre; 4e-6
rad at 2 mrad).
Everything from joint j on turns with its frame. The gains are identified: 1 when the
sensor measures exactly the turn of the frame, less when it sits on a stiffer part, of the
other sign when it is mounted the other way round; 1/3 ≤ |g| ≤ 3 plausible (a sensor that
reads a third of the turn, or three times it, is mounted elsewhere than the effect is bound;
a gain of 1e-3 is a reading in milliradians stated as radians). The constant part of the
tilt, the angle at which the frame stands as the URDF states, is the geometric placement of
joint j (the base pose for the first joint), identified with the geometry: a separate offset
parameter would be that placement twice and never distinguishable from it. Parameters
``measured_tilt.<joint>.<sensor>.gx``, ``.gy``.

The diagnosis proposes the effect at every joint for each sensor whose two angles the
measurements carry (:data:`~kpi_calib_ros.core.effects.registry.COVARIATE_CANDIDATES`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable

import casadi as ca
import numpy as np

from kpi_calib_ros.core.effects.effect_types import BoundEffect, EffectType
from kpi_calib_ros.core.effects.registry import ARGUMENT_EFFECTS, COVARIATE_CANDIDATES
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.model.kinematics import axis_rotation
from kpi_calib_ros.core.model.robot import RobotModel

__all__ = ['MEASURED_TILT', 'TILT_PREFIX', 'GAIN_BOUND', 'MeasuredTilt', 'measured_tilt',
           'tilt_covariates', 'tilt_sensors', 'tilt_candidates']

MEASURED_TILT = 'measured_tilt'
TILT_PREFIX = 'tilt.'
GAIN_BOUND = 3.0


def tilt_covariates(sensor: str) -> tuple[str, str]:
    """Return the covariate names of a tilt sensor: ``tilt.<sensor>.x``, ``tilt.<sensor>.y``.

    ``tilt.x``, ``tilt.y`` for the unnamed sensor ``''``.
    """
    stem = TILT_PREFIX + (f'{sensor}.' if sensor else '')
    return stem + 'x', stem + 'y'


def tilt_sensors(covariates: Iterable[str]) -> list[str]:
    """Return the tilt sensors whose two angles are among ``covariates`` (``''``: unnamed)."""
    names = set(covariates)
    found = {name[len(TILT_PREFIX):-2] for name in names
             if name.startswith(TILT_PREFIX) and name.endswith('.x')}
    if TILT_PREFIX + 'x' in names:
        found.add('')
    return sorted(s for s in found if set(tilt_covariates(s)) <= names)


def _no_joint_value(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX, z: ca.SX) -> ca.SX:
    return 0 * theta[0]  # the tilt turns the frame (tilt_correction), not the joint value


TILT_KIND = EffectType(
    MEASURED_TILT, ('gx', 'gy'), ('1', '1'), _no_joint_value, typical=(1.0, 1.0),
    plausible=(GAIN_BOUND, GAIN_BOUND), prismatic_plausible=(GAIN_BOUND, GAIN_BOUND),
    gains=True,
    prismatic_units=('1', '1'), inputs=(TILT_PREFIX + 'x', TILT_PREFIX + 'y'),
    description='the frame of the joint turned by a measured tilt (an inclinometer or '
                'accelerometer on a column) with an identified gain per axis',
    hint='measure while the recorded tilt changes (different loads, stops on different '
         'ground), with poses that move the point away from {joint} in several directions',
    signature='measured tilt (frame of {joint})')


@dataclass(frozen=True)
class MeasuredTilt(BoundEffect):
    """Joint j's frame turned by g_x·t_x about the base's x axis and g_y·t_y about its y axis."""

    sensor: str = ''
    tilt_inputs: tuple[str, str] = field(default=('tilt.x', 'tilt.y'))

    def __post_init__(self) -> None:
        """Name the effect, its parameters and its inputs after the joint and the sensor."""
        super().__post_init__()
        suffix = f':{self.sensor}' if self.sensor else ''
        middle = f'.{self.sensor}' if self.sensor else ''
        object.__setattr__(self, 'name', f'{MEASURED_TILT}:{self.joint}{suffix}')
        object.__setattr__(self, 'parameter_names', tuple(
            f'{MEASURED_TILT}.{self.joint}{middle}.{s}' for s in self.kind.parameters))
        object.__setattr__(self, 'tilt_inputs', tilt_covariates(self.sensor))

    @property
    def inputs(self) -> tuple[str, ...]:
        """The sensor's two angles, ``tilt.<sensor>.x`` and ``tilt.<sensor>.y`` (rad)."""
        return self.tilt_inputs

    def tilt_correction(self, theta: ca.SX, z: Any = None) -> Any:
        """``(joint index, rotation (3x3) in the base axes)`` of this joint's placed frame."""
        assert self.joint_index is not None  # set by the binder
        if z is None:
            z = ca.DM.zeros(2)
        rotation = (axis_rotation(np.array([1.0, 0.0, 0.0]), theta[0] * z[0])
                    @ axis_rotation(np.array([0.0, 1.0, 0.0]), theta[1] * z[1]))
        return self.joint_index, rotation


def measured_tilt(robot: RobotModel, joint: str | None, sensor: str = '',
                  key: str = 'effects') -> MeasuredTilt:
    """Bind ``measured_tilt:<joint>[:<sensor>]`` to ``robot``.

    Raises
    ------
    ConfigError
        Unknown joint, or a sensor name that is not a plain word.
    """
    names = robot.joint_names
    if joint not in names:
        raise ConfigError(key, f'effect {MEASURED_TILT!r} acts on one joint: write '
                          f'{MEASURED_TILT}:<joint>[:<sensor>] with a joint of {names}'
                          + (f' (not {joint!r})' if joint else ''))
    sensor = sensor.strip()
    if sensor and not all(c.isalnum() or c in '_-' for c in sensor):
        raise ConfigError(key, f'{MEASURED_TILT}:{joint}:{sensor}: the sensor name is a plain '
                          'word (letters, digits, _ or -), the middle of the covariates '
                          'tilt.<sensor>.x and tilt.<sensor>.y')
    index = names.index(joint)
    return MeasuredTilt(TILT_KIND, joint, index, len(names), robot.joints[index].kind,
                        sensor=sensor)


def tilt_candidates(robot: RobotModel, covariates: Iterable[str]) -> list[BoundEffect]:
    """``measured_tilt`` at every joint for every sensor whose two angles are recorded."""
    return [measured_tilt(robot, joint, sensor) for sensor in tilt_sensors(covariates)
            for joint in robot.joint_names]


ARGUMENT_EFFECTS[MEASURED_TILT] = measured_tilt
COVARIATE_CANDIDATES.append(tilt_candidates)

"""What a calibration's misfit may depend on: the inputs of the residual analysis.

Each :class:`ResidualInput` is a value per measurement row and its *direction fields*: how
a unit of a function of it moves each row's point. :func:`residual_inputs` builds the
standard ones (every joint angle and loaded joint's gravity torque along ∂p/∂q_j, the
tracker distance along the line of sight, time, the reflector) and one per covariate
given (a temperature, any recorded quantity) along the tracker axes and the scale about
the points' centroid. A new covariate needs no code: pass it in ``covariates``; a new
kind of direction is one more :class:`ResidualInput`.
:mod:`kpi_calib_ros.core.diagnosis.residual_analysis` scores them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.payload import payload_torques
from kpi_calib_ros.core.measurement.recordings import row_recording
from kpi_calib_ros.core.measurement.tracker import MeasurementModel

__all__ = ['ResidualInput', 'residual_inputs']


@dataclass(frozen=True)
class ResidualInput:
    """One input the misfit may depend on.

    Attributes
    ----------
    name : str
        Shown in tables and plots (``'elbow_joint'``, ``'gravity torque elbow_joint'``).
    values : (N,) ndarray
        The input at every measurement row, in ``unit``.
    fields : (N, 3, d) ndarray
        How a unit of each of its ``d`` functions moves each row's point (m per unit);
        0 on rows it cannot move.
    field_names : tuple of str
        (d,) what each function is (``'joint error'``, ``'drift x'``, ``'scale'``).
    field_units : tuple of str
        (d,) the unit of each function's value (``'rad'``, ``'m'``, ``''``).
    unit : str
        Unit of ``values``.
    kind : str
        ``'joint'``, ``'torque'`` or ``'covariate'``.
    categorical : bool
        ``values`` are category codes (a constant per code, no smoothness).
    periodic : bool
        ``values`` are angles (rad) of a revolute joint: Fourier bases (harmonics of the
        turn, as a gear's errors are) are tried beside the splines.
    """

    name: str
    values: np.ndarray
    fields: np.ndarray
    field_names: tuple[str, ...]
    field_units: tuple[str, ...]
    unit: str
    kind: str = 'covariate'
    categorical: bool = False
    periodic: bool = False



def residual_inputs(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                    covariates: Mapping[str, tuple[np.ndarray, str]] | None = None,
                    tau: np.ndarray | None = None) -> list[ResidualInput]:
    """Return the standard inputs of a calibration's measurements.

    Every joint angle and every loaded joint's gravity torque (field ∂p/∂q_j), the
    distance to the tracker (line of sight), time since the first stamp when stamped, the
    reflector when there are several (categorical), and each ``covariates`` entry
    ``name -> ((N,) values, unit)`` (e.g. a temperature): the covariate fields (tracker
    axes and the scale about the points' centroid). Distances and fields are those of the
    predicted points h(p̂, q), free of the measurement noise.
    """
    q = np.atleast_2d(data.q)
    n = len(q)
    n_ref = model.n_reflectors
    point = np.ones(n, bool) if data.reflector is None else np.asarray(data.reflector) < n_ref
    jq = model.joint_jacobian(result.values, q, tau if tau is not None else data.tau,
                              data.reflector, data.rotation, data.covariates)
    robot = model.robot
    revolute = [j.kind != 'prismatic' for j in robot.joints]
    out = []
    for j, name in enumerate(robot.joint_names):
        unit = 'rad' if revolute[j] else 'm'
        out.append(ResidualInput(name, q[:, j], jq[:, :, j:j + 1], ('joint error',), (unit,),
                                 unit, 'joint', periodic=revolute[j]))
    torque = payload_torques(robot, q, data.covariates, gradient=model.uses_torque) \
        if tau is None and data.tau is None \
        else np.asarray(tau if tau is not None else data.tau, float)
    for j, name in enumerate(robot.joint_names):
        if np.ptp(torque[:, j]) > 1e-6:
            out.append(ResidualInput(
                f'gravity torque {name}', torque[:, j], jq[:, :, j:j + 1], ('joint error',),
                ('rad' if revolute[j] else 'm',), 'N m' if revolute[j] else 'N', 'torque'))
    # Predicted, not measured, points: a field built from the measured point would contain
    # the residual itself (with a cubic in the distance, η = |η|·η/|η| is one column, and
    # the geometry spans h(p̂), so the residual would be "explained" exactly).
    eta = model.predict(result.values, q, torque, data.reflector, data.rotation,
                        data.covariates)
    distance = np.linalg.norm(eta, axis=1)
    if point.any():
        filler = float(np.median(distance[point]))
        sight = np.zeros((n, 3, 1))
        sight[point, :, 0] = eta[point] / distance[point, None]
        out.append(ResidualInput('tracker distance', np.where(point, distance, filler), sight,
                                 ('range error',), ('m',), 'm'))
    fields = _covariate_fields(eta, point,
                               row_recording(data, ('',) + tuple(model.recordings)))
    names = ('drift x', 'drift y', 'drift z', 'scale')
    units = ('m', 'm', 'm', '')
    if data.stamps_ns is not None and len(data.stamps_ns) == n:
        stamps = np.asarray(data.stamps_ns, float)
        out.append(ResidualInput('time', (stamps - stamps.min()) * 1e-9, fields, names, units,
                                 's'))
    for name, (values, unit) in (covariates or {}).items():
        values = np.asarray(values, float)
        if values.shape != (n,):
            raise ValueError(f'covariate {name!r} must have one value per measurement '
                             f'({n}), got shape {values.shape}')
        if np.all(np.isfinite(values)) and np.ptp(values) > 0:
            # two values (a recording's one-hot, a payload changed once): a level each, not
            # a curve between them ("where recording.b is 0.5377 to 1")
            out.append(ResidualInput(name, values, fields, names, units, unit,
                                     categorical=len(np.unique(values)) == 2))
    if data.reflector is not None and len(np.unique(np.asarray(data.reflector)[point])) > 1:
        out.append(ResidualInput('reflector', np.asarray(data.reflector, float), fields[:, :, :3],
                                 names[:3], units[:3], '', categorical=True))
    return out


def _covariate_fields(eta: np.ndarray, point: np.ndarray, group: np.ndarray) -> np.ndarray:
    """(N, 3, 4) fields of an input with no direction.

    Each tracker axis and the offset of the (predicted) points ``eta`` from the centroid of
    their recording's (``group`` (N,): each recording is in its own tracker frame; about the
    centroid of every recording's points together, a station's 122 ppm scale read 4.95
    ppm); 0 on rotation rows.
    """
    fields = np.zeros((len(eta), 3, 4))
    fields[point, :, :3] = np.eye(3)
    for g in np.unique(group[point]):
        rows = point & (group == g)
        fields[rows, :, 3] = eta[rows] - eta[rows].mean(axis=0)
    return fields

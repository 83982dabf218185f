"""The payload of each row: a campaign that mixes loads, and the gravity torques it makes.

A row may carry its own payload as covariates (``Measurements.covariates``, the names a
recording puts on every row it measured with that load)::

    payload.mass                              kg, >= 0
    payload.com.x, payload.com.y, payload.com.z   m, its centre of mass in the tip frame

A row without ``payload.com.*`` takes the cell's payload centre. The gravity torques of such
a row are the robot's with that payload on the tip in place of the cell's
(:meth:`~kpi_calib_ros.core.model.robot.RobotModel.gravity_torques`), so an effect that reads
the gravity torque (``joint_compliance``) is identified from the difference between the
loads: the way a compliance is proved, the same poses measured unloaded and loaded.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from kpi_calib_ros.core.model.robot import Payload, RobotModel

__all__ = ['PAYLOAD_MASS', 'PAYLOAD_COM', 'PAYLOAD_MASS_LIMIT_KG', 'PAYLOAD_COM_LIMIT_M',
           'payload_name_error', 'row_payloads', 'payload_torques', 'payload_range',
           'outside_payloads', 'reads_load', 'cell_payload_inputs', 'row_masses',
           'gravity_gradient', 'gravity_input', 'GRADIENT_STEP']

PAYLOAD_MASS = 'payload.mass'
PAYLOAD_COM = ('payload.com.x', 'payload.com.y', 'payload.com.z')
# What any arm a tracker calibrates may lift, with margin (the largest industrial arms carry
# 2.3 t): a value beyond is a unit slip (grams) or a fault of the controller's report.
PAYLOAD_MASS_LIMIT_KG = 5000.0
# How far a payload's centre of mass may lie from the tip frame, per axis: a tool, not a
# second arm; beyond, millimetres written as metres.
PAYLOAD_COM_LIMIT_M = 2.0


def payload_name_error(name: str) -> str | None:
    """Return why ``name`` is a misspelled payload input, or None.

    A name in the ``payload.`` namespace that is none of its names (``payload.mas``) would be
    read by nothing; any other name is None.
    """
    if not name.startswith('payload.') or name == PAYLOAD_MASS or name in PAYLOAD_COM:
        return None
    return (f'{name!r} is no payload input: the payload is {PAYLOAD_MASS} (kg) and '
            f'{", ".join(PAYLOAD_COM)} (m, tip frame)')


def row_payloads(covariates: Mapping[str, np.ndarray] | None, n: int,
                 default: Payload) -> list[Payload] | None:
    """Return the payload of each of ``n`` rows from ``covariates``; None when they carry no mass.

    ``payload.mass`` (kg) per row, ``payload.com.*`` (m, tip frame) where given, else the
    centre of ``default`` (the cell's payload).

    Raises
    ------
    ValueError
        A mass negative, beyond :data:`PAYLOAD_MASS_LIMIT_KG` or not finite, a centre not
        finite, only some of the three centre coordinates, or another length than ``n``.
    """
    if not covariates:
        return None
    misspelled = [e for e in map(payload_name_error, covariates) if e]
    if misspelled:
        raise ValueError(misspelled[0])
    if PAYLOAD_MASS not in covariates:
        if any(name in covariates for name in PAYLOAD_COM):
            raise ValueError(f'a payload centre without a mass: give {PAYLOAD_MASS} (kg) with '
                             f'{list(PAYLOAD_COM)}')
        return None
    mass = np.asarray(covariates[PAYLOAD_MASS], float).reshape(-1)
    given = [name for name in PAYLOAD_COM if name in covariates]
    if given and len(given) != 3:
        raise ValueError(f'the payload centre needs all of {list(PAYLOAD_COM)} (m, tip frame), '
                         f'got only {given}')
    com = (np.column_stack([np.asarray(covariates[c], float).reshape(-1) for c in PAYLOAD_COM])
           if given else np.tile(np.asarray(default.com, float), (len(mass), 1)))
    if mass.shape != (n,) or com.shape != (n, 3):
        raise ValueError(f'{PAYLOAD_MASS} must hold one value per row ({n}), got {mass.shape}')
    bad = ~(np.isfinite(mass) & (mass >= 0) & (mass <= PAYLOAD_MASS_LIMIT_KG)
            & np.all(np.isfinite(com), axis=1)
            & np.all(np.abs(com) <= PAYLOAD_COM_LIMIT_M, axis=1))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f'row {i}: payload {float(mass[i])!r} kg at {com[i].tolist()} m is not a '
                         f'payload (finite, 0 to {PAYLOAD_MASS_LIMIT_KG:g} kg, its centre within '
                         f'{PAYLOAD_COM_LIMIT_M:g} m of the tip frame per axis, SI units)')
    return [Payload(float(m), (float(c[0]), float(c[1]), float(c[2])))
            for m, c in zip(mass, com)]


def payload_torques(robot: RobotModel, q: np.ndarray,
                    covariates: Mapping[str, np.ndarray] | None = None,
                    gradient: bool = False) -> np.ndarray:
    """Return the gravity torques (N, n) of rows ``q`` (N, n).

    Each with its own payload where ``covariates`` carry one (:func:`row_payloads`), else
    with the cell's. With ``gradient``, each row also carries its gradient ∂τ/∂q
    (:func:`gravity_gradient`), row-major: (N, n + n²), the torque input of a model whose
    effects read the torque (the torque at the deflected configuration,
    :class:`~kpi_calib_ros.core.measurement.tracker.MeasurementModel`).
    """
    q = np.atleast_2d(q)
    payloads = row_payloads(covariates, len(q), robot.payload)
    if gradient:
        return gravity_input(robot, q, payloads)
    return np.atleast_2d(robot.gravity_torques(q, payloads))


def gravity_input(robot: RobotModel, q: np.ndarray,
                  payloads: list[Payload] | None = None) -> np.ndarray:
    """Return the gravity torques of rows ``q`` (N, n) with their gradient, (N, n + n²).

    Each row with its payload (None: the cell's); the torque input of a model whose effects
    read the torque (:mod:`kpi_calib_ros.core.measurement.deflection`).
    """
    q = np.atleast_2d(np.asarray(q, float))
    tau = np.atleast_2d(robot.gravity_torques(q, payloads))
    n = q.shape[1]
    if not len(q):
        return np.zeros((0, n * (n + 1)))
    return np.hstack([tau, gravity_gradient(robot, q, payloads).reshape(len(q), n * n)])


# Central differences of the gravity torques: exact to ~1e-10 relative for a step of 1 µrad
# (the torques are smooth trigonometric sums).
GRADIENT_STEP = 1e-6


def gravity_gradient(robot: RobotModel, q: np.ndarray,
                     payloads: list[Payload] | None = None) -> np.ndarray:
    """Return ∂τ_i/∂q_j (N, n, n) of the gravity torques at rows ``q`` (N, n).

    Each row with its payload (None: the cell's): how much a deflection changes the torque,
    since a joint that bends under its load is held by the deflected configuration's torque.
    """
    q = np.atleast_2d(np.asarray(q, float))
    n = q.shape[1]
    out = np.empty((len(q), n, n))
    for j in range(n):
        step = np.zeros(n)
        step[j] = GRADIENT_STEP
        up = np.atleast_2d(robot.gravity_torques(q + step, payloads))
        down = np.atleast_2d(robot.gravity_torques(q - step, payloads))
        out[:, :, j] = (up - down) / (2 * GRADIENT_STEP)
    return out


def row_masses(covariates: Mapping[str, np.ndarray] | None, n: int,
               default_mass: float) -> np.ndarray:
    """Return the payload mass (kg) of each of ``n`` rows, (n,).

    Each row's ``payload.mass`` where the covariates carry it, else ``default_mass`` (the
    cell's).
    """
    if not covariates or PAYLOAD_MASS not in covariates:
        return np.full(n, float(default_mass))
    return np.asarray(covariates[PAYLOAD_MASS], float).reshape(-1)


def payload_range(covariates: Mapping[str, np.ndarray] | None, n: int,
                  default_mass: float) -> tuple[float, float]:
    """Return the lightest and heaviest payload (kg) of ``n`` measured rows.

    Each row's mass as :func:`row_masses` gives it; ``default_mass`` for no row.
    """
    mass = row_masses(covariates, n, default_mass)
    if not len(mass):
        return float(default_mass), float(default_mass)
    return float(mass.min()), float(mass.max())


# A working pose's payload is within the measured loads when it lies inside their range
# widened by this fraction of the heaviest (and PAYLOAD_TOLERANCE_KG): a tool's mass stated
# to a few per cent.
PAYLOAD_TOLERANCE_KG = 0.01
PAYLOAD_TOLERANCE_FRACTION = 0.05


def outside_payloads(mass: float, measured: tuple[float, float]) -> bool:
    """Whether a payload of ``mass`` kg lies outside the ``measured`` (lightest, heaviest) loads.

    There the joints' deflection under it is extrapolated (or, with no effect reading the
    load, in no prediction) and no measured pose checks it.
    """
    lo, hi = measured
    tol = max(PAYLOAD_TOLERANCE_KG, PAYLOAD_TOLERANCE_FRACTION * hi)
    return not lo - tol <= mass <= hi + tol


def reads_load(model: Any) -> bool:
    """Return whether ``model`` (a MeasurementModel) predicts anything from a row's payload.

    An effect of the gravity torque does, or one that reads the payload inputs (link bending).
    """
    return bool(model.uses_torque or PAYLOAD_MASS in model.inputs)


def cell_payload_inputs(payload: Payload) -> dict[str, float]:
    """Return the payload inputs (:data:`PAYLOAD_MASS`, :data:`PAYLOAD_COM`) of ``payload``.

    What a row that states no payload carries: the cell's.
    """
    return {PAYLOAD_MASS: float(payload.mass), **dict(zip(PAYLOAD_COM, map(float, payload.com)))}

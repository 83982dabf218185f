"""A tracked 6-DoF pose (position and orientation of a body on the tool) as a measurement.

A tracker that follows a rigid body (a 6-DoF probe, a motion-capture rigid body)
reports its position and its orientation. The position is a reflector point like any
other (:mod:`kpi_calib_ros.core.measurement.tracker`). The orientation adds one row of three
residuals: the rotation between the measured body orientation ``R_m`` and the
predicted one ``R(p, q) = R_tracker_base(p) · R_base_tip(p, q) · R_tip_body``,

    r = log3(R(p, q)ᵀ · R_m) · σ / σ_rot            (3,), in metres at the stated σ

``log3`` is the SO(3) logarithm (rotation vector, rad), exact in CasADi so the
Jacobian of the row is exact like the point rows'. Scaling by σ / σ_rot (the tracker's
position σ per axis over the orientation σ ``noise.sigma_rotation``, rad) makes the row
weigh exactly 1/σ_rot per radian under the common 1/σ weights, so estimation, eq. (19),
χ², robust scale and validation stack these rows with the point rows unchanged: a
tracked pose is one position row and one rotation row (6 residuals).

The measured rotation ``R_m`` is data, so the rotation row's prediction takes it as an
input (``Measurements.rotation``); the row's ``eta`` is zero.

A body whose orientation in the tip frame is not known (``orientation: identify`` in the
cell) has three parameters ``reflector.<name>.r{x,y,z}`` (rad, nominal 0): the rotation
vector ω of ``R_tip_body = R_stated · exp(ω)`` (:func:`body_orientation`), ``R_stated`` the
cell's guess (the identity when it gives none).
"""
from __future__ import annotations

from typing import Sequence

import casadi as ca
import numpy as np

from kpi_calib_ros.core.model.kinematics import Expr

__all__ = [
    'log3_expression', 'measured_rotation_input', 'rotation_residual_expression',
    'rotation_from_rpy', 'pose_matrix', 'rotation_from_quaternion', 'quaternion_from_rotation',
    'rotation_exp', 'noisy_rotations', 'ORIENTATION_COMPONENTS', 'orientation_names',
    'exp3_expression', 'body_orientation',
]

# The components of an identified body orientation: a rotation vector (rad).
ORIENTATION_COMPONENTS = ('rx', 'ry', 'rz')

# Below this sin²θ the logarithm uses its series: θ/sin θ = 1 + sin²θ/6 + O(θ⁴), with an
# error below 1e-16 there, and neither branch divides by zero (both are evaluated).
_SERIES_BELOW = 1e-8


def log3_expression(rotation: ca.SX) -> ca.SX:
    """SO(3) logarithm (3,) of a 3x3 CasADi rotation: axis · angle (rad), angle in [0, π).

    Smooth at the identity (where the residuals of a fit sit), exact elsewhere; at an
    angle of π the axis is ambiguous and the value is not meaningful (a residual of π
    rad is no measurement of this robot).
    """
    v = 0.5 * ca.vertcat(rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                         rotation[1, 0] - rotation[0, 1])            # sin θ · axis
    s2 = ca.dot(v, v)
    c = 0.5 * (rotation[0, 0] + rotation[1, 1] + rotation[2, 2] - 1.0)   # cos θ
    s = ca.sqrt(ca.fmax(s2, _SERIES_BELOW))
    factor = ca.if_else(s2 < _SERIES_BELOW, 1.0 + s2 / 6.0, ca.atan2(s, c) / s)
    return factor * v


def exp3_expression(omega: Expr) -> ca.SX:
    """SO(3) exponential (3x3) of a rotation vector ``omega`` (3,) rad (Rodrigues).

    Smooth at 0 (series below :data:`_SERIES_BELOW` in θ²).
    """
    w = ca.vertcat(omega[0], omega[1], omega[2])
    t2 = ca.dot(w, w)
    t = ca.sqrt(ca.fmax(t2, _SERIES_BELOW))
    a = ca.if_else(t2 < _SERIES_BELOW, 1.0 - t2 / 6.0, ca.sin(t) / t)
    b = ca.if_else(t2 < _SERIES_BELOW, 0.5 - t2 / 24.0, (1.0 - ca.cos(t)) / (t * t))
    skew = ca.vertcat(ca.horzcat(0, -w[2], w[1]), ca.horzcat(w[2], 0, -w[0]),
                      ca.horzcat(-w[1], w[0], 0))
    return ca.DM.eye(3) + a * skew + b * (skew @ skew)


def orientation_names(prefix: str) -> list[str]:
    """Return ``<prefix>.r{x,y,z}``, the identified orientation of reflector ``prefix``'s body.

    ``prefix`` e.g. ``reflector.probe``.
    """
    return [f'{prefix}.{c}' for c in ORIENTATION_COMPONENTS]


def body_orientation(names: Sequence[str], p: Expr, stated: np.ndarray,
                     prefix: str, remounted: Sequence[tuple[Expr, str]] = ()) -> Expr:
    """Return ``R_tip_body`` (3x3) of reflector ``prefix``.

    ``stated`` times ``exp(ω)``, ω the parameters :func:`orientation_names` when ``names``
    (the model's parameter names) has them, else ``stated``. ``remounted``: (condition,
    prefix) of each recording whose probe was remounted; where its condition holds, its own
    ``<prefix>.r*`` (when ``names`` has them) turn ``stated`` instead.
    """
    def turned(which: str) -> Expr:
        wanted = orientation_names(which)
        if wanted[0] not in names:
            return ca.DM(np.asarray(stated, float))
        index = [list(names).index(n) for n in wanted]
        return ca.DM(np.asarray(stated, float)) @ exp3_expression(
            ca.vertcat(*[p[i] for i in index]))
    rotation = turned(prefix)
    for condition, own in remounted:
        if orientation_names(own)[0] in names:
            rotation = ca.if_else(condition, turned(own), rotation)
    return rotation


def measured_rotation_input(rotations: np.ndarray) -> np.ndarray:
    """(N, 9) column-major rows of (N, 3, 3) rotations, as the CasADi functions take them."""
    r = np.asarray(rotations, float).reshape(-1, 3, 3)
    return r.transpose(0, 2, 1).reshape(-1, 9)


def rotation_residual_expression(measured9: Expr, predicted: Expr, scale: Expr) -> ca.SX:
    """Rotation row prediction ``log3(R_mᵀ R(p, q)) ⊙ scale`` (3,).

    With ``eta = 0`` the residual ``eta - h`` is ``log3(R(p, q)ᵀ R_m) ⊙ scale``, the measured
    rotation relative to the predicted one in the body frame (scale: σ/σ_rot per axis, m/rad).
    """
    measured = ca.reshape(measured9, 3, 3)
    return log3_expression(measured.T @ predicted) * ca.DM(np.asarray(scale, float))


def rotation_from_rpy(rpy: Sequence[float] | np.ndarray) -> np.ndarray:
    """3x3 rotation of URDF roll, pitch, yaw (rad): Rz(yaw) · Ry(pitch) · Rx(roll)."""
    r, p, y = (float(a) for a in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def pose_matrix(pose: Sequence[float] | np.ndarray) -> np.ndarray:
    """4x4 transform (m) of ``[x, y, z, roll, pitch, yaw]`` (m, rad, URDF convention).

    The numeric twin of :func:`kpi_calib_ros.core.model.kinematics.pose6`, equal to it to the
    bit.
    """
    v = np.asarray(pose, float).reshape(-1)
    if v.shape != (6,):
        raise ValueError(f'a pose is 6 numbers [x, y, z, roll, pitch, yaw], got {v.tolist()}')
    out = np.eye(4)
    out[:3, :3] = rotation_from_rpy(v[3:])
    out[:3, 3] = v[:3]
    return out


def rotation_from_quaternion(xyzw: Sequence[float] | np.ndarray) -> np.ndarray:
    """3x3 rotation of a unit quaternion [x, y, z, w] (the geometry_msgs order).

    Raises ValueError when the quaternion is not finite or not of unit length (1e-3):
    a wrong order or a non-normalised message is an error, not silently normalised.
    """
    q = np.asarray(xyzw, float).reshape(-1)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise ValueError(f'a quaternion is 4 finite numbers [x, y, z, w], got {q.tolist()}')
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        raise ValueError(f'quaternion {q.tolist()} has length {norm:.6g}, not 1')
    x, y, z, w = q / norm
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def quaternion_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """Return the unit quaternion [x, y, z, w] (w >= 0) of a 3x3 rotation."""
    m = np.asarray(rotation, float)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = s / 4
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    out = np.array(q)
    return out if out[3] >= 0 else -out


def rotation_exp(omega: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) of a rotation vector ``omega`` (3,) rad (Rodrigues)."""
    w = np.asarray(omega, float).reshape(3)
    angle = float(np.linalg.norm(w))
    skew = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if angle < 1e-8:
        return np.eye(3) + skew + 0.5 * skew @ skew
    return (np.eye(3) + np.sin(angle) / angle * skew
            + (1.0 - np.cos(angle)) / angle ** 2 * skew @ skew)


def noisy_rotations(rotations: np.ndarray, sigma_rotation: float,
                    rng: np.random.Generator) -> np.ndarray:
    """Draw (N, 3, 3) rotations ``R · exp(ω)``, ω ~ N(0, σ_rot² I) in the body frame.

    What a 6-DoF tracker of orientation noise ``sigma_rotation`` (rad) reports.
    """
    rotations = np.asarray(rotations, float).reshape(-1, 3, 3)
    noise = rng.normal(size=(len(rotations), 3)) * float(sigma_rotation)
    return np.array([r @ rotation_exp(w) for r, w in zip(rotations, noise)])

"""Denavit-Hartenberg / Hayati description of a (calibrated) chain, for reporting.

The estimation never uses DH: it is ill-conditioned for parallel axes. But many
engineers think in (θ, d, a, α), so the calibrated joint axes are re-expressed
as the common-normal geometry of consecutive axis lines at q = 0. Where two
consecutive axes are (nearly) parallel, the common normal is not defined (or
lies metres away along the axes: a DH ``d`` of several metres between two
nearly parallel axes is an artefact, not geometry), and the Hayati form
(Hayati & Mirmirani 1985) is reported instead: ``theta`` and ``a`` to the point
where the next axis crosses the plane normal to this axis through the current
origin, then the small twists ``alpha`` (about x) and ``beta`` (about y), with
``d`` = 0. A pair is Hayati when its axes are within :data:`PARALLEL_SIN`, or when
the DH common normal would lie more than :data:`FOOT_LIMIT` times the distance
between the joint origins (and at least 1 m) away; :func:`dh_table` decides on the
NOMINAL geometry, so a calibrated tilt never switches a row's convention.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from kpi_calib_ros.core.model.kinematics import link_poses_function
from kpi_calib_ros.core.model.parameters import ParameterSet
from kpi_calib_ros.core.model.robot import RobotModel

__all__ = ['PARALLEL_SIN', 'FOOT_LIMIT', 'AxisPair', 'axis_lines', 'describe', 'dh_table']

PARALLEL_SIN = 1e-2  # axes closer than ~0.57° are treated as parallel (Hayati)
FOOT_LIMIT = 10.0  # DH normal foot farther than this many joint spacings: Hayati


@dataclass(frozen=True)
class AxisPair:
    """Geometry between joint ``joint`` and the next one (m, rad).

    ``convention`` is ``'DH'`` (``d``, ``theta``, ``a``, ``alpha``; ``beta`` = 0) or
    ``'Hayati'`` (``theta``, ``a``, ``alpha``, ``beta``; ``d`` = 0 by definition).
    """

    joint: str
    next_joint: str
    convention: str
    d: float
    theta: float
    a: float
    alpha: float
    beta: float


def axis_lines(robot: RobotModel, params: ParameterSet, p: np.ndarray) -> list[tuple]:
    """(point, unit direction) of every joint axis in the base frame at q = 0."""
    poses = link_poses_function(robot, params)(p, np.zeros(robot.n_joints))
    lines = []
    for joint, pose in zip(robot.joints, poses[:-1]):
        pose = np.array(pose)
        lines.append((pose[:3, 3], pose[:3, :3] @ joint.axis))
    return lines


def _common_normal(o1: np.ndarray, z1: np.ndarray, o2: np.ndarray,
                   z2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = np.cross(z1, z2)
    n /= np.linalg.norm(n)
    # Closest points o1 + s z1 and o2 + t z2 on the two lines.
    w = o1 - o2
    b = z1 @ z2
    s = (b * (z2 @ w) - (z1 @ w)) / (1 - b * b)
    t = ((z2 @ w) - b * (z1 @ w)) / (1 - b * b)
    return n, o1 + s * z1, o2 + t * z2


def describe(robot: RobotModel, params: ParameterSet, p: np.ndarray,
             conventions: Sequence[str] | None = None) -> list[AxisPair]:
    """DH (or Hayati for nearly parallel axes) geometry between consecutive joint axes.

    Parameters
    ----------
    robot, params, p
        Chain, its parameter set and values (m, rad).
    conventions : sequence of str, optional
        ``'DH'`` or ``'Hayati'`` per consecutive pair (n_joints - 1); chosen from
        this geometry when omitted (module docstring).

    Returns
    -------
    list of AxisPair
    """
    lines = axis_lines(robot, params, p)
    if conventions is not None and len(conventions) != len(lines) - 1:
        raise ValueError(f'conventions must have {len(lines) - 1} entries, got {len(conventions)}')
    out: list[AxisPair] = []
    prev_x, prev_foot = None, None
    for i in range(len(lines) - 1):
        (o1, z1), (o2, z2) = lines[i], lines[i + 1]
        name, nxt = robot.joints[i].name, robot.joints[i + 1].name
        origin = o1 if prev_foot is None else prev_foot
        sin = float(np.linalg.norm(np.cross(z1, z2)))
        dh = None if sin < 1e-12 else _common_normal(o1, z1, o2, z2)
        if conventions is not None:
            hayati = conventions[i] == 'Hayati'
        else:
            limit = max(1.0, FOOT_LIMIT * float(np.linalg.norm(o2 - o1)))
            hayati = bool(dh is None or sin < PARALLEL_SIN or max(
                np.linalg.norm(dh[1] - origin), np.linalg.norm(dh[2] - o2)) > limit)
        if hayati:
            # Origin of the next frame: where axis 2 crosses the plane normal to z1
            # through this frame's origin (a point on axis 2 nearest to it if z2 ⟂ z1).
            along = z1 @ z2
            s = (z1 @ (origin - o2)) / along if abs(along) > 1e-12 else 0.0
            foot = o2 + s * z2
            offset = foot - origin
            a = float(np.linalg.norm(offset))
            x = offset / a if a > 1e-12 else (prev_x if prev_x is not None else _any_normal(z1))
            y = np.cross(z1, x)
            # z2 = Rx(alpha) Ry(beta) e_z in (x, y, z1): (sin b, -sin a cos b, cos a cos b).
            beta = float(np.arcsin(np.clip(z2 @ x, -1.0, 1.0)))
            alpha = float(np.arctan2(-(z2 @ y), z2 @ z1))
            out.append(AxisPair(name, nxt, 'Hayati', 0.0, _angle(prev_x, x, z1), a, alpha, beta))
            prev_x, prev_foot = x, foot
            continue
        x, foot1, foot2 = dh if dh is not None else _common_normal(o1, z1, o2, z2)
        a = float((foot2 - foot1) @ x)
        alpha = float(np.arctan2(np.cross(z1, z2) @ x, z1 @ z2))
        d = float((foot1 - prev_foot) @ z1) if prev_foot is not None else float(foot1 @ z1)
        out.append(AxisPair(name, nxt, 'DH', d, _angle(prev_x, x, z1), a, alpha, 0.0))
        prev_x, prev_foot = x, foot2
    return out


def _any_normal(z: np.ndarray) -> np.ndarray:
    helper = np.eye(3)[int(np.argmin(np.abs(z)))]
    v = np.cross(z, helper)
    return v / np.linalg.norm(v)


def _angle(prev_x: np.ndarray | None, x: np.ndarray, z: np.ndarray) -> float:
    """Rotation about ``z`` from the previous common normal to ``x`` (0 for the first)."""
    if prev_x is None:
        return 0.0
    return float(np.arctan2(np.cross(prev_x, x) @ z, prev_x @ x))


def dh_table(robot: RobotModel, params: ParameterSet, p_nominal: np.ndarray,
             p_calibrated: np.ndarray) -> list[dict]:
    """Nominal and calibrated DH/Hayati values side by side (YAML-ready).

    The convention of each row is chosen on the nominal geometry and imposed on
    the calibrated one, so both columns hold the same quantities.
    """
    rows = []
    nominal = describe(robot, params, p_nominal)
    calibrated = describe(robot, params, p_calibrated, [r.convention for r in nominal])
    for nom, cal in zip(nominal, calibrated):
        keys = (('theta', 'a', 'alpha', 'beta') if cal.convention == 'Hayati'
                else ('d', 'theta', 'a', 'alpha'))
        rows.append({'joints': f'{cal.joint} -> {cal.next_joint}', 'convention': cal.convention,
                     'nominal': {k: float(getattr(nom, k)) for k in keys},
                     'calibrated': {k: float(getattr(cal, k)) for k in keys}})
    return rows

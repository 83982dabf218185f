"""Denavit-Hartenberg / Hayati description of a (calibrated) chain, for reporting.

The estimation never uses DH: it is ill-conditioned for parallel axes. But many
engineers think in (θ, d, a, α), so the calibrated joint axes are re-expressed
as the common-normal geometry of consecutive axis lines at q = 0. Where two
consecutive axes are (nearly) parallel, the common normal is not defined and
the Hayati form is reported instead: the length ``a`` between the lines and
the small tilt ``beta`` between them, with ``d`` fixed to 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kpi_calib_ros.core.kinematics import link_poses_function
from kpi_calib_ros.core.parameters import ParameterSet
from kpi_calib_ros.core.robot import RobotModel

PARALLEL_SIN = 1e-2  # axes closer than ~0.57° are treated as parallel (Hayati)


@dataclass(frozen=True)
class AxisPair:
    """Geometry between joint ``joint`` and the next one (m, rad).

    ``convention`` is ``'DH'`` (``d``, ``theta``, ``a``, ``alpha``) or
    ``'Hayati'`` (``a``, ``beta``; ``d`` = 0, ``alpha`` = 0 by definition).
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


def _common_normal(o1, z1, o2, z2):
    n = np.cross(z1, z2)
    n /= np.linalg.norm(n)
    # Closest points o1 + s z1 and o2 + t z2 on the two lines.
    w = o1 - o2
    b = z1 @ z2
    s = (b * (z2 @ w) - (z1 @ w)) / (1 - b * b)
    t = ((z2 @ w) - b * (z1 @ w)) / (1 - b * b)
    return n, o1 + s * z1, o2 + t * z2


def describe(robot: RobotModel, params: ParameterSet, p: np.ndarray) -> list[AxisPair]:
    """DH (or Hayati for parallel axes) geometry between consecutive joint axes."""
    lines = axis_lines(robot, params, p)
    out: list[AxisPair] = []
    prev_x, prev_foot = None, None
    for i in range(len(lines) - 1):
        (o1, z1), (o2, z2) = lines[i], lines[i + 1]
        name, nxt = robot.joints[i].name, robot.joints[i + 1].name
        sin = np.linalg.norm(np.cross(z1, z2))
        if sin < PARALLEL_SIN:
            offset = (o2 - o1) - ((o2 - o1) @ z1) * z1
            a = float(np.linalg.norm(offset))
            x = offset / a if a > 1e-12 else (prev_x if prev_x is not None else _any_normal(z1))
            beta = float(np.arctan2(np.cross(z1, z2) @ np.cross(z1, x), z1 @ z2))
            out.append(AxisPair(name, nxt, 'Hayati', 0.0, _angle(prev_x, x, z1), a, 0.0, beta))
            prev_x, prev_foot = x, o1
            continue
        x, foot1, foot2 = _common_normal(o1, z1, o2, z2)
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
    """Nominal and calibrated DH/Hayati values side by side (YAML-ready)."""
    rows = []
    for nom, cal in zip(describe(robot, params, p_nominal), describe(robot, params, p_calibrated)):
        keys = ('a', 'beta') if cal.convention == 'Hayati' else ('d', 'theta', 'a', 'alpha')
        rows.append({'joints': f'{cal.joint} -> {cal.next_joint}', 'convention': cal.convention,
                     'nominal': {k: float(getattr(nom, k)) for k in keys},
                     'calibrated': {k: float(getattr(cal, k)) for k in keys}})
    return rows

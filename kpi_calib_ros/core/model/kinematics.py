"""Symbolic kinematics in CasADi with the error parameters built in.

Each chain joint contributes ``M_i · Trans(t_i) · RPY(r_i) · Motion_i(q_i + o_i)``:
the nominal URDF placement ``M_i``, a small 6-DoF placement error, and the joint
motion about/along its axis with a zero offset. Expressions are CasADi SX so
derivatives are exact; the same code evaluates numerically through
:class:`casadi.Function`.
"""
from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from kpi_calib_ros.core.model.parameters import ParameterSet, reflector_prefixes
from kpi_calib_ros.core.model.robot import RobotModel

__all__ = [
    'rot_x', 'rot_y', 'rot_z', 'rpy_matrix', 'homogeneous', 'axis_rotation', 'error_rotation',
    'reflector_point', 'pose6', 'SymbolicChain', 'nominal_fk_function', 'link_poses_function',
    'link_poses',
]

# A CasADi expression (SX symbolic, DM numeric) or a number: these functions serve the
# symbolic model and its numeric checks alike.
Expr = Any


def rot_x(a: Expr) -> Expr:
    """Rotation matrix SX (3, 3) about x by ``a`` (rad)."""
    c, s = ca.cos(a), ca.sin(a)
    return ca.vertcat(ca.horzcat(1, 0, 0), ca.horzcat(0, c, -s), ca.horzcat(0, s, c))


def rot_y(a: Expr) -> Expr:
    """Rotation matrix SX (3, 3) about y by ``a`` (rad)."""
    c, s = ca.cos(a), ca.sin(a)
    return ca.vertcat(ca.horzcat(c, 0, s), ca.horzcat(0, 1, 0), ca.horzcat(-s, 0, c))


def rot_z(a: Expr) -> Expr:
    """Rotation matrix SX (3, 3) about z by ``a`` (rad)."""
    c, s = ca.cos(a), ca.sin(a)
    return ca.vertcat(ca.horzcat(c, -s, 0), ca.horzcat(s, c, 0), ca.horzcat(0, 0, 1))


def rpy_matrix(roll: Expr, pitch: Expr, yaw: Expr) -> Expr:
    """URDF convention: R = Rz(yaw) · Ry(pitch) · Rx(roll)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def homogeneous(rotation: Expr, translation: Expr) -> Expr:
    """4x4 transform from a 3x3 rotation and a 3-vector (CasADi or numeric)."""
    return ca.vertcat(ca.horzcat(rotation, ca.reshape(translation, 3, 1)),
                      ca.horzcat(0, 0, 0, 1))


def axis_rotation(axis: np.ndarray, angle: Expr) -> Expr:
    """Rodrigues rotation about a constant unit ``axis`` (3,) by symbolic ``angle``."""
    k = np.asarray(axis, float)
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return (ca.DM.eye(3) + ca.sin(angle) * ca.DM(skew)
            + (1 - ca.cos(angle)) * ca.DM(skew @ skew))


def error_rotation(axis: np.ndarray, rx: Expr, ry: Expr, rz: Expr) -> Expr:
    """Small placement rotation error with the component about the joint axis applied last.

    Next to the joint motion, the rotation about the joint's own axis is then
    exactly a joint offset (not only to first order), and the other two
    components commute with nothing they should not. For an axis that is not
    along x, y or z, the frame axis closest to it plays that role.
    """
    rots = {0: rot_x(rx), 1: rot_y(ry), 2: rot_z(rz)}
    last = int(np.argmax(np.abs(axis)))
    first, second = [k for k in (2, 1, 0) if k != last]
    return rots[first] @ rots[second] @ rots[last]


def reflector_point(pose: Expr, offset: Expr) -> Expr:
    """Reflector centre in the frame ``pose`` (4x4) is given in: ``R · offset + t``.

    ``pose`` is the tip pose (in the base or tracker frame) and ``offset`` (3,) the
    reflector centre in the tip frame; works on numpy arrays and CasADi expressions
    alike, so the model, the design constraints and their independent check share it.
    """
    return pose[0:3, 0:3] @ offset + pose[0:3, 3]


def pose6(v: Expr) -> Expr:
    """4x4 transform from [x, y, z, roll, pitch, yaw]."""
    return homogeneous(rpy_matrix(v[3], v[4], v[5]), v[0:3])


class SymbolicChain:
    """Forward kinematics of ``robot`` as a function of (p, q).

    ``p`` is the vector of a :class:`ParameterSet` that contains the geometric
    parameter names of :func:`geometric_parameters`; extra (effect) entries are
    ignored here.
    """

    def __init__(self, robot: RobotModel, params: ParameterSet) -> None:
        self.robot = robot
        self.params = params
        self._base = params.indices([f'base.{c}' for c in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')])
        self._placement = [params.indices([f'{j.name}.placement.{c}'
                                           for c in ('tx', 'ty', 'tz', 'rx', 'ry', 'rz')])
                           for j in robot.joints]
        self._offset = params.indices([f'{j.name}.offset' for j in robot.joints])
        self._reflectors = [params.indices([f'{r}.x', f'{r}.y', f'{r}.z'])
                            for r in reflector_prefixes(params)]

    def placement_indices(self, joint: int) -> list[int]:
        """Return the indices in p of chain joint ``joint``'s placement error.

        In the order tx, ty, tz, rx, ry, rz.
        """
        return [int(i) for i in self._placement[joint]]

    def link_transforms(self, p: Expr, q: Expr,
                        deflections: dict[int, Expr] | None = None,
                        tilts: dict[int, Expr] | None = None) -> list:
        """Poses (4x4) of every chain joint frame in the base frame, base to tip.

        ``deflections``: {chain joint index: rotation (3x3)} applied to that joint's frame
        after its motion (a link bent by its load; the physical effects supply them).
        ``tilts``: {chain joint index: rotation (3x3) in the base frame's axes} turning that
        joint's frame, as placed and before its motion, about its own origin (a column
        leaning by a measured angle): everything from that joint on turns with it.
        """
        transforms = []
        current = ca.DM.eye(4)
        for i, joint in enumerate(self.robot.joints):
            e = p[self._placement[i]]
            error = homogeneous(error_rotation(joint.axis, e[3], e[4], e[5]), e[0:3])
            value = q[i] + p[self._offset[i]]
            if joint.kind == 'prismatic':
                motion = homogeneous(ca.DM.eye(3), ca.DM(joint.axis) * value)
            else:
                motion = homogeneous(axis_rotation(joint.axis, value), ca.DM.zeros(3))
            current = current @ ca.DM(joint.placement) @ error
            if tilts and i in tilts:
                current = homogeneous(tilts[i] @ current[0:3, 0:3], current[0:3, 3])
            current = current @ motion
            if deflections and i in deflections:
                current = current @ homogeneous(deflections[i], ca.DM.zeros(3))
            transforms.append(current)
        return transforms

    def link_poses(self, p: Expr, q: Expr) -> tuple[dict, object]:
        """{link name: pose (4x4)} in the base frame (base link: identity) and the tip pose.

        Link ``i + 1`` of ``robot.link_names`` is the child link of chain joint ``i``.
        """
        transforms = self.link_transforms(p, q)
        poses = {self.robot.link_names[0]: ca.DM.eye(4)}
        poses.update(zip(self.robot.link_names[1:], transforms))
        return poses, transforms[-1] @ ca.DM(self.robot.tip_placement)

    def tip_transform(self, p: Expr, q: Expr,
                      deflections: dict[int, Expr] | None = None,
                      tilts: dict[int, Expr] | None = None) -> Expr:
        """Tip frame pose (4x4) in the base frame.

        ``deflections``, ``tilts``: see :meth:`link_transforms`.
        """
        return (self.link_transforms(p, q, deflections, tilts)[-1]
                @ ca.DM(self.robot.tip_placement))

    def base_in_tracker(self, p: Expr) -> Expr:
        """Return the base frame pose (4x4) in the tracker frame."""
        return pose6(p[self._base])

    @property
    def n_reflectors(self) -> int:
        """Reflectors (or markers) on the tool, each with its own offset triple."""
        return len(self._reflectors)

    def reflector(self, p: Expr, k: int = 0) -> Expr:
        """Centre (3,) of reflector ``k`` in the tip frame (0: the KPI reflector)."""
        return p[self._reflectors[k]]


def nominal_fk_function(robot: RobotModel, params: ParameterSet) -> ca.Function:
    """CasADi Function ``fk(p, q) -> 4x4 tip pose in the base frame``."""
    chain = SymbolicChain(robot, params)
    p = ca.SX.sym('p', len(params))
    q = ca.SX.sym('q', robot.n_joints)
    return ca.Function('fk', [p, q], [chain.tip_transform(p, q)], ['p', 'q'], ['T'])


def link_poses_function(robot: RobotModel, params: ParameterSet) -> ca.Function:
    """CasADi Function ``(p, q) -> (T_link_1, ..., T_link_n, T_tip)`` in the base frame.

    Link ``i`` is the child link of chain joint ``i`` (``robot.link_names[i + 1]``).
    """
    chain = SymbolicChain(robot, params)
    p = ca.SX.sym('p', len(params))
    q = ca.SX.sym('q', robot.n_joints)
    return ca.Function('link_poses', [p, q],
                       chain.link_transforms(p, q) + [chain.tip_transform(p, q)])


def link_poses(function: ca.Function, robot: RobotModel, p: np.ndarray,
               q: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Numeric link poses {link name: (4, 4)} (base link = identity) and the tip pose."""
    out = function(p, q)
    poses = {robot.link_names[0]: np.eye(4)}
    for name, pose in zip(robot.link_names[1:], out[:-1]):
        poses[name] = np.array(pose)
    return poses, np.array(out[-1])

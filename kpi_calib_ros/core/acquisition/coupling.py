"""Coupled controller joints: from the joint values a controller reports to the URDF chain's.

The affine map from the joint values a controller reports to the joint values of the URDF
chain.

Many industrial controllers do not report URDF joint angles. A FANUC arm reports J3
against the horizontal, so the URDF ``joint_3`` is J3 + J2; parallelogram and
palletising arms are coupled the same way, some with a constant offset between the two
zeros. A robot description with mimic joints (a lifting column whose two stages each
move ``0.5 · lift − 0.1``) reports only the actuated joints: the URDF's mimic relations
give the rest. The map is

    q_urdf = M · q_controller + d

with ``M`` (n, m) in chain order, ``d`` (n,): the cell's ``robot.joint_coupling`` (a
square map over the actuated joints) followed by the URDF's mimic relations. ``M`` has
full column rank, so ``q_controller`` is recovered from URDF values that respect it.
Joint states are converted to URDF values where they enter (pairing output, live node)
and back to controller values where joint values leave (designed poses).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from kpi_calib_ros.core.model.robot import RobotModel


@dataclass(frozen=True)
class JointCoupling:
    """q_urdf = matrix @ q_controller + offset.

    Attributes
    ----------
    joint_names : tuple of str
        Chain joint names (URDF), the order of ``q_urdf``.
    matrix : (n, m) ndarray
        Row i: URDF joint i as a combination of controller joints (dimensionless for
        joints of one kind; rad/rad or m/m).
    controller_names : tuple of str
        The joints the controller reports, the order of ``q_controller``; empty: the
        chain's own names (a square map).
    offset : (n,) ndarray or None
        Constant part (rad or m); None: zero.
    """

    joint_names: tuple[str, ...]
    matrix: np.ndarray
    controller_names: tuple[str, ...] = field(default=())
    offset: np.ndarray | None = None

    def __post_init__(self) -> None:
        """Fill the defaults: controller names the chain's, zero offset."""
        if not self.controller_names:
            object.__setattr__(self, 'controller_names', tuple(self.joint_names))
        if self.offset is None:
            object.__setattr__(self, 'offset', np.zeros(len(self.joint_names)))
        if self.matrix.shape != (len(self.joint_names), len(self.controller_names)):
            raise ValueError(f'matrix must be ({len(self.joint_names)}, '
                             f'{len(self.controller_names)}), got {self.matrix.shape}')

    @property
    def _offset(self) -> np.ndarray:
        assert self.offset is not None  # filled in __post_init__
        return self.offset

    @property
    def is_identity(self) -> bool:
        """Whether the controller values are the URDF joint values (no coupling)."""
        return bool(self.controller_names == self.joint_names
                    and np.array_equal(self.matrix, np.eye(len(self.joint_names)))
                    and not self._offset.any())

    def to_urdf(self, q: np.ndarray) -> np.ndarray:
        """URDF joint values (n,) or (N, n) of controller readings ``q`` ((m,) or (N, m))."""
        q = np.asarray(q, float)
        return q if self.is_identity else q @ self.matrix.T + self._offset

    def to_controller(self, q: np.ndarray) -> np.ndarray:
        """Return the controller values (m,) or (N, m) of URDF joint values ``q``.

        ``q`` is (n,) or (N, n) in chain order; exact when it respects the map, else the
        map's least-squares inverse.
        """
        q = np.asarray(q, float)
        if self.is_identity:
            return q
        rhs = (q - self._offset).T
        if self.matrix.shape[0] == self.matrix.shape[1]:
            return np.linalg.solve(self.matrix, rhs).T
        return np.linalg.lstsq(self.matrix, rhs, rcond=None)[0].T

    def derived(self) -> dict[str, tuple[np.ndarray, float]]:
        """Return {URDF joint the controller does not report: (row (m,), offset)}.

        These are the mimic joints, whose values a joint state may carry too (checked by
        the pairing against the row and offset).
        """
        return {name: (self.matrix[i].copy(), float(self._offset[i]))
                for i, name in enumerate(self.joint_names)
                if name not in self.controller_names}

    def then(self, outer: 'JointCoupling') -> 'JointCoupling':
        """Return the map ``outer(self(x))``.

        ``outer``'s controller joints are this map's URDF joints.
        """
        if outer.controller_names != self.joint_names:
            raise ValueError(f'{outer.controller_names} are not {self.joint_names}')
        return JointCoupling(outer.joint_names, outer.matrix @ self.matrix,
                             self.controller_names, outer.matrix @ self._offset + outer._offset)


def identity_coupling(joint_names: Sequence[str]) -> JointCoupling:
    """Return the uncoupled controller: it reports URDF joint values."""
    return JointCoupling(tuple(joint_names), np.eye(len(joint_names)))


def mimic_coupling(robot: RobotModel) -> JointCoupling:
    """Return the URDF's mimic relations of ``robot`` as a map.

    From its actuated joints to its chain joints; the identity when nothing mimics.
    """
    if not robot.has_mimic:
        return identity_coupling(robot.joint_names)
    return JointCoupling(tuple(robot.joint_names), robot.mimic_matrix, robot.actuated_names,
                         robot.mimic_offset)


__all__ = ['JointCoupling', 'identity_coupling', 'mimic_coupling']

"""Coupled controller joints: from the joint values a controller reports to the URDF chain's.

The linear map from the joint values a controller reports to the joint values of the URDF chain.

Many industrial controllers do not report URDF joint angles. A FANUC arm reports J3
against the horizontal, so the URDF ``joint_3`` is J3 + J2; parallelogram and
palletising arms are coupled the same way. The map is

    q_urdf = M · q_controller,        q_controller = M⁻¹ · q_urdf

with ``M`` (n, n) in chain order, the identity for joints the cell does not list.
Joint states are converted to URDF values where they enter (pairing output, live
node) and back to controller values where joint values leave (designed poses).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


@dataclass(frozen=True)
class JointCoupling:
    """q_urdf = matrix @ q_controller, both in the chain order ``joint_names``.

    Attributes
    ----------
    joint_names : tuple of str
        Chain joint names (URDF), the order of both vectors.
    matrix : (n, n) ndarray
        Row i: URDF joint i as a combination of controller joints (dimensionless for
        joints of one kind; rad/rad or m/m).
    """

    joint_names: tuple[str, ...]
    matrix: np.ndarray

    @property
    def is_identity(self) -> bool:
        """Whether the controller values are the URDF joint values (no coupling)."""
        return bool(np.array_equal(self.matrix, np.eye(len(self.joint_names))))

    def to_urdf(self, q: np.ndarray) -> np.ndarray:
        """URDF joint values of controller readings ``q`` ((n,) or (N, n), chain order)."""
        q = np.asarray(q, float)
        return q if self.is_identity else q @ self.matrix.T

    def to_controller(self, q: np.ndarray) -> np.ndarray:
        """Return the controller values of URDF joint values ``q`` ((n,) or (N, n), chain order)."""
        q = np.asarray(q, float)
        return q if self.is_identity else np.linalg.solve(self.matrix, q.T).T


def identity_coupling(joint_names: Sequence[str]) -> JointCoupling:
    """Return the uncoupled controller: it reports URDF joint values."""
    return JointCoupling(tuple(joint_names), np.eye(len(joint_names)))


__all__ = ['JointCoupling', 'identity_coupling']

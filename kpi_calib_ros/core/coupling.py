"""Coupled controller joints: the linear map from the joint values a controller reports
to the joint values of the URDF chain.

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
from typing import Any, Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.errors import ConfigError

# Below this the map is too close to singular to invert at joint-reading precision
# (1e-6 rad readings would come back with errors > 1e-6 · cond).
MAX_CONDITION = 1e6


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
        """Controller values of URDF joint values ``q`` ((n,) or (N, n), chain order)."""
        q = np.asarray(q, float)
        return q if self.is_identity else np.linalg.solve(self.matrix, q.T).T


def identity_coupling(joint_names: Sequence[str]) -> JointCoupling:
    """The uncoupled controller: it reports URDF joint values."""
    return JointCoupling(tuple(joint_names), np.eye(len(joint_names)))


def coupling_from_mapping(raw: Mapping[str, Any] | None, joint_names: Sequence[str],
                          key: str = 'robot.joint_coupling') -> JointCoupling:
    """Validate ``{urdf_joint: {controller_joint: factor, ...}, ...}``.

    A listed URDF joint is exactly the given combination (list itself with 1.0 to keep
    its own reading); an unlisted one equals its controller value.

    Raises
    ------
    ConfigError
        Unknown joint names, non-numeric factors, or a map that cannot be inverted.
    """
    names = list(joint_names)
    matrix = np.eye(len(names))
    if not raw:
        return JointCoupling(tuple(names), matrix)
    if not isinstance(raw, Mapping):
        raise ConfigError(key, 'must map URDF joints to {controller_joint: factor}, e.g. '
                          '{joint_3: {joint_3: 1.0, joint_2: 1.0}}')
    for urdf_joint, row in raw.items():
        if urdf_joint not in names:
            raise ConfigError(f'{key}.{urdf_joint}', f'not a chain joint; joints are {names}')
        if not isinstance(row, Mapping) or not row:
            raise ConfigError(f'{key}.{urdf_joint}', 'must map controller joints to factors, '
                              f'e.g. {{{urdf_joint}: 1.0, joint_2: 1.0}}')
        i = names.index(urdf_joint)
        matrix[i] = 0.0
        for source, factor in row.items():
            if source not in names:
                raise ConfigError(f'{key}.{urdf_joint}.{source}',
                                  f'not a chain joint; joints are {names}')
            if isinstance(factor, bool) or not isinstance(factor, (int, float)) \
                    or not np.isfinite(factor):
                raise ConfigError(f'{key}.{urdf_joint}.{source}',
                                  f'must be a finite number, got {factor!r}')
            matrix[i, names.index(source)] = float(factor)
    cond = np.linalg.cond(matrix)
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise ConfigError(key, f'the map is not invertible (condition {cond:.3g}): each URDF '
                          'joint must be recoverable from the controller joints and back; '
                          'a listed joint usually keeps itself with factor 1.0')
    return JointCoupling(tuple(names), matrix)


__all__ = ['JointCoupling', 'coupling_from_mapping', 'identity_coupling']

"""What pairing yields: for each point a measurement or a rejection, for a batch its result.

:class:`PairedMeasurement` is a point accepted with the robot configuration it was measured
at; :class:`Rejection` a point (or joint sample) that did not become one, for one of the
:data:`REJECTION_REASONS`; a :data:`Decision` is either. :class:`PairingResult` stacks the
accepted rows of a batch (:func:`~kpi_calib_ros.core.acquisition.pairing.pair_measurements`,
or a stored measurement log) beside its rejections. The rule that decides is
:class:`~kpi_calib_ros.core.acquisition.pairing.Pairer`'s.

Units: stamps in integer nanoseconds, joint positions in rad (m for prismatic joints),
points in metres.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence, Union

import numpy as np

from kpi_calib_ros.core.acquisition.reflector_frames import split_frame
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample

__all__ = ['REJECTION_REASONS', 'Rejection', 'PairedMeasurement', 'Decision', 'PairingResult',
           'stacked_rotations']

REJECTION_REASONS = (
    'non_finite_point', 'wrong_frame', 'no_joint_state', 'robot_moving',
    'missing_joints', 'non_finite_joint_state', 'duplicate_stamp', 'oversized_joint_state',
    'unknown_reflector', 'invalid_orientation', 'mimic_mismatch', 'outside_joint_limits',
)


@dataclass(frozen=True)
class Rejection:
    """A point or joint sample that did not become a measurement.

    ``reason`` is one of :data:`REJECTION_REASONS`, ``detail`` says why in words.
    """

    stamp_ns: int
    reason: str
    detail: str


@dataclass(frozen=True, eq=False)
class PairedMeasurement:
    """An accepted point with the robot configuration it was measured at.

    ``q`` (n,) is the mean of the still joint states within ±window of ``stamp_ns``,
    ordered as ``joint_names``; ``eta`` (3,) is the point (m) in ``frame_id``;
    ``spread_rad`` is the largest joint position spread seen in the window.
    """

    stamp_ns: int
    joint_names: tuple[str, ...]
    q: np.ndarray
    eta: np.ndarray
    frame_id: str
    n_joint_samples: int
    spread_rad: float
    orientation: np.ndarray | None = None   # quaternion of a tracked 6-DoF pose, else None

    def joint_sample(self) -> JointSample:
        """Return the averaged configuration as a joint sample stamped like the point."""
        return JointSample(self.stamp_ns, self.joint_names, self.q, None)

    def point_sample(self) -> PointSample:
        """Return the tracker reading (point, and orientation of a 6-DoF pose) as a point sample."""
        return PointSample(self.stamp_ns, self.frame_id, self.eta, self.orientation)

    @property
    def rotation(self) -> np.ndarray | None:
        """(3, 3) body rotation of a tracked 6-DoF pose, None for a point."""
        return self.point_sample().rotation

    @property
    def reflector(self) -> str:
        """Reflector name of the point ('' for a cell's single reflector)."""
        return split_frame(self.frame_id)[1]


# What the pairer decides for a point (or a joint sample it refuses).
Decision = Union[PairedMeasurement, Rejection]


@dataclass(frozen=True, eq=False)
class PairingResult:
    """Outcome of :func:`~kpi_calib_ros.core.acquisition.pairing.pair_measurements`.

    ``q`` (N, n) rad ordered as ``joint_names``, ``eta`` (N, 3) m, ``stamps_ns`` (N,)
    int64, sorted by stamp. ``rejections`` counts reasons that occurred;
    ``rejected`` lists every rejection in stamp order; ``reflectors`` (N,) names the
    reflector of every row ('' the single one; empty tuple: all ''); ``rotations``
    (N, 3, 3) the measured body rotation of tracked 6-DoF poses (NaN on plain points),
    None when no row has one.
    """

    joint_names: tuple[str, ...]
    tracker_frame: str
    q: np.ndarray
    eta: np.ndarray
    stamps_ns: np.ndarray
    rejections: dict[str, int] = field(default_factory=dict)
    rejected: list[Rejection] = field(default_factory=list)
    reflectors: tuple[str, ...] = ()
    rotations: np.ndarray | None = None
    # False: the stamps number the rows of a table that had no times, no clock.
    stamps_are_times: bool = True

    def reflector_indices(self, names: Sequence[str]) -> np.ndarray:
        """(N,) index of every row's reflector in ``names`` (the cell's order)."""
        rows = self.reflectors or ('',) * len(self)
        position = {n: i for i, n in enumerate(names)}
        unknown = sorted({r for r in rows if r not in position})
        if unknown:
            raise ValueError(f'reflectors {unknown} are not among {list(names)}')
        return np.array([position[r] for r in rows], dtype=int)

    def __len__(self) -> int:
        """Return the number of rows."""
        return len(self.stamps_ns)


def stacked_rotations(rotations: Sequence[np.ndarray | None]) -> np.ndarray | None:
    """(N, 3, 3) rotations of accepted rows, NaN where a row is a plain point.

    None when no row carries one.
    """
    if all(r is None for r in rotations):
        return None
    return np.array([np.full((3, 3), np.nan) if r is None else r for r in rotations])

"""Timestamped joint-state and tracker-point streams of a cell, and their synthesis.

A cell produces two streams: joint states at ~50 Hz from the robot driver and one
reflector point per pose from the laser tracker, each with its own stamp. This
module holds the sample types and :func:`synthesize_streams` (what a cell records
while the robot visits a list of poses); pairing the streams into measurements is
:mod:`kpi_calib_ros.core.acquisition.pairing`.

Units: stamps in integer nanoseconds, joint positions in rad (m for prismatic
joints), velocities in rad/s (m/s), points in metres.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike

from kpi_calib_ros.core.measurement.pose import rotation_from_quaternion

__all__ = ['frozen_array', 'JointSample', 'PointSample', 'checked_rotation', 'synthesize_streams']


def frozen_array(values: ArrayLike, shape: tuple[int, ...], name: str) -> np.ndarray:
    """``values`` as a read-only float array of ``shape``; ValueError naming ``name``."""
    array = np.array(values, dtype=float)
    if array.shape != shape:
        raise ValueError(f'{name} must have shape {shape}, got {array.shape}')
    array.flags.writeable = False
    return array


@dataclass(frozen=True, eq=False)
class JointSample:
    """One joint-state message.

    Parameters
    ----------
    stamp_ns : int
        Header stamp (ns).
    names : tuple of str
        Joint names in message order; may contain joints the calibration ignores.
    positions : ndarray, shape (len(names),)
        Joint positions (rad or m). NaN is allowed here; the pairer rejects it.
    velocities : ndarray, shape (len(names),), or None
        Joint velocities (rad/s or m/s); None when the driver publishes none.
    efforts : ndarray, shape (len(names),), or None
        Joint efforts (N m or N), NaN where a joint has none; None when none is published.
    """

    stamp_ns: int
    names: tuple[str, ...]
    positions: np.ndarray
    velocities: np.ndarray | None = None
    efforts: np.ndarray | None = None

    def __post_init__(self) -> None:
        """Store the stamp as int, positions and velocities as frozen (len(names),) arrays."""
        names = tuple(self.names)
        object.__setattr__(self, 'stamp_ns', int(self.stamp_ns))
        object.__setattr__(self, 'names', names)
        object.__setattr__(self, 'positions',
                           frozen_array(self.positions, (len(names),), 'positions'))
        if self.velocities is not None:
            object.__setattr__(self, 'velocities',
                               frozen_array(self.velocities, (len(names),), 'velocities'))
        if self.efforts is not None:
            object.__setattr__(self, 'efforts',
                               frozen_array(self.efforts, (len(names),), 'efforts'))


@dataclass(frozen=True, eq=False)
class PointSample:
    """One tracker point: reflector centre ``xyz`` (3,) in metres, in frame ``frame_id``.

    A tracked 6-DoF pose is a point with ``orientation``, the body's unit quaternion
    [x, y, z, w] in that frame, kept exactly as received so that a logged and restored
    pose is bit for bit the live one; :attr:`rotation` is its matrix.
    """

    stamp_ns: int
    frame_id: str
    xyz: np.ndarray
    orientation: np.ndarray | None = None

    def __post_init__(self) -> None:
        """Store the stamp as int, ``xyz`` (3,) and ``orientation`` (4,) as frozen arrays."""
        object.__setattr__(self, 'stamp_ns', int(self.stamp_ns))
        object.__setattr__(self, 'xyz', frozen_array(self.xyz, (3,), 'xyz'))
        if self.orientation is not None:
            object.__setattr__(self, 'orientation', frozen_array(self.orientation, (4,),
                                                                 'orientation'))

    @property
    def rotation(self) -> np.ndarray | None:
        """(3, 3) rotation of ``orientation``; None for a plain point.

        All NaN when it is not a finite unit quaternion (rejected when paired).
        """
        return None if self.orientation is None else checked_rotation(self.orientation)


def checked_rotation(quaternion: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a quaternion [x, y, z, w]; all NaN if it is not finite and unit."""
    try:
        return rotation_from_quaternion(quaternion)
    except ValueError:
        return np.full((3, 3), np.nan)


def _quintic(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rest-to-rest profile s(τ) and ds/dτ on τ ∈ [0, 1].

    Zero velocity and acceleration at both ends, so holds are genuinely still.
    """
    s = tau ** 3 * (10.0 - 15.0 * tau + 6.0 * tau ** 2)
    ds = 30.0 * tau ** 2 * (1.0 - tau) ** 2
    return s, ds


def synthesize_streams(
    configurations: np.ndarray,
    joint_names: Sequence[str],
    points: np.ndarray,
    tracker_frame: str,
    rate_hz: float = 50.0,
    move_time_s: float = 2.0,
    hold_time_s: float = 2.0,
    start_ns: int = 1_700_000_000_000_000_000,
    joint_noise_rad: float = 0.0,
    rng: np.random.Generator | None = None,
    home: np.ndarray | None = None,
) -> tuple[list[JointSample], list[PointSample]]:
    """Simulate the streams a cell produces while the robot visits ``configurations``.

    The robot starts at ``home`` at ``start_ns`` and, for each pose, moves there in
    ``move_time_s`` (quintic rest-to-rest profile) and holds for ``hold_time_s``.
    Joint states (positions and exact profile velocities) stream at ``rate_hz``
    throughout; the tracker reports one point per pose in the middle of the hold.

    Parameters
    ----------
    configurations : ndarray, shape (N, n)
        Joint positions (rad) of the poses, in visiting order.
    joint_names : sequence of str, length n
    points : ndarray, shape (N, 3)
        Reflector centres (m) in ``tracker_frame`` reported at each pose.
    tracker_frame : str
    rate_hz : float
        Joint-state rate (Hz).
    move_time_s, hold_time_s : float
        Duration of each move and hold (s).
    start_ns : int
        Stamp of the first joint state (ns).
    joint_noise_rad : float
        Standard deviation of white noise added to every published position (rad).
    rng : numpy.random.Generator, optional
        Source of that noise.
    home : ndarray, shape (n,), optional
        Start configuration (rad); zeros by default.

    Returns
    -------
    joint_samples : list of JointSample
        In stamp order, names in ``joint_names`` order.
    point_samples : list of PointSample
        One per pose, in stamp order.
    """
    q_poses = np.asarray(configurations, dtype=float)
    eta = np.asarray(points, dtype=float)
    names = tuple(joint_names)
    if q_poses.ndim != 2 or q_poses.shape[1] != len(names) or len(q_poses) == 0:
        raise ValueError(f'configurations must have shape (N, {len(names)}) with N >= 1, '
                         f'got {q_poses.shape}')
    if eta.shape != (len(q_poses), 3):
        raise ValueError(f'points must have shape ({len(q_poses)}, 3), got {eta.shape}')
    if rate_hz <= 0 or move_time_s <= 0 or hold_time_s <= 0:
        raise ValueError('rate_hz, move_time_s and hold_time_s must be positive')
    if joint_noise_rad < 0:
        raise ValueError(f'joint_noise_rad must be >= 0, got {joint_noise_rad}')
    q_home = np.zeros(len(names)) if home is None else np.asarray(home, dtype=float)
    if q_home.shape != (len(names),):
        raise ValueError(f'home must have shape ({len(names)},), got {q_home.shape}')
    rng = np.random.default_rng() if rng is None else rng

    move_ns, hold_ns = round(move_time_s * 1e9), round(hold_time_s * 1e9)
    segment_ns = move_ns + hold_ns
    period_ns = round(1e9 / rate_hz)
    t = np.arange(0, len(q_poses) * segment_ns + 1, period_ns, dtype=np.int64)
    k = np.minimum(t // segment_ns, len(q_poses) - 1)
    tau = np.clip((t - k * segment_ns) / move_ns, 0.0, 1.0)
    s, ds = _quintic(tau)
    q_from = np.vstack([q_home, q_poses[:-1]])[k]
    delta = q_poses[k] - q_from
    positions = q_from + s[:, None] * delta
    velocities = ds[:, None] * delta / move_time_s
    if joint_noise_rad > 0:
        positions = positions + rng.normal(0.0, joint_noise_rad, positions.shape)

    joints = [JointSample(int(start_ns + ti), names, p, v)
              for ti, p, v in zip(t, positions, velocities)]
    stamps = start_ns + np.arange(len(q_poses)) * segment_ns + move_ns + hold_ns // 2
    tracker = [PointSample(int(st), tracker_frame, e) for st, e in zip(stamps, eta)]
    return joints, tracker

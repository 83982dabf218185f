"""A recording whose placement changed while it was measured: the tracker or the robot moved.

One recording is one placement of the tracker relative to the robot
(:mod:`kpi_calib_ros.core.measurement.recordings`). A tracker knocked half way, a tripod
that settled, a robot base that slipped move every later point of the recording rigidly.
Identified as one placement, the rows before and after are fitted by a compromise: the
recording's residuals grow by the jump, the robot absorbs part of it, and the TCP is stated
in a frame no measurement was taken in (measured: a Z1 whose tracker moved by 0.5 mm and 0.2
mrad half way through one of four recordings was called valid; its TCP was 168 µm from the
truth before the jump and 193 µm after, its held-out station missed by 35.9 µm against
11.5 µm without the jump and 14.6 µm with the recording split there).

The test. The fit's residuals r_i of a recording's point rows in stamp order, and their
predicted points p_i (tracker frame). A small rigid motion (t, θ) of the tracker frame moves
p_i by t + θ × p_i = A_i (t, θ), A_i = [I, −[p_i]×]. For every split k (at least
:data:`MIN_ROWS` poses each side) the rows before and after get a motion each, fitted by
weighted linear least squares; Δ(k) is the drop of the recording's χ². The joint fit placed
the recording already, so one common motion drops nothing to first order: Δ(k) measures the
relative motion, 6 degrees of freedom. Against the χ² the split leaves,
F(k) = (Δ(k)/6) / (χ²_rest/(3n − 12)), F(6, 3n − 12) distributed without a jump at any scale
of the residuals (a misfit that inflates them all makes no jump). A jump is named when the
largest F's p-value times the number of splits tried (Bonferroni) is below :data:`ALPHA`,
and the split explains at least :data:`SHARE` of the recording's χ² beyond its coordinates
(3n): a misfit of the robot that the poses' order in time happens to follow is absorbed by
a rigid motion in part only. A motion in proportion to time (6 parameters, as the step's)
that explains more than the best step makes it a steady drift (a tracker warming up, a base
creeping), named as such.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import scipy.stats

__all__ = ['PlacementJump', 'placement_jumps', 'MIN_ROWS', 'ALPHA', 'SHARE']

MIN_ROWS = 6     # poses on each side of a split: 18 coordinates for a motion of 6
ALPHA = 1e-3     # family-wise false-alarm level of one recording's scan
SHARE = 0.5      # of the recording's χ² beyond 3n the split must explain


@dataclass(frozen=True)
class PlacementJump:
    """Where a recording's placement changed, by how much, and how sure.

    ``at_s``: seconds from the recording's first row to half way between the last row before
    and the first after; ``translation_m`` / ``rotation_rad``: the motion of the rows after
    relative to those before, at the centroid of the recording's points; ``chi2`` the
    recording's χ² as fitted, ``chi2_split`` with a placement each side; ``p_value``
    Bonferroni-corrected.
    """

    recording: str
    at_s: float
    stamp_ns: int
    before: int
    after: int
    translation_m: float
    rotation_rad: float
    chi2: float
    chi2_split: float
    p_value: float
    # A steady drift over the recording explains it better than a step (χ² with a motion in
    # proportion to time, 6 parameters as the step's): a tracker warming up, a base creeping.
    drift: bool = False
    chi2_drift: float = float('nan')

    def text(self) -> str:
        """One line: which recording, when, how much, and the fix."""
        head = f'recording {self.recording}: its placement changed while it was measured'
        if self.drift:
            return (f'{head}: it drifted steadily, by {self.translation_m * 1e3:.3f} mm and '
                    f'{self.rotation_rad * 1e3:.3f} mrad from the half before '
                    f'{self.at_s:.1f} s to the half after (χ² {self.chi2:.1f} -> '
                    f'{self.chi2_drift:.1f} with a motion in proportion to time, '
                    f'{self.chi2_split:.1f} with a step; p = {self.p_value:.2g}): a tracker '
                    'warming up or a base creeping; let the tracker warm up and measure it '
                    'again, or split it into shorter recordings (split_at on this recording '
                    'in a --recordings manifest)')
        return (f'{head}, at {self.at_s:.1f} s (after {self.before} of its '
                f'{self.before + self.after} rows): the rows after moved rigidly by '
                f'{self.translation_m * 1e3:.3f} mm and {self.rotation_rad * 1e3:.3f} mrad '
                f'(χ² {self.chi2:.1f} -> {self.chi2_split:.1f} with a placement each side, '
                f'p = {self.p_value:.2g}): the tracker or the robot moved; split it there '
                f'(split_at: [{self.at_s:.1f}] on this recording in a --recordings manifest) '
                'or measure it again')

    def to_dict(self) -> dict[str, Any]:
        """Return the fields as plain numbers (calibration.yaml)."""
        return {'recording': self.recording, 'at_s': float(self.at_s),
                'stamp_ns': int(self.stamp_ns), 'rows_before': int(self.before),
                'rows_after': int(self.after), 'translation_m': float(self.translation_m),
                'rotation_rad': float(self.rotation_rad), 'chi2': float(self.chi2),
                'chi2_split': float(self.chi2_split), 'p_value': float(self.p_value),
                'drift': bool(self.drift),
                'chi2_drift': None if np.isnan(self.chi2_drift) else float(self.chi2_drift)}


def _motion_rows(points: np.ndarray) -> np.ndarray:
    """A_i (n, 3, 6): the displacement of each point by a small rigid motion (t, θ)."""
    a = np.zeros((len(points), 3, 6))
    a[:, :, :3] = np.eye(3)
    x, y, z = points.T
    # θ × p = −[p]× θ
    a[:, 0, 4], a[:, 0, 5] = z, -y
    a[:, 1, 3], a[:, 1, 5] = -z, x
    a[:, 2, 3], a[:, 2, 4] = y, -x
    return a


def _scan(residuals: np.ndarray, points: np.ndarray, sigma: np.ndarray,
          allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Return the drop of χ² at every allowed split k beyond one motion of all the rows.

    Rows [0, k) and [k, n) each get a motion; ``allowed`` (n + 1,) bool; also returns the
    motions' difference (n + 1, 6) and the χ² with the one motion.
    """
    w = 1.0 / sigma                                       # (n, 3)
    a = _motion_rows(points) * w[:, :, None]              # weighted A_i
    b = residuals * w
    ata = np.einsum('nij,nik->njk', a, a)                 # (n, 6, 6)
    atb = np.einsum('nij,ni->nj', a, b)                   # (n, 6)
    cum_m = np.concatenate([np.zeros((1, 6, 6)), np.cumsum(ata, axis=0)])
    cum_v = np.concatenate([np.zeros((1, 6)), np.cumsum(atb, axis=0)])
    n = len(residuals)
    # one motion for all the rows: what a placement held by a prior may leave
    common = float(cum_v[n] @ np.linalg.lstsq(cum_m[n], cum_v[n], rcond=None)[0])
    drop = np.zeros(n + 1)
    delta = np.zeros((n + 1, 6))
    for k in np.flatnonzero(allowed):
        m1, v1 = cum_m[k], cum_v[k]
        m2, v2 = cum_m[n] - m1, cum_v[n] - v1
        x1 = np.linalg.lstsq(m1, v1, rcond=None)[0]
        x2 = np.linalg.lstsq(m2, v2, rcond=None)[0]
        drop[k] = float(v1 @ x1 + v2 @ x2) - common
        delta[k] = x2 - x1
    return drop, delta, float(np.sum(b ** 2)) - common


def _drift_drop(residuals: np.ndarray, points: np.ndarray, sigma: np.ndarray,
                time: np.ndarray) -> float:
    """Return the drop of χ² by a motion in proportion to time, beyond one motion of all."""
    w = 1.0 / sigma
    a = _motion_rows(points) * w[:, :, None]
    b = (residuals * w).reshape(-1)
    both = np.concatenate([a, a * (time - time.mean())[:, None, None]], axis=2).reshape(-1, 12)
    one = a.reshape(-1, 6)

    def explained(m: np.ndarray) -> float:
        x = np.linalg.lstsq(m, b, rcond=None)[0]
        return float(b @ (m @ x))
    return explained(both) - explained(one)


def placement_jumps(residuals: np.ndarray, predicted: np.ndarray, sigma: np.ndarray,
                    stamps_ns: np.ndarray, groups: Sequence[tuple[str, np.ndarray]]
                    ) -> list[PlacementJump]:
    """Return the recordings of ``groups`` whose placement changed while measured.

    The test is the module docstring's.

    ``residuals``, ``predicted``, ``sigma`` (N, 3) of the fit's point rows (tracker frame, m),
    ``stamps_ns`` (N,); ``groups``: (recording name, its row indices). A pose is the rows of
    one stamp (its reflectors): splits fall between poses. A recording with fewer than 2
    :data:`MIN_ROWS` poses is not judged.
    """
    out = []
    for name, rows in groups:
        rows = np.asarray(rows, int)
        stamps = np.asarray(stamps_ns)[rows]
        if np.unique(stamps).size < 2 * MIN_ROWS:
            continue
        order = rows[np.argsort(stamps, kind='stable')]
        sorted_stamps = np.asarray(stamps_ns)[order]
        n = len(order)
        new_pose = np.r_[True, sorted_stamps[1:] != sorted_stamps[:-1]]
        poses_before = np.r_[0, np.cumsum(new_pose)]  # distinct poses among rows [0, k)
        allowed = np.r_[new_pose, False] & (poses_before >= MIN_ROWS) \
            & (poses_before[-1] - poses_before >= MIN_ROWS)
        if not allowed.any():
            continue
        drop, delta, chi2 = _scan(residuals[order], predicted[order], sigma[order], allowed)
        dof = 3 * n - 12
        splits = int(allowed.sum())
        with np.errstate(divide='ignore', invalid='ignore'):
            f = np.where(allowed, (drop / 6.0) / np.maximum(chi2 - drop, 1e-300) * dof, -1.0)
        k = int(np.argmax(f))
        p = min(1.0, float(scipy.stats.f.sf(f[k], 6, dof)) * splits)
        if not (p < ALPHA and drop[k] >= SHARE * (chi2 - 3 * n)):
            continue
        centre = predicted[order].mean(axis=0)
        t, theta = delta[k, :3], delta[k, 3:]
        s = np.asarray(stamps_ns)[order].astype(np.int64)
        steady = _drift_drop(residuals[order], predicted[order], sigma[order],
                             (s - s[0]) * 1e-9)
        out.append(PlacementJump(
            name, float((s[k - 1] + s[k]) / 2 - s[0]) * 1e-9, int(s[k]), k, n - k,
            float(np.linalg.norm(t + np.cross(theta, centre))), float(np.linalg.norm(theta)),
            chi2, chi2 - float(drop[k]), p, steady > drop[k], chi2 - steady))
    return out

"""Paired measurement data: joint values, measured points and each row's stated σ.

A tracker states its uncertainty per point (it grows with the distance, e.g. 15 µm + 6 µm/m):
``Measurements.sigma`` (N, 3) holds it per row and axis (m), NaN where a row states none;
:func:`row_sigma` puts it in place of the cell's σ row by row, so that σ in the covariance
of the measurement model, every weight and every statistic in units of σ is that row's own
(:func:`kpi_calib_ros.core.measurement.weighting.noise_weights`, the one place the weights of
data rows are formed).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

__all__ = ['Measurements', 'row_sigma', 'stated_sigma', 'joint_noise']


@dataclass(frozen=True)
class Measurements:
    """Paired measurement data.

    q : (N, n) joint values in chain order; eta : (N, 3) measured points in the
    tracker frame (m); tau : (N, n) gravity torques or None; stamps_ns : (N,);
    reflector : (N,) int index of the reflector each row measured, or None (all 0);
    ``n_reflectors + k`` marks the rotation row of reflector ``k``'s tracked body.
    rotation : (N, 3, 3) measured body rotations in the tracker frame on rotation rows
    (ignored on point rows), or None when there are none.
    sigma : (N, 3) the tracker's stated standard deviation of each row per axis (m), NaN
    where a row states none (the cell's σ applies, :func:`row_sigma`), or None: none stated.
    covariates : mapping {name: (N,) ndarray} of per-row inputs beside the joint state
    (``temperature.<frame_id>`` °C, ``delta_temperature`` K, see
    :mod:`kpi_calib_ros.core.measurement.covariates`), or None: none recorded.
    One pose measured by R reflectors is R rows with the same ``q``.
    """

    q: np.ndarray
    eta: np.ndarray
    tau: np.ndarray | None = None
    stamps_ns: np.ndarray | None = field(default=None)
    reflector: np.ndarray | None = field(default=None)
    rotation: np.ndarray | None = field(default=None)
    sigma: np.ndarray | None = field(default=None)
    covariates: Mapping[str, np.ndarray] | None = field(default=None)

    def __len__(self) -> int:
        """Return the number of rows."""
        return len(self.q)

    def subset(self, keep: np.ndarray) -> Measurements:
        """Return the rows selected by the boolean or index array ``keep``, every field kept."""
        def pick(values: np.ndarray | None) -> np.ndarray | None:
            return None if values is None else np.asarray(values)[keep]
        return Measurements(q=np.atleast_2d(self.q)[keep], eta=np.atleast_2d(self.eta)[keep],
                            tau=pick(self.tau), stamps_ns=pick(self.stamps_ns),
                            reflector=pick(self.reflector), rotation=pick(self.rotation),
                            sigma=pick(self.sigma),
                            covariates=None if self.covariates is None else {
                                name: np.asarray(v)[keep] for name, v in self.covariates.items()})


def row_sigma(sigma: float | np.ndarray, data_sigma: np.ndarray | None, n: int) -> np.ndarray:
    """Return the standard deviation (N, 3) of every row and axis, m.

    The stated per-row σ ``data_sigma`` (N, 3) where finite, the cell's ``sigma`` (scalar or
    (3,)) elsewhere.

    Raises
    ------
    ValueError
        ``sigma`` not positive, ``data_sigma`` of another shape or a stated σ <= 0 / inf.
    """
    cell = np.broadcast_to(np.asarray(sigma, float), (3,))
    if not np.all(np.isfinite(cell)) or np.any(cell <= 0):
        raise ValueError(f'noise sigma must be positive and finite, got {cell}')
    out = np.broadcast_to(cell, (n, 3)).copy()
    if data_sigma is None:
        return out
    given = np.asarray(data_sigma, float)
    if given.shape != (n, 3):
        raise ValueError(f'per-row sigma must be ({n}, 3) (m, NaN: none stated), got '
                         f'{given.shape}')
    stated = ~np.isnan(given)
    if np.any(given[stated] <= 0) or not np.all(np.isfinite(given[stated])):
        raise ValueError('per-row sigma must be positive and finite where stated (NaN: the '
                         f'cell\'s sigma), got {given[stated & ~(given > 0)][:3]}')
    out[stated] = given[stated]
    return out


def stated_sigma(sigma: float | np.ndarray, data_sigma: np.ndarray | None, n: int) -> float:
    """Return the one σ per axis (m) the rows state together.

    The mean over the axes of the cell's ``sigma`` without per-row σ; with it, of each
    axis's root mean square over the rows (:func:`row_sigma`). Whitened residuals (each
    row in units of its own σ) times this are residuals in metres of the size the rows'
    noise has: a robust σ̂ computed from them compares with it, and with the residuals'
    rms, whatever the cell's ``noise.sigma`` says.
    """
    if data_sigma is None or n == 0:
        return float(np.mean(np.broadcast_to(np.asarray(sigma, float), (3,))))
    rows = row_sigma(sigma, data_sigma, n)
    return float(np.mean(np.sqrt(np.mean(rows ** 2, axis=0))))


def joint_noise(joint_sigma: np.ndarray | Sequence[float] | None, n: int
                ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Return the joint-reading noise as a map and each chain reading's std: (S, σ_q).

    The chain readings are q + S ε, ε ~ N(0, I): ``joint_sigma`` (n,) independent stds give
    S = diag(joint_sigma); an (n, k) map is S itself (the readings of actuated joints that
    mimic joints follow: M diag(σ_x), :func:`kpi_calib_ros.io.cell_sections.joint_noise_map`).
    σ_q (n,) is each reading's std, √(S Sᵀ)_ii. (None, None) without noise.

    Raises
    ------
    ValueError
        Not n finite numbers >= 0 nor a finite map of n rows.
    """
    if joint_sigma is None:
        return None, None
    given = np.asarray(joint_sigma, float)
    if not (given.ndim in (1, 2) and given.shape[0] == n and np.all(np.isfinite(given))
            and (given.ndim == 2 or np.all(given >= 0))):
        raise ValueError(f'joint_sigma must be {n} finite numbers >= 0 (one per joint, chain '
                         f'order) or a finite map of {n} rows, got {given}')
    if given.ndim == 1:
        return np.diag(given), given
    return given, np.sqrt(np.sum(given ** 2, axis=1))

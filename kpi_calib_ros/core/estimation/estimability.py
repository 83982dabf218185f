"""Estimability of the KPI: whether each working pose's TCP is determined by the measurements.

A TCP covariance is only meaningful when the TCP point s_w = h(p, q_w) is an estimable
function of the parameters: its gradient with respect to ALL free parameters (not only the
ones QR kept, which fixes the others by a choice of gauge) must lie in the row space of the
weighted data Jacobian F. Then every parameter vector that fits the data equally well gives
the same s_w, to first order. Otherwise the reported covariance is that of one arbitrary
gauge, and a small number (60 points from one pose: "2.6 µm" with a true error of 20 mm)
is a lie.

The test, in column-equilibrated coordinates (D = diag(1/‖F_j‖), a reparametrisation that
leaves the row space unchanged): with V the right singular vectors of F D whose singular
values exceed ``rank_tolerance`` × the largest, the relative projection residual of each
KPI gradient row g D is ‖g D − (g D) V Vᵀ‖ / ‖g D‖; a working pose is estimable when the
largest over its three rows is below ``tolerance``. The parameters carrying most of that
residual are what the data misses: measure poses that move them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from kpi_calib_ros.core.estimation.identifiability import DEFAULT_TOLERANCE
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import weighted_rows

__all__ = [
    'ESTIMABILITY_TOLERANCE', 'KpiEstimability', 'kpi_estimability', 'information_rows',
    'result_estimability',
]

ESTIMABILITY_TOLERANCE = 1e-6


@dataclass(frozen=True)
class KpiEstimability:
    """Per working pose: estimable or not, the projection residual, what is missing.

    Attributes
    ----------
    working_pose_names : tuple of str
    relative_residual : (t,) ndarray
        Largest relative projection residual of the pose's three TCP gradient rows.
    estimable : (t,) bool ndarray
        ``relative_residual < tolerance``.
    missing : tuple of tuple of str
        Per pose, the free parameters (at most 5) carrying most of the residual; empty
        when estimable.
    tolerance : float
    """

    working_pose_names: tuple[str, ...]
    relative_residual: np.ndarray
    estimable: np.ndarray
    missing: tuple[tuple[str, ...], ...]
    tolerance: float

    @property
    def all_estimable(self) -> bool:
        """Whether the TCP is estimable at every working pose."""
        return bool(np.all(self.estimable))

    def summary(self) -> str:
        """One line: all estimable, or which poses are not and what would determine them."""
        if self.all_estimable:
            return (f'TCP estimable at every working pose (projection residual <= '
                    f'{float(np.max(self.relative_residual, initial=0.0)):.1e})')
        bad = [f'{name} (residual {res:.2g}; not determined: {", ".join(miss)})'
               for name, res, ok, miss in zip(self.working_pose_names, self.relative_residual,
                                              self.estimable, self.missing) if not ok]
        return ('TCP NOT estimable from the measurements at ' + '; '.join(bad) +
                ': measure more poses that move these parameters (spread every joint)')

    def to_dict(self) -> dict:
        """YAML-ready form (``tcp_estimability`` of calibration.yaml)."""
        return {'tcp_estimable': self.all_estimable, 'tolerance': float(self.tolerance),
                'poses': [{'name': n, 'estimable': bool(ok), 'relative_residual': float(r),
                           'not_determined': list(m)}
                          for n, r, ok, m in zip(self.working_pose_names,
                                                 self.relative_residual, self.estimable,
                                                 self.missing)]}


def kpi_estimability(data_jacobian: np.ndarray, kpi_jacobian: np.ndarray,
                     names: list[str] | tuple[str, ...],
                     working_pose_names: list[str] | tuple[str, ...],
                     tolerance: float = ESTIMABILITY_TOLERANCE,
                     rank_tolerance: float = DEFAULT_TOLERANCE) -> KpiEstimability:
    """Check that every KPI gradient row lies in the row space of the data Jacobian.

    Parameters
    ----------
    data_jacobian : (m, k) ndarray
        Weighted measurement Jacobian w.r.t. ALL free parameters (rows in σ units).
    kpi_jacobian : (3t, k) ndarray
        Jacobian of the stacked working-pose TCP points (m) w.r.t. the same parameters.
    names : sequence of str
        The k free parameter names.
    working_pose_names : sequence of str
        The t working poses.
    tolerance : float
        Largest relative projection residual of an estimable pose.
    rank_tolerance : float
        Singular values below this fraction of the largest count as zero (the same
        tolerance as the QR identifiability selection).
    """
    f = np.asarray(data_jacobian, float)
    g = np.asarray(kpi_jacobian, float)
    if f.shape[1] != g.shape[1] or f.shape[1] != len(names) or g.shape[0] % 3:
        raise ValueError(f'Jacobian shapes do not fit: data {f.shape}, KPI {g.shape}, '
                         f'{len(names)} names')
    t = g.shape[0] // 3
    if len(working_pose_names) != t:
        raise ValueError(f'{t} working poses in the KPI Jacobian, {len(working_pose_names)} '
                         'names')
    col = np.linalg.norm(f, axis=0)
    # A parameter the data does not move at all: scale by its KPI column, so that a KPI
    # depending on it shows as a full residual.
    fallback = np.linalg.norm(g, axis=0)
    scale = np.where(col > 0, col, np.where(fallback > 0, fallback, 1.0))
    a = f / scale
    b = g / scale
    _, s, vt = np.linalg.svd(a, full_matrices=False)
    basis = vt[s > rank_tolerance * s[0]] if len(s) and s[0] > 0 else vt[:0]
    residual = b - (b @ basis.T) @ basis
    norms = np.linalg.norm(b, axis=1)
    rel_rows = np.linalg.norm(residual, axis=1) / np.where(norms > 0, norms, 1.0)
    rel = rel_rows.reshape(t, 3).max(axis=1)
    ok = rel < tolerance
    missing = []
    for i in range(t):
        if ok[i]:
            missing.append(())
            continue
        weight = np.linalg.norm(residual[3 * i:3 * i + 3], axis=0)
        order = np.argsort(weight)[::-1]
        top = [names[j] for j in order[:5] if weight[j] > 0.05 * weight[order[0]]]
        missing.append(tuple(top))
    return KpiEstimability(tuple(working_pose_names), rel, ok, tuple(missing), tolerance)


def information_rows(model: MeasurementModel, p: np.ndarray, q: np.ndarray,
                     sigma: float | np.ndarray, idx: np.ndarray, prior: Prior | None = None,
                     reflector: np.ndarray | None = None,
                     rotation: np.ndarray | None = None,
                     covariates: Mapping[str, np.ndarray] | None = None,
                     tau: np.ndarray | None = None) -> np.ndarray:
    """Information of measured poses ``q`` (N, n) at ``p`` in columns ``idx``.

    The data Jacobian weighted by 1/σ, with a ``prior``'s L rows below (what it determines
    counts as determined); ``tau``, ``reflector``, ``rotation`` and ``covariates`` as for
    :meth:`~kpi_calib_ros.core.measurement.tracker.MeasurementModel.jacobian`.
    """
    _, jac = model.jacobian(p, np.atleast_2d(q), tau, reflector, rotation, covariates)
    rows = weighted_rows(jac, 1.0 / np.broadcast_to(np.asarray(sigma, float), (3,)), idx)
    return rows if prior is None else np.vstack([rows, prior.rows(model.params)[0][:, idx]])


def result_estimability(model: MeasurementModel, q: np.ndarray, sigma: np.ndarray,
                        p: np.ndarray, q_work: np.ndarray,
                        working_pose_names: list[str] | tuple[str, ...],
                        free: list[str] | tuple[str, ...] | None = None,
                        tolerance: float = ESTIMABILITY_TOLERANCE,
                        prior: Prior | None = None,
                        reflector: np.ndarray | None = None,
                        rotation: np.ndarray | None = None,
                        covariates: Mapping[str, np.ndarray] | None = None,
                        tau: np.ndarray | None = None,
                        tau_work: np.ndarray | None = None) -> KpiEstimability:
    """:func:`kpi_estimability` of a model at parameters ``p`` for measured poses ``q`` (N, n).

    σ (3,) and working poses ``q_work`` (t, n); ``free`` names the free parameters (all by
    default); ``reflector`` (N,) the reflector each row measured. A ``rotation`` (N, 3, 3) the
    measured rotations of rotation rows; ``covariates`` the rows' covariates (their recording,
    their payload). ``tau`` (N, n): the torques the rows' effects read (measured joint
    torques; default the gravity torques with each row's payload); ``tau_work`` (t, n):
    those at the working poses (each with its own payload; default the cell's). A
    ``prior``'s rows count as information: what it determines is estimable.
    """
    names = list(free) if free else list(model.params.names)
    idx = model.params.indices(names)
    data_jac = information_rows(model, p, q, sigma, idx, prior, reflector, rotation, covariates,
                                tau)
    _, kpi = model.jacobian(p, np.atleast_2d(q_work), tau_work)
    return kpi_estimability(data_jac, kpi.reshape(-1, len(p))[:, idx], names,
                            working_pose_names, tolerance)

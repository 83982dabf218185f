"""Weights of the measurement rows and the weighted Jacobian and residuals they form.

Each row is weighted by 1/σ of its own (:func:`kpi_calib_ros.core.measurement.data.row_sigma`),
or whitened with joint-reading noise
(:meth:`kpi_calib_ros.core.measurement.tracker.MeasurementModel.whitening`).
"""
from __future__ import annotations

import numpy as np

from kpi_calib_ros.core.measurement.data import Measurements, row_sigma
from kpi_calib_ros.core.measurement.payload import payload_torques
from kpi_calib_ros.core.measurement.tracker import MeasurementModel

__all__ = ['row_torques', 'noise_weights', 'weighted_rows', 'weighted_residuals', 'unweighted',
           'point_rows', 'point_rms', 'row_noise_variance']


def row_torques(model: MeasurementModel, data: Measurements) -> np.ndarray | None:
    """Return the torques (N, n) the effects of ``model`` read at ``data``'s rows, or None.

    ``data.tau`` where recorded (measured joint torques, (N, n)); else, when an effect reads
    the gravity torque, the robot's at every row with that row's payload
    (:mod:`kpi_calib_ros.core.measurement.payload`: ``payload.mass`` among the covariates, else
    the cell's payload) with its gradient, (N, n + n²): the model takes the torque at the
    deflected configuration from it; None when no effect reads a torque. Column j < n is
    joint j's torque either way.
    """
    if data.tau is not None:
        return np.atleast_2d(np.asarray(data.tau, float))
    if not model.uses_torque:
        return None
    return payload_torques(model.robot, np.atleast_2d(data.q), data.covariates, gradient=True)


def noise_weights(model: MeasurementModel, p: np.ndarray, data: Measurements,
                  sigma: float | np.ndarray, tau: np.ndarray | None = None,
                  point_weights: np.ndarray | None = None) -> np.ndarray:
    """Weights of ``data``'s rows at ``p`` for :func:`weighted_rows`.

    (N, 3) 1/σ_i,a (each row's stated σ or the cell's ``sigma``, :func:`row_sigma`) times √ω_i,
    or (N, 3, 3) whitening with joint-reading noise (:meth:`MeasurementModel.whitening`).
    """
    q = np.atleast_2d(data.q)
    rows = row_sigma(sigma, data.sigma, len(q))
    if tau is None:
        tau = row_torques(model, data)
    return model.whitening(np.asarray(p, float), q, rows, tau, data.reflector, data.rotation,
                           point_weights, data.covariates)


def weighted_rows(jac: np.ndarray, w: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
    """Stacked weighted Jacobian ``W J`` (3N, k) of point Jacobians ``jac`` (N, 3, n_p).

    Parameters
    ----------
    jac : (N, 3, n_p) ndarray
        d h_i / d p per measurement (m per unit of each parameter).
    w : (3,), (3R,), (N, 3) or (N, 3, 3) ndarray
        1/σ per tracker axis (1/m); (3R,) for rows of ``MeasurementModel.pose_jacobian``;
        (N, 3) per measurement and axis (robustness weights); (N, 3, 3) a whitening
        matrix per measurement (joint-reading noise, :meth:`MeasurementModel.whitening`).
    idx : (k,) int ndarray, optional
        Parameter columns to keep (default all).

    Returns
    -------
    (3N, k) ndarray
        Row 3i + a is axis a of measurement i, in units of σ.
    """
    w = np.asarray(w)
    if w.ndim == 3:
        rows = np.einsum('nab,nbk->nak', w, jac).reshape(-1, jac.shape[2])
    else:
        rows = (jac * (w[None, :, None] if w.ndim == 1 else w[:, :, None])
                ).reshape(-1, jac.shape[2])
    return rows if idx is None else rows[:, idx]


def weighted_residuals(residuals: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Stacked weighted residuals (3N,) of ``residuals`` (N, 3) in m, in units of σ.

    ``w`` are the weights of :func:`weighted_rows` ((3,), (N, 3) or (N, 3, 3)).
    """
    return weighted_rows(np.asarray(residuals, float)[:, :, None], w)[:, 0]


def unweighted(r: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Residuals (N, 3) in m from weighted residuals ``r`` (3N,).

    The inverse of :func:`weighted_residuals` (a row of weight 0 gives 0).
    """
    r = np.asarray(r, float).reshape(-1, 3)
    w = np.asarray(w, float)
    if w.ndim == 3:
        return np.einsum('nab,nb->na', np.linalg.pinv(w), r)
    return np.divide(r, w, out=np.zeros_like(r), where=w != 0)


def point_rows(reflector: np.ndarray | None, n_reflectors: int) -> np.ndarray | None:
    """Return which rows (N,) bool are points, not a tracked body's rotations; None: all.

    A rotation row's residual is in rad: an rms in m takes the point rows only (the rows
    of channels from ``n_reflectors`` on are rotations, as the fit's own rms counts them).
    """
    if reflector is None:
        return None
    points = np.asarray(reflector, int) < n_reflectors
    return None if points.all() else points


def point_rms(metres: np.ndarray, points: np.ndarray | None) -> float:
    """Return the rms (m) of the residuals (N, 3) ``metres`` over rows ``points`` (None: all)."""
    metres = np.asarray(metres, float).reshape(-1, 3)
    if points is not None:
        metres = metres[points]
    return float(np.sqrt(np.mean(np.sum(metres ** 2, axis=1))))


def row_noise_variance(w: np.ndarray, n: int) -> np.ndarray:
    """Return the total noise variance Σ_a σ_a² (n,) (m²) the weights ``w`` state per row.

    ``w``: weights 1/σ as :func:`unweighted` takes them, or whitening matrices W
    (n, 3, 3), whose point covariance is (WᵀW)⁻¹.
    """
    w = np.asarray(w, float)
    if w.ndim == 3:
        return np.trace(np.linalg.inv(np.einsum('nba,nbc->nac', w, w)), axis1=1, axis2=2)
    return np.sum(unweighted(np.ones(3 * n), w) ** 2, axis=1)

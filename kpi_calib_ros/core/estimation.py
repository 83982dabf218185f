"""Constrained least-squares identification with KPI variables, eq. (13) and (19).

The estimate solves

    min_v ½‖Σ⁻¹(η − h(p, q_meas))‖²  s.t.  s = h(p, q_work)

over the identifiable parameters p and the KPI points s. Because s enters only
the constraint, the minimiser is p̂ of the plain weighted least squares and
ŝ = h(p̂, q_work); the covariance of v = (p, s) comes from the KKT matrix,
eq. (19). Non-convergence is reported as a status, not an exception.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.stats

from kpi_calib_ros.core.covariance import kkt_covariance, kpi_jacobians
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.identifiability import (DroppedParameter, Identifiability,
                                                select_identifiable)
from kpi_calib_ros.core.measurement import MeasurementModel, Measurements, weighted_rows


# A nominal model is off by millimetres, a wrong unit or frame by metres.
MAX_START_ERROR = 0.1
MAX_SELECTION_ROUNDS = 4
MIN_PREDICTED_DECREASE = 1e-9


@dataclass(frozen=True)
class CalibrationResult:
    """Everything an identification produces.

    Attributes
    ----------
    names : tuple of str
        All parameter names of the model, in vector order.
    values : (n_p,) ndarray
        Estimated values (dropped parameters stay at their prior value).
    estimated : tuple of str
        Names of the identified parameters.
    std : (k,) ndarray
        Standard deviations of the identified parameters (from the stated σ).
    covariance : (k, k) ndarray
        C_p block of eq. (19).
    residuals : (N, 3) ndarray
        η − h(p̂, q) per measurement, tracker frame, m.
    rms_m : float
        sqrt(mean ‖r_i‖²), m.
    tcp : (t, 3) ndarray
        KPI points ŝ at the working poses, tracker frame, m.
    tcp_covariance : (t, 3, 3) ndarray
        C_s blocks of eq. (19), m².
    chi2, dof, p_value : float, int, float
        Weighted residual sum against σ, degrees of freedom, upper-tail probability.
    """

    names: tuple[str, ...]
    values: np.ndarray
    units: tuple[str, ...]
    estimated: tuple[str, ...]
    std: np.ndarray
    covariance: np.ndarray
    residuals: np.ndarray
    rms_m: float
    tcp: np.ndarray
    tcp_covariance: np.ndarray
    working_pose_names: tuple[str, ...]
    sigma: np.ndarray
    chi2: float
    dof: int
    p_value: float
    converged: bool
    status: str
    iterations: int
    identifiability: Identifiability

    @property
    def correlation(self) -> np.ndarray:
        return self.covariance / np.outer(self.std, self.std)

    @property
    def dropped(self) -> tuple[DroppedParameter, ...]:
        return self.identifiability.dropped

    def value(self, name: str) -> float:
        return float(self.values[self.names.index(name)])

    def std_of(self, name: str) -> float:
        return float(self.std[self.estimated.index(name)])


def weights(sigma: float | np.ndarray) -> np.ndarray:
    """Per-axis weights 1/σ (3,) from a scalar or (3,) σ in metres."""
    sigma = np.broadcast_to(np.asarray(sigma, float), (3,))
    if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise ValueError(f'noise sigma must be positive and finite, got {sigma}')
    return 1.0 / sigma


def identify(model: MeasurementModel, data: Measurements, sigma: float | np.ndarray,
             q_work: np.ndarray, working_pose_names: list[str] | None = None,
             p0: np.ndarray | None = None, free: list[str] | None = None,
             max_iterations: int = 50, identifiability_method: str = 'pivoted',
             priority: list[str] | None = None) -> CalibrationResult:
    """Identify the parameters of ``model`` from tracker data.

    Parameters
    ----------
    model : MeasurementModel
    data : Measurements
        q (N, n) in chain order, eta (N, 3) in the tracker frame, m.
    sigma : float or (3,) array
        Tracker noise standard deviation per axis, m.
    q_work : (t, n) ndarray
        Working configurations whose KPI points are estimated.
    p0 : (n_p,) ndarray, optional
        Start values; the model's nominal values by default.
    free : list of str, optional
        Parameters allowed to vary; all by default. The identifiable subset of
        these is chosen by QR on the data Jacobian at ``p0``.

    Raises
    ------
    DataError
        Non-finite data or too few measurements for the identifiable set.
    """
    w = weights(sigma)
    q, eta = np.atleast_2d(data.q), np.atleast_2d(data.eta)
    if q.shape[0] != eta.shape[0] or eta.shape[1] != 3 or q.shape[1] != model.robot.n_joints:
        raise DataError(f'measurement shapes do not fit: q {q.shape}, eta {eta.shape}, '
                        f'{model.robot.n_joints} joints')
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(eta))):
        raise DataError('measurements contain NaN or inf; reject them before identification')
    q_work = np.atleast_2d(np.asarray(q_work, float))
    names = working_pose_names or [f'work_{i + 1}' for i in range(len(q_work))]
    tau = model.robot.gravity_torques(q) if model.uses_torque else None
    tau_work = model.robot.gravity_torques(q_work) if model.uses_torque else None
    p = np.array(model.params.nominal if p0 is None else p0, dtype=float)
    free_idx = model.params.indices(free) if free else np.arange(len(p))

    pred, _ = model.jacobian(p, q, tau)
    start_error = float(np.median(np.linalg.norm(eta - pred, axis=1)))
    if start_error > MAX_START_ERROR:
        raise DataError(f'measured points are {start_error:.3g} m (median) from the nominal '
                        'prediction; check that points are in metres, in the tracker frame, and '
                        'that tracker.base_in_tracker and the joint order/units are right')
    free_names = [model.params.names[i] for i in free_idx]
    # Identifiability depends on the geometry: at a nominal reflector exactly on the
    # flange axis some directions vanish that the real (slightly off-axis) robot has.
    # Select at the start, fit, and select again at the estimate until the set is stable.
    # A parameter dropped in a later round keeps the value it was fitted to: the full
    # vector stays one exact solution (one gauge); resetting it would restart the fit.
    ident, iterations, kept_before = None, 0, None
    for _ in range(MAX_SELECTION_ROUNDS):
        _, jac = model.jacobian(p, q, tau)
        stacked = weighted_rows(jac, w, free_idx)
        ident = select_identifiable(stacked, free_names, method=identifiability_method,
                                    priority=priority)
        if kept_before is not None and ident.rank == len(kept_before):
            # Same rank: the fitted set still spans the identifiable directions (QR may
            # merely prefer an equivalent subset here). Keep it; restate its reasons here.
            kept_first = list(kept_before) + [n for n in free_names if n not in kept_before]
            again = select_identifiable(stacked, free_names, method='priority',
                                        priority=kept_first)
            if again.kept == kept_before:
                ident = again
                break
        if ident.kept == kept_before:
            break
        idx = model.params.indices(ident.kept)
        if 3 * len(q) <= len(idx):
            raise DataError(f'too few measurements: {len(q)} points give {3 * len(q)} '
                            f'equations for {len(idx)} identifiable parameters; measure at '
                            f'least {len(idx) // 3 + 2} poses (better 3-5x that)')
        p, converged, status, used = _gauss_newton(model, p, idx, q, eta, tau, w,
                                                   max_iterations)
        iterations += used
        kept_before = ident.kept
    pred, jac = model.jacobian(p, q, tau)
    residuals = eta - pred
    f1_p = weighted_rows(jac, w, idx)
    tcp, tcp_jac = model.jacobian(p, q_work, tau_work)
    f1, f2 = kpi_jacobians(f1_p, tcp_jac.reshape(-1, len(p))[:, idx])
    c_v = kkt_covariance(f1, f2)
    k = len(idx)
    c_p = c_v[:k, :k]
    c_s = c_v[k:, k:]
    t = len(q_work)
    tcp_cov = np.array([c_s[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(t)])
    chi2 = float(np.sum((residuals * w) ** 2))
    dof = 3 * len(q) - k
    return CalibrationResult(
        names=model.params.names, values=p, units=model.params.units,
        estimated=ident.kept, std=np.sqrt(np.diag(c_p)), covariance=c_p,
        residuals=residuals, rms_m=float(np.sqrt(np.mean(np.sum(residuals ** 2, axis=1)))),
        tcp=tcp, tcp_covariance=tcp_cov, working_pose_names=tuple(names),
        sigma=1.0 / w, chi2=chi2, dof=dof, p_value=float(scipy.stats.chi2.sf(chi2, dof)),
        converged=converged, status=status, iterations=iterations, identifiability=ident)


def _gauss_newton(model: MeasurementModel, p: np.ndarray, idx: np.ndarray, q: np.ndarray,
                  eta: np.ndarray, tau: np.ndarray | None, w: np.ndarray,
                  max_iterations: int) -> tuple[np.ndarray, bool, str, int]:
    """Gauss-Newton with Armijo backtracking; Levenberg-Marquardt damping when that stalls."""
    def evaluate(pp):
        pred, jac = model.jacobian(pp, q, tau)
        r = ((eta - pred) * w).ravel()
        f = (jac * w[None, :, None]).reshape(-1, len(pp))[:, idx]
        return r, f

    r, f = evaluate(p)
    cost = 0.5 * r @ r
    for iteration in range(1, max_iterations + 1):
        scale = np.linalg.norm(f, axis=0)
        step_scaled, *_ = np.linalg.lstsq(f / scale, r, rcond=None)
        step = step_scaled / scale
        # Converged when the step is negligible against the parameters' own std:
        # |Δ_i| σ_i⁻¹ ≈ |step_scaled_i| in equilibrated units.
        if np.max(np.abs(step_scaled)) < 1e-8 * max(1.0, np.sqrt(2 * cost)):
            return p, True, 'converged: step below 1e-8 of parameter std', iteration
        # Gauss-Newton predicts a decrease of ½‖F Δ‖² in ½χ²; below 1e-9 nothing is left to
        # gain (round-off in flat directions would only make the line search fail slowly).
        predicted = 0.5 * np.sum((f @ step) ** 2)
        if predicted < MIN_PREDICTED_DECREASE:
            return p, True, 'converged: predicted χ² decrease below 1e-9', iteration
        accepted = False
        for damping in (0.0, 1e-3, 1e-1, 10.0):
            if damping:
                a = f / scale
                lhs = a.T @ a + damping * np.eye(len(idx))
                step = np.linalg.solve(lhs, a.T @ r) / scale
            alpha = 1.0
            slope = -(f.T @ r) @ step  # directional derivative of the cost (negative)
            while alpha > 1e-6:
                trial = p.copy()
                trial[idx] += alpha * step
                r_try, f_try = evaluate(trial)
                cost_try = 0.5 * r_try @ r_try
                if cost_try <= cost + 1e-4 * alpha * slope:
                    accepted = True
                    break
                alpha *= 0.5
            if accepted:
                break
        if not accepted:
            return p, True, 'converged: no descent direction improves the cost', iteration
        relative = (cost - cost_try) / max(cost, 1e-300)
        p, r, f, cost = trial, r_try, f_try, cost_try
        if relative < 1e-14:
            return p, True, 'converged: cost change below 1e-14', iteration
    return p, False, f'not converged after {max_iterations} iterations', max_iterations

"""Gauss-Newton in a trust region: the solver of the identification, its stopping tests.

As SciPy's ``least_squares`` (``trf`` without bounds): the stopping tests are named
tolerances with their formulas (:class:`Tolerances`), a run ends with an integer status and
its message (:data:`STATUS_MESSAGES`). The identification around it (the identifiable set,
the reweighting, the covariance) is :func:`kpi_calib_ros.core.estimation.least_squares.identify`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import scipy.optimize

from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import weighted_residuals, weighted_rows

__all__ = [
    'PriorRows', 'Tolerances', 'TOLERANCES', 'LINE_SEARCH_FAILED', 'MAX_ITERATIONS', 'GTOL',
    'FTOL', 'XTOL', 'PREDICTED_DECREASE', 'STATISTICAL', 'STATUS_MESSAGES', 'SHRINK', 'GROW',
    'ACCELERATION_PROBE', 'ACCELERATION_RATIO', 'gauss_newton',
]

# Prior rows over the full parameter vector: L (n_rows, n_p) and L m (n_rows,).
PriorRows = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class Tolerances:
    """Stopping tests of the Gauss-Newton iteration, as SciPy's ``least_squares`` names them.

    Notation: r (m,) the weighted residual (η − h(p, q))/σ, dimensionless; F (m, k) its
    Jacobian with respect to the identified parameters; D = diag(‖F_i‖) the column norms
    (equilibration); C = ½‖r‖² the cost; Δ the Gauss-Newton step, so D Δ is the step in
    equilibrated units. The tests run in the order below and the first that holds sets the
    status code (see `STATUS_MESSAGES`).

    Attributes
    ----------
    gtol : float
        Gradient test, status 1: ``max_i |F_iᵀ r| / (‖F_i‖ ‖r‖) < gtol``, the largest cosine
        between the residual and a Jacobian column (SciPy's ``'lm'`` gtol): r is orthogonal
        to every direction the parameters can move it in.
    xtol : float
        Step test, status 3: ``‖D Δ‖∞ < xtol · max(1, ‖r‖)``. |Δ_i| ‖F_i‖ is the step of
        parameter i against its own std, so this is a step far below the uncertainty.
    pred_tol : float
        Predicted-decrease test, status 4: ``½‖F Δ‖² < max(pred_tol, roundoff · ε_C)``.
        ½‖F Δ‖² is the decrease of C the linear model promises, and also half the squared
        Mahalanobis length of Δ against C_p = (FᵀF)⁻¹: 1e-9 is a step of 4.5e-5 std.
        ε_C = eps · ‖r‖ · ‖w∘η‖ / √m is the round-off of the evaluated cost (each r_j is the
        difference of two numbers of size |w_j η_j| and carries about eps times that; the
        errors add in r·δr as a random walk; measured on the default cell, 60 and 500 poses,
        residuals at and 20x the noise, over 200 relative perturbations of p by 1e-15: std
        0.2-0.3 ε_C, range 1.0-1.7 ε_C). A decrease the cost cannot resolve is convergence,
        never a line-search failure.
    roundoff : float
        Safety factor on ε_C in the predicted-decrease test.
    ftol : float
        Cost test, status 2, on an accepted step Δ whose gain ratio ρ (actual over
        predicted decrease) exceeds 0.25, so the linear model held along it: both its actual
        relative decrease ``(C_old − C_new) / C_old`` and its predicted relative decrease
        ``(−∇Cᵀ Δ − ½‖F Δ‖²) / C_old`` are below ``ftol``. This is MINPACK's ``lmder`` ftol
        test (info 1), with SciPy's ``least_squares`` condition ρ > 0.25 and its default
        1e-8. Δ is the step taken (the Gauss-Newton step, or the damped step on the trust
        region's boundary): in the trust region, where the model was just confirmed, no step
        gains ``ftol`` of the cost. A step the cost test does not look at: a rejected trial
        (it is no estimate), and an accepted step with ρ ≤ 0.25 (the model failed; the
        region shrinks and the iteration goes on). Found on simulated starts 5-20 mm /
        10-50 mrad off the truth (``bench/solver_vs_trf.py``): some end in a wrong minimum
        (0.6-14 mm rms) on a nearly singular Jacobian, the Gauss-Newton step 10⁷-10⁹ in
        equilibrated units and predicting the whole cost, while damped steps gain 1e-8 to
        1e-7 of it each; no Gauss-Newton test can hold there, and SciPy's TRF stops on this
        test. SciPy's other two tests are not taken over: its gtol is absolute in the units
        of r (``gtol`` here is the scale-free cosine) and its xtol compares the step with
        ‖p‖, which adds metres to radians (``xtol`` here is against the parameter std).
    stat_tol : float
        Statistical test, status 5: the last step had to be damped (the linear model
        failed along the Gauss-Newton step) and the Gauss-Newton step now predicts
        ``½‖F Δ‖² < stat_tol``: what is left to gain moves the estimate by less than
        √(2 · stat_tol) = 0.14 of its std in the Mahalanobis sense, far below its
        precision. Found on MAP fits with a previous calibration as prior and 10 poses,
        where the re-selected parameter set is nearly dependent (smallest singular value
        3e-7 of the equilibrated Jacobian): the remaining predicted decrease stayed at
        0.0086 while damped steps gained 5e-10 each, 50 iterations without end.
    armijo : float
        Sufficient decrease for accepting a step Δ (Gauss-Newton or damped):
        ``C(p + Δ) ≤ C(p) − armijo · (−∇Cᵀ Δ)``. A trial that fails it shrinks the trust
        region to a quarter of its length; once the region is smaller than the step test's
        ``xtol · max(1, ‖r‖)`` without a step that passes: status -1.
    """

    gtol: float = 1e-10
    xtol: float = 1e-8
    pred_tol: float = 1e-9
    stat_tol: float = 1e-2
    roundoff: float = 10.0
    ftol: float = 1e-8
    armijo: float = 1e-4


TOLERANCES = Tolerances()

# Status codes of an identification. Positive: a convergence test held (converged);
# 0 and negative: the iteration stopped without converging.
LINE_SEARCH_FAILED = -1
MAX_ITERATIONS = 0
GTOL = 1
FTOL = 2
XTOL = 3
PREDICTED_DECREASE = 4
STATISTICAL = 5
STATUS_MESSAGES = {
    LINE_SEARCH_FAILED: 'failed: neither the Gauss-Newton step nor a damped step in a '
                        'trust region down to the step tolerance decreases the cost '
                        '(predicted decrease {pred:.3g} above round-off)',
    MAX_ITERATIONS: 'not converged: maximum number of iterations ({iterations}) reached',
    GTOL: 'converged: gradient test, max cosine(residual, Jacobian column) < gtol {gtol:g}',
    FTOL: 'converged: cost test, the last step (gain ratio {rho:.2f}) decreased ½χ² = '
          '{cost:.6g} by {decrease:.3g} and predicted {model:.3g}, both < ftol {ftol:g} of it',
    XTOL: 'converged: step test, step < xtol {xtol:g} of parameter std',
    PREDICTED_DECREASE: 'converged: predicted decrease of ½χ² {pred:.3g} below '
                        'max(pred_tol {pred_tol:g}, cost round-off)',
    STATISTICAL: 'converged: statistical test, the remaining Gauss-Newton step predicts a '
                 'decrease of ½χ² {pred:.3g} < stat_tol {stat_tol:g} (under 0.14 std) and '
                 'the last step was damped by nonlinearity',
}


# Trust-region radius updates (Nocedal & Wright, Algorithm 4.1; SciPy's ``trf``).
SHRINK, GROW = 0.25, 2.0
# Geodesic acceleration of a damped step (Transtrum & Sethna 2012, arXiv:1207.4999): the
# residuals' curvature along the step from one more prediction at this fraction of it, and
# the largest 2‖a‖/‖v‖ it is used at. On a curved valley (a TIAGo MAP fit with three
# joint plays, 79 parameters) the trust region took 2984 steps without it, 434 with it,
# to a cost 1e-2 lower; SciPy's TRF stopped after 1047 evaluations 0.23 above.
ACCELERATION_PROBE = 0.1
ACCELERATION_RATIO = 0.75


def _boundary_step(u: np.ndarray, s: np.ndarray, vt: np.ndarray, r: np.ndarray,
                   radius: float) -> tuple[np.ndarray, float]:
    """Return the Levenberg-Marquardt step on the trust-region boundary and its λ.

    z(λ) = V diag(s / (s² + λ)) Uᵀ r of A = U diag(s) Vᵀ with ‖z(λ)‖ = ``radius``, the
    minimiser of ‖r − A z‖ on the boundary (valid when the Gauss-Newton step z(0) is longer
    than ``radius``).
    """
    sc = s * (u.T @ r)

    def excess(lam: float) -> float:
        return float(np.linalg.norm(sc / (s ** 2 + lam))) - radius
    # ‖z(λ)‖ falls monotonically from ‖z(0)‖ > radius and is below ‖S c‖/λ.
    upper = float(np.linalg.norm(sc)) / radius
    lam = upper if excess(upper) >= 0 else scipy.optimize.brentq(excess, 0.0, upper,
                                                                 xtol=1e-12 * upper, rtol=1e-10)
    return vt.T @ (sc / (s ** 2 + lam)), lam


def _damped_solve(u: np.ndarray, s: np.ndarray, vt: np.ndarray, b: np.ndarray,
                  lam: float) -> np.ndarray:
    """Return z = (AᵀA + λ I)⁻¹ Aᵀ b of A = U diag(s) Vᵀ."""
    return vt.T @ (s * (u.T @ b) / (s ** 2 + lam))


def gauss_newton(model: MeasurementModel, p: np.ndarray, idx: np.ndarray, q: np.ndarray,
                  eta: np.ndarray, tau: np.ndarray | None, w: np.ndarray, max_iterations: int,
                  tol: Tolerances = TOLERANCES, reflector: np.ndarray | None = None,
                  rows: PriorRows | None = None,
                  rotation: np.ndarray | None = None,
                  covariates: Mapping[str, np.ndarray] | None = None
                  ) -> tuple[np.ndarray, int, str, int]:
    """Gauss-Newton in a trust region (Levenberg-Marquardt), as SciPy's ``trf`` without bounds.

    The step z = D Δ lives in equilibrated units (D the largest column norms of F seen so
    far, SciPy's ``x_scale='jac'``). The Gauss-Newton step is taken whole while it lies in
    the trust region (at the start the region is unbounded, so a well-behaved fit takes
    exactly the Gauss-Newton steps); otherwise the damped step (AᵀA + λ I) z = Aᵀ r,
    A = F D⁻¹, on the region's boundary. The region shrinks to a quarter of the step when
    the gain ratio ρ (actual over predicted decrease) is below 0.25 and doubles when
    ρ > 0.75 on the boundary (Nocedal & Wright, Algorithm 4.1). Unlike a line search
    along the Gauss-Newton direction, the damped step turns towards the steepest descent,
    which follows the curved valleys of a nearly dependent parameter set.

    Returns
    -------
    p : (n_p,) ndarray
        Last accepted parameters (only ``idx`` moved).
    status, message : int, str
        See `STATUS_MESSAGES` and `Tolerances`.
    iterations : int
        Accepted steps (each may have needed several trials of λ).
    """
    def residual(pp: np.ndarray, pred: np.ndarray) -> np.ndarray:
        r = weighted_residuals(eta - pred, w)
        # Prior rows: residual L(m − p), Jacobian L (as for h, F = ∂(Lp)/∂p).
        return r if rows is None else np.concatenate([r, rows[1] - rows[0] @ pp])

    def evaluate(pp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pred, jac = model.jacobian(pp, q, tau, reflector, rotation, covariates)
        f = weighted_rows(jac, w, idx)
        if rows is not None:
            f = np.vstack([f, rows[0][:, idx]])
        return residual(pp, pred), f

    def acceleration(velocity: np.ndarray, svd: tuple[np.ndarray, np.ndarray, np.ndarray],
                     lam: float) -> np.ndarray:
        """Geodesic acceleration of the damped step ``velocity`` (Δ units), equilibrated.

        The second directional derivative of the residuals along the step, from one more
        prediction at ``ACCELERATION_PROBE`` of it, solved with the step's own damping;
        zero where it is not small beside the step (``ACCELERATION_RATIO``) or not finite.
        """
        probe = p.copy()
        probe[idx] += ACCELERATION_PROBE * velocity
        r_probe = residual(probe, model.predict(probe, q, tau, reflector, rotation, covariates))
        h = ACCELERATION_PROBE
        second = 2.0 * (r_probe - r + h * (f @ velocity)) / h ** 2
        z_a = _damped_solve(svd[0], svd[1], svd[2], second, lam)
        z_v = region * velocity
        if not (np.all(np.isfinite(z_a))
                and 2.0 * np.linalg.norm(z_a) <= ACCELERATION_RATIO * np.linalg.norm(z_v)):
            return np.zeros_like(z_v)
        return z_a

    def stop(status: int, iteration: int, **figures: float) -> tuple[np.ndarray, int, str, int]:
        text = STATUS_MESSAGES[status].format(**figures, **tol.__dict__,
                                              iterations=max_iterations)
        return p, status, text, iteration

    # Size of the measured values the residuals are differences of (see Tolerances.pred_tol).
    eta_scale = np.linalg.norm(weighted_residuals(eta, w)) / np.sqrt(eta.size)
    r, f = evaluate(p)
    cost = 0.5 * r @ r
    # Whether the last accepted step was damped (the linear model failed along the
    # Gauss-Newton step).
    nonlinear = False
    region: np.ndarray | None = None
    radius = float(np.inf)  # trust region on the equilibrated step DΔ; none until a step fails
    for iteration in range(1, max_iterations + 1):
        # A column can vanish on the way (a saturating effect's shape parameter once
        # tanh is flat at every pose): no step along it, not a NaN step.
        scale = np.linalg.norm(f, axis=0)
        scale[scale == 0] = 1.0
        # The trust region lives in units D Δ with D the largest column norms so far (as
        # SciPy's x_scale='jac'): a radius keeps its meaning from one iteration to the next.
        region = scale if region is None else np.maximum(region, scale)
        norm_r = np.sqrt(2 * cost)
        gradient = f.T @ r  # = −∇C (F is ∂h/∂p weighted, r = w(η − h))
        if np.max(np.abs(gradient) / scale) < tol.gtol * norm_r:
            return stop(GTOL, iteration)
        a = f / scale
        step_scaled, *_ = np.linalg.lstsq(a, r, rcond=None)
        if np.max(np.abs(step_scaled)) < tol.xtol * max(1.0, norm_r):
            return stop(XTOL, iteration)
        predicted = 0.5 * np.sum((a @ step_scaled) ** 2)
        roundoff = np.finfo(float).eps * norm_r * eta_scale
        if predicted < max(tol.pred_tol, tol.roundoff * roundoff):
            return stop(PREDICTED_DECREASE, iteration, pred=predicted)
        if nonlinear and predicted < tol.stat_tol:
            return stop(STATISTICAL, iteration, pred=predicted)
        gn_step = step_scaled / scale
        gn_length = float(np.linalg.norm(region * gn_step))
        svd = None
        while True:
            step = gn_step
            if gn_length > radius:
                # The Gauss-Newton step leaves the trust region: the damped step on its
                # boundary, (AᵀA + λ I) z = Aᵀ r with ‖z‖ = radius, A = F D⁻¹.
                if svd is None:
                    svd = np.linalg.svd(f / region, full_matrices=False)
                velocity, lam = _boundary_step(*svd, r, radius)
                step = (velocity + 0.5 * acceleration(velocity / region, svd, lam)) / region
            length = float(np.linalg.norm(region * step))
            linear = gradient @ step  # decrease of the cost along Δ to first order (> 0)
            model_decrease = linear - 0.5 * np.sum((f @ step) ** 2)
            trial = p.copy()
            trial[idx] += step
            r_try, f_try = evaluate(trial)
            cost_try = 0.5 * r_try @ r_try
            # A point where the Jacobian is not finite (a saturating effect's shape
            # parameter driven to a sharp step) is no step to take.
            if cost_try <= cost - tol.armijo * linear and np.all(np.isfinite(f_try)):
                break
            radius = SHRINK * length
            if radius < tol.xtol * max(1.0, norm_r):
                return stop(LINE_SEARCH_FAILED, iteration, pred=predicted)
        nonlinear = bool(gn_length > radius)
        rho = (cost - cost_try) / model_decrease if model_decrease > 0 else 0.0
        if rho < 0.25:
            radius = SHRINK * length
        elif rho > 0.75 and nonlinear:
            radius = GROW * radius
        decrease = cost - cost_try
        converged = (rho > 0.25 and decrease < tol.ftol * cost
                     and model_decrease < tol.ftol * cost)
        p, r, f, cost_old, cost = trial, r_try, f_try, cost, cost_try
        if converged:
            return stop(FTOL, iteration, rho=rho, cost=cost_old, decrease=decrease,
                        model=model_decrease)
    return p, MAX_ITERATIONS, STATUS_MESSAGES[MAX_ITERATIONS].format(
        iterations=max_iterations), max_iterations

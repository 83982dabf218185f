"""Constrained least-squares identification with KPI variables, eq. (13) and (19).

The estimate solves

    min_v ½‖Σ⁻¹(η − h(p, q_meas))‖²  s.t.  s = h(p, q_work)

over the identifiable parameters p and the KPI points s. Because s enters only
the constraint, the minimiser is p̂ of the plain weighted least squares and
ŝ = h(p̂, q_work); the covariance of v = (p, s) comes from the KKT matrix,
eq. (19). A Gaussian prior (:class:`~kpi_calib_ros.core.estimation.prior.Prior`) adds the rows
L (m − p), LᵀL = Λ, to the weighted residual: the estimate is then the maximum a
posteriori one and C_p = (FᵀF + Λ)⁻¹ on the identified set. Non-convergence is
reported as a status, not an exception: as in SciPy's ``least_squares``, the
stopping tests are named tolerances with their formulas
(:class:`~kpi_calib_ros.core.estimation.gauss_newton.Tolerances`), the result
carries an integer ``status`` with a ``message``, and ``converged`` is true only when a
convergence test held.

The identifiable set is selected at the start (QR with column pivoting,
:mod:`~kpi_calib_ros.core.estimation.identifiability`), fitted, and selected again at the
estimate until it is stable: a real robot off the nominal geometry has directions the
nominal lacks. But the noise alone also moves the estimate off the nominal geometry, and a
direction it made has a singular value of the size of its noise, along which the trust
region crawls: a direction the selection at the estimate adds is kept only when a Wald
test says the truth has it
(:func:`~kpi_calib_ros.core.estimation.identifiability.significant_rank`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.optimize
import scipy.stats

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.covariance import (
    kkt_covariance,
    kpi_jacobians,
    standard_deviations,
)
from kpi_calib_ros.core.estimation.gauss_newton import (
    TOLERANCES,
    PriorRows,
    Tolerances,
    gauss_newton,
)
from kpi_calib_ros.core.estimation.identifiability import (
    DroppedParameter,
    Identifiability,
    select_identifiable,
    significant_rank,
)
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.measurement.data import Measurements, row_sigma
from kpi_calib_ros.core.measurement.payload import gravity_input
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import (
    point_rms,
    point_rows,
    row_torques,
    weighted_residuals,
    weighted_rows,
)
from kpi_calib_ros.core.model.parameters import RECORDING_PREFIX

__all__ = [
    'MAX_START_ERROR', 'MAX_SELECTION_ROUNDS', 'MAX_REWEIGHT_ROUNDS', 'REWEIGHT_RTOL',
    'ITERATIONS_PER_PARAMETER', 'DEFAULT_MAX_ITERATIONS', 'CalibrationResult',
    'iteration_limit', 'weights', 'identify', 'point_sigma_squares',
]

# A nominal model is off by millimetres, a wrong unit or frame by metres.
MAX_START_ERROR = 0.1
MAX_SELECTION_ROUNDS = 4
# Joint-reading noise makes the row weights depend on p (core.measurement): they are
# evaluated at the estimate and the fit repeated until no weight moves by more than
# REWEIGHT_RTOL of the largest (a relative change ε of the weights moves the estimate by
# about ε of its std).
MAX_REWEIGHT_ROUNDS = 4
REWEIGHT_RTOL = 1e-3
# Trust-region iterations per selection round, by default 100 per identified parameter:
# SciPy's least_squares allows 100 n evaluations (max_nfev of 'trf'), and an iteration here
# is one accepted step. A well-posed fit converges in 3-20; a nearly dependent parameter set
# follows a long curved valley: 120 real UR10 poses with an unknown probe offset took
# 7-244, starts 5-20 mm off the truth 251-2479 in a wrong minimum (27 parameters)
# (identification.max_iterations sets a fixed limit per cell).
ITERATIONS_PER_PARAMETER = 100
DEFAULT_MAX_ITERATIONS: int | None = None


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
        η − h(p̂, q) per measurement, tracker frame, m (a rotation row of a tracked
        pose: rad × σ/σ_rot, see :mod:`kpi_calib_ros.core.measurement.pose`).
    rms_m : float
        sqrt(mean ‖r_i‖²) over the point rows, m.
    tcp : (t, 3) ndarray
        KPI points ŝ at the working poses, tracker frame, m.
    tcp_covariance : (t, 3, 3) ndarray
        C_s blocks of eq. (19), m².
    chi2, dof, p_value : float, int, float
        Weighted residual sum against σ, degrees of freedom, upper-tail probability.
        With a prior, χ² counts the data rows only and dof = round(3N − k_eff) with
        k_eff = tr(F C_p Fᵀ) (F the weighted data Jacobian), the number of parameters
        the data rather than the prior determine: E[χ²] = 3N − k_eff when the truth is
        drawn from the prior. Without a prior k_eff = k.
    status : int
        Why the last Gauss-Newton run stopped, one of `STATUS_MESSAGES`: 1-5 a convergence
        test of `Tolerances` held, 0 the iteration limit, -1 no step (Gauss-Newton or
        damped) decreased the cost.
    message : str
        The status in words, with the figure that decided it.
    iterations : int
        Gauss-Newton iterations over all identifiability-selection rounds.
    covariance_scale : float
        Factor applied to every covariance above: 1 (stated σ), or χ²/dof when the model
        is not adequate (see :func:`kpi_calib_ros.core.estimation.precision.honest_precision`).
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
    status: int
    message: str
    iterations: int
    identifiability: Identifiability
    # 1 when std/covariances come from the stated σ; χ²/dof when they were scaled to
    # the estimated σ because the model failed the χ² test (core.estimation.precision).
    covariance_scale: float = 1.0
    # Joint-reading noise (rad, chain order) the row weights carried; None: exact readings.
    joint_sigma: np.ndarray | None = None
    # (N, 3) σ of every row and axis the weights carried (m): the tracker's stated σ per
    # point where the data gave one, ``sigma`` elsewhere; None: ``sigma`` for every row.
    point_sigma: np.ndarray | None = None

    @property
    def converged(self) -> bool:
        """True only when a convergence test held (status 1-5)."""
        return self.status > 0

    @property
    def correlation(self) -> np.ndarray:
        """Correlation matrix (k, k) of the estimated parameters (dimensionless)."""
        return self.covariance / np.outer(self.std, self.std)

    @property
    def dropped(self) -> tuple[DroppedParameter, ...]:
        """Parameters left at their nominal value as not identifiable, with the reason."""
        return self.identifiability.dropped

    def value(self, name: str) -> float:
        """Return the identified value of parameter ``name`` (its unit); ValueError if unknown."""
        return float(self.values[self.names.index(name)])

    def std_of(self, name: str) -> float:
        """Return the standard deviation of estimated parameter ``name`` (its unit).

        ValueError if it was not estimated.
        """
        return float(self.std[self.estimated.index(name)])


def iteration_limit(max_iterations: int | None, k: int) -> int:
    """Return the iteration limit of a fit of ``k`` parameters.

    ``max_iterations``, or when None `ITERATIONS_PER_PARAMETER` · k (SciPy's ``max_nfev``
    of ``'trf'``).
    """
    return ITERATIONS_PER_PARAMETER * k if max_iterations is None else max_iterations


def weights(sigma: float | np.ndarray) -> np.ndarray:
    """Per-axis weights 1/σ (3,) from a scalar or (3,) σ in metres."""
    sigma = np.broadcast_to(np.asarray(sigma, float), (3,))
    if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise ValueError(f'noise sigma must be positive and finite, got {sigma}')
    return 1.0 / sigma


def identify(model: MeasurementModel, data: Measurements, sigma: float | np.ndarray,
             q_work: np.ndarray, working_pose_names: list[str] | None = None,
             p0: np.ndarray | None = None, free: list[str] | None = None,
             max_iterations: int | None = DEFAULT_MAX_ITERATIONS,
             identifiability_method: str = 'pivoted',
             priority: list[str] | None = None,
             tolerances: Tolerances = TOLERANCES,
             point_weights: np.ndarray | None = None,
             prior: Prior | None = None,
             tau_work: np.ndarray | None = None) -> CalibrationResult:
    """Identify the parameters of ``model`` from tracker data.

    Parameters
    ----------
    model : MeasurementModel
    data : Measurements
        q (N, n) in chain order, eta (N, 3) in the tracker frame, m.
    sigma : float or (3,) array
        Tracker noise standard deviation per axis, m; a row whose ``data.sigma`` states
        its own (the tracker's per-point uncertainty) is weighed by that one instead
        (:func:`~kpi_calib_ros.core.measurement.data.row_sigma`). With joint-reading noise in the
        model (``model.joint_sigma``) each measurement's covariance is
        σ²I + J_q Σ_q J_qᵀ: its rows are whitened at the current estimate
        (:meth:`MeasurementModel.whitening`), and after the fit the weights are evaluated
        at the estimate and the fit repeated until they settle (`REWEIGHT_RTOL`).
    q_work : (t, n) ndarray
        Working configurations whose KPI points are estimated.
    p0 : (n_p,) ndarray, optional
        Start values; the model's nominal values by default.
    free : list of str, optional
        Parameters allowed to vary; all by default. The identifiable subset of
        these is chosen by QR on the data Jacobian at ``p0``.
    max_iterations : int, optional
        Iteration limit of each trust-region Gauss-Newton run (status 0 when reached);
        default `ITERATIONS_PER_PARAMETER` times the number of identified parameters.
    tolerances : Tolerances, optional
        Stopping tests of the Gauss-Newton iteration; the result's ``status`` says which held.
    point_weights : (N,) ndarray, optional
        Robustness weights ω_i in [0, 1] of the measurements (IRLS, see
        :mod:`kpi_calib_ros.core.estimation.robust`): measurement i counts as if its σ were σ/√ω_i.
        The covariance and χ² are those of that weighted problem. Default: all 1.
    prior : Prior, optional
        Gaussian prior on some parameters (maximum a posteriori estimate); parameters it
        does not name are unconstrained. Its rows take part in the identifiability
        selection, so a parameter the prior determines is identified; a prior on a
        parameter that is not identified is conditioned on the held value.

    Raises
    ------
    DataError
        Non-finite data or too few measurements for the identifiable set.
    """
    w_axis = weights(sigma)
    q, eta = np.atleast_2d(data.q), np.atleast_2d(data.eta)
    if q.shape[0] != eta.shape[0] or eta.shape[1] != 3 or q.shape[1] != model.robot.n_joints:
        raise DataError(f'measurement shapes do not fit: q {q.shape}, eta {eta.shape}, '
                        f'{model.robot.n_joints} joints')
    try:
        sigma_rows = row_sigma(sigma, data.sigma, len(q))
    except ValueError as exc:
        raise DataError(f'{exc}; the per-point sigma comes from the tracker (m)') from None
    w = _row_weights(1.0 / sigma_rows, point_weights, len(q))
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(eta))):
        raise DataError('measurements contain NaN or inf; reject them before identification')
    q_work = np.atleast_2d(np.asarray(q_work, float))
    names = working_pose_names or [f'work_{i + 1}' for i in range(len(q_work))]
    # each row's torques: measured, or the gravity torques with its own payload
    tau = row_torques(model, data)
    if tau_work is None and model.uses_torque:
        tau_work = gravity_input(model.robot, q_work)
    p = np.array(model.params.nominal if p0 is None else p0, dtype=float)
    free_idx = model.params.indices(free) if free else np.arange(len(p))
    ref = data.reflector  # (pose, reflector) rows; None: reflector 0 throughout
    rot = data.rotation   # measured rotations of the rotation rows (tracked poses)
    cov = data.covariates  # per-row covariates the effects read (temperature, …)
    try:
        model.input_values(len(q), cov)  # a covariate the effects read is there and finite
    except ValueError as exc:
        raise DataError(str(exc)) from None
    rows = prior.rows(model.params) if prior is not None else None

    def reweighted(pp: np.ndarray) -> np.ndarray:
        """Row weights at ``pp``: fixed 1/σ, or whitening with joint-reading noise."""
        if model.joint_sigma is None:
            return w
        return model.whitening(pp, q, sigma_rows, tau, ref, rot, point_weights, cov)

    def limit(idx: np.ndarray) -> int:
        return iteration_limit(max_iterations, len(idx))

    pred, _ = model.jacobian(p, q, tau, ref, rot, cov)
    start_error = float(np.median(np.linalg.norm(eta - pred, axis=1)))
    if start_error > MAX_START_ERROR:
        raise DataError(f'measured points are {start_error:.3g} m (median) from the nominal '
                        'prediction; check that points are in metres, in the tracker frame, and '
                        'that tracker.base_in_tracker and the joint order/units are right, that '
                        'coupled controller joints are mapped (robot.joint_coupling), and that '
                        'the point topic carries one reflector (several reflectors on one '
                        'topic pair each pose with points of the others)')
    free_names = [model.params.names[i] for i in free_idx]
    # The preferred order among the parameters this fit may move: a smaller level (the
    # registration, the joint offsets) leaves the cell's other preferred names held.
    priority = None if priority is None else [n for n in priority if n in free_names]
    # Identifiability depends on the geometry: at a nominal reflector exactly on the
    # flange axis some directions vanish that the real (slightly off-axis) robot has.
    # Select at the start, fit, and select again at the estimate until the set is stable.
    # A parameter dropped in a later round keeps the value it was fitted to: the full
    # vector stays one exact solution (one gauge); resetting it would restart the fit.
    # But off it is also where the noise puts the estimate: a direction added at the
    # estimate is kept only if a Wald test says the truth has it (`significant_rank`).
    # A direction only the noise made has a singular value of the size of its noise
    # (measured: nominal KR15 of the default cell, 30 designed poses, noise only: Wald
    # p 0.18-0.96 over 20 fits); fitting it, the trust region crawled 658-2702 iterations
    # along a curved valley (Gauss-Newton step 5e4-3e5 equilibrated units, predicted
    # decrease 0.2-2.0).
    ident, iterations, kept_before = None, 0, None
    w = reweighted(p)
    # Several recordings: every set-up's placement is kept first, so the gauge they share
    # with the robot (a change of the base frame) is carried by the robot's parameters,
    # never by one set-up's placement (core.measurement.recordings).
    first = ([n for n in free_names if n.startswith(('base.', RECORDING_PREFIX))]
             if model.recordings else [])
    # The rounds select without the dropped parameters' reasons (most of the time of a
    # selection); the selection kept is made again with them at the end, the same call.
    chosen: tuple[np.ndarray, dict[str, Any]] | None = None

    def select(matrix: np.ndarray, **options: Any
               ) -> tuple[Identifiability, tuple[np.ndarray, dict[str, Any]]]:
        return (select_identifiable(matrix, free_names, explain=False, first=first,
                                    **options),
                (matrix, options))

    # A measured input an effect reads (a tilt, a temperature) turns or stretches the
    # robot by a little at every row; through it, a geometric direction the robot's
    # structure leaves a gauge (a column stage's placement tilt and the base roll) becomes
    # "determined" by second-order terms: the commutator of a 6 mrad tilt with the placement
    # separated the two to 25 mrad, and the fit moved both by 66 mrad in opposite senses,
    # writing a URDF 100 mm off in its own frame that predicted the tracker's points.
    # The geometric columns are selected as the structure at zero input has them; the
    # effects' columns with the inputs as measured.
    measured = [k for k in (cov or {}) if k in model.inputs
                and not k.startswith(RECORDING_PREFIX)]
    zeroed = {k: np.zeros(len(q)) if k in measured else v for k, v in (cov or {}).items()}
    n_geo = len(model.geometric)

    def stacked_at(x: np.ndarray) -> np.ndarray:
        pp = p.copy()
        pp[free_idx] = x
        _, jac_x = model.jacobian(pp, q, tau, ref, rot, cov)
        if measured:
            _, structure = model.jacobian(pp, q, tau, ref, rot, zeroed)
            jac_x[..., :n_geo] = structure[..., :n_geo]
        return _with_prior(weighted_rows(jac_x, w, free_idx), rows, free_idx)

    for _ in range(MAX_SELECTION_ROUNDS):
        stacked = stacked_at(p[free_idx])
        ident, chosen = select(stacked, method=identifiability_method, priority=priority)
        max_rank: int | None = None
        cut_reason = 'beyond the rank limit'
        if kept_before is not None and ident.rank > len(kept_before):
            test = significant_rank(stacked_at, p[free_idx],
                                    [free_names.index(n) for n in ident.kept],
                                    [free_names.index(n) for n in kept_before])
            if test.rank < ident.rank:
                max_rank, cut_reason = test.rank, test.reason()
                ident, chosen = select(stacked, method=identifiability_method,
                                       priority=priority, max_rank=max_rank,
                                       cut_reason=cut_reason)
        if kept_before is not None and ident.rank == len(kept_before):
            # Same rank: the fitted set still spans the identifiable directions (QR may
            # merely prefer an equivalent subset here). Keep it; restate its reasons here.
            kept_first = list(kept_before) + [n for n in free_names if n not in kept_before]
            again, how = select(stacked, method='priority', priority=kept_first,
                                pivot_fraction=0.0, max_rank=max_rank, cut_reason=cut_reason)
            if again.kept == kept_before:
                ident, chosen = again, how
                break
        if ident.kept == kept_before:
            break
        idx = model.params.indices(ident.kept)
        if 3 * len(q) + (0 if rows is None else len(rows[0])) <= len(idx):
            raise DataError(f'too few measurements: {len(q)} points give {3 * len(q)} '
                            f'equations for {len(idx)} identifiable parameters; measure at '
                            f'least {len(idx) // 3 + 1} poses (better 3-5x that)')
        p, status, message, used = gauss_newton(model, p, idx, q, eta, tau, w,
                                                 limit(idx), tolerances, ref, rows, rot, cov)
        iterations += used
        kept_before = ident.kept
    if ident is None or chosen is None:
        raise RuntimeError(f'MAX_SELECTION_ROUNDS = {MAX_SELECTION_ROUNDS}: no round selected '
                           'the identifiable parameters')
    ident = select_identifiable(chosen[0], free_names, **chosen[1])
    for _ in range(MAX_REWEIGHT_ROUNDS if model.joint_sigma is not None else 0):
        new = reweighted(p)
        change = float(np.max(np.abs(new - w)) / np.max(np.abs(w)))
        w = new
        if change < REWEIGHT_RTOL:
            break
        p, status, message, used = gauss_newton(model, p, idx, q, eta, tau, w,
                                                 limit(idx), tolerances, ref, rows, rot, cov)
        iterations += used
    pred, jac = model.jacobian(p, q, tau, ref, rot, cov)
    residuals = eta - pred
    f_data = weighted_rows(jac, w, idx)
    tcp, tcp_jac = model.jacobian(p, q_work, tau_work)
    f1, f2 = kpi_jacobians(_with_prior(f_data, rows, idx), tcp_jac.reshape(-1, len(p))[:, idx])
    c_v = kkt_covariance(f1, f2)
    k = len(idx)
    c_p = c_v[:k, :k]
    c_s = c_v[k:, k:]
    t = len(q_work)
    tcp_cov = np.array([c_s[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(t)])
    chi2 = float(np.sum(weighted_residuals(residuals, w) ** 2))
    # χ² of the data rows only; the prior rows are information, not measurements.
    dof = 3 * len(q) - k
    if rows is not None:
        dof = int(round(3 * len(q) - float(np.sum((f_data @ c_p) * f_data))))
    return CalibrationResult(
        names=model.params.names, values=p, units=model.params.units,
        estimated=ident.kept, std=standard_deviations(c_p), covariance=c_p,
        residuals=residuals, rms_m=point_rms(residuals, point_rows(ref, model.n_reflectors)),
        tcp=tcp, tcp_covariance=tcp_cov, working_pose_names=tuple(names),
        sigma=1.0 / w_axis, chi2=chi2, dof=dof, p_value=float(scipy.stats.chi2.sf(chi2, dof)),
        status=status, message=message, iterations=iterations, identifiability=ident,
        joint_sigma=model.joint_sigma, point_sigma=None if data.sigma is None else sigma_rows)


def point_sigma_squares(result: CalibrationResult, reflector: np.ndarray | None,
                        n_reflectors: int) -> np.ndarray:
    """Return Σ_a σ_i,a² (m²) of every point row of the fit (rotation rows left out).

    Each row's stated σ (``result.point_sigma``) or the cell's σ; (N_points,), or (1,) when
    the fit took the cell's σ for every row.
    """
    if result.point_sigma is None:
        return np.array([float(np.sum(np.asarray(result.sigma) ** 2))])
    rows = np.asarray(result.point_sigma)
    if reflector is not None:
        rows = rows[np.asarray(reflector) < n_reflectors]
    return np.sum(rows ** 2, axis=1)


def _with_prior(f: np.ndarray, rows: PriorRows | None, idx: np.ndarray) -> np.ndarray:
    """Weighted data Jacobian columns ``idx`` with the prior's L rows below."""
    return f if rows is None else np.vstack([f, rows[0][:, idx]])


def _row_weights(w_axis: np.ndarray, point_weights: np.ndarray | None, n: int) -> np.ndarray:
    """Return the (N, 3) weights w_i,a·√ω_i of every residual component (1/m).

    ``w_axis`` (3,) or (N, 3).
    """
    w_axis = np.broadcast_to(w_axis, (n, 3))
    if point_weights is None:
        return w_axis.copy()
    omega = np.asarray(point_weights, float)
    if omega.shape != (n,) or not np.all(np.isfinite(omega)) or np.any(omega < 0):
        raise ValueError(f'point_weights must be {n} finite numbers >= 0, got shape '
                         f'{omega.shape}')
    return w_axis * np.sqrt(omega)[:, None]

"""Precision that holds when the stated σ is too small.

The covariances of an identification (eq. 19) assume the stated measurement σ.
When the χ² test rejects the model (residuals larger than σ explains: an understated
σ or an effect the model lacks) those covariances promise too much. Least-squares
practice then uses the estimated σ̂² = σ² · χ²/dof, i.e. scales every covariance by
χ²/dof (SciPy's ``curve_fit`` with ``absolute_sigma=False``; Bevington & Robinson §8).
The scaling is only applied when the model fails the test, and it is stated.

The same σ̂ must weigh the data against a tolerance prior (:func:`balanced_prior`). A
MAP fit minimises ½‖W(η − h)‖² + ½(p − m)ᵀΛ(p − m): with W from a σ that is 5× too small
the data count 25× too much, and the prior's tolerances hold nothing. On the TIAGo
mocap data (stated 0.2 mm, residuals 1.3 mm) a 5 mrad tolerance on the axis tilts let the
fit tilt arm_7's axis by 110 ± 48 mrad, which predicts postures outside the training
ranges 15–21 mm off. Weighing by σ̂ is the same as tightening the prior by s = χ²/dof
(Λ → sΛ) at the stated σ; the covariance scaled by s is then exactly the posterior
(FᵀF/s + Λ)⁻¹ with σ̂, and the χ² verdict stays the one against the stated σ.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.stats

from kpi_calib_ros.core.estimation.cross_validation import prior_system
from kpi_calib_ros.core.estimation.folds import (
    LEAVE_ONE_OUT,
    RANK_TOLERANCE,
    fold_rows,
    held_out_blocks,
    identifiable_folds,
)
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult, point_sigma_squares
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.estimation.residuals import (
    ADEQUACY_ALPHA,
    is_adequate,
    linearized_fit,
    orthonormal_basis,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.replicates import as_first_of_pose
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import point_rms, point_rows, unweighted

# A pose whose hat-matrix block has an eigenvalue this close to 1 is the only one that
# determines some direction of the parameters: leaving it out is an extrapolation, not a
# held-out pose like the measured ones (its held-out noise alone is 1/(1 − h) >= 10 times a
# measurement's, its systematic part amplified alike). The misfit b is stated from the other
# poses, and the poses left out are named.
LEVERAGE_LIMIT = 0.9


def noise_scale(result: CalibrationResult, alpha: float = ADEQUACY_ALPHA) -> float:
    """χ²/dof of ``result`` when the χ² test rejects it and it exceeds 1, else 1."""
    return chi2_scale(result.chi2, result.dof, alpha)


def chi2_scale(chi2: float, dof: int, alpha: float = ADEQUACY_ALPHA) -> float:
    """Factor on every covariance of a fit with this χ²: χ²/dof when the test rejects, else 1.

    χ²/dof when the χ² test (``dof`` degrees of freedom) rejects ``chi2`` and it exceeds 1, else
    1 (see the module).
    """
    if dof <= 0 or is_adequate(float(scipy.stats.chi2.sf(chi2, dof)), alpha):
        return 1.0
    return max(1.0, float(chi2 / dof))


def honest_precision(result: CalibrationResult,
                     alpha: float = ADEQUACY_ALPHA) -> CalibrationResult:
    """Return ``result`` with its covariances from the estimated σ when χ² rejects the model.

    Parameters
    ----------
    result : CalibrationResult
        Covariances from the stated σ (``covariance_scale`` 1).
    alpha : float
        Level of the χ² adequacy test.

    Returns
    -------
    CalibrationResult
        Unchanged when adequate (or without degrees of freedom); else ``std`` × √s,
        ``covariance`` and ``tcp_covariance`` × s with s = χ²/dof > 1, and
        ``covariance_scale`` = s.
    """
    scale = noise_scale(result, alpha)
    if result.covariance_scale != 1.0 or scale == 1.0:
        return result
    return dataclasses.replace(result, std=result.std * np.sqrt(scale),
                               covariance=result.covariance * scale,
                               tcp_covariance=result.tcp_covariance * scale,
                               covariance_scale=scale)


JOINT_NOISE_CAUSE = ('joint readings noisier than exact are one cause (a controller read-back '
                     'of 0.02-0.05 deg moves the point by 0.2-0.9 mm at 1 m): state them as '
                     'noise.joint_sigma (rad, per joint) in the cell')


def precision_statement(scale: float, joint_sigma: np.ndarray | None = None) -> str:
    """How the reported std were obtained, for files, summaries and the node.

    ``joint_sigma``: the joint-reading noise the fit assumed (rad, chain order), None when
    the cell stated none; then the joint readings are named as a cause of a rejection.
    """
    if scale == 1.0:
        return 'from the stated sigma (model adequate)'
    text = (f'scaled by chi2/dof = {scale:.4g} (estimated sigma = {np.sqrt(scale):.3g} x '
            'stated): the model is not adequate, the stated sigma understates the residuals')
    return text + ('; ' + JOINT_NOISE_CAUSE if joint_sigma is None else '')


@dataclass(frozen=True)
class ExpectedTcpError:
    """How far the KPI point of every working pose is expected to be from the truth.

    The TCP covariance says how well the parameters are known; with an effect the model
    lacks, the point also misses by a systematic error the covariance does not hold. When
    χ² rejects the model that misfit is estimated from the fit itself: the held-out
    (leave one pose out) rms of the measurements, less the noise a held-out measurement
    carries, is the systematic level b that a prediction at a pose like the measured ones
    misses by (beyond the parameter part that rms also holds). A pose of leverage >=
    :data:`LEVERAGE_LIMIT` is not like the others (they cannot predict it without it): it is
    left out of that rms and named (:func:`typical_held_out_rms`). The expected error at
    working pose w is sqrt(tr C_w + b²).

    Attributes
    ----------
    tcp_std_m : (t,) ndarray
        sqrt(trace) of each working pose's TCP covariance as reported (χ²-scaled when the
        model is not adequate): the parameter part, m.
    misfit_m : float
        b, the systematic residual level, m (0 when χ² accepts the model).
    expected_tcp_error_m : (t,) ndarray
        sqrt(tcp_std_m² + b²), m.
    validation_rms_m, noise_floor_m : float
        The held-out rms and the rms noise of one measurement it was reduced by, m.
    left_out : tuple of int
        Poses (indices of the measurements' pose folds) of leverage >= :data:`LEVERAGE_LIMIT`
        left out of the held-out rms (:func:`typical_held_out_rms`).
    """

    working_pose_names: tuple[str, ...]
    tcp_std_m: np.ndarray
    misfit_m: float
    expected_tcp_error_m: np.ndarray
    validation_rms_m: float
    noise_floor_m: float
    adequate: bool
    left_out: tuple[int, ...] = ()

    @property
    def basis(self) -> str:
        """What the expected TCP error rests on.

        The parameter part alone, or with the systematic misfit (and its figures in µm), or
        unknown.
        """
        if self.adequate:
            return ('model adequate (chi2 accepts it): the expected TCP error is the '
                    'parameter part tcp_std_m alone')
        if not np.isfinite(self.misfit_m):
            return ('model not adequate and its misfit not estimable from this design (no '
                    'held-out rms): the expected TCP error is unknown beyond tcp_std_m')
        left = (f'; {len(self.left_out)} pose(s) of leverage >= {LEVERAGE_LIMIT:g} left out '
                f'of the held-out rms (measurements {list(self.left_out)[:10]}): without them '
                'the others cannot predict them, an extrapolation, not a pose like the '
                'measured ones' if self.left_out else '')
        return (f'model not adequate: expected TCP error = sqrt(tcp_std_m^2 + b^2) with the '
                f'systematic misfit b = {self.misfit_m * 1e6:.1f} um (held-out rms '
                f'{self.validation_rms_m * 1e6:.1f} um less the noise of a measurement '
                f'{self.noise_floor_m * 1e6:.1f} um{left}); tcp_std_m is the parameter part '
                'only')

    def to_dict(self) -> dict:
        """YAML-ready form (m); a figure that is not finite is None."""
        def metres(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None
        return {'tcp_std_m': {n: metres(v) for n, v in zip(self.working_pose_names,
                                                            self.tcp_std_m)},
                'expected_tcp_error_m': {n: metres(v) for n, v in zip(
                    self.working_pose_names, self.expected_tcp_error_m)},
                'misfit_m': metres(self.misfit_m),
                'validation_rms_m': metres(self.validation_rms_m),
                'noise_floor_m': float(self.noise_floor_m),
                'high_leverage_left_out': list(self.left_out),
                'expected_tcp_error_basis': self.basis}


def measurement_noise_ms(model: MeasurementModel, data: Measurements,
                         result: CalibrationResult) -> float:
    """Mean square noise (m²) of one point measurement.

    Σ_a σ_a² (the mean over the points of their own σ where the tracker stated it), plus the
    joint readings' mean tr(J_q Σ_q J_qᵀ) when the model carries joint-reading noise.
    """
    noise = float(np.mean(point_sigma_squares(result, data.reflector, model.n_reflectors)))
    if model.joint_sigma is None:
        return noise
    point = (np.ones(len(data), bool) if data.reflector is None
             else np.asarray(data.reflector) < model.n_reflectors)
    jq = model.joint_jacobian(result.values, np.atleast_2d(data.q)[point],
                              None if data.tau is None else data.tau[point],
                              None if data.reflector is None else data.reflector[point],
                              covariates=data.subset(point).covariates)
    return noise + float(np.mean(np.sum((jq @ model.joint_noise_map) ** 2, axis=(1, 2))))


def expected_tcp_error(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                       alpha: float = ADEQUACY_ALPHA,
                       prior: Prior | None = None) -> ExpectedTcpError:
    """Return the expected TCP error at every working pose, the misfit included.

    See :class:`ExpectedTcpError`.

    Parameters
    ----------
    model, data : MeasurementModel, Measurements
        The model ``result`` was identified with and its measurements.
    result : CalibrationResult
        Its TCP covariance as reported (after :func:`honest_precision`).
    prior : Prior, optional
        The prior the fit used, kept in the held-out refits of the misfit's estimate.
    """
    covariance = np.asarray(result.tcp_covariance, float).reshape(-1, 3, 3)  # (0, 3, 3): no
    tcp_std = np.sqrt(np.trace(covariance, axis1=1, axis2=2))              # working pose
    noise = float(np.sqrt(measurement_noise_ms(model, data, result)))
    if result.dof <= 0:  # no residual left to tell a misfit from the noise
        return ExpectedTcpError(result.working_pose_names, tcp_std, float('nan'),
                                np.full(len(tcp_std), np.nan), float('nan'), noise, False)
    if is_adequate(result.p_value, alpha):
        return ExpectedTcpError(result.working_pose_names, tcp_std, 0.0, tcp_std,
                                float('nan'), noise, True)
    cv, left_out = typical_held_out_rms(model, data, result, prior=prior)
    misfit = float(np.sqrt(max(cv ** 2 - noise ** 2, 0.0))) if np.isfinite(cv) else np.nan
    return ExpectedTcpError(result.working_pose_names, tcp_std, misfit,
                            np.sqrt(tcp_std ** 2 + misfit ** 2), cv, noise, False, left_out)


def typical_held_out_rms(model: MeasurementModel, data: Measurements,
                         result: CalibrationResult, leverage_limit: float = LEVERAGE_LIMIT,
                         prior: Prior | None = None) -> tuple[float, tuple[int, ...]]:
    """Leave-one-pose-out rms (m) over the poses like the measured ones, and those left out.

    As :func:`~kpi_calib_ros.core.estimation.cross_validation.validation_rms` (the PRESS identity:
    pose F's held-out residual is (I − H_FF)⁻¹ e_F), over the poses whose hat-matrix block
    H_FF has every eigenvalue below ``leverage_limit``. A pose at or above it alone determines
    some direction of the parameters: its held-out residual is amplified by up to 1/(1 − h)
    (one such pose made the held-out rms 22× the others' and the expected TCP error 13 mm
    against 0.6 mm). Returns NaN when no folds keep the parameters determined or every pose is
    left out, and the indices of the first measurement of each pose left out. ``prior``: the
    prior the fit used, whose rows stay in every refit (never held out).
    """
    sys_ = linearized_fit(model, data, result)
    # A posture measured again (another session of the same program, readings within a
    # reading's tolerance) is held out with its repeats: left in, they predict it and the
    # misfit a new pose meets is understated.
    q = as_first_of_pose(data.q)
    prior_rows, prior_r = prior_system(model, result, prior)
    a = np.vstack([sys_.jac, prior_rows])
    folds = identifiable_folds(a, q, LEAVE_ONE_OUT, 0)
    if folds is None:
        return float('nan'), ()
    # PRESS of the stacked system: the prior's rows are in the hat matrix, not in the folds.
    n_data = len(sys_.r)
    u_all = orthonormal_basis(a)
    b = np.concatenate([sys_.r, prior_r])
    r = (b - u_all @ (u_all.T @ b))[:n_data]
    u = u_all[:n_data]
    held = np.full_like(r, np.nan)
    left: list[int] = []
    tests = [test for _, test in fold_rows(folds)]
    for test, m in zip(tests, held_out_blocks(u, tests)):
        if m.smallest <= 1.0 - leverage_limit:
            left.append(int(test[0]) // 3)
            continue
        if m.smallest <= RANK_TOLERANCE:
            return float('nan'), ()
        held[test] = m.solve(r[test])
    kept = ~np.isnan(held.reshape(-1, 3)[:, 0])
    points = point_rows(data.reflector, model.n_reflectors)
    if points is not None:  # a tracked body's rotation rows are no length
        kept &= points
    if not kept.any():
        return float('nan'), tuple(left)
    return point_rms(unweighted(held, sys_.w), kept), tuple(left)


BALANCE_ROUNDS = 12
BALANCE_RTOL = 0.02


def tightened(prior: Prior, scale: float) -> Prior:
    """``prior`` with its covariance divided by ``scale`` (Λ → scale·Λ).

    At the stated σ, the balance of the data weighed by σ·√scale against ``prior``.
    """
    if scale == 1.0:
        return prior
    return Prior(prior.names, prior.mean, prior.covariance / scale)


def balanced_prior(fit: Callable[[Prior], CalibrationResult], prior: Prior,
                   alpha: float = ADEQUACY_ALPHA) -> tuple[Prior, float, CalibrationResult]:
    """Return a tolerance prior balanced against the noise the residuals show.

    ``fit(prior)`` identifies with the stated σ and the given prior. While the χ² test
    rejects the fit, the prior is tightened by s = χ²/dof of the fit with the tightened
    prior (the fixed point s = χ²(s)/dof(s): the σ̂ the residuals show with that balance,
    MacKay's re-estimation of the noise level), until s changes by less than
    :data:`BALANCE_RTOL`. An adequate model keeps the prior as it is (s = 1).

    Returns the tightened prior, s and the last fit.
    """
    scale, result = 1.0, fit(prior)
    for _ in range(BALANCE_ROUNDS):
        new = noise_scale(result, alpha)
        if abs(new - scale) <= BALANCE_RTOL * scale:
            break
        scale = new
        result = fit(tightened(prior, scale))
    return tightened(prior, scale), scale, result


def fit_prior(prior: Prior | None, result: CalibrationResult, balanced: bool) -> Prior | None:
    """Return the prior ``result`` was fitted with.

    ``prior`` tightened by the noise scale of ``result`` when the fit balanced it
    (:func:`balanced_prior`: at its fixed point the scale is that of the last fit), else
    ``prior`` as given.
    """
    if prior is None or not balanced:
        return prior
    return tightened(prior, noise_scale(result))


__all__ = ['ExpectedTcpError', 'JOINT_NOISE_CAUSE', 'LEVERAGE_LIMIT', 'balanced_prior',
           'chi2_scale', 'expected_tcp_error', 'fit_prior', 'measurement_noise_ms',
           'honest_precision', 'noise_scale', 'precision_statement', 'tightened',
           'typical_held_out_rms']

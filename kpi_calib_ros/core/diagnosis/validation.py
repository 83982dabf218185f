"""Validation of a calibration on new measurements.

Do the new points fall within the errors the calibration itself predicts?

A new point ``η_i`` is predicted as ``h(p̂, q_i)``; its error is the measurement noise
plus the propagated uncertainty of the identified parameters,

    C_i = Σ + J_i C_p J_iᵀ        (J_i = ∂h/∂p of the identified parameters at q_i),

plus J_q Σ_q J_qᵀ when the model states joint-reading noise,

per point. The new points' noise is independent of the fit, but every new point carries
the same error of the identified parameters, so the points are not independent of each
other: χ² is ``eᵀ V⁻¹ e``, ``e`` every residual stacked (3N) and
``V = blockdiag(C_i − J_i C_p J_iᵀ) + J C_p Jᵀ`` their joint covariance (the noise per point
plus the shared parameters' part), which follows χ²(3N) when the calibration holds. Summed
point by point (``Σ_i r_iᵀ C_i⁻¹ r_i``) it would not: a calibration from few poses, or
validated far from them, would fail on many new points for no fault of its own.

Σ is the noise the calibration showed: the stated σ, or
σ̂ = σ·√(χ²/dof) when its model was not adequate and its covariance was scaled by that
(:mod:`kpi_calib_ros.core.estimation.precision`), as its predicted out-of-sample error
(:mod:`kpi_calib_ros.core.diagnosis.out_of_sample`) and a re-identification from it take it. The
verdict is this test at the adequacy level.

The new poses fall in three groups, reported apart (the groups of a held-out protocol):
*outside* the joint ranges the calibration was identified on (extrapolation, where a
geometric model fails first); *repeated*, inside them and the same pose as a training pose
(:func:`~kpi_calib_ros.core.measurement.replicates.same_pose`: the same configuration measured
again: their error is the robot's and the instrument's repeatability between the campaigns, which
no model of the configuration removes); *new* poses inside the ranges (generalisation).

A validation recording is usually made with the tracker (or the probe) set up again, so
its points are in another tracker frame. With ``registered`` the base pose (and, if
named, the reflector offsets) are re-fitted on the new recording alone
(:func:`kpi_calib_ros.core.estimation.registration.reregister`, least squares with the other
values held: the residuals and rms reported). The calibration's uncertainty of those
parameters is absorbed by the fit, that of the others is common to every new point, and
χ² is the minimum over them of ``eᵀ V⁻¹ e`` with the full covariance V
(noise plus ``J_u C_u J_uᵀ`` across all points), which follows χ²(3N − r), r the rank
of the re-fitted parameters' Jacobian: the degrees of freedom the registration costs.
The per-point distances keep the per-point ``C_i`` of the other parameters.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import scipy.stats

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.registration import Reregistration, reregister
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA
from kpi_calib_ros.core.measurement.replicates import same_pose
from kpi_calib_ros.core.measurement.tracker import MeasurementModel, Measurements, row_sigma

__all__ = ['Validation', 'shared_chi2', 'validate']


@dataclass(frozen=True)
class Validation:
    """Prediction of new measurements by a calibration.

    Attributes
    ----------
    residuals : (N, 3) ndarray
        η − h(p̂, q) per new measurement, tracker frame (m).
    predicted_std : (N,) ndarray
        sqrt(trace C_i / 3): the calibration's own predicted error per axis (m).
    mahalanobis : (N,) ndarray
        sqrt(r_iᵀ C_i⁻¹ r_i) per point.
    outside : (N,) bool ndarray
        Pose beyond the training joint range of some joint.
    repeated : (N,) bool ndarray
        Pose inside the ranges and the same pose as a training pose
        (:func:`~kpi_calib_ros.core.measurement.replicates.same_pose`; all False when the training
        poses are not known).
    chi2, dof, p_value : float, int, float
        dof is 3N less the degrees of freedom the re-registration took.
    holds : bool
        p_value >= alpha.
    registration : Reregistration or None
        The placement re-fitted on the new recording (``registered`` of :func:`validate`).
    """

    residuals: np.ndarray
    predicted_std: np.ndarray
    mahalanobis: np.ndarray
    outside: np.ndarray
    repeated: np.ndarray
    chi2: float
    dof: int
    p_value: float
    alpha: float
    registration: Reregistration | None = None

    @property
    def holds(self) -> bool:
        """Whether the calibration passes: p-value at least ``alpha``."""
        return bool(self.p_value >= self.alpha)

    @property
    def rms_m(self) -> float:
        """sqrt(mean ‖r_i‖²) over every new point (m)."""
        return _rms(self.residuals)

    def rms_where(self, mask: np.ndarray) -> float:
        """Root mean square (m) over the points of ``mask`` (NaN when there are none)."""
        return _rms(self.residuals[mask]) if np.any(mask) else float('nan')


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))


def shared_chi2(residuals: np.ndarray, jacobian: np.ndarray, covariance: np.ndarray,
                noise: np.ndarray) -> float:
    """Return ``eᵀ V⁻¹ e`` of points that share the parameters' error.

    ``V = blockdiag(noise_i) + J C Jᵀ``; computed as the least-squares minimum over a
    correction ``δ = R u`` of the parameters (``C = R Rᵀ``) of
    ``Σ_i ‖L_i⁻¹ (e_i − J_i R u)‖² + ‖u‖²`` (``noise_i = L_i L_iᵀ``), which equals it
    without forming V.

    Parameters
    ----------
    residuals : (N, 3) ndarray
        e_i, m.
    jacobian : (N, 3, k) ndarray
        J_i of the k identified parameters.
    covariance : (k, k) ndarray
        C, their covariance.
    noise : (N, 3, 3) ndarray
        Each point's own noise covariance, m².
    """
    e = np.asarray(residuals, float).reshape(-1, 3)
    jac = np.asarray(jacobian, float).reshape(len(e), 3, -1)
    eig, vec = np.linalg.eigh(0.5 * (covariance + np.transpose(covariance)))
    root = vec * np.sqrt(np.clip(eig, 0.0, None))
    whiten = np.linalg.inv(np.linalg.cholesky(noise))
    rows = np.einsum('nab,nbk->nak', whiten, jac @ root).reshape(3 * len(e), -1)
    rhs = np.einsum('nab,nb->na', whiten, e).reshape(-1)
    k = rows.shape[1]
    system = np.vstack([rows, np.eye(k)])
    target = np.concatenate([rhs, np.zeros(k)])
    step = np.linalg.lstsq(system, target, rcond=None)[0]
    return float(np.sum((target - system @ step) ** 2))


def validate(model: MeasurementModel, p: np.ndarray, estimated: np.ndarray,
             covariance: np.ndarray, sigma: np.ndarray, data: Measurements,
             lower: np.ndarray, upper: np.ndarray,
             alpha: float = ADEQUACY_ALPHA,
             training_q: np.ndarray | None = None,
             noise_scale: float = 1.0,
             registered: np.ndarray | None = None) -> Validation:
    """Predict ``data`` with the calibration ``p`` and test the residuals.

    Parameters
    ----------
    model : MeasurementModel
        The calibrated model (effects included).
    p : (n_p,) ndarray
        Calibrated parameter values.
    estimated : (k,) int ndarray
        Indices in ``p`` of the identified parameters, ordered as ``covariance``.
    covariance : (k, k) ndarray
        C_p of the identified parameters.
    sigma : (3,) ndarray
        Noise std per axis (m) of a new point about the calibrated prediction; a row of
        ``data`` with its own stated σ (``data.sigma``) takes that one, times
        √``noise_scale``.
    data : Measurements
        New (pose, reflector) rows.
    lower, upper : (n,) ndarray
        Training joint ranges; a pose with any joint outside is marked.
    training_q : (M, n) ndarray, optional
        The training poses (chain order): a pose inside the ranges near one is marked
        repeated.
    registered : (r,) int ndarray, optional
        Indices in ``p`` re-fitted on ``data`` first (the tracker set up again: the
        ``base.*`` parameters, optionally the reflector offsets). The re-registration's
        own χ² holds the tracker noise and the parameters' share, not the joint-reading
        noise.
    noise_scale : float
        The factor ``sigma`` was scaled by (χ²/dof of a calibration whose model was not
        adequate); the joint-reading noise of the model, ``J_q Σ_q J_qᵀ`` per point, is
        added scaled by it as well.
    """
    q = np.atleast_2d(data.q)
    tau = model.robot.gravity_torques(q) if model.uses_torque else None
    estimated = np.asarray(estimated, dtype=int)
    covariance = np.asarray(covariance, dtype=float)
    keep = ~np.isin(estimated, [] if registered is None else registered)
    estimated, covariance = estimated[keep], covariance[np.ix_(keep, keep)]

    stated = None if data.sigma is None else np.asarray(data.sigma, float) * np.sqrt(noise_scale)
    try:
        sigma_rows = row_sigma(sigma, stated, len(q))
    except ValueError as exc:
        raise DataError(f'{exc}; the per-point sigma of the validation data') from None

    def noise_covariance(p_now: np.ndarray) -> np.ndarray:
        """(N, 3, 3) each point's own noise: the tracker's and the joint readings'."""
        noise = sigma_rows[:, :, None] ** 2 * np.eye(3)
        if model.joint_sigma is not None:
            jq = (model.joint_jacobian(p_now, q, tau, data.reflector, data.rotation,
                                       data.covariates)
                  * model.joint_sigma)
            noise = noise + noise_scale * np.einsum('nak,nbk->nab', jq, jq)
        return noise

    registration = None
    if registered is not None and len(registered):
        registration = reregister(model, p, dataclasses.replace(data, tau=tau), registered,
                                  sigma_rows, estimated, covariance)
        p = registration.p
    pred, jac = model.jacobian(p, q, tau, data.reflector, data.rotation, data.covariates)
    residuals = np.atleast_2d(data.eta) - pred
    j = jac[:, :, estimated]
    noise = noise_covariance(p)
    cov = np.einsum('nak,kl,nbl->nab', j, covariance, j) + noise
    solved = np.linalg.solve(cov, residuals[:, :, None])[:, :, 0]
    d2 = np.sum(residuals * solved, axis=1)
    chi2 = (shared_chi2(residuals, j, covariance, noise) if registration is None
            else registration.chi2)
    dof = 3 * len(q) - (registration.dof if registration is not None else 0)
    tol = 1e-9
    outside = np.any((q < np.asarray(lower) - tol) | (q > np.asarray(upper) + tol), axis=1)
    repeated = np.zeros(len(q), dtype=bool)
    if training_q is not None and len(training_q):
        repeated = same_pose(q, np.asarray(training_q, float)) & ~outside
    return Validation(residuals, np.sqrt(np.trace(cov, axis1=1, axis2=2) / 3), np.sqrt(d2),
                      outside, repeated, chi2, dof, float(scipy.stats.chi2.sf(chi2, dof)),
                      alpha, registration)

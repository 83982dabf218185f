"""Residuals of a calibration: goodness of fit, leverage, outliers, validation rms.

Everything is computed on the weighted, locally linear problem at the
identified parameters: the residual r = Σ⁻¹(η − h(p̂, q)) and the Jacobian of
the identified parameters. The χ² test compares Σ‖r_i/σ‖² with χ²(dof); the
hat matrix H = U Uᵀ (U an orthonormal basis of the Jacobian's columns) gives
each pose's leverage and the covariance I − H_ii of its residual; k-fold
cross-validation refits on the other poses and predicts the held-out ones
(exact for the linear model, which a converged fit is to far below σ).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.stats

from kpi_calib_ros.core.estimation import CalibrationResult, weights
from kpi_calib_ros.core.measurement import MeasurementModel, Measurements, weighted_rows

PERCENTILES = (50, 90, 95, 99)
# Level of the χ² model-adequacy test everywhere a verdict is given (files, node status,
# diagnosis): below it the residuals are larger than the stated σ explains.
ADEQUACY_ALPHA = 0.01


@dataclass(frozen=True)
class ResidualReport:
    """Goodness of fit of one calibration.

    Attributes
    ----------
    residuals : (N, 3) ndarray
        η − h(p̂, q), tracker frame, m.
    norms : (N,) ndarray
        ‖r_i‖, m.
    rms_m, max_m : float
        sqrt(mean ‖r_i‖²) and max ‖r_i‖, m.
    percentiles_m : dict
        {50, 90, 95, 99} -> percentile of ‖r_i‖, m.
    chi2, dof, p_value : float, int, float
        Σ‖r_i/σ‖² against χ²(dof); p is the upper tail.
    adequate : bool
        p_value >= alpha: the residuals are as small as the stated σ predicts.
    leverage : (N,) ndarray
        Trace of the 3×3 hat-matrix block of each pose (0..3, mean k/N).
    standardized : (N,) ndarray
        r_iᵀ (I − H_ii)⁻¹ r_i in σ units, χ²(3) under the model.
    outlier, high_leverage : (N,) bool ndarray
        Bonferroni-corrected χ²(3) test of ``standardized`` at ``alpha``;
        leverage above three times the mean.
    """

    residuals: np.ndarray
    norms: np.ndarray
    rms_m: float
    max_m: float
    percentiles_m: dict[int, float]
    chi2: float
    dof: int
    p_value: float
    adequate: bool
    leverage: np.ndarray
    standardized: np.ndarray
    outlier: np.ndarray
    high_leverage: np.ndarray
    alpha: float




@dataclass(frozen=True)
class LinearizedFit:
    """A calibration as a linear least-squares problem at p̂.

    r : (3N,) weighted residuals; jac : (3N, k) weighted Jacobian of the
    identified parameters; basis : orthonormal basis of span(jac); w : (3,)
    weights 1/σ; tau : (N, n) gravity torques or None; p : (n_p,) p̂.
    """

    r: np.ndarray
    jac: np.ndarray
    basis: np.ndarray  # orthonormal basis of span(J)
    w: np.ndarray
    tau: np.ndarray | None
    p: np.ndarray
    reflector: np.ndarray | None = None  # (N,) reflector index of every row, None: all 0


def is_adequate(p_value: float, alpha: float = ADEQUACY_ALPHA) -> bool:
    """The χ² adequacy verdict: True when ``p_value >= alpha`` (residuals as small as σ
    predicts); NaN (no degrees of freedom) is never adequate."""
    return bool(p_value >= alpha)


def linearized_fit(model: MeasurementModel, data: Measurements, result: CalibrationResult,
            tau: np.ndarray | None = None) -> LinearizedFit:
    w = weights(result.sigma)
    q = np.atleast_2d(data.q)
    if tau is None and model.uses_torque:
        tau = model.robot.gravity_torques(q)
    p = np.asarray(result.values, float)
    pred, jac = model.jacobian(p, q, tau, data.reflector)
    r = ((np.atleast_2d(data.eta) - pred) * w).ravel()
    idx = model.params.indices(result.estimated)
    f = weighted_rows(jac, w, idx)
    basis = orthonormal_basis(f)
    return LinearizedFit(r, f, basis, w, tau, p, data.reflector)


def orthonormal_basis(a: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(a, axis=0)
    a = a[:, norms > 0] / norms[norms > 0]
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    return u[:, s > 1e-9 * s[0]] if len(s) else u


def fold_ids(n_poses: int, folds: int, seed: int) -> np.ndarray:
    if not 2 <= folds <= n_poses:
        raise ValueError(f'folds must be in [2, {n_poses}] (number of poses), got {folds}')
    ids = np.empty(n_poses, dtype=int)
    ids[np.random.default_rng(seed).permutation(n_poses)] = np.arange(n_poses) % folds
    return ids


def cv_rms(a: np.ndarray, r: np.ndarray, w: np.ndarray, pose_folds: np.ndarray) -> float:
    """k-fold cross-validated rms (m) of the linear model r ≈ a·δ, folds over poses."""
    rows = np.repeat(pose_folds, 3)
    scale = np.linalg.norm(a, axis=0)
    scale[scale == 0] = 1.0
    a = a / scale
    held = np.empty_like(r)
    for k in np.unique(pose_folds):
        test = rows == k
        delta, *_ = np.linalg.lstsq(a[~test], r[~test], rcond=None)
        held[test] = r[test] - a[test] @ delta
    metres = held.reshape(-1, 3) / w
    return float(np.sqrt(np.mean(np.sum(metres ** 2, axis=1))))


def residual_report(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                    alpha: float = ADEQUACY_ALPHA) -> ResidualReport:
    """Residual statistics, χ² test, leverage and outliers of ``result`` on ``data``.

    Parameters
    ----------
    model : MeasurementModel
        The model ``result`` was identified with.
    data : Measurements
        The measurements ``result`` was identified from.
    alpha : float
        Level of the χ² adequacy test and of the (Bonferroni) outlier test.
    """
    sys_ = linearized_fit(model, data, result)
    n = len(data)
    residuals = sys_.r.reshape(n, 3) / sys_.w
    norms = np.linalg.norm(residuals, axis=1)
    u = sys_.basis.reshape(n, 3, -1)
    blocks = np.einsum('nik,njk->nij', u, u)  # H_ii, (N, 3, 3)
    leverage = np.trace(blocks, axis1=1, axis2=2)
    # cov(r_i) = I − H_ii in σ units; pinv because a pose with leverage 1 along some
    # direction has no residual there.
    standardized = np.array([ri @ np.linalg.pinv(np.eye(3) - h, rcond=1e-9) @ ri
                             for ri, h in zip(sys_.r.reshape(n, 3), blocks)])
    outlier = scipy.stats.chi2.sf(standardized, 3) * n < alpha
    k = sys_.basis.shape[1]
    dof = 3 * n - k
    chi2 = float(sys_.r @ sys_.r)
    p_value = float(scipy.stats.chi2.sf(chi2, dof)) if dof > 0 else float('nan')
    return ResidualReport(
        residuals=residuals, norms=norms,
        rms_m=float(np.sqrt(np.mean(norms ** 2))), max_m=float(norms.max()),
        percentiles_m={p: float(np.percentile(norms, p)) for p in PERCENTILES},
        chi2=chi2, dof=dof, p_value=p_value, adequate=is_adequate(p_value, alpha),
        leverage=leverage, standardized=standardized, outlier=outlier,
        high_leverage=leverage > 3 * k / n, alpha=alpha)


def pose_folds(data: Measurements, folds: int, seed: int) -> np.ndarray:
    """Fold id (N,) of every row, the rows of one pose (several reflectors measured at
    the same joint values) always in one fold: held-out poses, not held-out points."""
    if data.reflector is None:
        return fold_ids(len(data), folds, seed)
    _, pose = np.unique(np.atleast_2d(data.q), axis=0, return_inverse=True)
    pose = np.asarray(pose).reshape(-1)
    return fold_ids(int(pose.max()) + 1, folds, seed)[pose]


def cross_validated_rms(model: MeasurementModel, data: Measurements,
                        result: CalibrationResult, folds: int = 5, seed: int = 0) -> float:
    """k-fold cross-validated rms (m) of the identified model over held-out poses.

    Each fold refits the identified parameters on the other poses (a
    Gauss-Newton step from ``result``, exact for the locally linear model) and
    predicts the held-out ones. Compare with the noise floor σ√3.
    """
    sys_ = linearized_fit(model, data, result)
    return cv_rms(sys_.jac, sys_.r, sys_.w, pose_folds(data, folds, seed))

"""Residuals of a calibration: goodness of fit, leverage, outliers, the adequacy level.

Everything is computed on the weighted, locally linear problem at the
identified parameters (:func:`linearized_fit`): the residual r = Σ⁻¹(η − h(p̂, q)) and the
Jacobian of the identified parameters. The χ² test compares Σ‖r_i/σ‖² with χ²(dof) (its
lower tail judges the stated σ, :func:`noise_verdict`); the hat matrix H = U Uᵀ (U an
orthonormal basis of the Jacobian's columns) gives each pose's leverage and the covariance
I − H_ii of its residual. The error on poses a refit did not see is
:mod:`kpi_calib_ros.core.estimation.cross_validation`'s, over the folds of
:mod:`kpi_calib_ros.core.estimation.folds`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import scipy.stats

from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.robust import (
    SIGMA_RATIO_WARNING,
    robust_sigma,
    sigma_warning,
    stated_source,
)
from kpi_calib_ros.core.measurement.data import Measurements, stated_sigma
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import (
    noise_weights,
    point_rows,
    row_torques,
    unweighted,
    weighted_residuals,
    weighted_rows,
)

__all__ = [
    'PERCENTILES', 'ADEQUACY_ALPHA', 'ResidualReport', 'LinearizedFit', 'is_adequate',
    'SIGMA_OVERSTATED', 'SIGMA_CONSISTENT', 'SIGMA_NOT_TESTED', 'noise_verdict',
    'sigma_overstated_text', 'linearized_fit', 'orthonormal_basis', 'residual_report',
]

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
        sqrt(mean ‖r_i‖²) and max ‖r_i‖ over the point rows (a tracked body's rotation
        rows, in rad, are no length), m.
    percentiles_m : dict
        {50, 90, 95, 99} -> percentile of ‖r_i‖ over the point rows, m.
    chi2, dof, p_value : float, int, float
        Σ‖r_i/σ‖² against χ²(dof); p is the upper tail.
    adequate : bool
        p_value >= alpha: the residuals are as small as the stated σ predicts.
    leverage : (N,) ndarray
        Trace of the 3×3 hat-matrix block of each pose (0..3, mean k/N).
    standardized : (N,) ndarray
        r_iᵀ (I − H_ii)⁻¹ r_i in σ units, χ²(3) under the model.
    outlier, high_leverage : (N,) bool ndarray
        Bonferroni-corrected χ²(3) test of ``standardized`` at ``alpha``, against the
        larger of the stated σ and the robust σ̂ (so an understated σ does not make most
        points outliers); leverage above three times the mean.
    sigma_robust_m : float
        σ̂ per axis from the residuals (:func:`kpi_calib_ros.core.estimation.robust.robust_sigma`),
        m.
    sigma_warning : str
        '' or the warning that σ̂ and the stated σ differ by more than 2×.
    sigma_stated_m : float
        The σ per axis the rows state (m): the cell's, or the rms of the points' own
        (:func:`~kpi_calib_ros.core.measurement.data.stated_sigma`), what σ̂ compares with.
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
    sigma_robust_m: float = float('nan')
    sigma_warning: str = ''
    sigma_stated_m: float = float('nan')




@dataclass(frozen=True)
class LinearizedFit:
    """A calibration as a linear least-squares problem at p̂.

    r : (3N,) weighted residuals; jac : (3N, k) weighted Jacobian of the
    identified parameters; basis : orthonormal basis of span(jac); w : (3,)
    weights 1/σ, or (N, 3, 3) whitening matrices with joint-reading noise
    (:meth:`~kpi_calib_ros.core.measurement.tracker.MeasurementModel.whitening`);
    tau : (N, n) gravity torques or None; p : (n_p,) p̂.
    """

    r: np.ndarray
    jac: np.ndarray
    basis: np.ndarray  # orthonormal basis of span(J)
    w: np.ndarray
    tau: np.ndarray | None
    p: np.ndarray
    reflector: np.ndarray | None = None  # (N,) reflector index of every row, None: all 0
    rotation: np.ndarray | None = None   # (N, 3, 3) measured rotations of rotation rows
    covariates: Mapping[str, np.ndarray] | None = None  # per-row covariates of the data


def is_adequate(p_value: float, alpha: float = ADEQUACY_ALPHA) -> bool:
    """Return the χ² adequacy verdict: True when ``p_value >= alpha``.

    True means residuals as small as σ predicts; NaN (no degrees of freedom) is never adequate.
    """
    return bool(p_value >= alpha)


# The noise verdicts of the χ² test's two tails (calibration.yaml model_adequacy).
SIGMA_OVERSTATED = 'sigma overstated'
SIGMA_CONSISTENT = 'sigma consistent'
SIGMA_NOT_TESTED = 'not tested'


def noise_verdict(chi2: float, dof: int, alpha: float = ADEQUACY_ALPHA) -> tuple[str, float]:
    """Return the lower tail of the χ² test: (verdict, P(χ²_dof <= chi2)).

    χ² far *below* its dof is a verdict too: the residuals are smaller than the stated σ
    allows, the σ is overstated (every std and covariance resting on it is too large)
    and the upper-tail adequacy test (:func:`is_adequate`) has lost its power. The two
    tails are two questions, each at the adequacy level ``alpha``: ``adequate`` (upper
    tail) stays about the model, this about the stated σ. :data:`SIGMA_OVERSTATED` when
    the lower tail is below ``alpha``; :data:`SIGMA_NOT_TESTED` with no dof.
    """
    if dof <= 0 or not np.isfinite(chi2):
        return SIGMA_NOT_TESTED, float('nan')
    lower = float(scipy.stats.chi2.cdf(chi2, dof))
    return (SIGMA_OVERSTATED if lower < alpha else SIGMA_CONSISTENT), lower


def sigma_overstated_text(chi2: float, dof: int, lower_p: float,
                          alpha: float = ADEQUACY_ALPHA, ratio: float | None = None) -> str:
    """Return the warning of :data:`SIGMA_OVERSTATED`, naming the key to fix.

    ``ratio``: the residuals over the stated noise alone, when χ² holds more than the noise
    (validation: the parameters' part too); default √(χ²/dof), a fit's own residuals.
    """
    ratio = float(np.sqrt(chi2 / dof)) if ratio is None else ratio
    return (f'{SIGMA_OVERSTATED}: chi2/dof = {chi2:.3g}/{dof} is far below its dof '
            f'(P(chi2 <= {chi2:.3g}) = {lower_p:.2g} < {alpha:g}): the residuals are '
            f'{ratio:.3g} x the stated noise.sigma; every std and covariance '
            'resting on it is too large and the adequacy test cannot fail; check '
            'noise.sigma (units: m)')


def linearized_fit(model: MeasurementModel, data: Measurements, result: CalibrationResult,
            tau: np.ndarray | None = None) -> LinearizedFit:
    """Linearize the calibration ``result`` at p̂ over ``data`` (N poses).

    Residuals and Jacobian rows are whitened as in the fit (each point's stated σ where
    given); ``tau`` (N, n) are the gravity torques (computed from the model when it needs
    them and None is given).
    """
    q = np.atleast_2d(data.q)
    if tau is None:
        tau = row_torques(model, data)
    p = np.asarray(result.values, float)
    w = noise_weights(model, p, data, result.sigma, tau)
    pred, jac = model.jacobian(p, q, tau, data.reflector, data.rotation, data.covariates)
    r = weighted_residuals(np.atleast_2d(data.eta) - pred, w)
    idx = model.params.indices(result.estimated)
    f = weighted_rows(jac, w, idx)
    basis = orthonormal_basis(f)
    return LinearizedFit(r, f, basis, w, tau, p, data.reflector, data.rotation, data.covariates)


def orthonormal_basis(a: np.ndarray) -> np.ndarray:
    """Orthonormal basis (m, r) of the column span of ``a`` (m, k), zero columns dropped.

    Columns are normalized first, so r is the numerical rank at 1e-9 of the largest
    singular value whatever the columns' units.
    """
    norms = np.linalg.norm(a, axis=0)
    a = a[:, norms > 0] / norms[norms > 0]
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    return u[:, s > 1e-9 * s[0]] if len(s) else u


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
    residuals = unweighted(sys_.r, sys_.w)
    norms = np.linalg.norm(residuals, axis=1)
    u = sys_.basis.reshape(n, 3, -1)
    blocks = np.einsum('nik,njk->nij', u, u)  # H_ii, (N, 3, 3)
    leverage = np.trace(blocks, axis1=1, axis2=2)
    # cov(r_i) = I − H_ii in σ units; pinv because a pose with leverage 1 along some
    # direction has no residual there.
    standardized = np.array([ri @ np.linalg.pinv(np.eye(3) - h, rcond=1e-9) @ ri
                             for ri, h in zip(sys_.r.reshape(n, 3), blocks)])
    k = sys_.basis.shape[1]
    dof = 3 * n - k
    # The σ the rows state: the cell's, or the points' own (core.estimation.robust.noise_units).
    stated = stated_sigma(result.sigma, data.sigma, n)
    # With joint-reading noise σ̂ is that of the whitened residuals at the stated σ: the
    # joints' share of the scatter is stated, not a misfit (core.estimation.robust).
    sigma_hat = robust_sigma(residuals if model.joint_sigma is None and data.sigma is None
                             else sys_.r.reshape(n, 3) * stated, dof)
    inflation = max(1.0, sigma_hat / stated) if np.isfinite(sigma_hat) else 1.0
    outlier = scipy.stats.chi2.sf(standardized / inflation ** 2, 3) * n < alpha
    ratio = sigma_hat / stated
    warning = sigma_warning(sigma_hat, stated, stated_source(data)) if np.isfinite(ratio) and not (
        1 / SIGMA_RATIO_WARNING <= ratio <= SIGMA_RATIO_WARNING) else ''
    chi2 = float(sys_.r @ sys_.r)
    p_value = float(scipy.stats.chi2.sf(chi2, dof)) if dof > 0 else float('nan')
    points = point_rows(data.reflector, model.n_reflectors)
    lengths = norms if points is None else norms[points]
    return ResidualReport(
        residuals=residuals, norms=norms,
        rms_m=float(np.sqrt(np.mean(lengths ** 2))), max_m=float(lengths.max()),
        percentiles_m={p: float(np.percentile(lengths, p)) for p in PERCENTILES},
        chi2=chi2, dof=dof, p_value=p_value, adequate=is_adequate(p_value, alpha),
        leverage=leverage, standardized=standardized, outlier=outlier,
        high_leverage=leverage > 3 * k / n, alpha=alpha, sigma_robust_m=sigma_hat,
        sigma_warning=warning, sigma_stated_m=stated)

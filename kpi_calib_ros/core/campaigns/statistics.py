"""The statistics a sequential campaign stops on: σ's upper limit, pure error, lack of fit.

See :mod:`kpi_calib_ros.core.campaigns.sequential` (*Model adequacy*).
"""
from __future__ import annotations

import numpy as np
import scipy.stats

from kpi_calib_ros.core.measurement.replicates import pose_groups

__all__ = ['sigma_upper_limit', 'pure_error', 'lack_of_fit']


def sigma_upper_limit(chi2: float, dof: int, sigma: float, confidence: float) -> float:
    """Upper ``confidence`` limit of σ (m) from χ² against ``sigma`` with ``dof`` dof.

    σ √(χ² / χ²_dof(1 − confidence)); inf without dof.
    """
    if dof <= 0:
        return float('inf')
    return float(sigma * np.sqrt(chi2 / scipy.stats.chi2.ppf(1.0 - confidence, dof)))


def pure_error(q: np.ndarray, eta: np.ndarray, weight: np.ndarray,
               reflector: np.ndarray | None = None) -> tuple[float, int]:
    """Weighted sum of squares (σ units) and dof of the scatter of repeated poses.

    Repeated poses as :func:`~kpi_calib_ros.core.measurement.replicates.pose_groups` finds them:
    3 (m − 1) dof per pose measured m times, per reflector (``reflector`` (N,) the reflector of
    each point row; None: one).
    """
    ss, dof = 0.0, 0
    labels = pose_groups(q)
    if reflector is not None:
        labels = labels * (int(np.max(reflector, initial=0)) + 1) + np.asarray(reflector)
    for g in np.unique(labels):
        pts = eta[labels == g] * weight
        if len(pts) > 1:
            ss += float(np.sum((pts - pts.mean(axis=0)) ** 2))
            dof += 3 * (len(pts) - 1)
    return ss, dof


def lack_of_fit(chi2: float, dof: int, ss_pe: float, dof_pe: int, target_w: float,
                alpha: float) -> dict:
    """F test of "systematic residual rms per axis > target" (σ units throughout).

    MS_lof = (χ² − SS_pe)/(dof − dof_pe) estimates σ² + b², MS_pe estimates σ²; the
    statistic (MS_lof − target²)/MS_pe is F(dof_lof, dof_pe) at b = target. Returns
    ``bias_rms`` (σ units, ≥ 0), ``p_value`` and ``rejects`` (1.0: bias > target).
    """
    dof_lof = dof - dof_pe
    if dof_pe <= 0 or dof_lof <= 0 or ss_pe <= 0:
        return {}
    ms_pe, ms_lof = ss_pe / dof_pe, max(chi2 - ss_pe, 0.0) / dof_lof
    f = (ms_lof - target_w ** 2) / ms_pe
    p = float(scipy.stats.f.sf(f, dof_lof, dof_pe))
    return {'pure_error_dof': float(dof_pe), 'lack_of_fit_dof': float(dof_lof),
            'bias_rms_sigma': float(np.sqrt(max(ms_lof - ms_pe, 0.0))),
            'sigma_pure_error_sigma': float(np.sqrt(ms_pe)),
            'p_value': p, 'rejects': float(p < alpha)}


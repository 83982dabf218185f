"""Precision that holds when the stated σ is too small.

The covariances of an identification (eq. 19) assume the stated measurement σ.
When the χ² test rejects the model (residuals larger than σ explains: an understated
σ or an effect the model lacks) those covariances promise too much. Least-squares
practice then uses the estimated σ̂² = σ² · χ²/dof, i.e. scales every covariance by
χ²/dof (SciPy's ``curve_fit`` with ``absolute_sigma=False``; Bevington & Robinson §8).
The scaling is only applied when the model fails the test, and it is stated.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from kpi_calib_ros.core.estimation import CalibrationResult
from kpi_calib_ros.core.residuals import ADEQUACY_ALPHA, is_adequate


def honest_precision(result: CalibrationResult,
                     alpha: float = ADEQUACY_ALPHA) -> CalibrationResult:
    """``result`` with its covariances from the estimated σ when χ² rejects the model.

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
    if result.covariance_scale != 1.0 or result.dof <= 0 or is_adequate(result.p_value, alpha):
        return result
    scale = float(result.chi2 / result.dof)
    if scale <= 1.0:
        return result
    return dataclasses.replace(result, std=result.std * np.sqrt(scale),
                               covariance=result.covariance * scale,
                               tcp_covariance=result.tcp_covariance * scale,
                               covariance_scale=scale)


def precision_statement(scale: float) -> str:
    """How the reported std were obtained, for files, summaries and the node."""
    if scale == 1.0:
        return 'from the stated sigma (model adequate)'
    return (f'scaled by chi2/dof = {scale:.4g} (estimated sigma = {np.sqrt(scale):.3g} x '
            'stated): the model is not adequate, the stated sigma understates the residuals')


__all__ = ['honest_precision', 'precision_statement']

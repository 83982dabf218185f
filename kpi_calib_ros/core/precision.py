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
from typing import Callable

import numpy as np
import scipy.stats

from kpi_calib_ros.core.estimation import CalibrationResult
from kpi_calib_ros.core.prior import Prior
from kpi_calib_ros.core.residuals import ADEQUACY_ALPHA, is_adequate


def noise_scale(result: CalibrationResult, alpha: float = ADEQUACY_ALPHA) -> float:
    """χ²/dof of ``result`` when the χ² test rejects it and it exceeds 1, else 1."""
    return chi2_scale(result.chi2, result.dof, alpha)


def chi2_scale(chi2: float, dof: int, alpha: float = ADEQUACY_ALPHA) -> float:
    """χ²/dof when the χ² test (``dof`` degrees of freedom) rejects ``chi2`` and it exceeds
    1, else 1: the factor on every covariance of a fit with that χ² (see the module)."""
    if dof <= 0 or is_adequate(float(scipy.stats.chi2.sf(chi2, dof)), alpha):
        return 1.0
    return max(1.0, float(chi2 / dof))


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
    scale = noise_scale(result, alpha)
    if result.covariance_scale != 1.0 or scale == 1.0:
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


BALANCE_ROUNDS = 12
BALANCE_RTOL = 0.02


def tightened(prior: Prior, scale: float) -> Prior:
    """``prior`` with its covariance divided by ``scale`` (Λ → scale·Λ): at the stated σ, the
    balance of the data weighed by σ·√scale against ``prior``."""
    if scale == 1.0:
        return prior
    return Prior(prior.names, prior.mean, prior.covariance / scale)


def balanced_prior(fit: Callable[[Prior], CalibrationResult], prior: Prior,
                   alpha: float = ADEQUACY_ALPHA) -> tuple[Prior, float, CalibrationResult]:
    """A tolerance prior balanced against the noise the residuals show.

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


__all__ = ['balanced_prior', 'chi2_scale', 'honest_precision', 'noise_scale', 'precision_statement',
           'tightened']

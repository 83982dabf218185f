"""Change detection: innovation tests of a new cycle's data against the prior prediction.

Is a new cycle's data consistent with the prior prediction?

A re-identification blends new points with a previous calibration (a Gaussian prior
N(m, C), C widened by the drift model). That is only right while the robot moved no more
than the drift model says; after a collision, a tool change or on another robot the
blend would hide the change. Two tests at the MAP estimate p̂ of the new cycle
(:func:`kpi_calib_ros.core.estimation.least_squares.identify` with the prior), linearised there:

* **global**: J = ‖W(η − h(p̂))‖² + ‖L(m − p̂)‖², the data and prior residuals together
  (LᵀL = C⁻¹). For a linear model with consistent data J ~ χ²(3N + n_prior − k),
  k the identified parameters: the minimum of the joint cost is the normalised
  innovation of the new points against the prior prediction (covariance: the prior mapped
  through the Jacobian plus the tracker noise), in information form so unconstrained
  parameters (a re-registered base) are handled exactly.
* **per parameter** (which parameter moved): the likelihood ratio of releasing the prior
  mean of parameter j by a free shift δ_j. With A = [F; L] the stacked Jacobian of the
  identified parameters, b the stacked residual, P = I − A A⁺ and c_j = [0; L e_j]:
  LR_j = (c_jᵀ P b)² / (c_jᵀ P c_j) ~ χ²(1) under consistency, the shift estimate
  δ̂_j = −c_jᵀ P b / (c_jᵀ P c_j) with std 1/√(c_jᵀ P c_j) (the standardized shift is
  √LR_j).

The data are *inconsistent* when the global test or any per-parameter test (Bonferroni
over the prior's parameters) rejects, each at α/2: family-wise false-alarm level α.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.stats

from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import (
    noise_weights,
    row_torques,
    weighted_residuals,
    weighted_rows,
)

__all__ = ['CHANGE_ALPHA', 'ParameterShift', 'ChangeTest', 'change_test']

# Family-wise false-alarm level of a change per cycle: over a day of 20 cycles a false
# alarm in at most 2 % of days.
CHANGE_ALPHA = 1e-3


@dataclass(frozen=True)
class ParameterShift:
    """Likelihood-ratio test of one prior parameter (SI units)."""

    name: str
    lr: float
    p_value: float
    shift: float
    shift_std: float
    prior_std: float


@dataclass(frozen=True)
class ChangeTest:
    """Outcome of :func:`change_test`.

    ``moved`` lists the parameters beyond the drift model, largest likelihood ratio first.
    """

    consistent: bool
    alpha: float
    chi2: float
    dof: int
    p_value: float
    lr_threshold: float
    parameters: tuple[ParameterShift, ...]
    moved: tuple[ParameterShift, ...]
    caveat: str = ''

    def summary(self) -> str:
        """One line for reports: consistent or the moved parameters, with the test figures."""
        head = (f'innovation chi2 {self.chi2:.1f} for {self.dof} dof (p = {self.p_value:.3g}); '
                f'per-parameter LR threshold {self.lr_threshold:.1f} (family-wise alpha '
                f'{self.alpha:g})')
        if self.consistent:
            return 'new data consistent with the prior and its drift model: ' + head
        moved = ', '.join(f'{m.name} ({m.shift:+.4g} ± {m.shift_std:.2g}, LR {m.lr:.0f})'
                          for m in self.moved) or 'no single parameter (a broad change)'
        return ('CHANGE DETECTED: the new data contradict the prior calibration beyond its '
                f'drift model ({head}); moved: {moved}. The update was not blended: measure '
                'a full campaign (kpi-calib design --n 60, then identify without --prior)'
                + (f'. {self.caveat}' if self.caveat else ''))

    def to_dict(self) -> dict[str, Any]:
        """YAML-ready form: the test figures and the moved parameters (SI units)."""
        def entry(m: ParameterShift) -> dict[str, Any]:
            return {'name': m.name, 'lr': m.lr, 'p_value': m.p_value, 'shift': m.shift,
                    'shift_std': m.shift_std, 'prior_std': m.prior_std}
        return {'consistent': self.consistent, 'alpha': float(self.alpha), 'chi2': self.chi2,
                'dof': self.dof, 'p_value': self.p_value, 'lr_threshold': self.lr_threshold,
                'moved': [entry(m) for m in self.moved], 'caveat': self.caveat,
                'parameters': [entry(m) for m in self.parameters]}


def change_test(model: MeasurementModel, data: Measurements, sigma: float | np.ndarray,
                result: CalibrationResult, prior: Prior,
                alpha: float = CHANGE_ALPHA, sigma_dof: int | None = None) -> ChangeTest:
    """Innovation tests of ``data`` against ``prior`` at the MAP estimate ``result``.

    ``result`` is identified with that prior on the same data, every row weighted as the
    identification weighs it (``sigma`` or the row's own stated σ, the joint-reading noise)
    and predicted with its own torques (its payload, its measured efforts).

    ``sigma_dof``: ``sigma`` is itself an estimate on that many degrees of freedom (σ̂ of
    a previous calibration whose model was not adequate); the tests then use the F
    distribution (F(dof, sigma_dof) for the global one, F(1, sigma_dof) per parameter)
    instead of χ², so the uncertainty of σ̂ raises no false alarm.

    Raises
    ------
    ValueError
        ``alpha`` outside (0, 1).
    """
    if not 0 < alpha < 1:
        raise ValueError(f'alpha must be in (0, 1), got {alpha}')
    p = np.asarray(result.values, float)
    idx = model.params.indices(list(result.estimated))
    q = np.atleast_2d(data.q)
    # Each row as the identification takes it: its own torques (payload, measured efforts),
    # its own stated σ and the joint-reading noise.
    tau = row_torques(model, data)
    w = noise_weights(model, p, data, sigma, tau)
    pred, jac = model.jacobian(p, q, tau, data.reflector, data.rotation, data.covariates)
    r_data = weighted_residuals(np.atleast_2d(data.eta) - pred, w).ravel()
    f_data = weighted_rows(jac, w, idx)
    l_full, lm = prior.rows(model.params)
    r_prior = lm - l_full @ p
    a = np.vstack([f_data, l_full[:, idx]])
    b = np.concatenate([r_data, r_prior])
    n_prior = len(prior.names)
    chi2 = float(b @ b)
    dof = max(int(len(r_data) + n_prior - len(idx)), 1)
    if sigma_dof is None:
        p_global = float(scipy.stats.chi2.sf(chi2, dof))
        threshold = float(scipy.stats.chi2.isf(alpha / (2 * n_prior), 1))

        def p_one(lr: float) -> float:
            return float(scipy.stats.chi2.sf(lr, 1))
    else:
        p_global = float(scipy.stats.f.sf(chi2 / dof, dof, sigma_dof))
        threshold = float(scipy.stats.f.isf(alpha / (2 * n_prior), 1, sigma_dof))

        def p_one(lr: float) -> float:
            return float(scipy.stats.f.sf(lr, 1, sigma_dof))
    # Projector onto the complement of the identified directions (orthonormal basis).
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    u = u[:, s > s[0] * 1e-12]
    pb = b - u @ (u.T @ b)
    prior_std = prior.std
    shifts = []
    for j, name in enumerate(prior.names):
        c = np.concatenate([np.zeros(len(r_data)), l_full[:, model.params.index(name)]])
        pc = c - u @ (u.T @ c)
        denominator = float(c @ pc)
        if denominator <= 1e-12 * float(c @ c):
            continue  # the identified parameters absorb this shift entirely: not testable
        numerator = float(c @ pb)
        lr = numerator ** 2 / denominator
        shifts.append(ParameterShift(name, float(lr), p_one(lr),
                                     float(-numerator / denominator),
                                     float(1.0 / np.sqrt(denominator)),
                                     float(prior_std[j])))
    shifts.sort(key=lambda m: -m.lr)
    moved = tuple(m for m in shifts if m.lr > threshold)
    consistent = bool(p_global >= alpha / 2 and not moved)
    return ChangeTest(consistent, alpha, chi2, dof, p_global, threshold, tuple(shifts), moved)

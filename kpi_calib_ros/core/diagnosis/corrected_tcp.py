"""The TCP predicted with the learned residual: its position and both parts of uncertainty.

The physical model's TCP plus the learned residual's correction δ(q)
(:mod:`kpi_calib_ros.core.diagnosis.learned_residual`), with the parameters' covariance
weighted between the one inside the fitted region and the one outside it, plus the learned
residual's latent variance.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kpi_calib_ros.core.diagnosis.learned_residual import LearnedResidual, ResidualPrediction

__all__ = ['CorrectedTcp', 'outside_weight', 'corrected_tcp']


@dataclass(frozen=True)
class CorrectedTcp:
    """TCP (KPI point) predictions with the learned residual.

    Attributes
    ----------
    position : (M, 3) ndarray
        Physical prediction + δ(q), tracker frame, m.
    covariance : (M, 3, 3) ndarray
        Parameter part + the learned residual's latent variance, m².
    physical_covariance : (M, 3, 3) ndarray
        The parameter part alone, m².
    correction : ResidualPrediction
        δ(q) with its variance, distance and inside flag (None: no learned residual).
    """

    position: np.ndarray
    covariance: np.ndarray
    physical_covariance: np.ndarray
    correction: ResidualPrediction | None

    @property
    def std_m(self) -> np.ndarray:
        """(M,) sqrt(trace) of ``covariance``, m."""
        return np.sqrt(np.trace(self.covariance, axis1=1, axis2=2))


def outside_weight(model: LearnedResidual, prediction: ResidualPrediction) -> np.ndarray:
    """Return the (M,) weight of the inside covariance at each query (:func:`corrected_tcp`).

    1 − ((latent variance)/c)²: 1 at the training poses, 0 where the learned residual has
    returned to its prior.
    """
    latent = np.trace(prediction.covariance, axis1=1, axis2=2) / (3.0 * model.amplitude_m2)
    return np.clip(1.0 - latent ** 2, 0.0, 1.0)


def corrected_tcp(tcp: np.ndarray, tcp_jacobian: np.ndarray, covariance_inside: np.ndarray,
                  q: np.ndarray, model: LearnedResidual | None,
                  covariance_outside: np.ndarray | None = None) -> CorrectedTcp:
    """Predict the TCP: the physical model plus the learned residual, both uncertainties.

    Inside the fitted region the learned residual knows the misfit there, the part the
    parameters absorbed included, so the parameters' covariance is the one with the noise
    it leaves (``covariance_inside``). Far from the training poses the correction has
    returned to 0 with its prior variance c, and the parameters' error shows in full: the
    fit took part of the misfit field into them, and the field's correlation over nearby
    poses leaves them less known than independent rows would (``covariance_outside``,
    :func:`~kpi_calib_ros.core.diagnosis.learned_residual.field_parameter_covariance`).
    Between the two the weight is the share of the prior variance the training poses
    explain at the query, 1 − ((latent variance)/c)²: 1 where the learned residual knows
    δ, 0 where it has returned to its prior.

    Parameters
    ----------
    tcp : (M, 3) ndarray
        Physical model's TCP at the query poses, tracker frame, m.
    tcp_jacobian : (M, 3, k) ndarray
        d tcp / d p of the k estimated parameters.
    covariance_inside : (k, k) ndarray
        Their covariance with the noise the learned residual leaves
        (:func:`~kpi_calib_ros.core.diagnosis.learned_residual.residual_noise_scale`); without a
        learned residual, the one reported.
    q : (M, n) ndarray
        The query poses (URDF chain order).
    model : LearnedResidual or None
        None: the physical prediction alone.
    covariance_outside : (k, k) ndarray, optional
        Their covariance when the misfit is the learned field
        (:func:`~kpi_calib_ros.core.diagnosis.learned_residual.field_parameter_covariance`); default
        ``covariance_inside``.
    """
    tcp = np.asarray(tcp, float).reshape(-1, 3)
    # The parameter count from the covariance: with no query (a cell without working
    # poses) the Jacobian is empty and its last axis cannot be inferred.
    jac = np.asarray(tcp_jacobian, float).reshape(len(tcp), 3, len(covariance_inside))

    def propagated(cov: np.ndarray) -> np.ndarray:
        return np.einsum('mik,kl,mjl->mij', jac, cov, jac)
    inside = propagated(covariance_inside)
    if model is None:
        return CorrectedTcp(tcp, inside, inside, None)
    pred = model.predict(q)
    physical = inside
    if covariance_outside is not None:
        weight = outside_weight(model, pred)[:, None, None]
        physical = weight * inside + (1.0 - weight) * propagated(covariance_outside)
    return CorrectedTcp(tcp + pred.mean, physical + pred.covariance, physical, pred)

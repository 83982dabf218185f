"""Points that share their errors: the joint statement over a recording and its test.

A calibration's predictions at many poses are not independent. Every point carries the same
error of the estimated parameters (propagated through its own Jacobian), and with a learned
residual the same smooth field δ(q) over nearby poses. The per-point covariance
(:func:`kpi_calib_ros.core.diagnosis.corrected_tcp.corrected_tcp`) is right for each point,
but summing the points' χ² as if they were independent overstates the evidence of a large
recording: 600 poses far from the training region may all sit on one draw of the parameters'
error and carry the evidence of a handful of independent points.

:func:`statement_covariance` builds the covariance of all points jointly, cross-pose terms
included; its diagonal blocks are the per-point statement. :func:`shared_error_test` keeps
the statistic a person reads (T = Σ_m e_mᵀ C_m⁻¹ e_m, the points' χ²) but takes its
distribution under the joint statement: T is a quadratic form of a Gaussian vector, a
weighted sum of χ²₁ whose first two moments give the scaled χ² g · χ²_h
(Satterthwaite): with R the joint covariance whitened point by point,

    E T = 3M = tr R,   var T = 2 ‖R‖²_F,   g = ‖R‖²_F / 3M,   h = (3M)² / ‖R‖²_F.

Without cross-pose terms R = I, g = 1 and h = 3M: the usual χ² test. h / 3 is the number of
independent points the recording is worth. Seeded draws of the joint statement also give the
range the share of points inside their 95 % ellipsoid takes over recordings that agree with
the statement, and where the observed share lies in it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.stats

from kpi_calib_ros.core.diagnosis.corrected_tcp import outside_weight
from kpi_calib_ros.core.diagnosis.learned_residual import LearnedResidual

ELLIPSOID_95 = float(scipy.stats.chi2.ppf(0.95, 3))
DRAWS = 1000  # draws of the joint statement for the share's range
MAX_POINTS = 600  # larger recordings: a seeded subset of this many points is tested


def statement_covariance(tcp_jacobian: np.ndarray, covariance_inside: np.ndarray,
                         q: np.ndarray, model: LearnedResidual | None = None,
                         covariance_outside: np.ndarray | None = None,
                         noise_m2: np.ndarray | None = None) -> np.ndarray:
    """Joint covariance of the prediction errors at M points, cross-pose terms included.

    The statement of :func:`~kpi_calib_ros.core.diagnosis.corrected_tcp.corrected_tcp`
    over all points at once. The parameters' error is shared: with w_m the weight of the
    inside covariance at point m, the parameter part is
    √(w_m w_n) J_m C_in J_nᵀ + √((1 − w_m)(1 − w_n)) J_m C_out J_nᵀ (one error drawn inside,
    one far from the training poses, blended as each point's own statement blends them).
    The learned field's part is its posterior covariance between the points times its
    output shape A; the noise (``noise_m2``, 3 × 3 per point) is independent between points.

    Parameters
    ----------
    tcp_jacobian : (M, 3, k) ndarray
        d point / d p of the k estimated parameters.
    covariance_inside : (k, k) ndarray
        The parameters' covariance (with a learned residual: with the noise it leaves).
    q : (M, n) ndarray
        Joint values of the points (URDF chain order).
    model : LearnedResidual or None
        None: the physical statement alone (then only ``covariance_inside`` is used).
    covariance_outside : (k, k) ndarray, optional
        The parameters' covariance under the learned field; default ``covariance_inside``.
    noise_m2 : (3, 3) ndarray, optional
        A measurement's noise covariance, m² (None: the true point, no noise).

    Returns
    -------
    (3M, 3M) ndarray
        m², rows and columns ordered point by point (x, y, z of point 0, then point 1 …).
    """
    jac = np.asarray(tcp_jacobian, float)
    m = len(jac)
    flat = jac.reshape(3 * m, -1)
    c_in = np.asarray(covariance_inside, float)
    if model is None:
        joint = flat @ c_in @ flat.T
    else:
        q = np.atleast_2d(np.asarray(q, float))
        weight = outside_weight(model, model.predict(q))
        c_out = c_in if covariance_outside is None else np.asarray(covariance_outside, float)
        root_in = np.repeat(np.sqrt(weight), 3)[:, None] * flat
        root_out = np.repeat(np.sqrt(1.0 - weight), 3)[:, None] * flat
        joint = (root_in @ c_in @ root_in.T + root_out @ c_out @ root_out.T
                 + np.kron(model.latent_covariance(q), model.output_shape))
    if noise_m2 is not None:
        joint = joint + np.kron(np.eye(m), np.asarray(noise_m2, float))
    return 0.5 * (joint + joint.T)


@dataclass(frozen=True)
class SharedErrorTest:
    """Do M points agree with a joint statement? (:func:`shared_error_test`).

    Attributes
    ----------
    points : int
        Points tested.
    chi2 : float
        T = Σ_m e_mᵀ C_m⁻¹ e_m over the points, C_m each point's own statement.
    dof : int
        3M: T's mean under the statement.
    effective_points : float
        h / 3: the independent points the recording is worth under the statement.
    p_value : float
        P(T ≥ observed) under the joint statement (g · χ²_h).
    share : float
        Share of the points inside their stated 95 % ellipsoid.
    share_range : tuple of float
        2.5 % and 97.5 % quantiles of that share over draws of the joint statement.
    share_percentile : float
        Share of the draws whose share is at most the observed one.
    """

    points: int
    chi2: float
    dof: int
    effective_points: float
    p_value: float
    share: float
    share_range: tuple[float, float]
    share_percentile: float


def shared_error_test(errors: np.ndarray, covariance: np.ndarray, draws: int = DRAWS,
                      seed: int = 0) -> SharedErrorTest:
    """Test M points' errors against their joint statement (module docstring).

    Parameters
    ----------
    errors : (M, 3) ndarray
        Measured minus predicted, m.
    covariance : (3M, 3M) ndarray
        Their joint statement (:func:`statement_covariance`), m².
    draws : int
        Draws of the joint statement for the share's range.
    seed : int
        Seed of the draws.

    Returns
    -------
    SharedErrorTest
    """
    e = np.asarray(errors, float).reshape(-1, 3)
    m = len(e)
    joint = np.asarray(covariance, float)
    if joint.shape != (3 * m, 3 * m):
        raise ValueError(f'covariance must be {3 * m} x {3 * m} for {m} points, '
                         f'got {joint.shape}')
    idx = np.arange(m)
    blocks = joint.reshape(m, 3, m, 3)[idx, :, idx, :]
    # Whiten point by point: z_m = L_m⁻¹ e_m with C_m = L_m L_mᵀ, so ‖z_m‖² = e_mᵀ C_m⁻¹ e_m.
    inv_roots = np.linalg.inv(np.linalg.cholesky(blocks))
    z = np.einsum('mij,mj->mi', inv_roots, e)
    m2 = np.sum(z ** 2, axis=1)
    r = np.einsum('mab,mbnc,ndc->mand', inv_roots, joint.reshape(m, 3, m, 3),
                  inv_roots, optimize=True).reshape(3 * m, 3 * m)
    r = 0.5 * (r + r.T)
    frobenius = float(np.sum(r ** 2))
    dof = 3 * m
    scale, h = frobenius / dof, dof ** 2 / frobenius
    chi2 = float(np.sum(m2))
    eig, vec = np.linalg.eigh(r)
    root = vec * np.sqrt(np.clip(eig, 0.0, None))
    sample = root @ np.random.default_rng(seed).normal(size=(3 * m, draws))
    shares = np.mean(np.sum(sample.T.reshape(draws, m, 3) ** 2, axis=2) <= ELLIPSOID_95,
                     axis=1)
    share = float(np.mean(m2 <= ELLIPSOID_95))
    low, high = np.quantile(shares, [0.025, 0.975])
    return SharedErrorTest(m, chi2, dof, h / 3.0, float(scipy.stats.chi2.sf(chi2 / scale, h)),
                           share, (float(low), float(high)), float(np.mean(shares <= share)))


def joint_test_points(n: int, max_points: int = MAX_POINTS, seed: int = 0) -> np.ndarray:
    """Return the indices of the points a joint test uses.

    All ``n``, or a seeded subset of ``max_points`` in their order (the joint covariance
    grows with n²).
    """
    if n <= max_points:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))


__all__ = ['DRAWS', 'MAX_POINTS', 'SharedErrorTest', 'joint_test_points', 'shared_error_test',
           'statement_covariance']

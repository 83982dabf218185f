"""Covariance of the constrained least-squares estimate with KPI variables.

The constrained problem (13a-b) has variables v = (p, s), residual Jacobian
F1 = [Σ⁻¹ dh/dp, 0] and constraint Jacobian F2 = [dTCP/dp, -I]. Its covariance is
eq. (19)

    C_v = [I 0] · [[F1ᵀF1, F2ᵀ], [F2, 0]]⁻¹ · [I; 0].

The appendix of the paper shows that this equals the null-space form
Z (Zᵀ F1ᵀ F1 Z)⁻¹ Zᵀ (Z spanning ker F2) and, for the KPI block, the plain
propagation J_w C_p J_wᵀ of the unconstrained covariance. All three are here so
tests can prove that they agree.

Scales differ by ~10 orders of magnitude (σ ~ 1e-5 m, angles ~ 1 rad), so every
form is evaluated in column-equilibrated coordinates and mapped back.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = [
    'kpi_jacobians', 'kkt_covariance', 'nullspace_covariance', 'parameter_covariance',
    'propagated_kpi_covariance', 'standard_deviations',
]


def kpi_jacobians(f1_p: np.ndarray, tcp_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """F1 and F2 of eq. (14) for v = (p, s).

    Parameters
    ----------
    f1_p : (m, k) ndarray
        Weighted measurement Jacobian Σ⁻¹ dh/dp of the estimated parameters.
    tcp_p : (n_s, k) ndarray
        Jacobian of the KPI points (stacked working poses) w.r.t. the same parameters.
    """
    m, k = f1_p.shape
    n_s = tcp_p.shape[0]
    f1 = np.hstack([f1_p, np.zeros((m, n_s))])
    f2 = np.hstack([tcp_p, -np.eye(n_s)])
    return f1, f2


def _column_scale(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(f1, axis=0)
    fallback = np.linalg.norm(f2, axis=0)
    scale = np.where(norms > 0, norms, fallback)
    return 1.0 / np.where(scale > 0, scale, 1.0)


def standard_deviations(covariance: np.ndarray) -> np.ndarray:
    """Return the std of each parameter of ``covariance`` (k, k); inf where not determined.

    A negative or non-finite variance is a direction the KKT solve lost (its matrix
    numerically singular there: on the real TIAGo a play trial's fit gave −1.2e6 m² for a
    link length): the parameter is not determined, and its std is inf, which every bound
    and tolerance test refuses, never the NaN that every comparison passes.
    """
    var = np.diag(np.atleast_2d(covariance))
    return np.sqrt(np.where(np.isfinite(var) & (var >= 0.0), var, np.inf))


def kkt_covariance(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Eq. (19): covariance (n_v, n_v) of v from the KKT matrix.

    Raises
    ------
    numpy.linalg.LinAlgError
        When (CQ) or (PD) of eq. (15) fails and the KKT matrix is singular.
    """
    d = _column_scale(f1, f2)
    a = f1 * d
    b = f2 * d
    b = b / np.linalg.norm(b, axis=1, keepdims=True)  # row scaling leaves C_v unchanged
    n_v, n_2 = a.shape[1], b.shape[0]
    kkt = np.block([[a.T @ a, b.T], [b, np.zeros((n_2, n_2))]])
    rhs = np.vstack([np.eye(n_v), np.zeros((n_2, n_v))])
    scaled = np.linalg.solve(kkt, rhs)[:n_v]
    return d[:, None] * scaled * d[None, :]


def nullspace_covariance(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Appendix form Z (Zᵀ F1ᵀ F1 Z)⁻¹ Zᵀ with Z an orthonormal basis of ker F2."""
    d = _column_scale(f1, f2)
    a = f1 * d
    z = scipy.linalg.null_space(f2 * d)
    reduced = np.linalg.inv(z.T @ a.T @ a @ z)
    return d[:, None] * (z @ reduced @ z.T) * d[None, :]


def parameter_covariance(f1_p: np.ndarray) -> np.ndarray:
    """Unconstrained covariance (F1ᵀ F1)⁻¹ (k, k), via a scaled QR (no normal equations)."""
    d = 1.0 / np.linalg.norm(f1_p, axis=0)
    # numpy's stubs type every qr() as QRResult; mode='r' returns the R array alone.
    r: np.ndarray = np.linalg.qr(f1_p * d, mode='r')  # type: ignore[assignment]
    r_inv = scipy.linalg.solve_triangular(r, np.eye(r.shape[0]))
    return d[:, None] * (r_inv @ r_inv.T) * d[None, :]


def propagated_kpi_covariance(f1_p: np.ndarray, tcp_p: np.ndarray) -> np.ndarray:
    """Unconstrained propagation J_w C_p J_wᵀ (n_s, n_s)."""
    return tcp_p @ parameter_covariance(f1_p) @ tcp_p.T

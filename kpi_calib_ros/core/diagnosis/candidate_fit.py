"""The augmented fit of one candidate effect, and how the candidates' fits compare.

The augmented fits are Gauss-Newton steps from the converged geometric
solution: effects of a few tenths of a milliradian move the points by tenths
of a millimetre, so the second-order terms (≈ θ²·1 m ≈ 0.1 µm) are far below
the tracker noise and one linear step is the fit (:func:`fit_candidate`: its F-test
against the geometric fit and its cross-validated rms over held-out poses).

Between candidates: fits with the same signature are one candidate
(:func:`merge_same_signature`), an effect that nests simpler ones of its joint must beat
the best of them (:func:`nested_alternatives`), and backlash and compliance of one joint are
compared (:func:`torque_effect_notes`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import casadi as ca
import numpy as np
import scipy.stats

from kpi_calib_ros.core.effects.registry import BoundEffect, implausible
from kpi_calib_ros.core.estimation.cross_validation import linear_validation_rms
from kpi_calib_ros.core.estimation.precision import chi2_scale
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA, LinearizedFit
from kpi_calib_ros.core.measurement.weighting import point_rms, unweighted

__all__ = ['SAME_SIGNATURE', 'CandidateFit', 'fit_candidate', 'merge_same_signature',
           'nested_alternatives', 'torque_effect_notes']


@dataclass(frozen=True)
class CandidateFit:
    """The augmented fit of one candidate at one shape, before the candidates are ranked.

    Field names as in :class:`Candidate`; units of the effect's parameters.

    Attributes
    ----------
    effect : BoundEffect
    theta : (k,) ndarray
        Fitted sizes, then the shape parameters held at their grid value.
    std : (k,) ndarray
        Their std from the stated σ (NaN for the held shape parameters).
    rms_m, validation_rms_m : float
        rms (m) of the augmented fit and its cross-validated rms over held-out poses.
    chi2, dof : float, int
        Weighted residual sum of the augmented fit and its degrees of freedom.
    delta_chi2, f_statistic, p_value_raw : float
        χ² reduction over the geometric fit, its F statistic and single-test p-value.
    correlation, driver_correlation, unique_fraction : float
        As in :class:`Candidate`.
    unique : (3N, k) ndarray
        The part of the effect's weighted columns the geometry does not reproduce.
    merged : tuple of str
        Specs of candidates with the same signature merged into this one.
    """

    effect: BoundEffect
    theta: np.ndarray
    std: np.ndarray
    rms_m: float
    chi2: float
    dof: int
    unique: np.ndarray
    validation_rms_m: float
    delta_chi2: float
    f_statistic: float
    p_value_raw: float
    correlation: float
    driver_correlation: float
    unique_fraction: float
    merged: tuple[str, ...] = ()

    @property
    def covariance_scale(self) -> float:
        """Return χ²/dof of the augmented fit when its χ² test rejects, else 1.

        As :func:`~kpi_calib_ros.core.estimation.precision.chi2_scale` gives it.
        """
        return chi2_scale(self.chi2, self.dof)

    @property
    def scaled_std(self) -> np.ndarray:
        """Return the std as reported: scaled by :attr:`covariance_scale`."""
        return self.std * np.sqrt(self.covariance_scale)


def fit_candidate(effect: BoundEffect, cols: np.ndarray, sys_: LinearizedFit, r_perp: np.ndarray,
                  chi2_base: float, dof_base: int, pose_folds: np.ndarray | None,
                  joint_jac: np.ndarray, q: np.ndarray, tau: np.ndarray,
                  fraction: float, shape: tuple[float, ...] = (),
                  points: np.ndarray | None = None) -> CandidateFit:
    """Augmented least squares [J E] from the geometric solution, its F-test and CV.

    Shape parameters held at ``shape`` (chosen from a grid) count as fitted in the F-test's
    degrees of freedom; their std is NaN.
    """
    k = cols.shape[1] + len(shape)
    unique = cols - sys_.basis @ (sys_.basis.T @ cols)
    info = unique.T @ unique  # Schur complement: information on θ with geometry free
    cov = np.linalg.inv(info)
    size = cov @ (unique.T @ r_perp)
    r_aug = r_perp - unique @ size
    theta = np.concatenate([size, shape])
    std = np.concatenate([np.sqrt(np.diag(cov)), np.full(len(shape), np.nan)])
    chi2_aug = float(r_aug @ r_aug)
    delta = chi2_base - chi2_aug
    dof = dof_base - k
    f_stat = (delta / k) / (chi2_aug / dof)
    p_raw = float(scipy.stats.f.sf(f_stat, k, dof))
    cv = linear_validation_rms(np.hstack([sys_.jac, cols]), sys_.r, sys_.w, pose_folds,
                               points=points)
    rms = point_rms(unweighted(r_aug, sys_.w), points)
    corr = float(np.sqrt(max(delta, 0.0) / chi2_base)) if chi2_base > 0 else 0.0
    return CandidateFit(
        effect=effect, theta=theta, std=std, rms_m=rms, chi2=chi2_aug, dof=dof, unique=unique,
        validation_rms_m=cv, delta_chi2=delta, f_statistic=f_stat, p_value_raw=p_raw,
        correlation=corr,
        driver_correlation=_driver_correlation(effect, theta, unique, size, r_aug, sys_.w,
                                               joint_jac, q, tau),
        unique_fraction=fraction)


SAME_SIGNATURE = 1e-6  # sin of the largest principal angle between two signatures


def merge_same_signature(fits: list[CandidateFit]) -> list[CandidateFit]:
    """Merge candidates whose signatures span the same subspace.

    A signature is the part of a candidate's Jacobian columns the geometry does not reproduce;
    for one parameter, the same subspace is the same column up to scale. The best-fitting one
    stays, with the others' specs in ``'merged'``: the data cannot tell them apart, so they are
    one candidate, not several.
    """
    bases = [np.linalg.qr(f.unique)[0] for f in fits]
    order = sorted(range(len(fits)), key=lambda i: -fits[i].delta_chi2)
    taken: set[int] = set()
    out = []
    for i in order:
        if i in taken:
            continue
        merged: list[str] = []
        for j in order:
            if j == i or j in taken or bases[j].shape[1] != bases[i].shape[1]:
                continue
            gap = bases[j] - bases[i] @ (bases[i].T @ bases[j])
            if np.linalg.norm(gap, 2) < SAME_SIGNATURE:
                merged.append(fits[j].effect.name)
                taken.add(j)
        taken.add(i)
        out.append(replace(fits[i], merged=tuple(merged)))
    return out


def nested_alternatives(fits: list[CandidateFit], alpha: float = ADEQUACY_ALPHA
                        ) -> dict[str, str]:
    """Test effects that nest simpler ones of the same joint against the best simpler one.

    For an effect that contains simpler ones of the same joint (``EffectType.nests``: joint_play
    is joint_backlash as τ0 -> 0 and joint_compliance as τ0 -> ∞): is it significantly better
    than the best plausible simpler one (F-test of its extra parameters at ``alpha``)? If not,
    the simpler one is the explanation. Returns spec -> why it is not counted significant.
    """
    by_joint: dict[tuple[str | None, str], CandidateFit] = {
        (f.effect.joint, f.effect.kind.name): f for f in fits}
    out = {}
    for fit in fits:
        effect = fit.effect
        rivals = [by_joint[(effect.joint, name)] for name in effect.kind.nests
                  if (effect.joint, name) in by_joint]
        rivals = [r for r in rivals if not implausible(r.effect, r.theta)]
        if not rivals:
            continue
        rival = max(rivals, key=lambda r: r.delta_chi2)
        extra = len(fit.theta) - len(rival.theta)
        f_stat = (fit.delta_chi2 - rival.delta_chi2) / extra / (fit.chi2 / fit.dof)
        p = float(scipy.stats.f.sf(f_stat, extra, fit.dof)) if f_stat > 0 else 1.0
        if p >= alpha:
            out[effect.name] = (f'Not counted: the simpler {rival.effect.name} explains '
                                f'as much (F-test of the extra parameter p = {p:.3g} >= '
                                f'{alpha:g}).')
    return out


def torque_effect_notes(fits: list[CandidateFit]) -> dict[str, str]:
    """Compare backlash and compliance of a joint where both are candidates.

    For a joint with both backlash (a step with the sign of the gravity torque) and compliance
    (in proportion to it) among the candidates: which fits better, by the χ² reduction of each
    (both have one parameter). Returns spec -> note.
    """
    by_joint: dict[str, dict[str, CandidateFit]] = {}
    for f in fits:
        e = f.effect
        if e.kind.name in ('joint_backlash', 'joint_compliance') and e.joint is not None:
            by_joint.setdefault(e.joint, {})[e.kind.name] = f
    notes = {}
    for joint, pair in by_joint.items():
        if len(pair) < 2:
            continue
        b, c = pair['joint_backlash'], pair['joint_compliance']
        better = 'backlash (a sign flip with the torque)' if b.delta_chi2 > c.delta_chi2 \
            else 'compliance (in proportion to the torque)'
        text = (f'On {joint}, {better} fits better: χ² reduction {b.delta_chi2:.1f} for '
                f'backlash vs {c.delta_chi2:.1f} for compliance.')
        notes[b.effect.name] = notes[c.effect.name] = text
    return notes


def _driver_correlation(effect: BoundEffect, theta: np.ndarray, unique: np.ndarray,
                        size: np.ndarray, r_aug: np.ndarray, w: np.ndarray,
                        joint_jac: np.ndarray,
                        q: np.ndarray, tau: np.ndarray) -> float:
    """Correlation of the joint-angle error implied by the residuals with the fitted correction.

    The residual the effect explains (r_aug + Eθ̂, geometry refitted) is
    projected on the direction the point moves when joint j turns, giving an
    implied angle error per pose; it is correlated (weighted by the squared
    lever) with the effect's fitted correction δq_j(q, τ, θ̂).
    """
    if effect.joint_index is None or effect.kind.joint_function is None or effect.inputs:
        return float('nan')  # no correction of its joint's value from (q, τ) alone
    j = effect.joint_index
    explained = unweighted(r_aug + unique @ size, w)
    lever = joint_jac[:, :, j]
    lever2 = np.sum(lever ** 2, axis=1)
    ok = lever2 > 1e-12
    if ok.sum() < 3:
        return float('nan')
    implied = np.sum(lever * explained, axis=1)[ok] / lever2[ok]
    correction = _joint_correction_values(effect, q, tau, theta)[ok, j]
    wt = lever2[ok] / lever2[ok].sum()
    a = implied - wt @ implied
    b = correction - wt @ correction
    denom = np.sqrt((wt @ a ** 2) * (wt @ b ** 2))
    return float(wt @ (a * b) / denom) if denom > 0 else float('nan')


def _joint_correction_values(effect: BoundEffect, q: np.ndarray, tau: np.ndarray,
                             theta: np.ndarray) -> np.ndarray:
    """Numeric joint corrections (N, n) of ``effect`` at parameters ``theta``."""
    n = q.shape[1]
    qs, ts = ca.SX.sym('q', n), ca.SX.sym('tau', n)
    th = ca.SX.sym('theta', len(theta))
    fn = ca.Function('dq', [qs, ts, th], [effect.joint_correction(qs, ts, th)])
    return np.array(fn.map(len(q))(q.T, np.atleast_2d(tau)[:, :n].T, theta)).T  # τ, not G

"""Faults, not model misfit: which of the points far from a fit identification may exclude.

A point far from the fit is either a *fault* of that measurement (the tracker locked on
another target, a broken beam, a point of another reflector) or a *misfit* of the model at
that pose (an effect the model lacks: compliance at the end of a sweep, a gear error).
Excluding a misfit point removes what only it tells the fit (a pose at the end of a
one-joint sweep is the model's only information there) and makes the held-out error worse;
excluding a fault makes it better. What tells them apart is what the model can not do:

1. *Distance against leverage.* A point's distance is its studentized residual
   t_i = √(r_iᵀ (I − H_ii)⁺ r_i) / σ̂, H the hat matrix of the weighted data Jacobian
   (H_ii its 3×3 block of point i, σ̂ the robust σ of :mod:`kpi_calib_ros.core.estimation.robust`):
   a point of leverage h pulls the fit towards itself and its residual has covariance
   σ²(I − H_ii), so ‖r_i‖/σ̂ understates how far it is. A point is *over* when
   t_i > threshold.
2. *Replicates decide.* Points measured at one pose (the same pose of
   :mod:`kpi_calib_ros.core.measurement.replicates`: the other reflectors, the pose measured again)
   are replicates of each other. A model misfit moves the tip as a rigid body, so a pose's
   residuals are r_k ≈ t + ω × (η_k − c) plus noise whatever the model lacks; a fault moves
   one point alone. The part of the pose's residuals no rigid motion explains, e = (I − P)
   r, is noise under a misfit: ‖e‖²/σ̂² ~ χ²(3m − rank P) for m points. A pose beyond the
   Bonferroni bound of that test (over the poses tested) is *inconsistent*; its over point
   whose removal restores the most consistency (ties: the farther) is a *fault*, one per
   pose and round (the others are judged again after the refit). An over point of a
   consistent pose is *misfit*: its replicates disagree with the model alike. Two points
   must be off by the same vector (r_a − r_b ~ noise, χ²(3)): a rotation would leave only
   their distance to test and absorb most two-point faults. Exception: the pose's only
   point over the threshold, `SET_APART` times as far as any other point of the pose, is
   a fault: its replicates agree with the model (three close reflectors let a rotation of
   the pose absorb much of a one-point fault along the normal of their plane).
3. *No replicates.* An over point with no other point at its pose is a fault unless its
   leverage along some direction, the largest eigenvalue h of H_ii, exceeds
   `HIGH_LEVERAGE` = ½: the fit then moves more than half way to the point, so removing
   it changes the fit there by h/(1 − h) > 1 times the residual left: the point carries
   what no other pose tells (the end of a sweep), and nothing but the model it disagrees
   with says it is wrong; it is a misfit candidate, kept.

4. *Too many lone faults.* Tracker faults are few; a model that lacks an effect misfits
   everywhere. When the faults of rule 3 alone (no replicate confirms them) would number
   more than ``max_fraction`` of the campaign, they are a misfit:
   :func:`kpi_calib_ros.core.estimation.robust.robust_identify` restores every point rule 3
   excluded, refits from the start and keeps them as misfit (a real UR10 with 0.4 mm of systematic
   error and one probe point a pose: 57 points excluded in the first round, more beyond
   the threshold in the second). ``max_fraction`` caps these alone: a fault of rule 2 has
   evidence a misfit can not produce (its pose's other points do not move with it as one
   rigid body, or they agree with the model while it stands apart), so faults that
   replicates confirm, and gross points, are excluded whatever their number (30 % of 2700
   points of three reflectors, ``bench/outlier_scale.py``). A point whose pose's other
   points were all excluded has no replicate left and counts as lone.

Misfit points are kept in the fit and reported ("model misfit at these poses, see
kpi-calib diagnose"), never excluded. Gross points (metres off, a wrong unit or target)
are excluded before any fit (:func:`kpi_calib_ros.core.estimation.robust.gross_outliers`).
The hat matrix is the fit's, with its prior (H_ii = F_i C_p F_iᵀ). Limitation: without
replicates a misfit at ordinary leverage looks like a fault and is excluded (one-reflector
sweeps of 8 poses per joint with a hidden cubic joint error, 1 of 8 seeds: the pose next to a sweep
end, 4.5 σ̂ against the bound 4.42, leverage 0.30, its residual along the sweep end's
(cosine 0.83), held-out rms 39.6 µm against 39.2 µm keeping it; a leverage bound of 0.3
has no meaning like ½'s and would shield faults at up to 2 of 60 random poses, largest
leverage 0.25-0.40; a rule on the residual of the nearest pose would shield faults beside
a misfit pose); a one-point fault that is a rotation of its pose about the
line through two other points, with those points also over the threshold, counts as
misfit; rotation rows of tracked bodies are judged by rule 3 only.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.stats

from kpi_calib_ros.core.measurement.data import Measurements, row_sigma, stated_sigma
from kpi_calib_ros.core.measurement.replicates import pose_groups
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import (
    noise_weights,
    row_torques,
    weighted_residuals,
    weighted_rows,
)

__all__ = [
    'HIGH_LEVERAGE', 'CONSISTENCY_ALPHA', 'RANK_TOLERANCE', 'SET_APART', 'LONE_FAULT',
    'Judgement', 'hat_blocks', 'studentized', 'rigid_inconsistency', 'judge',
]

HIGH_LEVERAGE = 0.5
CONSISTENCY_ALPHA = 0.01
RANK_TOLERANCE = 1e-9
# A point this many times farther from the fit than every other point of its pose stands
# apart from its replicates (a misfit moves them alike: 1-1.3× in the sweeps of
# test_outliers).
SET_APART = 2.0

FAULT, MISFIT = 'fault', 'misfit'
LONE_FAULT = 'fault: no other point at this pose, ordinary leverage'


@dataclass(frozen=True)
class Judgement:
    """The verdict on every point of one fit.

    distance_sigma : (N,) studentized distance t_i in σ̂; over : (N,) t_i > threshold;
    fault : (N,) over points to exclude (at most one per pose); misfit : (N,) over points
    to keep; pose : (N,) pose index of every point; leverage : (N,) largest eigenvalue
    of H_ii (0 for excluded points);
    inconsistency : (P,) ‖e‖²/σ̂² of every pose (NaN: no replicates); why : (N,) reason
    of each fault or misfit ('' otherwise); lone : (N,) faults by rule 3 alone (no
    replicate confirms them: many of them together are a misfit, see
    :func:`kpi_calib_ros.core.estimation.robust.robust_identify`).
    """

    distance_sigma: np.ndarray
    over: np.ndarray
    fault: np.ndarray
    misfit: np.ndarray
    pose: np.ndarray
    leverage: np.ndarray
    inconsistency: np.ndarray
    why: tuple[str, ...]
    lone: np.ndarray


def hat_blocks(model: MeasurementModel, data: Measurements, p: np.ndarray,
               estimated: tuple[str, ...], sigma: float | np.ndarray,
               point_weights: np.ndarray | None = None,
               covariance: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted residuals (N, 3) in σ units and hat-matrix blocks H_ii (N, 3, 3) at ``p``.

    The hat matrix is that of the data Jacobian F of the ``estimated`` parameters; robustness
    weights ω_i scale point i's rows by √ω_i, as in the fit. With ``covariance`` (k, k), the
    fit's covariance of the estimated parameters at the stated σ, H_ii = F_i C Fᵢᵀ: a prior
    in the fit lowers the leverage (C = (FᵀF + RᵀR)⁻¹), which F's own projection ignores
    (10 poses re-identified with a prior: leverage near 1 for every point, whose residuals
    of 0.3 to 2 σ then read as 4 σ̂ outliers, and "model misfit" on clean data).
    """
    q = np.atleast_2d(data.q)
    tau = row_torques(model, data)
    pred, jac = model.jacobian(np.asarray(p, float), q, tau, data.reflector, data.rotation,
                               data.covariates)
    n = len(q)
    # The rows weighed as the fit weighs them: each point's σ (its own or the cell's), and
    # whitened (W_i, 3×3) with joint-reading noise.
    row_w = noise_weights(model, p, data, sigma, tau, point_weights)
    r = weighted_residuals(np.atleast_2d(data.eta) - pred, row_w).reshape(n, 3)
    f = weighted_rows(jac, row_w, model.params.indices(list(estimated)))
    if covariance is not None:
        rows = f.reshape(n, 3, -1)
        return r, np.einsum('nak,kl,nbl->nab', rows, np.asarray(covariance, float), rows)
    norms = np.linalg.norm(f, axis=0)
    f = f[:, norms > 0] / norms[norms > 0]
    u = scipy.linalg.orth(f, rcond=RANK_TOLERANCE) if f.size else np.zeros((3 * n, 0))
    u = u.reshape(n, 3, -1)
    return r, np.einsum('nik,njk->nij', u, u)


def studentized(r: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """r_iᵀ (I − H_ii)⁺ r_i (N,) of weighted residuals r (N, 3) and hat blocks (N, 3, 3).

    pinv: a point of leverage 1 along a direction has no residual there.
    """
    inv = np.linalg.pinv(np.eye(3) - blocks, rcond=RANK_TOLERANCE, hermitian=True)
    return np.einsum('ni,nij,nj->n', r, inv, r)


def rigid_inconsistency(residuals: np.ndarray, points: np.ndarray) -> tuple[float, int]:
    """‖(I − P) r‖² and its degrees of freedom 3m − rank for one pose's points.

    The residuals (m, 3) of one pose's points (m, 3): P projects on the rigid motions t + ω ×
    (η_k − c); for two points on the translations t alone (see the module text, rule 2).
    """
    m = len(points)
    c = points - points.mean(axis=0)
    a = np.zeros((3 * m, 6 if m > 2 else 3))
    a[:, :3] = np.tile(np.eye(3), (m, 1))
    for k, (x, y, z) in enumerate(c if m > 2 else ()):
        a[3 * k:3 * k + 3, 3:] = [[0.0, z, -y], [-z, 0.0, x], [y, -x, 0.0]]  # ω × c = −[c]×ω
    u = scipy.linalg.orth(a, rcond=1e-6)
    r = np.asarray(residuals, float).ravel()
    e = r - u @ (u.T @ r)
    return float(e @ e), 3 * m - u.shape[1]


def judge(model: MeasurementModel, data: Measurements, p: np.ndarray,
          estimated: tuple[str, ...], sigma: float | np.ndarray, scale: float,
          threshold: float, kept: np.ndarray, pose: np.ndarray | None = None,
          point_weights: np.ndarray | None = None,
          covariance: np.ndarray | None = None) -> Judgement:
    """Fault or misfit for every point of ``data`` (N) against the fit ``p`` of the ``kept`` points.

    See the module text.

    Parameters
    ----------
    model : MeasurementModel
    data : Measurements
        All N points (excluded ones too: they are judged against the fit, not in it).
    p, estimated : (n_p,) ndarray, names
        The fit and its identified parameters.
    sigma : float or (3,) array
        Stated σ (m) the fit weighs with; ``scale`` : σ̂ (m, per axis).
    threshold : float
        Distance in σ̂ beyond which a point is over.
    kept : (N,) bool
        Points in the fit; only they can be faults or misfits.
    pose : (N,) int, optional
        Pose index of every point (default :func:`pose_groups` of ``data.q``).
    point_weights : (n_kept,) ndarray, optional
        Robustness weights of the kept points in the fit.
    covariance : (k, k) ndarray, optional
        The fit's covariance of ``estimated`` at the stated σ: the leverage with the fit's
        prior (:func:`hat_blocks`).
    """
    n = len(data)
    kept = np.asarray(kept, bool)
    pose = pose_groups(data.q) if pose is None else np.asarray(pose)
    stated = np.broadcast_to(np.asarray(sigma, float), (3,))
    # The σ whitened rows are multiplied by to compare with σ̂ (core.estimation.robust.noise_units):
    # the cell's, or the points' own.
    reference = stated_sigma(stated, data.sigma, n)
    # σ̂ below the stated σ is the noise of the estimate (a MAD of 30 residuals with 14
    # degrees of freedom came out at half the stated 20 µm and made points of 2.1 and
    # 2.6 σ "outliers beyond 4 σ̂" on clean data): a point is far by the larger of the two.
    scale = max(float(scale), float(np.max(reference)))
    ratio = reference / scale  # σ units -> σ̂ units
    t = np.zeros(n)
    lev = np.zeros(n)
    r_k, blocks = hat_blocks(model, data.subset(kept), p, estimated, sigma, point_weights,
                             covariance)
    t[kept] = np.sqrt(studentized(r_k, blocks)) * ratio
    lev[kept] = np.linalg.eigvalsh(blocks)[:, -1]
    # Excluded points: plain distance in σ̂ (no leverage: they are not in the fit).
    rest = ~kept
    if rest.any():
        out = data.subset(rest)
        pred = model.predict(p, np.atleast_2d(out.q), out.tau, out.reflector, out.rotation,
                             out.covariates)
        miss = np.atleast_2d(out.eta) - pred
        if model.joint_sigma is not None or out.sigma is not None:
            # In the stated σ's units, as the fit's σ̂ (core.estimation.robust.noise_units).
            white = noise_weights(model, p, out, stated)
            miss = weighted_residuals(miss, white).reshape(-1, 3) * reference
        t[rest] = np.linalg.norm(miss, axis=1) / scale
    over = kept & (t > threshold)
    # Residuals in σ̂ units of every kept point (unweighted by ω: consistency is geometry).
    resid = np.zeros((n, 3))
    kq = data.subset(kept)
    miss_k = np.atleast_2d(kq.eta) - model.predict(
        p, np.atleast_2d(kq.q), kq.tau, kq.reflector, kq.rotation, kq.covariates)
    if kq.sigma is not None:
        # Each point in units of its own σ, at the stated σ as σ̂
        # (core.estimation.robust.noise_units).
        miss_k = weighted_residuals(miss_k, 1.0 / row_sigma(stated, kq.sigma, len(miss_k))
                                    ).reshape(-1, 3) * reference
    resid[kept] = miss_k / scale
    is_point = np.ones(n, bool) if data.reflector is None else \
        np.asarray(data.reflector) < model.n_reflectors
    eta = np.atleast_2d(data.eta)
    n_poses = int(pose.max()) + 1 if n else 0
    inconsistency = np.full(n_poses, np.nan)
    fault = np.zeros(n, bool)
    misfit = np.zeros(n, bool)
    why = [''] * n
    high = lev > HIGH_LEVERAGE
    members = {int(g): np.flatnonzero((pose == g) & kept & is_point)
               for g in np.unique(pose[over])}
    tests = {g: rigid_inconsistency(resid[rows], eta[rows])
             for g, rows in members.items() if len(rows) >= 2}
    for g, (total, _) in tests.items():
        inconsistency[g] = total

    def bound(dof: int) -> float:
        return float(scipy.stats.chi2.isf(CONSISTENCY_ALPHA / len(tests), dof))
    for g, rows in members.items():
        candidates = [int(i) for i in np.flatnonzero((pose == g) & over)]
        for i in (i for i in candidates if not is_point[i]):  # rotation rows: rule 3
            _single(i, high, fault, misfit, why)
        candidates = [i for i in candidates if is_point[i]]
        if not candidates:
            continue
        if g not in tests:
            for i in candidates:
                _single(i, high, fault, misfit, why)
            continue
        total, dof = tests[g]
        consistent = total <= bound(dof)
        others = np.setdiff1d(rows, candidates)
        if consistent and len(candidates) == 1 and len(others) and \
                t[candidates[0]] > SET_APART * float(np.max(t[others])):
            # One point off while its replicates agree with the model: a rigid motion
            # may absorb it (three close reflectors), the replicates do not.
            fault[candidates[0]] = True
            why[candidates[0]] = (f'fault: the other {len(others)} point(s) of its pose '
                                  'agree with the model')
        elif consistent:
            for i in candidates:
                misfit[i] = True
                why[i] = (f'model misfit: the {len(rows)} points of this pose are off '
                          'alike; see kpi-calib diagnose')
        else:
            # The point whose removal restores the most consistency (two points: the
            # farther); the pose's other over points are judged again after the refit.
            drop = [total - rigid_inconsistency(resid[rows[rows != i]],
                                                eta[rows[rows != i]])[0]
                    if len(rows) > 2 else total for i in candidates]
            best = candidates[int(np.lexsort((t[candidates], np.round(drop, 6)))[-1])]
            fault[best] = True
            why[best] = (f'fault: disagrees with the other {len(rows) - 1} point(s) of its '
                         f'pose ({total:.1f} > {bound(dof):.1f} for χ²({dof}))')
    lone = fault & np.array([w.startswith(LONE_FAULT) for w in why], bool)
    return Judgement(t, over, fault, misfit, pose, lev, inconsistency, tuple(why), lone)


def _single(i: int, high: np.ndarray, fault: np.ndarray, misfit: np.ndarray,
            why: list[str]) -> None:
    """Rule 3: an over point with no replicate."""
    if high[i]:
        misfit[i] = True
        why[i] = ('model misfit candidate: high leverage and no other point at this pose '
                  'to tell a fault; see kpi-calib diagnose')
    else:
        fault[i] = True
        why[i] = LONE_FAULT

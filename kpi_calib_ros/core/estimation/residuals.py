"""Residuals of a calibration: goodness of fit, leverage, outliers, validation rms.

Everything is computed on the weighted, locally linear problem at the
identified parameters: the residual r = Σ⁻¹(η − h(p̂, q)) and the Jacobian of
the identified parameters. The χ² test compares Σ‖r_i/σ‖² with χ²(dof); the
hat matrix H = U Uᵀ (U an orthonormal basis of the Jacobian's columns) gives
each pose's leverage and the covariance I − H_ii of its residual; cross-validation
(leave one pose out by default, or k-fold) refits on the other poses and predicts the
held-out ones (exact for the linear model, which a converged fit is to far below σ),
with folds that keep every identified parameter determined. Region-blocked folds
(:func:`region_folds`) hold out whole clusters of poses in joint space: the error where
no pose was measured. A fit with a prior keeps it in every fold's refit
(:func:`prior_system`): the prior's rows are training rows of every fold.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Mapping

import numpy as np
import scipy.stats

from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.prior import Prior
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
    row_torques,
    unweighted,
    weighted_residuals,
    weighted_rows,
)

__all__ = [
    'PERCENTILES', 'ADEQUACY_ALPHA', 'ResidualReport', 'LinearizedFit', 'is_adequate',
    'SIGMA_OVERSTATED', 'SIGMA_CONSISTENT', 'SIGMA_NOT_TESTED', 'noise_verdict',
    'sigma_overstated_text', 'linearized_fit', 'orthonormal_basis', 'fold_ids', 'campaign_home',
    'moved_joints', 'stratified_fold_ids', 'RANK_TOLERANCE', 'LEAVE_ONE_OUT', 'folds_keep_rank',
    'identifiable_folds', 'pose_index', 'linear_validation_rms', 'residual_report',
    'validation_rms', 'REGION_BLOCKS', 'region_fold_ids', 'region_folds', 'prior_system',
    'RegionValidation', 'region_validation', 'validation_folds', 'RANGE_END',
    'range_end_folds', 'fold_rms',
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
        sqrt(mean ‖r_i‖²) and max ‖r_i‖, m.
    percentiles_m : dict
        {50, 90, 95, 99} -> percentile of ‖r_i‖, m.
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


def fold_ids(n_poses: int, folds: int, seed: int) -> np.ndarray:
    """Random fold of each pose, (n_poses,) ints in [0, folds), sizes within one."""
    if folds == LEAVE_ONE_OUT:
        return np.arange(n_poses)
    if not 2 <= folds <= n_poses:
        raise ValueError(f'folds must be in [2, {n_poses}] (number of poses), got {folds}')
    ids = np.empty(n_poses, dtype=int)
    ids[np.random.default_rng(seed).permutation(n_poses)] = np.arange(n_poses) % folds
    return ids


def campaign_home(q: np.ndarray, atol: float = 1e-6) -> np.ndarray:
    """(n,) the campaign's home configuration.

    The most frequent value of each joint (to ``atol``).
    """
    q = np.atleast_2d(np.asarray(q, float))
    home = np.empty(q.shape[1])
    for j in range(q.shape[1]):
        values, counts = np.unique(np.round(q[:, j] / atol), return_counts=True)
        home[j] = values[np.argmax(counts)] * atol
    return home


def moved_joints(q: np.ndarray, atol: float = 1e-6) -> np.ndarray:
    """(N, n) bool: which joints of each pose differ from the campaign's home value.

    The home value is that of :func:`campaign_home`. One-joint-at-a-time campaigns (the circle
    point method) give rows with a single True.
    """
    q = np.atleast_2d(np.asarray(q, float))
    return np.abs(q - campaign_home(q, atol)) > atol


def stratified_fold_ids(q: np.ndarray, folds: int, seed: int) -> np.ndarray:
    """Folds stratified by the joints moved.

    Each group of poses that move the same joints is dealt round the folds, so every fold holds
    out a share of every group and every training set keeps poses of every group.
    """
    q = np.atleast_2d(q)
    n = len(q)
    if folds == LEAVE_ONE_OUT:
        return np.arange(n)
    if not 2 <= folds <= n:
        raise ValueError(f'folds must be in [2, {n}] (number of poses), got {folds}')
    rng = np.random.default_rng(seed)
    _, group = np.unique(moved_joints(q), axis=0, return_inverse=True)
    ids = np.empty(n, dtype=int)
    next_fold = 0
    for g in rng.permutation(group.max() + 1):
        members = rng.permutation(np.flatnonzero(group.ravel() == g))
        ids[members] = (next_fold + np.arange(len(members))) % folds
        next_fold = (next_fold + len(members)) % folds
    return ids


# A fold whose training poses leave a direction of the identified parameters with less
# than this fraction of its full-data information cannot refit it (I − H_FF singular).
RANK_TOLERANCE = 1e-9
LEAVE_ONE_OUT = 0  # ``folds`` value: every pose its own fold (exact, the default)


def _fold_blocks(a: np.ndarray, pose_folds: np.ndarray, u: np.ndarray | None = None
                 ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(rows, I − H_FF) of each fold F, H = U Uᵀ the hat matrix of span(a).

    Rows of ``a`` after the 3N of the measurements (a prior's) are in every training set.
    """
    u = orthonormal_basis(a) if u is None else u
    rows = np.concatenate([np.repeat(pose_folds, 3),
                           np.full(a.shape[0] - 3 * len(pose_folds), -1)])
    for k in np.unique(pose_folds):
        test = rows == k  # never a prior row (-1)
        uf = u[test]
        yield test, np.eye(int(test.sum())) - uf @ uf.T


def folds_keep_rank(a: np.ndarray, pose_folds: np.ndarray) -> bool:
    """Return True when every fold's training rows determine every column of ``a`` (3N, k).

    The training rows are the other folds' poses: I − H_FF is nonsingular for every fold F.
    """
    return all(np.linalg.eigvalsh(m)[0] > RANK_TOLERANCE for _, m in _fold_blocks(a, pose_folds))


def identifiable_folds(a: np.ndarray, q: np.ndarray, folds: int,
                       seed: int) -> np.ndarray | None:
    """Folds over poses that keep every identified parameter determined in each fold.

    ``folds`` 0 (or >= N): leave one pose out. Otherwise random folds first; when one of
    them leaves a parameter without excitation (a fold that holds out the poses moving
    one joint), folds stratified by the joints moved. ``None`` when no such folds exist:
    the design cannot estimate an out-of-sample error by refitting without some of its
    poses ("not estimable from this design").

    Parameters
    ----------
    a : (3N, k) ndarray
        Weighted Jacobian of the identified parameters, three rows per measurement.
    q : (N, n) ndarray
        Joint values of the measurements (rad): rows with equal values are one pose.
    """
    # Rows measured at the same joint values (several reflectors, or repeated shots) are
    # one pose and stay in one fold: held-out poses, not held-out points.
    poses, pose = pose_index(q)
    n = len(poses)
    if folds == LEAVE_ONE_OUT or folds >= n:
        ids = pose
        return ids if folds_keep_rank(a, ids) else None
    for ids in (fold_ids(n, folds, seed)[pose], stratified_fold_ids(poses, folds, seed)[pose]):
        if folds_keep_rank(a, ids):
            return ids
    return None


def pose_index(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the distinct poses of ``q`` (N, n) in order of first appearance.

    Also each row's pose index (N,).
    """
    q = np.atleast_2d(q)
    _, first, inverse = np.unique(q, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # unique sorts; renumber by first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return q[np.sort(first)], rank[np.asarray(inverse).reshape(-1)]


def linear_validation_rms(a: np.ndarray, r: np.ndarray, w: np.ndarray,
                          pose_folds: np.ndarray | None,
                          prior_rows: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """Cross-validated rms (m) of the linear model r ≈ a·δ, folds over poses.

    ``prior_rows`` (L (m, k), its residual (m,), :func:`prior_system`): a prior the fit
    used, kept in every fold's refit (without it a fold refits a weaker, unregularised
    model and the figure can fall below the fit's own rms).

    Each fold's held-out residual is exactly that of the refit without it,
    (I − H_FF)⁻¹ e_F with e = (I − H) r the full-data residual (the PRESS identity; H
    the hat matrix of ``a``). NaN ("not
    estimable from this design") when ``pose_folds`` is None or a fold's training poses
    leave a column of ``a`` undetermined: a minimum-norm refit would then predict the
    held-out poses with a parameter the fold cannot see.
    """
    if pose_folds is None:
        return float('nan')
    n_rows = len(r)
    if prior_rows is not None and len(prior_rows[1]):
        a = np.vstack([a, prior_rows[0]])
        r = np.concatenate([r, prior_rows[1]])
    u = orthonormal_basis(a)
    r = r - u @ (u.T @ r)  # the full-data fit of r ≈ a·δ (r need not be converged on a)
    held = np.empty_like(r)
    for test, m in _fold_blocks(a, pose_folds, u):
        if np.linalg.eigvalsh(m)[0] <= RANK_TOLERANCE:
            return float('nan')
        held[test] = np.linalg.solve(m, r[test])
    metres = unweighted(held[:n_rows], w)
    return float(np.sqrt(np.mean(np.sum(metres ** 2, axis=1))))


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
    return ResidualReport(
        residuals=residuals, norms=norms,
        rms_m=float(np.sqrt(np.mean(norms ** 2))), max_m=float(norms.max()),
        percentiles_m={p: float(np.percentile(norms, p)) for p in PERCENTILES},
        chi2=chi2, dof=dof, p_value=p_value, adequate=is_adequate(p_value, alpha),
        leverage=leverage, standardized=standardized, outlier=outlier,
        high_leverage=leverage > 3 * k / n, alpha=alpha, sigma_robust_m=sigma_hat,
        sigma_warning=warning, sigma_stated_m=stated)


def validation_rms(model: MeasurementModel, data: Measurements,
                   result: CalibrationResult, folds: int = LEAVE_ONE_OUT,
                   seed: int = 0, prior: Prior | None = None) -> float:
    """Cross-validated rms (m) of the identified model over held-out poses.

    Each fold refits the identified parameters on the other poses (exact for the
    locally linear model, which a converged fit is to far below σ) and predicts the
    held-out ones. ``folds`` 0 (default) leaves one pose out at a time: the refits then
    differ least from the fit being judged, where k-fold refits on (k−1)/k of a small
    design would judge a weaker model. Compare with the noise floor σ√3. The folds keep
    every identified parameter determined (:func:`identifiable_folds`); NaN when no
    such folds exist ("not estimable from this design"). ``prior``: the prior the fit
    used (with a tolerance prior, the balanced one), kept in every fold's refit.
    """
    if folds != LEAVE_ONE_OUT and not 2 <= folds <= len(data):
        raise ValueError(f'folds must be 0 (leave one pose out) or in [2, {len(data)}] '
                         f'(number of poses), got {folds}')
    sys_ = linearized_fit(model, data, result)
    rows = prior_system(model, result, prior)
    a = np.vstack([sys_.jac, rows[0]])
    return linear_validation_rms(sys_.jac, sys_.r, sys_.w,
                                 identifiable_folds(a, np.atleast_2d(data.q), folds, seed),
                                 rows)


def prior_system(model: MeasurementModel, result: CalibrationResult, prior: Prior | None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Return the prior's rows in the identified parameters of ``result``: L (m, k), lm − L p̂.

    Whitened as the data rows are (LᵀL = C⁻¹), so they stack below the weighted Jacobian
    of :func:`linearized_fit`; rows on no identified parameter are left out. (0, k) and
    (0,) without a prior.
    """
    k = len(result.estimated)
    if prior is None:
        return np.zeros((0, k)), np.zeros(0)
    full, lm = prior.rows(model.params)
    rows = full[:, model.params.indices(list(result.estimated))]
    keep = np.any(rows != 0, axis=1)
    return rows[keep], (lm - full @ np.asarray(result.values, float))[keep]


# Region blocks of joint space a region-blocked cross-validation holds out in turn.
REGION_BLOCKS = 5
_KMEANS_ROUNDS = 50


def region_fold_ids(q: np.ndarray, blocks: int = REGION_BLOCKS, seed: int = 0) -> np.ndarray:
    """Region of each pose, (n_poses,) ints in [0, blocks): k-means in normalised joint space.

    ``q`` (n_poses, n) are distinct poses (rad, m). Each joint is scaled to [0, 1] over its
    measured range (a joint that does not move is left out), the seeded k-means++ start is
    refined by Lloyd's iterations. A fold is then a region of joint space held out whole:
    its prediction is the model's error where no pose was measured.
    """
    q = np.atleast_2d(np.asarray(q, float))
    n = len(q)
    if not 2 <= blocks <= n:
        raise ValueError(f'blocks must be in [2, {n}] (number of poses), got {blocks}')
    span = np.ptp(q, axis=0)
    x = (q[:, span > 0] - q[:, span > 0].min(axis=0)) / span[span > 0]
    rng = np.random.default_rng(seed)
    centres = [x[rng.integers(n)]]
    for _ in range(1, blocks):
        d2 = np.min([np.sum((x - c) ** 2, axis=1) for c in centres], axis=0)
        total = float(d2.sum())
        centres.append(x[rng.choice(n, p=d2 / total)] if total > 0 else x[rng.integers(n)])
    c = np.array(centres)
    label = np.zeros(n, int)
    for _ in range(_KMEANS_ROUNDS):
        label = np.argmin(((x[:, None, :] - c[None]) ** 2).sum(axis=2), axis=1)
        new = np.array([x[label == b].mean(axis=0) if np.any(label == b) else c[b]
                        for b in range(blocks)])
        if np.allclose(new, c):
            break
        c = new
    _, label = np.unique(label, return_inverse=True)  # empty clusters dropped
    return np.asarray(label).reshape(-1)


def region_folds(a: np.ndarray, q: np.ndarray, blocks: int = REGION_BLOCKS, seed: int = 0
                 ) -> tuple[np.ndarray, int] | None:
    """Region-blocked folds over the rows of ``q`` (N, n) that keep the rank of ``a``.

    ``a`` (3N (+ prior rows), k): the weighted Jacobian of the identified parameters.
    :func:`region_fold_ids` with ``blocks`` regions first; when a region's training poses
    leave an identified parameter undetermined (one region holds every pose that moves a
    joint), more and smaller regions (twice as many each time). Returns the pose folds and
    the number of regions, or None when not even one pose per region keeps the rank.
    """
    poses, pose = pose_index(q)
    n = len(poses)
    b = blocks
    while 2 <= b < n:
        ids = region_fold_ids(poses, b, seed)[pose]
        if folds_keep_rank(a, ids):
            return ids, int(ids.max()) + 1
        b *= 2
    return (pose, n) if n >= 2 and folds_keep_rank(a, pose) else None


def validation_folds(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                     prior: Prior | None = None, folds: int = LEAVE_ONE_OUT,
                     blocks: int = REGION_BLOCKS, seed: int = 0,
                     fit: LinearizedFit | None = None
                     ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Return the in-region and region-blocked pose folds (N,) of ``result``.

    :func:`identifiable_folds` and :func:`region_folds`, each None when no folds keep its
    rank. Those of a model keep the rank of every model it nests: judge them on the same
    folds.
    """
    sys_ = fit or linearized_fit(model, data, result)
    a = np.vstack([sys_.jac, prior_system(model, result, prior)[0]])
    q = np.atleast_2d(data.q)
    found = region_folds(a, q, blocks, seed)
    return identifiable_folds(a, q, folds, seed), None if found is None else found[0]


# Fraction of each joint's measured range a range-end fold holds out (its lowest and its
# highest fifth): the poses beyond the rest's range of that joint, which an effect of the
# joint (a periodic error, a scale, a bending) must predict by extrapolation.
RANGE_END = 0.2


def range_end_folds(q: np.ndarray, fraction: float = RANGE_END) -> list[np.ndarray]:
    """Pose masks (N,) bool of the range-end folds of ``q`` (N, n) (rad, m).

    For every joint that moves, the poses in the lowest ``fraction`` of its measured range
    and those in the highest; each is held out in turn. Unlike the k-means regions, which
    lie inside the measured ranges, these ask every joint's effect to extrapolate.
    """
    if not 0 < fraction < 0.5:
        raise ValueError(f'fraction must be in (0, 0.5), got {fraction}')
    q = np.atleast_2d(np.asarray(q, float))
    masks = []
    for j in range(q.shape[1]):
        lo, hi = float(q[:, j].min()), float(q[:, j].max())
        if hi - lo <= 0:
            continue
        for mask in (q[:, j] <= lo + fraction * (hi - lo), q[:, j] >= hi - fraction * (hi - lo)):
            if 0 < mask.sum() < len(q):
                masks.append(mask)
    return masks


def fold_rms(a: np.ndarray, r: np.ndarray, w: np.ndarray, masks: list[np.ndarray],
             prior_rows: tuple[np.ndarray, np.ndarray] | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Held-out rms (m) of each fold of the linear model r ≈ a·δ, and its noise, (len(masks),).

    ``masks``: held-out measurements (N,) bool per fold (folds may overlap). Each rms is
    that of the refit without the fold (the PRESS identity, as
    :func:`linear_validation_rms`, ``prior_rows`` kept); NaN for a fold whose training rows
    leave a column of ``a`` undetermined. The noise: the standard deviation the stated
    noise alone gives the rms of the fold's n points, σ_p/√(6n) with σ_p² the mean of the
    points' total variance (σ/√(2n) per axis σ; an rms of 3-D noise over n points).
    """
    if prior_rows is not None and len(prior_rows[1]):
        a = np.vstack([a, prior_rows[0]])
        r = np.concatenate([r, prior_rows[1]])
    u = orthonormal_basis(a)
    e = r - u @ (u.T @ r)
    w = np.asarray(w, float)
    if not masks:
        return np.zeros(0), np.zeros(0)
    if w.ndim == 3:  # whitening matrices W: the point's covariance (WᵀW)⁻¹
        variance = np.trace(np.linalg.inv(np.einsum('nba,nbc->nac', w, w)), axis1=1, axis2=2)
    else:
        variance = np.sum(unweighted(np.ones(3 * len(masks[0])), w) ** 2, axis=1)
    out, noise = np.full(len(masks), np.nan), np.full(len(masks), np.nan)
    for i, mask in enumerate(masks):
        noise[i] = float(np.sqrt(np.mean(variance[mask]) / (6 * mask.sum())))
        test = np.concatenate([np.repeat(mask, 3), np.zeros(len(r) - 3 * len(mask), bool)])
        uf = u[test]
        m = np.eye(int(test.sum())) - uf @ uf.T
        if np.linalg.eigvalsh(m)[0] <= RANK_TOLERANCE:
            continue
        metres = unweighted(np.linalg.solve(m, e[test]), w if w.ndim == 1 else w[mask])
        out[i] = float(np.sqrt(np.mean(np.sum(metres ** 2, axis=1))))
    return out, noise


@dataclass(frozen=True)
class RegionValidation:
    """Cross-validated rms of a calibration where it was measured and in other regions.

    ``in_region_m``: folds drawn like the measured poses (``folds``, 0 leave one pose out);
    ``other_region_m``: region-blocked folds (``blocks`` regions of joint space held out
    whole, :func:`region_folds`); NaN when not estimable from this design. Both refit
    with the fit's prior (m).
    """

    in_region_m: float
    other_region_m: float
    folds: int
    blocks: int
    # Held-out rms (m) of every fold that asks for a prediction away from the training
    # poses: each region block, then each range-end fold (:func:`range_end_folds`); NaN
    # where a fold leaves a parameter undetermined. Two models judged on the same folds
    # pair figure by figure; and what the stated noise alone spreads each by (m, fold_rms).
    held_out_folds_m: tuple[float, ...] = ()
    held_out_noise_m: tuple[float, ...] = ()

    def to_dict(self) -> dict:
        """YAML-ready figures (m; None where not estimable)."""
        def m(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None
        return {'in_region_rms_m': m(self.in_region_m),
                'other_region_rms_m': m(self.other_region_m),
                'folds': self.folds, 'region_blocks': self.blocks,
                'held_out_fold_rms_m': [m(v) for v in self.held_out_folds_m],
                'held_out_fold_noise_m': [m(v) for v in self.held_out_noise_m]}


def region_validation(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                      prior: Prior | None = None, folds: int = LEAVE_ONE_OUT,
                      blocks: int = REGION_BLOCKS, seed: int = 0,
                      pose_folds: tuple[np.ndarray | None, np.ndarray | None] | None = None
                      ) -> RegionValidation:
    """In-region and other-region cross-validated rms of ``result`` (linear refits, prior kept).

    ``pose_folds`` (in-region, region-blocked ids, each (N,) or None): given folds, so that
    two models are judged on the same ones (those of the larger model keep the rank of
    every model it nests); default: chosen here for this model.
    """
    sys_ = linearized_fit(model, data, result)
    rows = prior_system(model, result, prior)
    if pose_folds is None:
        pose_folds = validation_folds(model, data, result, prior, folds, blocks, seed, sys_)
    inside, region_ids = pose_folds
    used = 0 if region_ids is None else int(region_ids.max()) + 1
    poses, pose = pose_index(np.atleast_2d(data.q))
    masks = ([] if region_ids is None else [region_ids == b for b in range(used)]) + [
        m[pose] for m in range_end_folds(poses)]
    held, noise = fold_rms(sys_.jac, sys_.r, sys_.w, masks, rows)
    return RegionValidation(
        linear_validation_rms(sys_.jac, sys_.r, sys_.w, inside, rows),
        linear_validation_rms(sys_.jac, sys_.r, sys_.w, region_ids, rows), folds, used,
        tuple(float(v) for v in held), tuple(float(v) for v in noise))

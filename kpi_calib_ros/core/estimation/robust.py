"""Robust statistics of an identification: σ from the residuals, outliers, robust losses.

*Robust scale.* σ̂ = 1.4826 · MAD of the 3N per-axis residuals · √(3N / dof): the MAD of a
normal sample times 1.4826 estimates its σ whatever a few wild points do, and the factor
√(3N/dof) undoes the shrinking of residuals by the fit (a fit of k parameters leaves
dof = 3N − k degrees of freedom in 3N residuals). It is reported beside the stated σ and a
ratio beyond 2× either way is a warning: the stated σ, not σ̂, sets the covariance.

*Joint-reading noise.* With ``noise.joint_sigma`` stated a point's noise is σ²I + J_q Σ_q J_qᵀ,
larger where the joints' lever is long: σ̂ and the distances reported then take each
residual whitened (W_i r_i,
:meth:`~kpi_calib_ros.core.measurement.tracker.MeasurementModel.whitening`) times the stated σ, a
residual whose noise is the stated σ on every axis at every pose, and the studentized distances
below come from the whitened rows. With per-point σ (the tracker's own) the stated σ is that
of the points (their rms, :func:`~kpi_calib_ros.core.measurement.data.stated_sigma`), not
the cell's ``noise.sigma``.

*Outliers.* A measurement is over the threshold when its studentized distance
t_i = √(r_iᵀ (I − H_ii)⁺ r_i) / σ̂ exceeds ``threshold``. The default threshold is the
Bonferroni bound √χ²₃(1 − α/N), α = 0.01: a clean campaign loses a point in 1 % of
campaigns. A point over it is excluded only when it is a *fault*, not a *misfit* of the
model: the rule (replicates of the pose, a rigid motion of the pose, leverage) and its
reasoning are in :mod:`kpi_calib_ros.core.estimation.outliers`; misfit points are kept and named
("model misfit at these poses, see kpi-calib diagnose"). Faults are excluded in batches
and the fit repeated: each round the faults within half the farthest one's distance
(at least the threshold), so one gross point cannot drag good ones over the threshold
(swamping) and a campaign with hundreds of faults needs a few rounds, not hundreds; at
most one point per pose and round. A point farther than `GROSS_DISTANCE` from the nominal
prediction (a wrong unit, another target) is excluded before the first fit. Excluded
points are listed, never dropped silently.

*Robust losses* (``loss``, iteratively reweighted least squares in the Gauss-Newton of
:func:`~kpi_calib_ros.core.estimation.least_squares.identify`): with u_i = ‖r_i‖ / (c σ̂), σ̂
re-estimated each iteration and c = `LOSS_SCALE` (√χ²₃(0.95) = 2.80, so 95 % of good points are in
the quadratic zone), the weight of measurement i is ``huber``: min(1, 1/u_i); ``soft_l1``
(SciPy's ρ(z) = 2(√(1+z) − 1), z = u²): 1/√(1 + u_i²). The covariance is that of the last
weighted problem (the usual IRLS approximation).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np
import scipy.stats

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.least_squares import MAX_START_ERROR, CalibrationResult
from kpi_calib_ros.core.estimation.outliers import judge
from kpi_calib_ros.core.measurement.data import Measurements, stated_sigma
from kpi_calib_ros.core.measurement.replicates import pose_groups
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import noise_weights, weighted_residuals

__all__ = [
    'LOSSES', 'LOSS_SCALE', 'MAD_TO_SIGMA', 'OUTLIER_ALPHA', 'GROSS_DISTANCE', 'MISFIT_GAP',
    'SIGMA_RATIO_WARNING', 'IRLS_ITERATIONS', 'OutlierSettings', 'ExcludedMeasurement',
    'RobustResult', 'robust_sigma', 'outlier_threshold', 'loss_weights',
    'robust_identify', 'misfit_warning', 'gross_outliers', 'misfit_reach', 'sigma_warning',
    'noise_units', 'POINT_SIGMA', 'stated_source',
]

LOSSES = ('linear', 'huber', 'soft_l1')
LOSS_SCALE = float(np.sqrt(scipy.stats.chi2.ppf(0.95, 3)))
MAD_TO_SIGMA = 1.4826
OUTLIER_ALPHA = 0.01
# Farther than this from the nominal prediction a point is not a measurement of the robot
# (a nominal model misses by millimetres; see estimation.MAX_START_ERROR).
GROSS_DISTANCE = MAX_START_ERROR
# When more points are lone "faults" than faults happen they are taken as the model's misfit
# and restored, but not those beyond a gap of this ratio in distance (:func:`misfit_reach`).
MISFIT_GAP = 2.0
SIGMA_RATIO_WARNING = 2.0
IRLS_ITERATIONS = 20


@dataclass(frozen=True)
class OutlierSettings:
    """``identification.outliers`` of a cell file.

    exclude : exclude outliers and refit (else only report them);
    threshold : distance in units of σ̂ above which a point is an outlier (None: Bonferroni);
    max_fraction : at most this fraction of the measurements is excluded as lone faults
    (no other point at the pose to confirm them, rule 3 of
    :mod:`kpi_calib_ros.core.estimation.outliers`); beyond it they are kept as model misfit. Faults
    the other points of their pose confirm (rule 2) and gross points are excluded whatever their
    number.
    """

    exclude: bool = True
    threshold: float | None = None
    max_fraction: float = 0.05


@dataclass(frozen=True)
class ExcludedMeasurement:
    """One measurement left out of the fit: its index, stamp and distance to the fit (m)."""

    index: int
    stamp_ns: int | None
    distance_m: float
    distance_sigma: float
    reason: str

    def text(self) -> str:
        """Return the one line the log and the summary print.

        ``distance_sigma`` is the number calibration.yaml stores (distance from the final fit
        over its σ̂), so a point reads the same in both.
        """
        return (f'measurement {self.index} (stamp {self.stamp_ns} ns) excluded: '
                f'{self.distance_m * 1e6:.1f} µm from the final fit, distance_sigma '
                f'{self.distance_sigma:.2f} σ̂; {self.reason}')


@dataclass(frozen=True)
class RobustResult:
    """An identification with robust statistics.

    result : the final fit (on the kept measurements, with the loss's weights);
    kept : (N,) bool, measurements used; excluded : the others, in order of exclusion;
    outliers : indices over the threshold (excluded or, with exclude false, only reported);
    misfit : indices over the threshold kept as model misfit (core.estimation.outliers), not faults;
    sigma_robust : σ̂ (m, per axis) from the final residuals; sigma_stated : mean stated σ;
    threshold : outlier threshold in σ̂; loss : the loss used; warnings : texts for the user.
    """

    result: CalibrationResult
    kept: np.ndarray
    excluded: tuple[ExcludedMeasurement, ...]
    outliers: tuple[int, ...]
    sigma_robust: float
    sigma_stated: float
    threshold: float
    loss: str
    point_weights: np.ndarray | None
    warnings: tuple[str, ...] = field(default=())
    misfit: tuple[int, ...] = field(default=())

    @property
    def sigma_ratio(self) -> float:
        """σ̂ / stated σ."""
        return self.sigma_robust / self.sigma_stated


def robust_sigma(residuals: np.ndarray, dof: int) -> float:
    """σ̂ (m) per axis from residuals (N, 3): 1.4826 · MAD · √(3N / dof)."""
    r = np.asarray(residuals, float).ravel()
    if dof <= 0 or r.size == 0:
        return float('nan')
    mad = float(np.median(np.abs(r - np.median(r))))
    return MAD_TO_SIGMA * mad * float(np.sqrt(r.size / dof))


def outlier_threshold(n: int, alpha: float = OUTLIER_ALPHA) -> float:
    """Bonferroni bound on ‖r_i‖/σ: √χ²₃(1 − α/n)."""
    return float(np.sqrt(scipy.stats.chi2.isf(alpha / max(n, 1), 3)))


def loss_weights(loss: str, distances: np.ndarray, scale: float) -> np.ndarray:
    """IRLS weights ω_i (N,) of distances ‖r_i‖ (m) at scale c·σ̂ (see the module text)."""
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    u = np.asarray(distances, float) / (LOSS_SCALE * scale)
    if loss == 'huber':
        return np.minimum(1.0, 1.0 / np.maximum(u, 1e-300))
    if loss == 'soft_l1':
        return 1.0 / np.sqrt(1.0 + u ** 2)
    return np.ones_like(u)


Fit = Callable[..., CalibrationResult]


def robust_identify(model: MeasurementModel, data: Measurements, sigma: float | np.ndarray,
                    fit: Fit, loss: str = 'linear',
                    outliers: OutlierSettings = OutlierSettings(),
                    start: np.ndarray | None = None,
                    progress: Callable[[str], None] | None = None) -> RobustResult:
    """Identify with outlier exclusion and a robust loss.

    Parameters
    ----------
    model : MeasurementModel
    data : Measurements
        All measurements (N).
    sigma : float or (3,) array
        Stated tracker σ, m.
    fit : callable
        ``fit(data, p0=..., point_weights=...) -> CalibrationResult``: the plain
        identification (e.g. :func:`~kpi_calib_ros.core.estimation.least_squares.identify` with the
        cell's settings bound), called on the kept measurements.
    loss : {'linear', 'huber', 'soft_l1'}
    outliers : OutlierSettings
    start : (n_p,) ndarray, optional
        Parameters the gross-outlier test predicts with (default: the nominal ones);
        e.g. the registered placement.
    progress : callable, optional
        Called with one line of text after every exclusion round.

    Raises
    ------
    DataError
        When the kept measurements are too few for the fit (it names the excluded ones).
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    n = len(data)
    q, eta = np.atleast_2d(data.q), np.atleast_2d(data.eta)
    stamps = data.stamps_ns
    kept = np.ones(n, bool)
    excluded: list[ExcludedMeasurement] = []
    threshold = outliers.threshold or outlier_threshold(n)
    if outliers.exclude:
        gross, nominal = gross_outliers(model, data, start)
        for i in np.flatnonzero(gross):
            excluded.append(_excluded(int(i), stamps, nominal[i], float('inf'),
                                      'gross: farther than '
                                      f'{GROSS_DISTANCE:g} m from the nominal prediction'))
        kept &= ~gross
    max_lone = int(np.floor(outliers.max_fraction * n))
    pose = pose_groups(q)
    rounds = 0
    lone_misfit = False
    reach = np.inf  # taken as misfit, the distance beyond which a lone point is a fault
    lone_excluded: set[int] = set()
    # Every round fits from the fit's own start, not from the round before: a fit the faults
    # distorted (a 50 mm point moved a wrist placement 0.93 m along a direction the other
    # points hardly see) kept that move in a refit started there.
    while True:
        try:
            result, omega = _fit_with_loss(fit, data.subset(kept), loss, model, sigma)
        except DataError as exc:
            if not excluded:
                raise
            # 'too few measurements: 9 points' of 10 accepted: say which were left out.
            raise DataError(f'{exc} (after excluding {len(excluded)} of the {n} measurements: '
                            + '; '.join(f'{e.index}: {e.reason}' for e in excluded) + ')'
                            ) from None
        miss = eta - model.predict(result.values, q, data.tau, data.reflector, data.rotation,
                                   data.covariates)
        distances = np.linalg.norm(miss, axis=1)
        # What σ̂ and the reported distances see: the metric distances, or with joint-reading
        # noise the residuals at the stated σ (module text).
        tested, scaled = distances, result.residuals
        if model.joint_sigma is not None or data.sigma is not None:
            standard = noise_units(model, data, result.values, miss, sigma)
            tested, scaled = np.linalg.norm(standard, axis=1), standard[kept]
        scale = robust_sigma(scaled, result.dof)
        verdict = judge(model, data, result.values, result.estimated, sigma, scale,
                        threshold, kept, pose, omega,
                        np.asarray(result.covariance) / result.covariance_scale)
        t = verdict.distance_sigma
        # Taken as misfit, a lone fault is kept unless it lies beyond the misfit's reach.
        fault = verdict.fault & ~(verdict.lone & lone_misfit & (tested < reach))
        if not outliers.exclude or not fault.any():
            break
        # The faults within half the farthest one's distance: a batch a distorted fit
        # cannot have pushed good points into (swamping), then a refit.
        batch = fault & (t >= max(threshold, 0.5 * float(t[fault].max())))
        # max_fraction caps the points excluded on no evidence but their distance (rule 3
        # of core.estimation.outliers: no other point at the pose); a fault its pose's other points
        # confirm (rule 2), or a gross point, is excluded whatever the fraction.
        lone_count = len(lone_excluded) + int((batch & verdict.lone).sum())
        if lone_count > max_lone and not lone_misfit:
            # More lone "faults" than faults happen: points no replicate confirms, this
            # many, are the model's misfit (real arms with an effect the model lacks), not
            # the tracker's faults. Keep them, those excluded before too, and refit; but not
            # the points that stand apart from the misfit's tail (beyond a gap of MISFIT_GAP
            # in distance): 3 mm spikes on the real UR10 (rms 0.44 mm, its largest other
            # point 1.1 mm) were restored with the misfit's points and fitted.
            lone_misfit = True
            reach = misfit_reach(tested[sorted(lone_excluded | set(
                np.flatnonzero(batch & verdict.lone).tolist()))])
            restored = sorted(i for i in lone_excluded if tested[i] < reach)
            kept[restored] = True
            excluded = [e for e in excluded if e.index not in restored]
            lone_excluded.difference_update(restored)
            if progress is not None:
                progress(f'outliers: more than {outliers.max_fraction:.0%} of the points '
                         'would be excluded with no replicate to confirm them: taken as '
                         f'model misfit; {len(restored)} restored, refitting')
            continue
        # The reason carries no distance of its own: distance_sigma (against the final
        # fit, below) is the one figure reported for the point.
        for i in np.flatnonzero(batch)[np.argsort(-t[batch])]:
            excluded.append(_excluded(int(i), stamps, distances[i], tested[i] / scale,
                                      f'outlier: studentized residual beyond {threshold:.2f} '
                                      'σ̂ in the fit it was excluded from'))
        # Excluded by the lone-point rule alone (no replicate confirmed them as faults).
        lone_excluded.update(int(i) for i in np.flatnonzero(batch & verdict.lone))
        kept[batch] = False
        rounds += 1
        if progress is not None:
            progress(f'outliers: round {rounds}: excluded {int(batch.sum())} '
                     f'({len(excluded)} of {n} in all, σ̂ {scale * 1e6:.3g} µm), refitting '
                     f'{int(kept.sum())} points')
    # Distances of every measurement (excluded ones too) against the final fit.
    final_excluded = tuple(replace(e, distance_m=float(distances[e.index]),
                                   distance_sigma=float(tested[e.index] / scale))
                           for e in excluded)
    flagged = tuple(int(i) for i in np.flatnonzero(t > threshold))
    misfit = tuple(int(i) for i in np.flatnonzero(
        verdict.misfit | (verdict.fault & verdict.lone & lone_misfit)))
    # With per-point σ the σ they state, not the cell's noise.sigma (noise_units).
    stated = stated_sigma(sigma, data.sigma, n)
    warnings = []
    ratio = scale / stated
    if not (1 / SIGMA_RATIO_WARNING <= ratio <= SIGMA_RATIO_WARNING):
        warnings.append(sigma_warning(scale, stated, stated_source(data)))
    if flagged and not outliers.exclude:
        warnings.append(f'{len(flagged)} outlier(s) beyond {threshold:.2f} σ̂ kept in the fit '
                        '(identification.outliers.exclude is false)')
    if misfit:
        warnings.append(misfit_warning(misfit, pose, threshold,
                                       outliers.max_fraction if lone_misfit else None))
    return RobustResult(result, kept, final_excluded, flagged, scale, stated, threshold,
                        loss, omega, tuple(warnings), misfit)


def misfit_warning(misfit: tuple[int, ...], pose: np.ndarray, threshold: float,
                   too_many_lone: float | None = None) -> str:
    """Return the text naming the points over the threshold kept as model misfit.

    ``too_many_lone``: the fraction beyond which lone points were taken as misfit.
    """
    poses = sorted({int(pose[i]) for i in misfit})
    shown = ', '.join(str(g) for g in poses[:12]) + (', …' if len(poses) > 12 else '')
    why = ('their pose\'s other points agree with them, or they carry information no other '
           'pose has')
    if too_many_lone is not None:
        why += (f'; or, with no other point at their pose, they are more than '
                f'{too_many_lone:.0%} of the measurements: faults are few, a misfit is '
                'everywhere')
    return (f'model misfit at poses {shown} ({len(misfit)} point(s) beyond '
            f'{threshold:.2f} σ̂ kept: {why}); see kpi-calib diagnose')


def misfit_reach(distances: np.ndarray) -> float:
    """Return the distance beyond which a point is no part of a misfit's tail (inf: none).

    ``distances`` of the points taken as the model's misfit; sorted, the first gap where one
    is more than :data:`MISFIT_GAP` times the one below ends the tail, and the reach is
    MISFIT_GAP times the tail's largest.
    """
    d = np.sort(np.asarray(distances, float))
    d = d[d > 0]
    gaps = np.flatnonzero(d[1:] > MISFIT_GAP * d[:-1])
    return float(MISFIT_GAP * d[gaps[0]]) if len(gaps) else float('inf')


def gross_outliers(model: MeasurementModel, data: Measurements,
                   p: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Gross points: (N,) bool, and the (N,) distances from the prediction, m.

    A point is gross when farther than `GROSS_DISTANCE` (and 20× the median) from the prediction
    with ``p`` (default: the nominal parameters).
    """
    q, eta = np.atleast_2d(data.q), np.atleast_2d(data.eta)
    p = np.asarray(model.params.nominal if p is None else p, float)
    nominal = np.linalg.norm(eta - model.predict(p, q, data.tau, data.reflector,
                                               data.rotation, data.covariates), axis=1)
    return nominal > max(GROSS_DISTANCE, 20 * float(np.median(nominal))), nominal


POINT_SIGMA = "the points' own stated sigma"


def sigma_warning(robust: float, stated: float, source: str = 'noise.sigma') -> str:
    """Return the warning text for a robust σ̂ more than 2× away from the stated σ.

    ``source``: what stated it, the cell's ``noise.sigma`` or :data:`POINT_SIGMA` (the rms
    of the σ the tracker stated per point, :func:`stated_source`).
    """
    ratio = robust / stated
    side = 'smaller' if ratio < 1 else 'larger'
    return (f'noise σ estimated from the residuals ({robust * 1e6:.3g} µm) is {ratio:.3g}× the '
            f'stated {source} ({stated * 1e6:.3g} µm), {side} by more than '
            f'{SIGMA_RATIO_WARNING:g}×: the stated σ sets the χ² test (and every reported std '
            'while the model passes it); '
            f'check {source} (units: m) or the model (kpi-calib diagnose)')


def stated_source(data: Measurements) -> str:
    """Return what states the σ of ``data``'s rows: the cell's noise.sigma or the points'."""
    return 'noise.sigma' if data.sigma is None else POINT_SIGMA


def noise_units(model: MeasurementModel, data: Measurements, p: np.ndarray,
                residuals: np.ndarray, sigma: float | np.ndarray) -> np.ndarray:
    """Residuals (N, 3) of ``data`` at ``p`` as the robust statistics take them (m).

    As given without joint-reading noise and per-point σ; with either, W_i r_i times the
    stated σ (:func:`~kpi_calib_ros.core.measurement.data.stated_sigma`: the cell's, or the
    rms of the points' own), whose noise is that σ on every axis at every pose (a point's own
    σ from the tracker counts in units of itself,
    :func:`~kpi_calib_ros.core.measurement.weighting.noise_weights`). Scaled by the points' own
    σ, not the cell's: a robust σ̂ of 20.9 µm noise on points stating 10 µm reads 20.9 µm
    (2.09× the stated), not 2.09× the cell's noise.sigma.
    """
    if model.joint_sigma is None and data.sigma is None:
        return residuals
    sigma = np.broadcast_to(np.asarray(sigma, float), (3,))
    w = noise_weights(model, p, data, sigma)
    return (weighted_residuals(residuals, w).reshape(-1, 3)
            * stated_sigma(sigma, data.sigma, len(residuals)))


def _fit_with_loss(fit: Fit, data: Measurements, loss: str, model: MeasurementModel,
                   sigma: float | np.ndarray) -> tuple[CalibrationResult, np.ndarray | None]:
    result = fit(data)
    if loss == 'linear':
        return result, None
    omega = np.ones(len(data))
    for _ in range(IRLS_ITERATIONS):
        residuals = noise_units(model, data, result.values, result.residuals, sigma)
        scale = robust_sigma(residuals, result.dof)
        new = loss_weights(loss, np.linalg.norm(residuals, axis=1), scale)
        result = fit(data, p0=result.values, point_weights=new)
        if np.max(np.abs(new - omega)) < 1e-3:
            omega = new
            break
        omega = new
    return result, omega


def _excluded(i: int, stamps: Any, distance: float, in_sigma: float,
              reason: str) -> ExcludedMeasurement:
    stamp = None if stamps is None else int(stamps[i])
    return ExcludedMeasurement(int(i), stamp, float(distance), float(in_sigma), reason)

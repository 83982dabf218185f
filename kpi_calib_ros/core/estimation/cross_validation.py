"""Cross-validated rms of a calibration: its error on poses a refit did not see.

Each fold refits the identified parameters on the other poses and predicts the held-out
ones, exact for the locally linear model at p̂ (which a converged fit is to far below σ):
the held-out residual of a fold F is (I − H_FF)⁻¹ e_F, e the full-data residual and H the
hat matrix of the weighted Jacobian (the PRESS identity, :func:`linear_validation_rms`,
:func:`fold_rms`). The folds are :mod:`kpi_calib_ros.core.estimation.folds`'s: leave one
pose out or k-fold (:func:`validation_rms`), and region-blocked beside them
(:func:`region_validation`: the error where no pose was measured), and with several
recordings each recording held out whole (:func:`recording_held_out`: the robot refitted on
the others, the held-out recording's own placement registered on its rows, as ``validate
--register`` places a new set-up). A fit with a prior keeps it in every fold's refit
(:func:`prior_system`): the prior's rows are training rows of every fold.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from kpi_calib_ros.core.estimation.folds import (
    LEAVE_ONE_OUT,
    RANK_TOLERANCE,
    REGION_BLOCKS,
    HeldOutBlock,
    fold_blocks,
    identifiable_folds,
    pose_index,
    range_end_folds,
    region_folds,
)
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.estimation.residuals import (
    LinearizedFit,
    linearized_fit,
    orthonormal_basis,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.recordings import recording_names, row_recording
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import (
    point_rms,
    point_rows,
    row_noise_variance,
    unweighted,
)

__all__ = [
    'press_residuals', 'linear_validation_rms', 'validation_rms', 'prior_system',
    'validation_folds', 'fold_rms', 'fold_held_out', 'recording_held_out', 'RegionValidation',
    'region_validation', 'PLACEMENT_PREFIXES', 'fold_kinds', 'recording_masks',
]

# Parameters that place a recording (its base in the tracker frame, its reflector offsets):
# a recording held out whole has them registered on its own rows.
PLACEMENT_PREFIXES = ('base.', 'reflector.', 'recording.')


def press_residuals(a: np.ndarray, r: np.ndarray, pose_folds: np.ndarray,
                    prior_rows: tuple[np.ndarray, np.ndarray] | None = None
                    ) -> np.ndarray | None:
    """Held-out weighted residual (3N,) of each row of the linear model r ≈ a·δ.

    Each fold's (``pose_folds`` (N,)) held-out residual is exactly that of the refit
    without it, (I − H_FF)⁻¹ e_F with e = (I − H) r the full-data residual (the PRESS
    identity; H the hat matrix of ``a``), ``prior_rows`` (L (m, k), its residual (m,),
    :func:`prior_system`) kept in every refit. None when a fold's training poses leave a
    column of ``a`` undetermined: a minimum-norm refit would then predict the held-out
    poses with a parameter the fold cannot see.
    """
    n_rows = len(r)
    if prior_rows is not None and len(prior_rows[1]):
        a = np.vstack([a, prior_rows[0]])
        r = np.concatenate([r, prior_rows[1]])
    u = orthonormal_basis(a)
    r = r - u @ (u.T @ r)  # the full-data fit of r ≈ a·δ (r need not be converged on a)
    held = np.empty_like(r)
    for test, m in fold_blocks(a, pose_folds, u):
        if m.smallest <= RANK_TOLERANCE:
            return None
        held[test] = m.solve(r[test])
    return held[:n_rows]


def linear_validation_rms(a: np.ndarray, r: np.ndarray, w: np.ndarray,
                          pose_folds: np.ndarray | None,
                          prior_rows: tuple[np.ndarray, np.ndarray] | None = None,
                          points: np.ndarray | None = None) -> float:
    """Cross-validated rms (m) of the linear model r ≈ a·δ, folds over poses.

    ``prior_rows`` (L (m, k), its residual (m,), :func:`prior_system`): a prior the fit
    used, kept in every fold's refit (without it a fold refits a weaker, unregularised
    model and the figure can fall below the fit's own rms). ``points`` (N,) bool: the rows
    the rms is taken over (the point rows,
    :func:`~kpi_calib_ros.core.measurement.weighting.point_rows`; default every row): a
    tracked body's rotation rows are held out with their pose but are no length.

    The held-out residuals: :func:`press_residuals`. NaN ("not estimable from this
    design") when ``pose_folds`` is None or a fold's training poses leave a column of ``a``
    undetermined.
    """
    held = None if pose_folds is None else press_residuals(a, r, pose_folds, prior_rows)
    if held is None:
        return float('nan')
    return point_rms(unweighted(held, w), points)


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
                                 rows, point_rows(data.reflector, model.n_reflectors))


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


def fold_rms(a: np.ndarray, r: np.ndarray, w: np.ndarray, masks: list[np.ndarray],
             prior_rows: tuple[np.ndarray, np.ndarray] | None = None,
             points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Held-out rms (m) of each fold of the linear model r ≈ a·δ, and its noise, (len(masks),).

    ``masks``: held-out measurements (N,) bool per fold (folds may overlap). Each rms is
    that of the refit without the fold (the PRESS identity, as
    :func:`linear_validation_rms`, ``prior_rows`` kept); NaN for a fold whose training rows
    leave a column of ``a`` undetermined. The noise: the standard deviation the stated
    noise alone gives the rms of the fold's n points, σ_p/√(6n) with σ_p² the mean of the
    points' total variance (σ/√(2n) per axis σ; an rms of 3-D noise over n points).
    ``points`` (N,) bool: the rows both are taken over (as :func:`linear_validation_rms`);
    a fold's other rows are held out with it.
    """
    return _fold_figures(a, r, w, masks, prior_rows, points)[:2]


def fold_held_out(a: np.ndarray, r: np.ndarray, masks: list[np.ndarray],
                  prior_rows: tuple[np.ndarray, np.ndarray] | None = None
                  ) -> list[np.ndarray | None]:
    """Held-out weighted residuals of each fold's refit (3·|fold|,), None where undetermined.

    As :func:`fold_rms` (the PRESS identity, ``prior_rows`` kept in every refit), in the
    whitened units of ``r``: unit noise variance per row where the stated noise is right.
    """
    if prior_rows is not None and len(prior_rows[1]):
        a = np.vstack([a, prior_rows[0]])
        r = np.concatenate([r, prior_rows[1]])
    u = orthonormal_basis(a)
    e = r - u @ (u.T @ r)
    out: list[np.ndarray | None] = []
    for mask in masks:
        test = np.flatnonzero(np.repeat(mask, 3))
        m = HeldOutBlock(u[test])
        out.append(None if m.smallest <= RANK_TOLERANCE else m.solve(e[test]))
    return out


def recording_held_out(a: np.ndarray, r: np.ndarray, mask: np.ndarray, own: np.ndarray,
                       prior_rows: tuple[np.ndarray, np.ndarray] | None = None
                       ) -> np.ndarray | None:
    """Held-out weighted residuals (3·|mask|,) of a recording held out whole, or None.

    The columns ``own`` (bool (k,)) are the recording's own placement: no training row
    sees them. The other columns are refitted on the training rows (``prior_rows`` kept,
    its rows on the own columns left out), the held-out rows predicted, and the own
    columns registered on them (least squares); the rest is the held-out residual, in the
    whitened units of ``r``. None when the training rows leave a column undetermined or
    the held-out rows do not determine the own columns.
    """
    test = np.repeat(np.asarray(mask, bool), 3)
    keep = ~np.asarray(own, bool)
    a_t, r_t = a[~test][:, keep], r[~test]
    if prior_rows is not None and len(prior_rows[1]):
        rows = np.any(prior_rows[0][:, keep] != 0, axis=1)
        a_t = np.vstack([a_t, prior_rows[0][rows][:, keep]])
        r_t = np.concatenate([r_t, prior_rows[1][rows]])

    def determined(m: np.ndarray) -> bool:
        if not m.shape[1]:
            return True
        s = np.linalg.svd(m, compute_uv=False)
        return bool(s[-1] > RANK_TOLERANCE * max(s[0], 1e-300))
    a_own = a[test][:, ~keep]
    if not determined(a_t) or not determined(a_own):
        return None
    delta = np.linalg.lstsq(a_t, r_t, rcond=None)[0]
    e = r[test] - a[test][:, keep] @ delta
    if a_own.shape[1]:
        e = e - a_own @ np.linalg.lstsq(a_own, e, rcond=None)[0]
    return e


def fold_kinds(recordings: int) -> str:
    """Name the held-out folds of :func:`region_validation` ((region blocks ...))."""
    if not recordings:
        return '(region blocks and joint range ends)'
    return f'(region blocks, joint range ends and {recordings} recordings held out whole)'


def recording_masks(model: MeasurementModel, data: Measurements, estimated: list[str],
                    a: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Return the rows (N,) bool of each recording and its own placement columns (k,) bool.

    Empty with one recording. The own columns: the placement parameters (names starting
    with :data:`PLACEMENT_PREFIXES`) that no row of another recording sees.
    """
    names = recording_names(model.params)
    if not names:
        return []
    index = row_recording(data, ['first'] + names)
    placement = np.array([n.startswith(PLACEMENT_PREFIXES) for n in estimated], bool)
    norm = np.linalg.norm(a, axis=0)
    out = []
    for i in range(len(names) + 1):
        mask = index == i
        if not mask.any() or mask.all():
            continue
        elsewhere = np.linalg.norm(a[~np.repeat(mask, 3)], axis=0)
        own = placement & (elsewhere <= 1e-12 * np.maximum(norm, 1e-300))
        out.append((mask, own))
    return out


def _fold_figures(a: np.ndarray, r: np.ndarray, w: np.ndarray, masks: list[np.ndarray],
                  prior_rows: tuple[np.ndarray, np.ndarray] | None = None,
                  points: np.ndarray | None = None,
                  recordings: list[tuple[np.ndarray, np.ndarray]] | None = None
                  ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray | None]]:
    """Return :func:`fold_rms`'s rms and noise (m), and :func:`fold_held_out`'s residuals.

    Then those of each recording held out whole (:func:`recording_held_out`,
    ``recordings``: its rows and own placement columns).
    """
    w = np.asarray(w, float)
    recordings = recordings or []
    held = fold_held_out(a, r, masks, prior_rows) if masks else []
    held += [recording_held_out(a, r, mask, own, prior_rows) for mask, own in recordings]
    masks = list(masks) + [mask for mask, _ in recordings]
    if not masks:
        return np.zeros(0), np.zeros(0), []
    variance = row_noise_variance(w, len(masks[0]))
    out, noise = np.full(len(masks), np.nan), np.full(len(masks), np.nan)
    for i, (mask, h) in enumerate(zip(masks, held)):
        counted = mask if points is None else mask & points
        if not counted.any():
            continue
        noise[i] = float(np.sqrt(np.mean(variance[counted]) / (6 * counted.sum())))
        if h is None:
            continue
        metres = unweighted(h, w if w.ndim == 1 else w[mask])
        out[i] = point_rms(metres, None if points is None else points[mask])
    return out, noise, held


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
    # poses: each region block, then each range-end fold (:func:`range_end_folds`) that
    # holds other poses than the folds before it; NaN
    # where a fold leaves a parameter undetermined. Two models judged on the same folds
    # pair figure by figure; and what the stated noise alone spreads each by (m, fold_rms).
    held_out_folds_m: tuple[float, ...] = ()
    held_out_noise_m: tuple[float, ...] = ()
    # Each of those folds' held-out weighted residuals (fold_held_out; None where
    # undetermined): two models on the same folds pair row by row
    # (core.diagnosis.model_selection.held_out_gain).
    held_out_residuals: tuple[np.ndarray | None, ...] = dataclasses.field(
        default=(), compare=False, repr=False)
    # With several recordings, the last ``recordings`` of those folds hold out one recording
    # whole each (its placement registered on its rows, :func:`recording_held_out`).
    recordings: int = 0

    @property
    def other_recording_m(self) -> float:
        """Rms (m) over the recordings held out whole (NaN: none, or one not estimable)."""
        if not self.recordings:
            return float('nan')
        values = np.array(self.held_out_folds_m[-self.recordings:], float)
        if not np.all(np.isfinite(values)):
            return float('nan')
        return float(np.sqrt(np.mean(values ** 2)))

    def to_dict(self) -> dict:
        """YAML-ready figures (m; None where not estimable)."""
        def m(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None
        return {'in_region_rms_m': m(self.in_region_m),
                'other_region_rms_m': m(self.other_region_m),
                'other_recording_rms_m': m(self.other_recording_m),
                'recordings_held_out': self.recordings,
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
    masks = [] if region_ids is None else [region_ids == b for b in range(used)]
    for end in (m[pose] for m in range_end_folds(poses)):
        # A range end that holds the same poses as a region block or another end (joints
        # that move together) is one fold: counted twice, it was judged twice.
        if not any(np.array_equal(end, m) for m in masks):
            masks.append(end)
    points = point_rows(data.reflector, model.n_reflectors)
    recordings = recording_masks(model, data, list(result.estimated), sys_.jac)
    held, noise, residuals = _fold_figures(sys_.jac, sys_.r, sys_.w, masks, rows, points,
                                           recordings)
    return RegionValidation(
        linear_validation_rms(sys_.jac, sys_.r, sys_.w, inside, rows, points),
        linear_validation_rms(sys_.jac, sys_.r, sys_.w, region_ids, rows, points), folds, used,
        tuple(float(v) for v in held), tuple(float(v) for v in noise), tuple(residuals),
        len(recordings))

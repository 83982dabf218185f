"""Never worse than nominal, recording by recording.

A calibration of several recordings (tracker set-ups,
:mod:`kpi_calib_ros.core.measurement.recordings`) can predict held-out poses better than the
nominal robot over all rows together and still worse on one recording: a set-up whose few
poses the shared robot does not fit (a robot re-mastered or repaired between set-ups, a
load or a mounting the model does not know), outweighed by the others. The overall verdict
(:func:`kpi_calib_ros.core.diagnosis.model_selection.against_nominal`) cannot see it;
this module judges each recording on its own rows.

The rule. Both models -- the calibration, and the nominal robot with every recording's
placement registered -- are cross-validated on the folds of the overall comparison (the
calibration's, which keep the rank of every placement it contains), by linear refits with
each fit's prior kept: each row's held-out residual is that of the refit without the fold
that holds it (the PRESS identity, exact for the locally linear model, nothing refitted).
A recording's figure is the rms of the held-out residuals of its own rows: the same
numbers the overall figure averages, restricted, so the recordings' figures pool to the
overall one. This costs one linearisation of each model; refitting per recording would
judge each recording by a robot fitted without the others, which is not the calibration
published.

A recording is *harmed* when the calibration's figure where measured (folds drawn like
the measured poses) is above the nominal's by more than the noise: what the stated noise
alone spreads an rms of the recording's n rows by, σ_p/√(6n) with σ_p² the mean total
variance of its points (:func:`kpi_calib_ros.core.estimation.cross_validation.fold_rms`'s
noise of a fold), plus
:data:`~kpi_calib_ros.core.diagnosis.model_selection.TIE_M`. The two figures of one row
share its noise, so this margin is wide for a difference of them: a recording is named only
for a systematic loss. The figure over held-out regions of joint space is reported beside
it, not judged: its regions are drawn over every recording's poses together, and a region
may hold out most of a small recording, where the placement-only nominal model
extrapolates by construction better than a robot fitted on the rest. The overall verdict's
second figure, the error predicted from the fit, is one figure over all rows (its χ²/dof
pooled) and cannot see a recording: the recording's verdict rests on cross-validation.

Measured (default cell, set-ups of 40 and 20 poses, σ 20 µm, 10 seeds per row): with the
simulator's geometric errors scaled by 1, 0.1, 0.03 or 0.01 no recording is named (0 of
40); with a robot built exactly to its URDF 6 of 10 name one, all but one of them already
refused over all rows (the geometric fit's refits are above the nominal's), and none named
where the overall verdict holds. A set-up of 20 poses measuring a robot built to its URDF
beside 40 poses of the robot with errors, better over all rows in 10 of 10 seeds: that set-up
alone named in 10 of 10, predicted 2.7-9.2x worse than by the nominal robot.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from kpi_calib_ros.core.estimation.cross_validation import press_residuals, prior_system
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.estimation.residuals import linearized_fit
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.recordings import row_recording
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import (
    point_rms,
    point_rows,
    row_noise_variance,
    unweighted,
)

__all__ = ['RecordingComparison', 'held_out_residuals', 'recording_comparisons', 'named', 'FIX']

# What to do about a recording the calibration harms.
FIX = ('measure more poses in that set-up, or identify without it (drop its bag) and '
       'register it separately (kpi-calib validate --register base)')
# Two rms figures closer than this (m) are a tie (model_selection.TIE_M, not imported:
# model_selection imports this module).
_TIE_M = 1e-9


@dataclass(frozen=True)
class RecordingComparison:
    """One recording's cross-validated rms (m) of the calibration and of the nominal robot.

    ``name``: the recording's ('' for the first until :meth:`named`), ``rows`` its rows,
    ``in_region``: folds drawn like the measured poses, ``other_region``: region-blocked
    folds (NaN: not estimable), ``noise_m``: what the stated noise alone spreads an rms of
    its rows by (the margin of the verdict).
    """

    name: str
    rows: int
    calibrated_in_region_m: float
    nominal_in_region_m: float
    calibrated_other_region_m: float
    nominal_other_region_m: float
    noise_m: float

    @property
    def harmed(self) -> bool:
        """Whether the calibration predicts the recording's held-out rows worse than nominal.

        Worse than the nominal robot by more than the noise; False when a figure is not
        estimable.
        """
        a, b = self.calibrated_in_region_m, self.nominal_in_region_m
        return bool(np.isfinite(a) and np.isfinite(b)
                    and a > b + max(self.noise_m, 0.0) + _TIE_M)

    @property
    def label(self) -> str:
        """The recording's name as the text names it."""
        return repr(self.name) if self.name else 'the first'

    def named(self, name: str) -> RecordingComparison:
        """Return the comparison with the recording's ``name``."""
        return replace(self, name=name)

    def text(self) -> str:
        """One line: the recording, its figures and, when harmed, why and the fix."""
        def um(v: float) -> str:
            return f'{v * 1e6:.1f} µm' if np.isfinite(v) else 'not estimable'
        figures = (f'cross-validated rms of its {self.rows} rows where measured '
                   f'{um(self.calibrated_in_region_m)} (nominal robot with its placement '
                   f'registered {um(self.nominal_in_region_m)}; noise {um(self.noise_m)}), '
                   f'over held-out regions {um(self.calibrated_other_region_m)} (nominal '
                   f'{um(self.nominal_other_region_m)})')
        if not self.harmed:
            return f'recording {self.label}: not worse than nominal: {figures}'
        return (f'recording {self.label}: the calibration predicts its held-out poses WORSE '
                f'than the nominal robot beyond the noise: {figures}; {FIX}')

    def to_dict(self) -> dict:
        """YAML-ready figures (m; None where not estimable)."""
        def m(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None
        return {'worse_than_nominal': self.harmed, 'rows': self.rows,
                'in_region_rms_m': m(self.calibrated_in_region_m),
                'nominal_in_region_rms_m': m(self.nominal_in_region_m),
                'other_region_rms_m': m(self.calibrated_other_region_m),
                'nominal_other_region_rms_m': m(self.nominal_other_region_m),
                'noise_m': m(self.noise_m)}


def held_out_residuals(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                       prior: Prior | None, pose_folds: np.ndarray | None
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """Each row's held-out residual (N, 3) (m) and its noise variance (N,) (m²).

    The residual of the linear refit of ``result``'s identified parameters without the fold
    (``pose_folds`` (N,)) that holds the row, ``prior`` kept in every refit (the PRESS
    identity, as :func:`kpi_calib_ros.core.estimation.cross_validation.linear_validation_rms`); the
    variance the stated noise gives the row's point (its three axes). None when there are
    no folds or a fold's training rows leave an identified parameter undetermined.
    """
    if pose_folds is None:
        return None
    sys_ = linearized_fit(model, data, result)
    held = press_residuals(sys_.jac, sys_.r, pose_folds, prior_system(model, result, prior))
    if held is None:
        return None
    return unweighted(held, sys_.w), row_noise_variance(sys_.w, len(data))


def _rms(metres: np.ndarray | None, rows: np.ndarray) -> float:
    if metres is None or not rows.any():
        return float('nan')
    return point_rms(metres, rows)


def recording_comparisons(model: MeasurementModel, data: Measurements,
                          result: CalibrationResult, prior: Prior | None,
                          nominal_model: MeasurementModel, nominal: CalibrationResult,
                          nominal_prior: Prior | None,
                          folds: tuple[np.ndarray | None, np.ndarray | None],
                          nominal_folds: tuple[np.ndarray | None, np.ndarray | None] | None = None
                          ) -> tuple[RecordingComparison, ...]:
    """Judge the calibration ``result`` against the ``nominal`` fit on each recording's rows.

    Per recording of ``model`` (the first, then ``model.recordings``), by the rule of this
    module. ``folds`` (in-region, region-blocked pose folds (N,), each None when none keep the
    rank): those of the overall comparison; ``nominal_folds``: the nominal's when those
    do not keep its rank (default ``folds``). () with one recording.
    """
    if not model.recordings:
        return ()
    names = ('',) + tuple(model.recordings)
    index = row_recording(data, names)
    nominal_folds = nominal_folds or folds
    cal = [held_out_residuals(model, data, result, prior, f) for f in folds]
    nom = [held_out_residuals(nominal_model, data, nominal, nominal_prior, f)
           for f in nominal_folds]
    variance = next((h[1] for h in cal + nom if h is not None), None)
    points = point_rows(data.reflector, model.n_reflectors)
    out = []
    for i, name in enumerate(names):
        rows = index == i
        if points is not None:  # a tracked body's rotation rows are no length
            rows &= points
        n = int(rows.sum())
        noise = (float(np.sqrt(np.mean(variance[rows]) / (6 * n)))
                 if variance is not None and n else float('nan'))
        figures = [_rms(None if h is None else h[0], rows) for h in cal + nom]
        out.append(RecordingComparison(name, n, figures[0], figures[2], figures[1],
                                       figures[3], noise))
    return tuple(out)


def named(comparisons: Sequence[RecordingComparison], names: Sequence[str]
          ) -> tuple[RecordingComparison, ...]:
    """``comparisons`` with the recordings' ``names`` (every recording, first included)."""
    if len(names) != len(comparisons):
        raise ValueError(f'{len(names)} recording names for {len(comparisons)} recordings')
    return tuple(c.named(n) for c, n in zip(comparisons, names))

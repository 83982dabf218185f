"""Never worse than no calibration: a calibration against the nominal robot, placement registered.

Both are cross-validated on the same folds (where measured and over held-out regions of joint
space), their expected TCP errors at the working poses and their errors predicted from the
fit compared (:class:`NominalComparison`); with several recordings each one on its own rows
(:mod:`kpi_calib_ros.core.diagnosis.recording_verdict`). The rule is
:attr:`NominalComparison.better`, the scope statement
:attr:`NominalComparison.elsewhere_worse`, and the working poses' own test
:attr:`NominalComparison.undetermined_where_it_works`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from kpi_calib_ros.core.diagnosis.out_of_sample import out_of_sample_error
from kpi_calib_ros.core.diagnosis.recording_verdict import (
    RecordingComparison,
    named,
    recording_comparisons,
)
from kpi_calib_ros.core.estimation.cross_validation import (
    RegionValidation,
    region_validation,
    validation_folds,
)
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.precision import expected_tcp_error, honest_precision
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel

__all__ = ['TIE_M', 'NominalComparison', 'against_nominal']

# Two rms figures closer than this (m) are a tie, not a verdict: far below any tracker's
# resolution, it keeps the rounding of two fits that predict alike from deciding.
TIE_M = 1e-9


def _not_above(calibrated_m: float, nominal_m: float) -> bool:
    """Whether the calibration's figure is lower than the nominal's, or tied with it."""
    return calibrated_m < nominal_m or abs(calibrated_m - nominal_m) <= TIE_M


@dataclass(frozen=True)
class NominalComparison:
    """A calibration's cross-validated rms against the nominal model, placement registered.

    The nominal model: base in the tracker and reflector offsets fitted, the robot nominal;
    both on the same folds, where measured (``in_region``) and over held-out regions of
    joint space.

    ``better``: False (worse than no calibration) when the cross-validated figures (where
    measured, over held-out regions, the expected TCP error over the working poses) do not
    all favour the calibration *and* the error predicted from the fit itself at the
    measured configurations (:mod:`~kpi_calib_ros.core.diagnosis.out_of_sample`, no refits)
    does not either. Both are asked because each errs alone on real data: with 37 TIAGo
    postures of 4 markers and millimetre play, the leave-one-out refits of the geometric
    model (4.9 mm) are above the nominal robot's (4.5 mm), yet it predicts the other day
    with 4.2 mm against the nominal's 5.9 mm, as its predicted error (2.4 against 4.1 mm)
    says; the prediction from the fit is itself low where the model misfits.
    """

    calibrated: RegionValidation
    nominal: RegionValidation
    # rms over the working poses of the expected TCP error (parameter part and misfit,
    # core.estimation.precision.expected_tcp_error) of each, m; NaN: no working pose or no figure.
    calibrated_working_m: float = float('nan')
    nominal_working_m: float = float('nan')
    # Predicted rms of new measurements at the measured configurations, from each fit
    # (core.diagnosis.out_of_sample, like_measured), m; NaN: not estimable.
    calibrated_predicted_m: float = float('nan')
    nominal_predicted_m: float = float('nan')
    # With several recordings, each one's figures on its own rows, first included
    # (core.diagnosis.recording_verdict); () with one.
    recordings: tuple[RecordingComparison, ...] = ()
    # rms over the working poses of the calibration's parameter part alone (tcp_std), m.
    calibrated_working_parameter_m: float = float('nan')
    # 95 % intervals (m) of the predicted rms of each (core.diagnosis.out_of_sample).
    calibrated_predicted_interval_m: tuple[float, float] = (float('nan'), float('nan'))
    nominal_predicted_interval_m: tuple[float, float] = (float('nan'), float('nan'))
    # The nominal robot's registered placement {name: value} (base.*, reflector.*): validate
    # compares a calibration as used (its own placement) with it on new points.
    nominal_placement: dict[str, float] = dataclasses.field(default_factory=dict)

    @property
    def undetermined_where_it_works(self) -> bool:
        """Whether the calibration's uncertainty where it works exceeds the nominal's error.

        The parameter part of the expected TCP error (the identified parameters' covariance
        carried to the working poses, free of the misfit's sampling noise) above the
        nominal robot's expected error (its misfit, its placement's part): wherever the
        robot was measured, the poses do not determine it where it works, and using the
        calibration there is expected to be worse than using none. Real UR10 Series A,
        300 poses of one region, slab of the shoulder or hour of Series A: 1343-19502 µm
        against 516-923 µm, measured 3-20x worse than the nominal robot over the rest of
        the workspace, while every cross-validated figure, drawn from the measured poses,
        favoured the calibration; 300 or 60 poses over the workspace: 157 and 423 µm
        against 873 and 969 µm, measured better; the real TIAGo: 660 against 4538 µm.
        """
        a, b = self.calibrated_working_parameter_m, self.nominal_working_m
        return bool(np.isfinite(a) and np.isfinite(b) and a > b + TIE_M)

    def working_text(self) -> str:
        """Return the problem of :attr:`undetermined_where_it_works` ('' when it does not apply)."""
        if not self.undetermined_where_it_works:
            return ''
        return (f'the poses do not determine the robot where it works: the calibration\'s own '
                f'uncertainty at the working poses (parameter part of the expected TCP error, '
                f'{self.calibrated_working_parameter_m * 1e6:.1f} µm) exceeds the nominal '
                f'robot\'s whole expected error there ({self.nominal_working_m * 1e6:.1f} '
                'µm); measure poses around the working poses (kpi-calib design plans them), '
                'or identify fewer parameters (identification.model)')

    @property
    def harmed(self) -> tuple[RecordingComparison, ...]:
        """The recordings the calibration predicts worse than nominal beyond the noise."""
        return tuple(r for r in self.recordings if r.harmed)

    def named(self, names: Sequence[str]) -> NominalComparison:
        """Return the comparison with the recordings' ``names`` (first included)."""
        if not self.recordings:
            return self
        return dataclasses.replace(self, recordings=named(self.recordings, names))

    @property
    def compared(self) -> tuple[str, ...]:
        """The figures both models have: 'in_region', 'other_region'."""
        out = []
        for key in ('in_region', 'other_region', 'working'):
            a, b = self._figures(key)
            if np.isfinite(a) and np.isfinite(b):
                out.append(key)
        return tuple(out)

    def _figures(self, key: str) -> tuple[float, float]:
        if key == 'working':
            return self.calibrated_working_m, self.nominal_working_m
        return getattr(self.calibrated, f'{key}_m'), getattr(self.nominal, f'{key}_m')

    @property
    def better(self) -> bool:
        """False when the cross-validated and the predicted figures both favour the nominal.

        A figure favours the nominal only when it is lower by more than
        :data:`TIE_M` (noise-free data of a robot built to its URDF predict both at 0).
        The prediction from the fit outweighs cross-validated figures that favour the
        nominal only when it favours the calibration beyond its own uncertainty: the upper
        end of the calibration's 95 % interval below the lower end of the nominal's (the
        real TIAGo: 2405 against 4120 µm). On 300 poses of an hour of the real UR10's Series A
        every cross-validated figure favoured the nominal robot, the prediction the
        calibration by 1 % (349.0 against 353.4 µm), and the calibration predicted the rest
        of Series A 1.6x worse than the nominal robot (1490 against 939 µm).
        """
        return self._cv_better or self._predicted_better

    @property
    def _predicted_better(self) -> bool:
        a, b = self.calibrated_predicted_m, self.nominal_predicted_m
        if not (np.isfinite(a) and np.isfinite(b)):
            return False
        a_hi, b_lo = self.calibrated_predicted_interval_m[1], self.nominal_predicted_interval_m[0]
        if np.isfinite(a_hi) and np.isfinite(b_lo):
            return bool(a_hi < b_lo or abs(a - b) <= TIE_M)
        return _not_above(a, b)

    @property
    def elsewhere_worse(self) -> bool:
        """Whether a calibration found better predicts held-out regions worse than nominal.

        Found better (:attr:`better`), it predicts the held-out regions of joint space worse
        than the nominal robot, pooled and in at least half of the regions
        (:meth:`regions_worse`): better where it was measured, harmful beyond (a region-0
        geometric fit of the real UR10: 4566 µm over held-out regions
        against the registered nominal's 591 µm, and 4.3 mm against 1.3 mm measured there).
        Not refused (37 TIAGo postures put the nominal first over held-out regions, 4.9
        against 6.2 mm, while the calibration predicts the other days better, 4.2 against
        5.9 mm), but stated: its scope is the measured region. The pooled figure alone
        is one region's when one refit is undetermined: 60 poses over the real UR10's
        workspace, better than the nominal robot in 4 of 5 regions, pooled 36969 against
        1080 µm by one region's 143 mm, predict 1500 other poses at 501 against 850 µm.
        """
        a, b = self._figures('other_region')
        worse, compared = self.regions_worse()
        return bool(self.better and np.isfinite(a) and np.isfinite(b) and not _not_above(a, b)
                    and (not compared or 2 * worse >= compared))

    def regions_worse(self) -> tuple[int, int]:
        """Return the held-out regions predicted worse than nominal, and those compared.

        Regions of joint space where the calibration's rms exceeds the nominal robot's
        beyond :data:`TIE_M`, and the regions both predict (0 without per-region figures:
        the pooled figure decides alone).
        """
        blocks = min(self.calibrated.blocks, self.nominal.blocks)
        pairs = [(a, b) for a, b in zip(self.calibrated.held_out_folds_m[:blocks],
                                        self.nominal.held_out_folds_m[:blocks])
                 if np.isfinite(a) and np.isfinite(b)]
        return sum(not _not_above(a, b) for a, b in pairs), len(pairs)

    def scope_text(self) -> str:
        """Return the warning of :attr:`elsewhere_worse` ('' when it does not apply)."""
        if not self.elsewhere_worse:
            return ''
        a, b = self._figures('other_region')
        worse, compared = self.regions_worse()
        return (f'outside the region of joint space it was measured in, this calibration '
                f'predicts worse than the nominal robot with the placement registered '
                f'(cross-validated over held-out regions: {a * 1e6:.1f} µm against '
                f'{b * 1e6:.1f} µm, worse in {worse} of {compared} regions): use it within '
                'the measured joint ranges (training_joint_ranges), or measure poses over the '
                'region where the robot works and identify again')

    @property
    def _cv_better(self) -> bool:
        return not self.favour_nominal

    @property
    def favour_nominal(self) -> tuple[str, ...]:
        """The compared figures that favour the nominal robot (lower beyond :data:`TIE_M`)."""
        return tuple(k for k in self.compared if not _not_above(*self._figures(k)))

    def text(self) -> str:
        """One line: both figures of both models."""
        def um(v: float) -> str:
            return f'{v * 1e6:.1f} µm' if np.isfinite(v) else 'not estimable'
        c, n = self.calibrated, self.nominal
        split = self.better and not self._cv_better
        verdict = ('is not refused against' if split else
                   'predicts held-out poses better than' if self.better else
                   'does NOT predict held-out poses better than')
        labels = {'in_region': 'cross-validated where measured',
                  'other_region': 'cross-validated over held-out regions',
                  'working': 'expected TCP error over the working poses'}
        against = [labels[k] for k in self.favour_nominal]
        return (f'the calibration {verdict} the nominal robot with the placement registered: '
                f'cross-validated rms where measured {um(c.in_region_m)} (nominal '
                f'{um(n.in_region_m)}), over held-out regions of joint space '
                f'{um(c.other_region_m)} (nominal {um(n.other_region_m)}; {c.blocks or n.blocks} '
                f'regions, same folds), expected TCP error over the working poses '
                f'{um(self.calibrated_working_m)} (nominal {um(self.nominal_working_m)}); '
                f'predicted from the fit at the measured configurations '
                f'{um(self.calibrated_predicted_m)} (nominal {um(self.nominal_predicted_m)})'
                + (f'; {" and ".join(against)} favour the nominal robot, the prediction from '
                   'the fit the calibration' if split else ''))

    def to_dict(self) -> dict:
        """YAML-ready figures (m)."""
        def m(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None
        return {'better': self.better, 'compared': list(self.compared),
                # The cross-validated figures that favour the nominal robot: ``better`` with
                # some of them is the prediction from the fit outweighing them (not refused).
                'favour_nominal': list(self.favour_nominal),
                'elsewhere_worse': self.elsewhere_worse,
                'regions_worse': list(self.regions_worse()),
                'undetermined_where_it_works': self.undetermined_where_it_works,
                'calibrated': {**self.calibrated.to_dict(),
                               'working_poses_expected_rms_m': m(self.calibrated_working_m),
                               'working_poses_parameter_rms_m': m(
                                   self.calibrated_working_parameter_m),
                               'predicted_rms_m': m(self.calibrated_predicted_m)},
                'nominal': {**self.nominal.to_dict(),
                            'working_poses_expected_rms_m': m(self.nominal_working_m),
                            'predicted_rms_m': m(self.nominal_predicted_m),
                            'placement': {k: float(v) for k, v in
                                          self.nominal_placement.items()}},
                'text': self.text()}


def against_nominal(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                    nominal_model: MeasurementModel, nominal: CalibrationResult,
                    prior: Prior | None = None, nominal_prior: Prior | None = None,
                    seed: int = 0, free: list[str] | None = None,
                    nominal_free: list[str] | None = None) -> NominalComparison:
    """Compare the calibration ``result`` with the ``nominal`` fit (the placement only).

    Both are cross-validated (linear refits, each fit's prior kept) on the folds of the
    calibration, which keep the rank of the placement it contains; where those folds do not
    keep the nominal fit's rank, on its own. ``free``, ``nominal_free``: the free parameters
    of each fit (default: its estimated ones), for the error predicted from the fit. With
    several recordings each is also judged on its own rows, on the same folds
    (:func:`~kpi_calib_ros.core.diagnosis.recording_verdict.recording_comparisons`).
    """
    folds = validation_folds(model, data, result, prior, seed=seed)
    cal = region_validation(model, data, result, prior, seed=seed, pose_folds=folds)
    nom = region_validation(nominal_model, data, nominal, nominal_prior, seed=seed,
                            pose_folds=folds)
    nominal_folds = folds
    if not (np.isfinite(nom.in_region_m) and np.isfinite(nom.other_region_m)):
        nominal_folds = validation_folds(nominal_model, data, nominal, nominal_prior, seed=seed)
        nom = region_validation(nominal_model, data, nominal, nominal_prior, seed=seed,
                                pose_folds=nominal_folds)
    working, parameter = _working(model, data, result, prior)
    predicted = _predicted(model, data, result, free or list(result.estimated), prior, seed)
    nominal_predicted = _predicted(nominal_model, data, nominal,
                                   nominal_free or list(nominal.estimated), nominal_prior, seed)
    return NominalComparison(
        cal, nom, working, _working(nominal_model, data, nominal, nominal_prior)[0],
        predicted[0], nominal_predicted[0],
        recording_comparisons(model, data, result, prior, nominal_model, nominal,
                              nominal_prior, folds, nominal_folds), parameter,
        predicted[1], nominal_predicted[1])


def _predicted(model: MeasurementModel, data: Measurements, result: CalibrationResult,
               free: list[str], prior: Prior | None, seed: int
               ) -> tuple[float, tuple[float, float]]:
    """Predicted rms (m) of new measurements like the measured ones, and its 95 % interval.

    NaN (and a NaN interval) when not estimable.
    """
    none = float('nan'), (float('nan'), float('nan'))
    if result.dof <= 0:
        return none
    oos = out_of_sample_error(model, data, result, free, prior, seed,
                              domains=('like_measured',)).domains['like_measured']
    if not oos.estimable:
        return none
    return float(oos.rms_m), (float(oos.interval_m[0]), float(oos.interval_m[1]))


def _working(model: MeasurementModel, data: Measurements, result: CalibrationResult,
             prior: Prior | None) -> tuple[float, float]:
    """Rms over the working poses of the expected TCP error and its parameter part (m).

    NaN without a working pose.
    """
    errors = expected_tcp_error(model, data, honest_precision(result), prior=prior)
    values = np.asarray(errors.expected_tcp_error_m, float)
    part = np.asarray(errors.tcp_std_m, float)
    if not len(values):
        return float('nan'), float('nan')
    return float(np.sqrt(np.mean(values ** 2))), float(np.sqrt(np.mean(part ** 2)))

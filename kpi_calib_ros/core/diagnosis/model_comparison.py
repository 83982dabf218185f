"""Before/after adding effects: the numbers a person needs to trust the richer model.

:func:`compare_models` sets two fits side by side (the richer one's model holds the added
effects): rms, validation rms where the poses were measured and over held-out regions of
joint space, the added effects' parameters and the TCP std at the working poses.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kpi_calib_ros.core.diagnosis.model_selection import HeldOutGain, held_out_gain
from kpi_calib_ros.core.estimation.cross_validation import region_validation, validation_folds
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.precision import fit_prior, precision_statement
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel

__all__ = ['ModelComparison', 'compare_models', 'unconverged_warning']


@dataclass(frozen=True)
class ModelComparison:
    """Before/after adding effects: the numbers a person needs to trust the richer model."""

    effects: tuple[str, ...]
    rms_before_m: float
    rms_after_m: float
    validation_rms_before_m: float
    validation_rms_after_m: float
    p_value_before: float
    p_value_after: float
    effect_parameters: tuple[dict, ...]
    tcp_std_before_m: np.ndarray
    tcp_std_after_m: np.ndarray
    working_pose_names: tuple[str, ...] = field(default=())
    # A fit that did not converge, named with its stop: its figures are those of the last
    # iterate, not of a minimum, and the comparison says so.
    warnings: tuple[str, ...] = field(default=())
    # How the after-fit's std were obtained (core.estimation.precision.precision_statement).
    std_basis: str = ''
    # Cross-validated rms over held-out regions of joint space (whole k-means blocks of
    # poses, core.estimation.cross_validation.region_validation) before/after, on the
    # same folds; NaN where not estimable. ``validation_rms_*`` are the figures where the
    # poses were measured.
    other_region_rms_before_m: float = float('nan')
    other_region_rms_after_m: float = float('nan')
    region_blocks: int = 0
    # Held-out rms of each region block and each joint's range end, before/after, paired
    # (core.estimation.cross_validation.RegionValidation.held_out_folds_m), m.
    held_out_folds_before_m: tuple[float, ...] = ()
    held_out_folds_after_m: tuple[float, ...] = ()
    held_out_noise_m: tuple[float, ...] = ()  # each fold's rms spread by the noise alone
    # The richer model's gain over held-out regions and in each held-out fold, in units of
    # what the held-out noise can do (core.diagnosis.model_selection.held_out_gain).
    gain: HeldOutGain | None = None
    # Why an added effect would be extrapolated at the working poses
    # (core.diagnosis.effect_selection.extrapolated); never recommended then.
    extrapolated: tuple[str, ...] = ()
    # What the plausibility gate refuses in the richer fit that it did not in the smaller
    # (identify would call the calibration with the effect not valid); never recommended then.
    implausible: tuple[str, ...] = ()
    # Points excluded as outliers of the smaller model that the effect explains: both fits
    # and this comparison include them (indices into the given measurements).
    readmitted: tuple[int, ...] = ()
    # With several recordings, the rms over recordings held out whole (each one's placement
    # registered on its rows) before/after, and how many (the last folds above).
    other_recording_rms_before_m: float = float('nan')
    other_recording_rms_after_m: float = float('nan')
    recordings_held_out: int = 0

    @property
    def holds_elsewhere(self) -> bool:
        """Return whether the richer model holds over held-out regions of joint space.

        The test ``auto`` applies
        (:func:`~kpi_calib_ros.core.diagnosis.model_selection.holds_elsewhere`: better over
        held-out regions beyond noise, worse beyond noise in no held-out fold); only then is
        it recommended. Never when a fit did not converge (``warnings``): its cross-validated
        figures linearise a last iterate, not a minimum, as ``auto`` neither screens from nor
        adds such a fit.
        """
        if self.warnings or self.gain is None or self.extrapolated or self.implausible:
            return False
        return self.gain.holds()

    @property
    def worse_folds(self) -> tuple[int, int]:
        """(held-out folds the richer model predicts worse beyond noise, folds compared)."""
        if self.gain is None:
            return 0, 0
        return self.gain.worse, self.gain.compared


def compare_models(before: tuple[MeasurementModel, CalibrationResult],
                   after: tuple[MeasurementModel, CalibrationResult], data: Measurements,
                   folds: int = 0, seed: int = 0, prior: Prior | None = None,
                   balanced: bool = False) -> ModelComparison:
    """Rms, validation rms, effect parameters and TCP std before/after adding effects.

    ``after``'s model must contain the effects (its extra parameters are the
    effect parameters reported). The validation rms are those of ``folds`` folds of poses
    (where measured) and of folds that hold out whole regions of joint space, both models on
    the folds of ``after`` (which keep the rank of ``before``), every fold refitted with the
    fits' ``prior`` (``balanced``: balanced against the noise by the fits,
    :func:`~kpi_calib_ros.core.estimation.precision.fit_prior`). The richer model is judged
    alone (one choice: the held-out test at its level, :func:`held_out_gain`).
    """
    model_b, res_b = before
    model_a, res_a = after
    prior_b, prior_a = fit_prior(prior, res_b, balanced), fit_prior(prior, res_a, balanced)
    same = validation_folds(model_a, data, res_a, prior_a, folds, seed=seed)
    region_b = region_validation(model_b, data, res_b, prior_b, folds, seed=seed,
                                 pose_folds=same)
    region_a = region_validation(model_a, data, res_a, prior_a, folds, seed=seed,
                                 pose_folds=same)
    new = [e for e in model_a.effects if e.name not in {x.name for x in model_b.effects}]
    std = dict(zip(res_a.estimated, res_a.std))
    params = []
    dropped = {d.name: d.reason for d in res_a.dropped}
    for effect in new:
        for name, unit in zip(effect.parameter_names, effect.units):
            entry = {'name': name, 'value': res_a.value(name), 'unit': unit}
            if name in std:
                entry['std'] = float(std[name])
            else:
                entry['dropped'] = dropped.get(name, 'held at its start value (not free)')
            params.append(entry)
    return ModelComparison(
        effects=tuple(e.name for e in new),
        rms_before_m=res_b.rms_m, rms_after_m=res_a.rms_m,
        validation_rms_before_m=region_b.in_region_m,
        validation_rms_after_m=region_a.in_region_m,
        other_region_rms_before_m=region_b.other_region_m,
        other_region_rms_after_m=region_a.other_region_m,
        region_blocks=region_a.blocks,
        held_out_folds_before_m=region_b.held_out_folds_m,
        held_out_folds_after_m=region_a.held_out_folds_m,
        held_out_noise_m=region_a.held_out_noise_m,
        other_recording_rms_before_m=region_b.other_recording_m,
        other_recording_rms_after_m=region_a.other_recording_m,
        recordings_held_out=region_a.recordings,
        gain=held_out_gain(region_a, region_b),
        p_value_before=res_b.p_value, p_value_after=res_a.p_value,
        effect_parameters=tuple(params),
        tcp_std_before_m=_tcp_std(res_b),
        tcp_std_after_m=_tcp_std(res_a),
        working_pose_names=res_a.working_pose_names,
        warnings=tuple(unconverged_warning(res, which) for res, which in
                       ((res_b, 'before'), (res_a, 'after')) if not res.converged),
        std_basis=precision_statement(res_a.covariance_scale))


def _tcp_std(result: CalibrationResult) -> np.ndarray:
    """Return the (t, 3) standard deviations of the TCP at the working poses, m.

    (0, 3) for a cell without working poses (its covariance is then an empty array).
    """
    cov = np.reshape(result.tcp_covariance, (-1, 3, 3))
    return np.sqrt(np.diagonal(cov, axis1=1, axis2=2))


def unconverged_warning(result: CalibrationResult, which: str) -> str:
    """Say what a comparison with ``result``, a fit that did not converge, is worth."""
    return (f'the fit {which} did not converge ({result.message}): its figures are those of '
            'the last iterate, not of a minimum, and the comparison may favour the other '
            'side (identification.max_iterations / --max-iterations raises the limit)')

"""Measurement model: tracker points (eq. 3, 4), tracked 6-DoF poses, several recordings."""
from kpi_calib_ros.core.measurement.covariates import (
    DEFAULT_MAX_GAP_NS,
    DELTA_TEMPERATURE,
    REFERENCE_TEMPERATURE_C,
    TEMPERATURE_PREFIX,
    TemperatureSample,
    covariate_name,
    delta_temperature_name,
    interpolate,
    shift_temperature,
    temperature_covariates,
    with_covariates,
)
from kpi_calib_ros.core.measurement.data import Measurements, row_sigma
from kpi_calib_ros.core.measurement.effect_protocol import Effect, effect_inputs
from kpi_calib_ros.core.measurement.pose import (
    log3_expression,
    measured_rotation_input,
    noisy_rotations,
    pose_matrix,
    quaternion_from_rotation,
    rotation_exp,
    rotation_from_quaternion,
    rotation_from_rpy,
    rotation_residual_expression,
)
from kpi_calib_ros.core.measurement.pose_rows import with_rotation_rows
from kpi_calib_ros.core.measurement.recordings import (
    Contribution,
    Recording,
    combine,
    contributions,
    placed_model,
    recording_parameters,
    to_first_frame,
)
from kpi_calib_ros.core.measurement.replicates import SAME_POSE_TOLERANCE, pose_groups, same_pose
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import (
    noise_weights,
    unweighted,
    weighted_residuals,
    weighted_rows,
)

__all__ = [
    'Contribution', 'Recording', 'combine', 'contributions', 'placed_model',
    'recording_parameters', 'to_first_frame', 'DEFAULT_MAX_GAP_NS', 'DELTA_TEMPERATURE',
    'Effect', 'MeasurementModel', 'Measurements',
    'REFERENCE_TEMPERATURE_C', 'SAME_POSE_TOLERANCE', 'TEMPERATURE_PREFIX', 'TemperatureSample',
    'covariate_name', 'delta_temperature_name', 'effect_inputs', 'interpolate', 'log3_expression',
    'measured_rotation_input', 'noise_weights', 'noisy_rotations', 'pose_groups', 'pose_matrix',
    'quaternion_from_rotation', 'rotation_exp', 'rotation_from_quaternion', 'rotation_from_rpy',
    'rotation_residual_expression', 'row_sigma', 'same_pose', 'shift_temperature',
    'temperature_covariates', 'unweighted', 'weighted_residuals', 'weighted_rows',
    'with_covariates', 'with_rotation_rows',
]

"""Diagnosis: out-of-sample error, model and effect choice, candidate effects, validation.

Validation is on new data.
"""
from kpi_calib_ros.core.diagnosis.candidate_fit import CandidateFit
from kpi_calib_ros.core.diagnosis.cell_diagnosis import CellDiagnosis
from kpi_calib_ros.core.diagnosis.corrected_tcp import CorrectedTcp, corrected_tcp
from kpi_calib_ros.core.diagnosis.effect_selection import (
    MAX_EFFECTS,
    TRIALS,
    EffectChoice,
    EffectTrial,
    choose_effects,
    effect_start,
)
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.diagnosis.learned_residual import (
    CHOICE_ALPHA,
    INSIDE_DISTANCE,
    MIN_GAIN,
    LearnedResidual,
    ResidualChoice,
    ResidualPrediction,
    fit_learned_residual,
    fixed_kernel,
    residual_noise_scale,
)
from kpi_calib_ros.core.diagnosis.misfit import MisfitAnswer, Remedy, answer_misfit
from kpi_calib_ros.core.diagnosis.model_comparison import ModelComparison, compare_models
from kpi_calib_ros.core.diagnosis.model_selection import (
    DEFAULT_FOLDS,
    LEVELS,
    MODEL_CHOICES,
    PARSIMONY,
    ModelChoice,
    choose_model,
    cross_validated_level_rms,
    level_free,
)
from kpi_calib_ros.core.diagnosis.out_of_sample import (
    DOMAINS,
    NOT_ESTIMABLE,
    DomainError,
    OutOfSample,
    domain_configurations,
    measured_box,
    out_of_sample_error,
)
from kpi_calib_ros.core.diagnosis.periodic_search import (
    MAX_SEARCHED,
    Periodogram,
    periodic_candidates,
    periodograms,
    searched_cycles,
)
from kpi_calib_ros.core.diagnosis.residual_analysis import (
    BASIS_SIZES,
    HARMONICS,
    InputScore,
    PairScore,
    ResidualAnalysis,
    analyse_calibration,
    analyse_residuals,
)
from kpi_calib_ros.core.diagnosis.residual_bases import fourier_basis, spline_basis
from kpi_calib_ros.core.diagnosis.residual_inputs import ResidualInput, residual_inputs
from kpi_calib_ros.core.diagnosis.screening import Candidate, screen_effects
from kpi_calib_ros.core.diagnosis.validation import Validation, validate
from kpi_calib_ros.core.diagnosis.verdict import Diagnosis, diagnose, equivalent_joint_sigma
from kpi_calib_ros.core.estimation.cross_validation import validation_rms
from kpi_calib_ros.core.estimation.residuals import ResidualReport, residual_report

__all__ = [
    'BASIS_SIZES', 'CHOICE_ALPHA', 'Candidate', 'CandidateFit', 'CellDiagnosis', 'CorrectedTcp',
    'DEFAULT_FOLDS', 'DOMAINS', 'Diagnosis', 'DomainError', 'EffectChoice', 'EffectTrial',
    'HARMONICS', 'INSIDE_DISTANCE', 'InputScore', 'LEVELS', 'LearnedResidual', 'MAX_EFFECTS',
    'MAX_SEARCHED', 'MIN_GAIN', 'MODEL_CHOICES', 'MisfitAnswer', 'ModelChoice', 'ModelComparison',
    'NOT_ESTIMABLE', 'OutOfSample', 'PARSIMONY', 'PairScore', 'Periodogram', 'Remedy',
    'ResidualAnalysis', 'ResidualChoice', 'ResidualInput', 'ResidualPrediction', 'ResidualReport',
    'TRIALS', 'Validation', 'analyse_calibration', 'analyse_residuals', 'answer_misfit',
    'augmented_model', 'choose_effects', 'choose_model', 'compare_models', 'corrected_tcp',
    'cross_validated_level_rms', 'diagnose', 'domain_configurations', 'effect_start',
    'equivalent_joint_sigma', 'fit_learned_residual', 'fixed_kernel', 'fourier_basis',
    'level_free', 'measured_box', 'out_of_sample_error', 'periodic_candidates', 'periodograms',
    'residual_inputs', 'residual_noise_scale', 'residual_report', 'screen_effects',
    'searched_cycles', 'spline_basis', 'validate', 'validation_rms',
]

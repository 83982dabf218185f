"""Optimum experimental design (eq. 24): problem, criteria, constraints and algorithms.

The exchange algorithm and the NLP refinement.
"""
from kpi_calib_ros.core.design.cell import DesignCell
from kpi_calib_ros.core.design.constraints import (
    CandidateSet,
    DesignVerification,
    feasibility_function,
    flag_pairs,
    generate_candidates,
    scene_without,
    verify_design,
)
from kpi_calib_ros.core.design.criteria import (
    CRITERIA,
    NEGLIGIBLE_EFFECT,
    DesignProblem,
    build_problem,
    scales,
)
from kpi_calib_ros.core.design.exchange import (
    ConditionLoss,
    ExchangeResult,
    LogDetLoss,
    Loss,
    TraceLoss,
    exchange,
    information,
)
from kpi_calib_ros.core.design.nlp import NlpResult, solve_design_nlp
from kpi_calib_ros.core.design.optimum import (
    DESIGN_CRITERIA,
    DesignContext,
    DesignResult,
    DesignSettings,
    design_context,
    design_measurements,
)

__all__ = [
    'CRITERIA', 'CandidateSet', 'ConditionLoss', 'DESIGN_CRITERIA', 'DesignCell', 'DesignContext',
    'DesignProblem', 'DesignResult', 'DesignSettings', 'DesignVerification', 'ExchangeResult',
    'LogDetLoss', 'Loss', 'NEGLIGIBLE_EFFECT', 'NlpResult', 'TraceLoss', 'build_problem',
    'design_context', 'design_measurements', 'exchange', 'feasibility_function', 'flag_pairs',
    'generate_candidates', 'information', 'scales', 'scene_without', 'solve_design_nlp',
    'verify_design',
]

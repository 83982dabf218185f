"""Campaigns over time: sequential measurement and change detection."""
from kpi_calib_ros.core.campaigns.change_detection import (
    CHANGE_ALPHA,
    ChangeTest,
    ParameterShift,
    change_test,
)
from kpi_calib_ros.core.campaigns.sequential import (
    INITIAL_STARTS,
    MAX_HORIZON,
    MAX_MEASUREMENTS,
    MODEL_INADEQUATE,
    NESTED_FACTOR,
    PLAN_SWEEPS,
    REPLICATE_EVERY,
    TARGET_MET,
    CampaignSettings,
    CampaignStatus,
    SequentialCampaign,
    SimulatedRun,
    lack_of_fit,
    nested_order,
    plan_ahead,
    pure_error,
    sigma_upper_limit,
)

__all__ = [
    'CHANGE_ALPHA', 'CampaignSettings', 'CampaignStatus', 'ChangeTest', 'INITIAL_STARTS',
    'MAX_HORIZON', 'MAX_MEASUREMENTS', 'MODEL_INADEQUATE', 'NESTED_FACTOR', 'PLAN_SWEEPS',
    'ParameterShift', 'REPLICATE_EVERY', 'SequentialCampaign', 'SimulatedRun', 'TARGET_MET',
    'change_test', 'lack_of_fit', 'nested_order', 'plan_ahead', 'pure_error', 'sigma_upper_limit',
]

"""Campaigns over time: sequential measurement and change detection."""
from kpi_calib_ros.core.campaigns.change_detection import (
    CHANGE_ALPHA,
    ChangeTest,
    ParameterShift,
    change_test,
)
from kpi_calib_ros.core.campaigns.plan_order import PLAN_SWEEPS, nested_order, plan_ahead
from kpi_calib_ros.core.campaigns.sequential import (
    INITIAL_STARTS,
    MAX_HORIZON,
    NESTED_FACTOR,
    REPLICATE_EVERY,
    SequentialCampaign,
)
from kpi_calib_ros.core.campaigns.settings import (
    MAX_MEASUREMENTS,
    MODEL_INADEQUATE,
    TARGET_MET,
    CampaignSettings,
    CampaignStatus,
    SimulatedRun,
)
from kpi_calib_ros.core.campaigns.statistics import lack_of_fit, pure_error, sigma_upper_limit

__all__ = [
    'CHANGE_ALPHA', 'CampaignSettings', 'CampaignStatus', 'ChangeTest', 'INITIAL_STARTS',
    'MAX_HORIZON', 'MAX_MEASUREMENTS', 'MODEL_INADEQUATE', 'NESTED_FACTOR', 'PLAN_SWEEPS',
    'ParameterShift', 'REPLICATE_EVERY', 'SequentialCampaign', 'SimulatedRun', 'TARGET_MET',
    'change_test', 'lack_of_fit', 'nested_order', 'plan_ahead', 'pure_error', 'sigma_upper_limit',
]

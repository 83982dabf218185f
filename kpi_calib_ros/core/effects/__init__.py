"""Physical effects the geometric model lacks: the library and its special cases."""
from kpi_calib_ros.core.effects.effect_types import BoundEffect, EffectType
from kpi_calib_ros.core.effects.general import (
    LinkBending,
    PeriodicJointError,
    general_candidates,
    gravity_moment,
    link_bending,
    periodic_joint_error,
    periodic_kind,
)
from kpi_calib_ros.core.effects.gravity_compliance import (
    MassFreeCompliance,
    compliance_warnings,
    mass_free_compliance,
    mass_warning,
    massless_links,
    torque_regressor,
)
from kpi_calib_ros.core.effects.library import (
    BACKLASH_TORQUE_SCALE,
    LIBRARY,
    PLAY_GRID,
    PLAY_TORQUE_UNIT,
    THERMAL_EXPANSION_BOUND,
)
from kpi_calib_ros.core.effects.registry import (
    ARGUMENT_EFFECTS,
    CHAIN_EFFECTS,
    COVARIATE_CANDIDATES,
    ENTRY_POINT_GROUP,
    LINEAR_PLAY,
    available_effects,
    bind_effect,
    candidate_effects,
    implausible,
    parse_effect_spec,
    register_effect,
    resolve_effects,
    split_specs,
)
from kpi_calib_ros.core.effects.tilt import (
    MEASURED_TILT,
    MeasuredTilt,
    measured_tilt,
    tilt_candidates,
    tilt_covariates,
    tilt_sensors,
)

__all__ = [
    'ARGUMENT_EFFECTS', 'BACKLASH_TORQUE_SCALE', 'BoundEffect', 'CHAIN_EFFECTS',
    'COVARIATE_CANDIDATES', 'MEASURED_TILT', 'MeasuredTilt', 'measured_tilt', 'tilt_candidates',
    'tilt_covariates', 'tilt_sensors',
    'ENTRY_POINT_GROUP', 'EffectType', 'LIBRARY', 'LINEAR_PLAY', 'LinkBending',
    'MassFreeCompliance', 'PLAY_GRID', 'PLAY_TORQUE_UNIT', 'PeriodicJointError',
    'THERMAL_EXPANSION_BOUND', 'available_effects', 'bind_effect', 'candidate_effects',
    'compliance_warnings', 'general_candidates', 'gravity_moment', 'implausible', 'link_bending',
    'mass_free_compliance', 'mass_warning', 'massless_links', 'parse_effect_spec',
    'periodic_joint_error', 'periodic_kind', 'register_effect', 'resolve_effects', 'split_specs',
    'torque_regressor',
]

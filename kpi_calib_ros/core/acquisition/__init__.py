"""Acquisition: timestamped streams, pairing points with joint states, coupled controller joints."""
from kpi_calib_ros.core.acquisition.coupling import (
    JointCoupling,
    identity_coupling,
    mimic_coupling,
)
from kpi_calib_ros.core.acquisition.outcomes import (
    REJECTION_REASONS,
    PairedMeasurement,
    PairingResult,
    Rejection,
    stacked_rotations,
)
from kpi_calib_ros.core.acquisition.pairing import (
    EARLY_POINTS,
    INDEX_CACHE_SIZE,
    NAMES_KEPT,
    Pairer,
    pair_measurements,
)
from kpi_calib_ros.core.acquisition.reflector_frames import REFLECTOR_SEPARATOR, split_frame
from kpi_calib_ros.core.acquisition.streams import (
    JointSample,
    PointSample,
    checked_rotation,
    frozen_array,
    synthesize_streams,
)

__all__ = [
    'EARLY_POINTS', 'INDEX_CACHE_SIZE', 'JointCoupling', 'JointSample', 'NAMES_KEPT',
    'PairedMeasurement', 'Pairer', 'PairingResult', 'PointSample', 'REFLECTOR_SEPARATOR',
    'REJECTION_REASONS', 'Rejection', 'checked_rotation', 'frozen_array', 'identity_coupling',
    'mimic_coupling', 'pair_measurements', 'split_frame', 'stacked_rotations', 'synthesize_streams',
]

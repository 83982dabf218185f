"""Robot model: the URDF chain, error parameters, symbolic kinematics, DH report."""
from kpi_calib_ros.core.model.dh import (
    FOOT_LIMIT,
    PARALLEL_SIN,
    AxisPair,
    axis_lines,
    describe,
    dh_table,
)
from kpi_calib_ros.core.model.kinematics import (
    SymbolicChain,
    axis_rotation,
    error_rotation,
    homogeneous,
    link_poses,
    link_poses_function,
    nominal_fk_function,
    pose6,
    reflector_point,
    rot_x,
    rot_y,
    rot_z,
    rpy_matrix,
)
from kpi_calib_ros.core.model.parameters import (
    BASE_COMPONENTS,
    PLACEMENT_COMPONENTS,
    ParameterSet,
    geometric_parameters,
    reflector_prefixes,
)
from kpi_calib_ros.core.model.robot import MAX_URDF_ELEMENTS, ChainJoint, Payload, RobotModel
from kpi_calib_ros.core.model.robot_library import (
    DATA_DIR,
    KUKA_CONTROLLER_OFFSET,
    SHIPPED_ROBOTS,
    Industrial6RGeometry,
    industrial_6r_urdf,
    kr15_class,
    kr300_class,
    kr500_class,
    notional_manipulators,
    shipped_urdf_path,
    shipped_urdfs,
    ur_class_urdf,
)

__all__ = [
    'AxisPair', 'BASE_COMPONENTS', 'ChainJoint', 'DATA_DIR', 'FOOT_LIMIT', 'Industrial6RGeometry',
    'KUKA_CONTROLLER_OFFSET', 'MAX_URDF_ELEMENTS', 'PARALLEL_SIN', 'PLACEMENT_COMPONENTS',
    'ParameterSet', 'Payload', 'RobotModel', 'SHIPPED_ROBOTS', 'SymbolicChain', 'axis_lines',
    'axis_rotation', 'describe', 'dh_table', 'error_rotation', 'geometric_parameters',
    'homogeneous', 'industrial_6r_urdf', 'kr15_class', 'kr300_class', 'kr500_class', 'link_poses',
    'link_poses_function', 'nominal_fk_function', 'notional_manipulators', 'pose6',
    'reflector_point', 'reflector_prefixes', 'rot_x', 'rot_y', 'rot_z', 'rpy_matrix',
    'shipped_urdf_path', 'shipped_urdfs', 'ur_class_urdf',
]

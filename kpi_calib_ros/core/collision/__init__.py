"""Collision: capsules (eq. 20-22) and what works with them.

Their fit to URDF geometry, independent checks, and the link pairs to skip.
"""
from kpi_calib_ros.core.collision.capsule_fit import (
    capsules_from_urdf,
    collision_points,
    collision_vertices,
)
from kpi_calib_ros.core.collision.capsule_geometry import (
    capsule_volume,
    convex_hull_volume,
    enclosing_capsule,
    fit_capsules,
    outside_distance,
)
from kpi_calib_ros.core.collision.capsules import (
    BASE,
    BEAM,
    Capsule,
    CollisionScene,
    HalfSpace,
    capsule_margin,
    halfspace_margin,
    segment_distance,
)
from kpi_calib_ros.core.collision.check import (
    MeshCheck,
    Verification,
    mesh_collisions,
    verify_configuration,
)
from kpi_calib_ros.core.collision.matrix import (
    SKIPPED_KINDS,
    CollisionMatrix,
    PairClass,
    classify_link_pairs,
    link_transforms,
)

__all__ = [
    'BASE', 'BEAM', 'Capsule', 'CollisionMatrix', 'CollisionScene', 'HalfSpace', 'MeshCheck',
    'PairClass', 'SKIPPED_KINDS', 'Verification', 'capsule_margin', 'capsule_volume',
    'capsules_from_urdf', 'classify_link_pairs', 'collision_points', 'collision_vertices',
    'convex_hull_volume', 'enclosing_capsule', 'fit_capsules', 'halfspace_margin',
    'link_transforms', 'mesh_collisions', 'outside_distance', 'segment_distance',
    'verify_configuration',
]

"""Independent collision check of a configuration with coal (hpp-fcl).

The optimiser's margins come from the CasADi code in
:mod:`kpi_calib_ros.core.collision`; a returned design is verified here with
coal's own capsule and half-space distances, so a bug in one path cannot hide
a collision.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import coal
import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.collision import BASE, Capsule, CollisionScene, HalfSpace


@dataclass(frozen=True)
class Verification:
    """Independent (coal) check of one configuration.

    Attributes
    ----------
    distances : dict of str to float
        Signed distance per pair label (m).
    violated : list of str
        Labels whose distance is below the required clearance.
    """

    distances: dict[str, float]
    violated: list[str]

    @property
    def ok(self) -> bool:
        return not self.violated

    @property
    def min_distance(self) -> float:
        return min(self.distances.values(), default=float('inf'))


def _coal_capsule(a: np.ndarray, b: np.ndarray, radius: float) -> tuple[Any, Any]:
    """coal capsule (centred, along local z) and its pose for segment a-b."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    z = axis / length if length > 1e-15 else np.array([0.0, 0.0, 1.0])
    # Any rotation taking e_z to z: the capsule is symmetric about its axis.
    rot = pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), z).matrix()
    return coal.Capsule(radius, length), coal.Transform3s(rot, 0.5 * (a + b))


def verify_configuration(scene: CollisionScene, link_transforms: Mapping[str, Any],
                         tracker_point: Any, reflector_point: Any,
                         clearance: float = 0.0) -> Verification:
    """Signed distance of every pair of ``scene`` computed by coal, not CasADi.

    Parameters
    ----------
    scene : CollisionScene
        Pairs to check (the same labels as :attr:`CollisionScene.labels`).
    link_transforms : mapping of str to (4, 4) array_like
        Numeric poses of the scene's :attr:`~CollisionScene.frames` (m).
    tracker_point, reflector_point : (3,) array_like
        In the base frame (m).
    clearance : float
        A pair is violated when its distance is below this (m).

    Returns
    -------
    Verification
    """
    def world(cap: Capsule) -> tuple[np.ndarray, np.ndarray]:
        t = np.eye(4) if cap.frame == BASE else np.asarray(link_transforms[cap.frame], float)
        return tuple(t[:3, :3] @ np.asarray(p) + t[:3, 3] for p in (cap.a, cap.b))

    tracker = np.asarray(tracker_point, dtype=float).reshape(3)
    ray = np.asarray(reflector_point, dtype=float).reshape(3) - tracker
    length = float(np.linalg.norm(ray))
    keep = max(length - scene.beam_end_clearance, 0.0) / length if length > 1e-12 else 0.0
    beam = (tracker, tracker + keep * ray)
    request = coal.DistanceRequest()
    distances: dict[str, float] = {}
    for pair in scene._pairs:
        a1, b1 = beam if pair.first is None else world(pair.first)
        r1 = scene.beam_radius if pair.first is None else pair.first.radius
        shape1, pose1 = _coal_capsule(a1, b1, r1)
        obs = pair.second
        if isinstance(obs, HalfSpace):
            # coal's Halfspace(n, d) is the SOLID side n.x <= d: our obstacle side.
            shape2, pose2 = coal.Halfspace(np.array(obs.normal), obs.offset), coal.Transform3s()
        else:
            shape2, pose2 = _coal_capsule(*world(obs), obs.radius)
        distances[pair.label] = float(coal.distance(shape1, pose1, shape2, pose2, request,
                                                    coal.DistanceResult()))
    violated = [label for label, d in distances.items() if d < clearance]
    return Verification(distances, violated)

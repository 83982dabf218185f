"""Independent collision checks of configurations with coal (hpp-fcl).

The optimiser's margins come from the CasADi code in
:mod:`kpi_calib_ros.core.collision.capsules`; a returned design is verified here with
coal's own capsule and half-space distances (:func:`verify_configuration`), so a
bug in one path cannot hide a collision, and against the URDF's collision MESHES
themselves (:func:`mesh_collisions`), so a capsule that does not enclose its
link cannot either.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import coal
import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.collision.capsules import BASE, Capsule, CollisionScene, HalfSpace
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.model.robot import frame_id

__all__ = ['Verification', 'verify_configuration', 'MeshCheck', 'mesh_collisions']


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
        """Whether no pair is closer than its clearance."""
        return not self.violated

    @property
    def min_distance(self) -> float:
        """Smallest distance over the checked pairs (m); inf with no pair."""
        return min(self.distances.values(), default=float('inf'))


def _coal_capsule(a: np.ndarray, b: np.ndarray, radius: float) -> tuple[Any, Any]:
    """Return a coal capsule (centred, along local z) and its pose for segment a-b."""
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
    whole = (tracker, tracker + ray)  # against obstacles: to the reflector's centre
    request = coal.DistanceRequest()
    distances: dict[str, float] = {}
    for pair in scene._pairs:
        a1, b1 = ((whole if pair.whole_beam else beam) if pair.first is None
                  else world(pair.first))
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


@dataclass(frozen=True)
class MeshCheck:
    """Self-collision of configurations against the collision MESHES (Pinocchio + coal).

    Attributes
    ----------
    collisions : tuple of tuple of (str, str)
        Per configuration, the link pairs in contact (empty: collision-free).
    checked : tuple of (str, str)
        Link pairs tested.
    excluded : dict of (str, str) to str
        Link pairs not tested and why: ``'rigid'`` (no given joint between them), ``'adjacent'``
        (parent/child body) or ``'skipped'`` (in ``skip_pairs``).
    """

    collisions: tuple[tuple[tuple[str, str], ...], ...]
    checked: tuple[tuple[str, str], ...]
    excluded: dict[tuple[str, str], str]

    @property
    def colliding(self) -> list[int]:
        """Indices of the configurations with at least one collision."""
        return [k for k, pairs in enumerate(self.collisions) if pairs]


def _without_visuals(urdf_xml: str) -> str:
    """URDF without ``<visual>``: its meshes need not be found for a collision check."""
    root = ET.fromstring(urdf_xml)
    for link in root.findall('link'):
        for vis in list(link.findall('visual')):
            link.remove(vis)
    return ET.tostring(root, encoding='unicode')


def mesh_collisions(urdf_xml: str, package_dirs: Sequence[str], base_frame: str,
                    joint_names: Sequence[str], configurations: np.ndarray,
                    skip_pairs: Iterable[frozenset[str]] = ()) -> MeshCheck:
    """Link pairs in mesh contact, per configuration, by coal on the URDF collision geometry.

    Independent of the capsules: what is checked is the geometry the URDF ships
    (meshes and primitives). Bodies that no joint of ``joint_names`` moves apart
    (same joint, or only joints held at neutral between them, e.g. gripper fingers)
    and bodies on a parent/child joint pair are excluded, as are the link pairs of ``skip_pairs``
    (e.g. :meth:`CollisionMatrix.skip_pairs`); all are reported in ``excluded``.

    Parameters
    ----------
    urdf_xml : str
        URDF; collision mesh filenames absolute or findable through ``package_dirs``.
    package_dirs : sequence of str
        Passed to Pinocchio's mesh loader.
    base_frame : str
        Only bodies downstream of (or on) this frame's joint are checked.
    joint_names : sequence of str
        Names of the columns of ``configurations``; other joints stay neutral.
    configurations : (N, len(joint_names)) array
        Joint values (rad or m).
    skip_pairs : iterable of frozenset of two link names

    Returns
    -------
    MeshCheck

    Raises
    ------
    ValueError
        Unknown frame or joint, or ``configurations`` of the wrong shape.
    ConfigError
        A collision mesh cannot be loaded (key ``robot.package_dirs``).
    """
    xml = _without_visuals(urdf_xml)
    model = pin.buildModelFromXML(xml)
    try:
        geom = pin.buildGeomFromUrdfString(model, xml, pin.GeometryType.COLLISION,
                                           package_dirs=[str(d) for d in package_dirs])
    except (ValueError, RuntimeError, OSError) as exc:
        meshes = [m.get('filename') for c in ET.fromstring(xml).iter('collision')
                  for m in c.iter('mesh')]
        raise ConfigError('robot.package_dirs', f'collision meshes {meshes} cannot be loaded '
                          f'({exc}); searched {list(package_dirs)} and ROS_PACKAGE_PATH/'
                          'AMENT_PREFIX_PATH') from exc
    if not model.existFrame(base_frame):
        raise ValueError(f'base_frame {base_frame!r} is not in the URDF')
    q = np.atleast_2d(np.asarray(configurations, dtype=float))
    if q.shape[1] != len(joint_names):
        raise ValueError(f'configurations must have {len(joint_names)} columns '
                         f'({list(joint_names)}), got shape {q.shape}')
    unknown = [n for n in joint_names if not model.existJointName(n)]
    if unknown:
        raise ValueError(f'joints {unknown} are not in the URDF')
    idx_q = [model.joints[model.getJointId(n)].idx_q for n in joint_names]
    # A continuous joint is (cos θ, sin θ) in Pinocchio (nq 2, nv 1): the stock Kinova's
    # were refused here after a whole design had run.
    nq = [model.joints[model.getJointId(n)].nq for n in joint_names]
    if any(model.joints[model.getJointId(n)].nv != 1 or k not in (1, 2)
           for n, k in zip(joint_names, nq)):
        raise ValueError('only 1-DoF joints can be given (revolute, continuous, prismatic)')

    def pin_configuration(row: np.ndarray) -> np.ndarray:
        q_pin = pin.neutral(model)
        for idx, k, value in zip(idx_q, nq, row):
            if k == 2:
                q_pin[idx:idx + 2] = np.cos(value), np.sin(value)
            else:
                q_pin[idx] = value
        return q_pin

    def below(jid: int, root: int) -> bool:
        while jid != root and jid != 0:
            jid = model.parents[jid]
        return jid == root

    root = model.frames[frame_id(model, base_frame)].parentJoint
    objects = [(k, o) for k, o in enumerate(geom.geometryObjects) if below(o.parentJoint, root)]
    carrying = {o.parentJoint for _, o in objects}

    def body_parent(jid: int) -> int | None:
        """Nearest ancestor joint carrying geometry (MoveIt: geometry-less links merge)."""
        while jid != 0:
            jid = model.parents[jid]
            if jid in carrying:
                return jid
        return None

    given = {model.getJointId(n) for n in joint_names}

    def ancestry(jid: int) -> list[int]:
        chain = [jid]
        while jid != 0:
            jid = model.parents[jid]
            chain.append(jid)
        return chain

    def moving(j1: int, j2: int) -> bool:
        """Whether a given joint lies between the two bodies (others stay neutral)."""
        up1, up2 = ancestry(j1), ancestry(j2)
        path = set(up1).symmetric_difference(up2)  # joints below the common ancestor
        return bool(path & given)

    skip = {frozenset(p) for p in skip_pairs}
    link = {k: model.frames[o.parentFrame].name for k, o in objects}
    pair_links: list[tuple[str, str]] = []
    excluded: dict[tuple[str, str], str] = {}
    for i, (k1, o1) in enumerate(objects):
        for k2, o2 in objects[i + 1:]:
            names = (link[k1], link[k2])
            if not moving(o1.parentJoint, o2.parentJoint):
                reason = 'rigid'
            elif body_parent(o1.parentJoint) == o2.parentJoint or \
                    body_parent(o2.parentJoint) == o1.parentJoint:
                reason = 'adjacent'
            elif frozenset(names) in skip:
                reason = 'skipped'
            else:
                geom.addCollisionPair(pin.CollisionPair(k1, k2))
                pair_links.append(names)
                continue
            if names[0] != names[1]:
                excluded.setdefault(names, reason)
    data = model.createData()
    collisions = []
    for row in q:
        # Fresh geometry data per configuration: coal warm-starts GJK from the previous
        # query's result, and on the stock Baxter that made the verdict on a pose depend on
        # the poses checked before it (3 to 12 of 30 differed; a 13 mm overlap cleared).
        gdata = pin.GeometryData(geom)
        pin.computeCollisions(model, data, geom, gdata, pin_configuration(row), False)
        hit = {pair_links[c] for c, res in enumerate(gdata.collisionResults) if res.isCollision()}
        collisions.append(tuple(sorted(hit)))
    return MeshCheck(tuple(collisions), tuple(dict.fromkeys(pair_links)), excluded)

"""Collision geometry of a cell's robot, built only when a design needs it.

From the URDF and the cell file: collision meshes resolved the ROS way
(:mod:`kpi_calib_ros.io.resources`, the cell key ``robot.package_dirs``), capsules
fitted to every chain link without hand-given capsules (hand-given ones win), the
link pairs a design skips by a sampled collision matrix
(:mod:`kpi_calib_ros.core.collision.matrix`: adjacent, in collision at the default
configuration, always in collision) and the pairs of a fixed link (one no joint
moves, e.g. the base) with an obstacle it touches at rest (class ``fixed``: no
configuration can change them). :func:`mesh_check` then verifies designed
configurations against the MESHES with Pinocchio + coal, independently of the capsules.

Identification never calls this module: a URDF whose meshes cannot be found still
identifies.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.collision.capsule_fit import capsules_from_urdf
from kpi_calib_ros.core.collision.capsules import (
    Capsule,
    HalfSpace,
    capsule_margin,
    halfspace_margin,
)
from kpi_calib_ros.core.collision.check import MeshCheck, mesh_collisions
from kpi_calib_ros.core.collision.matrix import (
    CollisionMatrix,
    classify_link_pairs,
    link_transforms,
)
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.model.robot import RobotModel, frame_id
from kpi_calib_ros.io.resources import resolve_mesh_uris

# Random configurations of the sampled collision matrix (MoveIt's setup assistant
# uses 10 000 on a whole robot; 2000 classify an arm's pairs in about a second).
MATRIX_SAMPLES = 2000
MATRIX_SEED = 0
_CACHE: dict[Any, 'RobotGeometry'] = {}
_CACHE_SIZE = 4


@dataclass(frozen=True)
class RobotGeometry:
    """Robot capsules and the pairs a design skips, with where each came from.

    Attributes
    ----------
    capsules : tuple of Capsule
        Robot capsules in their link frames (m): the cell file's first, then the fitted ones.
    fitted_links : tuple of str
        Chain links whose capsules were fitted to the URDF collision geometry. Links off
        the chain but carried by a chain link (a hand, gripper fingers at their neutral
        position, a tool) are always fitted and carried by that link's frame.
    matrix : CollisionMatrix
        Sampled classes of the link pairs.
    fixed_pairs : tuple of (str, str)
        (fixed link, obstacle) pairs in contact at rest, skipped as class ``fixed``.
    urdf_xml : str
        The URDF with its collision mesh URIs resolved to absolute paths.
    has_meshes : bool
        Whether the URDF has collision meshes (then :func:`mesh_check` applies).
    n_given : int
        The first ``n_given`` of :attr:`capsules` come from the cell file.
    bare_links : tuple of str
        Chain links with no capsule in the cell file and no ``<collision>`` in the URDF:
        no body, so not checked for collisions (give capsules in the cell file if they
        have one).
    """

    capsules: tuple[Capsule, ...]
    fitted_links: tuple[str, ...]
    matrix: CollisionMatrix
    fixed_pairs: tuple[tuple[str, str], ...]
    urdf_xml: str
    has_meshes: bool
    n_given: int = 0
    bare_links: tuple[str, ...] = ()

    def skip_pairs(self) -> set[frozenset[str]]:
        """Link/obstacle pairs a design leaves out (besides ``collision.ignore_pairs``)."""
        return self.matrix.skip_pairs() | {frozenset(p) for p in self.fixed_pairs}

    def summary(self) -> dict[str, Any]:
        """YAML-ready: every robot capsule with its source, every skipped pair with its class."""
        skipped = self.matrix.summary() + [{'links': list(p), 'class': 'fixed', 'fraction': None}
                                           for p in self.fixed_pairs]
        doc: dict[str, Any] = {
            'capsules': [{'name': c.name, 'link': c.frame, 'a': [round(v, 6) for v in c.a],
                          'b': [round(v, 6) for v in c.b], 'radius': round(c.radius, 6),
                          'source': 'cell' if k < self.n_given else 'fitted'}
                         for k, c in enumerate(self.capsules)],
            'skipped_pairs': skipped,
            'matrix_samples': self.matrix.samples, 'matrix_seed': self.matrix.seed,
        }
        if self.bare_links:
            doc['links_without_collision_geometry'] = list(self.bare_links)
        return doc

    def summary_lines(self) -> list[str]:
        """The summary as readable lines for stdout."""
        doc = self.summary()
        lines = [f'  robot capsules ({len(self.capsules) - self.n_given} fitted to the URDF '
                 f'collision geometry, {self.n_given} from the cell file):']
        lines += [f"    {c['name']} on {c['link']} ({c['source']}): a {c['a']} b {c['b']} "
                  f"r {c['radius']} m" for c in doc['capsules']]
        if self.bare_links:
            lines.append(f'  links without collision geometry in the URDF, not checked for '
                         f'collisions (give capsules in the cell file if they have a body): '
                         f'{list(self.bare_links)}')
        lines.append(f"  skipped pairs ({len(doc['skipped_pairs'])}, sampled over "
                     f'{self.matrix.samples} configurations):')
        lines += [f"    {p['links'][0]} ~ {p['links'][1]}: {p['class']}"
                  + ('' if p['fraction'] is None else f" (in collision in {p['fraction']:.0%})")
                  for p in doc['skipped_pairs']]
        return lines


def _has_collision_meshes(urdf_xml: str) -> bool:
    root = ET.fromstring(urdf_xml)
    return any(True for col in root.iter('collision') for _ in col.iter('mesh'))


def robot_geometry(robot: RobotModel, urdf_xml: str, given: Sequence[Capsule],
                   obstacles: Sequence[Capsule | HalfSpace], package_dirs: Sequence[str] = (),
                   base_dir: str | None = None, referenced_by: str = 'the URDF'
                   ) -> RobotGeometry:
    """Capsules and skipped pairs of ``robot`` (cached: the same inputs are built once).

    Parameters
    ----------
    robot : RobotModel
    urdf_xml : str
        The URDF as given (``package://`` URIs allowed).
    given : sequence of Capsule
        Hand-given capsules (cell file); their links are not fitted.
    obstacles : sequence of Capsule or HalfSpace
        Obstacles in the base frame (for the ``fixed`` class).
    package_dirs : sequence of str
        Extra package search directories (``robot.package_dirs``), relative to ``base_dir``.
    base_dir : str, optional
        Folder of the cell file.
    referenced_by : str
        Where the URDF came from, for error messages.

    Raises
    ------
    ConfigError
        A collision mesh cannot be found (key ``robot.package_dirs``; the message names
        the URI, the URDF and every path tried) or a link has no usable collision geometry.
    """
    key = (urdf_xml, robot.base_frame, robot.tip_frame, tuple(given), tuple(obstacles),
           tuple(package_dirs), base_dir)
    if key in _CACHE:
        return _CACHE[key]
    links = robot.link_names
    have = {c.frame for c in given}
    to_fit = [link for link in links if link not in have]
    has_meshes = _has_collision_meshes(urdf_xml)
    try:
        resolved = resolve_mesh_uris(urdf_xml, package_dirs, base_dir,
                                     referenced_by=referenced_by) if has_meshes else urdf_xml
    except ConfigError:
        if to_fit:
            raise
        # Every link has hand-given capsules: the meshes are not needed for the design.
        resolved, has_meshes = urdf_xml, False
    fitted = capsules_from_urdf(resolved, to_fit) if to_fit else []
    attached = _attached_capsules(robot, resolved)
    capsules = tuple(given) + tuple(fitted) + tuple(attached)
    q_default = robot.middle_configuration()
    matrix = classify_link_pairs(robot, capsules, samples=MATRIX_SAMPLES, seed=MATRIX_SEED,
                                 q_default=q_default)
    covered = {c.frame for c in fitted}
    geometry = RobotGeometry(capsules, tuple(dict.fromkeys(c.frame for c in fitted)), matrix,
                             _fixed_pairs(robot, capsules, obstacles, q_default), resolved,
                             has_meshes, len(given),
                             tuple(link for link in to_fit if link not in covered))
    if len(_CACHE) >= _CACHE_SIZE:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[key] = geometry
    return geometry


def _attached_capsules(robot: RobotModel, urdf_xml: str) -> list[Capsule]:
    """Capsules of the links off the chain that a chain link carries, in its frame.

    A link is carried by the chain link whose joint is its nearest chain ancestor (fixed
    joints and joints not on the chain, e.g. gripper fingers, held at their neutral
    position, as the mesh check holds them); links upstream of the first chain joint
    are carried by the base link. Names are the carried link's (``panda_hand``).
    """
    model = robot.pin_model
    chain = robot.link_names
    root = ET.fromstring(urdf_xml)
    with_geometry = {link.get('name') for link in root.findall('link') if link.find('collision')
                     is not None}
    joint_of = {model.getJointId(j.name): j.child_link for j in robot.joints}
    base_link = chain[0]
    carried: dict[str, str] = {}
    for frame in model.frames:
        name = frame.name
        if frame.type != pin.FrameType.BODY or name in chain or name not in with_geometry:
            continue
        jid = frame.parentJoint
        while jid != 0 and jid not in joint_of:
            jid = model.parents[jid]
        carrier = joint_of.get(jid, base_link)
        if jid == 0 and model.frames[frame_id(model, robot.base_frame)].parentJoint != 0:
            continue  # upstream of a base that sits on a joint: not part of this arm
        carried[name] = carrier
    if not carried:
        return []
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    out = []
    for cap in capsules_from_urdf(urdf_xml, list(carried)):
        carrier = carried[cap.frame]
        rel = (data.oMf[model.getFrameId(carrier, pin.BODY)].inverse()
               * data.oMf[model.getFrameId(cap.frame, pin.BODY)])
        a, b = (rel.rotation @ np.asarray(p) + rel.translation for p in (cap.a, cap.b))
        out.append(Capsule(cap.name, carrier, a, b, cap.radius))
    return out


def _fixed_pairs(robot: RobotModel, capsules: Sequence[Capsule],
                 obstacles: Sequence[Capsule | HalfSpace], q_default: np.ndarray
                 ) -> tuple[tuple[str, str], ...]:
    """(link, obstacle) pairs in contact where the link is one no chain joint moves."""
    links = [c.frame for c in capsules]
    if not links or not obstacles:
        return ()
    frames = list(dict.fromkeys(links))
    rng = np.random.default_rng(MATRIX_SEED)
    q = np.vstack([q_default, robot.sample_configurations(rng, 3)])
    poses = link_transforms(robot, q, frames)
    fixed = {f for j, f in enumerate(frames) if np.allclose(poses[:, j], poses[0, j], atol=1e-12)}
    out: list[tuple[str, str]] = []
    for cap in capsules:
        if cap.frame not in fixed:
            continue
        t = poses[0, frames.index(cap.frame)]
        a, b = (t[:3, :3] @ np.asarray(p) + t[:3, 3] for p in (cap.a, cap.b))
        for obs in obstacles:
            if isinstance(obs, HalfSpace):
                margin = float(halfspace_margin(a, b, cap.radius, obs.normal, obs.offset))
            else:
                margin = float(capsule_margin(a, b, cap.radius, obs.a, obs.b, obs.radius))
            if margin < 0 and (cap.frame, obs.name) not in out:
                out.append((cap.frame, obs.name))
    return tuple(out)


def mesh_check(geometry: RobotGeometry, robot: RobotModel, configurations: np.ndarray,
               ignore_pairs: Sequence[frozenset[str]] = ()) -> tuple[MeshCheck, list[tuple[
                   str, str]]]:
    """Self-collision of ``configurations`` against the collision MESHES (coal).

    Pairs skipped: parent/child bodies and rigidly joined ones (by
    :func:`~kpi_calib_ros.core.collision.check.mesh_collisions`), pairs whose MESHES
    touch at the default configuration (the middle of the joint ranges: overlap by
    construction, judged on the meshes, not the capsules) and ``ignore_pairs``.

    Returns
    -------
    (MeshCheck, list of (str, str))
        The check and the link pairs skipped as touching at the default configuration.
    """
    q = np.vstack([robot.middle_configuration(), np.atleast_2d(configurations)])
    first = mesh_collisions(geometry.urdf_xml, (), robot.base_frame, robot.joint_names, q[:1],
                            skip_pairs=ignore_pairs)
    at_default = list(first.collisions[0])
    skip = set(ignore_pairs) | {frozenset(p) for p in at_default}
    check = mesh_collisions(geometry.urdf_xml, (), robot.base_frame, robot.joint_names, q[1:],
                            skip_pairs=skip)
    return check, at_default

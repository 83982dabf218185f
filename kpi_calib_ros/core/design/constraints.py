"""Where a measurement configuration may be: constraints of eq. (24b) and their checks.

A configuration is feasible when it is within the joint limits, the tracker
sees the reflector at an incidence angle ≤ ``max_incidence`` (eq. 4) and every
capsule pair of the :class:`CollisionScene` is apart (eq. 20-22, with the laser
beam as a thin capsule for the line of sight).

:func:`feasibility_function` writes the incidence and capsule margins once in
CasADi: the candidate filter and the NLP constraints use it. :func:`verify_design`
checks a finished design independently of that code: link poses from Pinocchio,
distances from coal, the incidence angle from Pinocchio's tip pose.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from kpi_calib_ros.core.collision.capsules import CollisionScene
from kpi_calib_ros.core.collision.check import verify_configuration
from kpi_calib_ros.core.design.cell import DesignCell
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.model.kinematics import reflector_point
from kpi_calib_ros.core.simulation import measurable_batch, sampling_bounds

__all__ = [
    'feasibility_function', 'CandidateSet', 'generate_candidates', 'flag_pairs', 'scene_without',
    'DesignVerification', 'verify_design',
]


def feasibility_function(cell: DesignCell, scene: CollisionScene | None) -> ca.Function:
    """CasADi ``q (n) -> [cos β; margins (count)]`` at the nominal parameters.

    The incidence cosine (eq. 4) comes first, then the scene's capsule margins
    (m) in :attr:`CollisionScene.labels` order. Used for the candidate filter
    and as the NLP constraints, so both see exactly the same expressions.
    """
    model = cell.model
    q = ca.SX.sym('q', cell.robot.n_joints)
    p = ca.DM(model.params.nominal)
    out = [model.incidence_cos_expression(p, q)]
    if scene is not None and scene.count:
        poses, tip = model.chain.link_poses(p, q)
        reflector = reflector_point(tip, model.chain.reflector(p))
        out.append(scene.margins(poses, ca.DM(cell.tracker_in_base[:3, 3]), reflector))
    return ca.Function('feasibility', [q], [ca.vertcat(*out)])


@dataclass(frozen=True)
class CandidateSet:
    """Random configurations satisfying every constraint, with draw statistics.

    ``violation_rate`` maps each pair label to the fraction of measurable random
    draws in which it was violated; ``flagged`` lists pairs at or above the
    flag threshold (nearly always in collision: usually overlapping capsules).
    """

    configurations: np.ndarray
    draws: int
    measurable: int
    violation_rate: dict[str, float]
    flagged: tuple[str, ...]


def generate_candidates(cell: DesignCell, scene: CollisionScene | None, count: int,
                        rng: np.random.Generator, clearance: float = 0.0,
                        incidence_clearance: float = 0.0, flag_threshold: float = 0.98,
                        max_draws: int = 20_000_000, batch: int = 20_000) -> CandidateSet:
    """``count`` configurations uniform in the joint ranges that satisfy all constraints.

    Raises
    ------
    ConfigError
        Too few feasible draws; names the pairs that are violated nearly always.
    """
    model = cell.model
    cos_max = np.cos(cell.max_incidence - incidence_clearance)
    fun = feasibility_function(cell, scene)
    labels = scene.labels if scene is not None else []
    violated = np.zeros(len(labels))
    found, n_found, drawn, measurable = [], 0, 0, 0
    while n_found < count and drawn < max_draws:
        q = measurable_batch(model, model.params.nominal, rng, batch, cos_max)
        drawn += batch
        measurable += len(q)
        if len(q) and labels:
            margins = np.array(fun.map(len(q))(q.T))[1:].T
            violated += np.sum(margins < clearance, axis=0)
            q = q[np.all(margins >= clearance, axis=1)]
        if cell.accept is not None and len(q):
            q = q[np.asarray(cell.accept(q), bool)]
        found.append(q)
        n_found += len(q)
        # Give up early when the feasible rate cannot reach ``count`` within max_draws.
        if drawn * count > max_draws * max(n_found, 0.05 * count):
            break
    if not measurable:
        raise ConfigError('reflector.max_incidence', f'no pose of {drawn} drawn in the joint '
                          'ranges sees the reflector within its incidence limit '
                          f'{cell.max_incidence:.3g} rad ({np.degrees(cell.max_incidence):.3g}°) '
                          'from the tracker: raise it to what the reflector takes (a 1.5-inch '
                          'SMR about 0.52 rad), or check reflector.axis (tip frame) and '
                          'tracker.base_in_tracker')
    rate = {lab: float(v / max(measurable, 1)) for lab, v in zip(labels, violated)}
    flagged = tuple(lab for lab, r in rate.items() if measurable and r >= flag_threshold)
    if n_found < count:
        hint = (f'; pairs violated in nearly every measurable pose: {list(flagged)} -- add them '
                'to collision.ignore_pairs if they never really collide, or set '
                'design.ignore_flagged: true') if flagged else ''
        raise ConfigError('design.candidates', f'only {n_found} of {count} feasible poses in '
                          f'{drawn} draws ({measurable} measurable){hint}')
    return CandidateSet(np.vstack(found)[:count], drawn, measurable, rate, flagged)


def flag_pairs(cell: DesignCell, scene: CollisionScene, rng: np.random.Generator,
               samples: int = 400, threshold: float = 0.98) -> dict[str, float]:
    """Pairs of ``scene`` violated in at least ``threshold`` of measurable random poses.

    Such pairs almost always are capsules that overlap by construction (a
    fitted capsule reaching through a short link); they make a design
    impossible and should be in ``collision.ignore_pairs``.
    """
    model = cell.model
    cos_max = np.cos(cell.max_incidence)
    found, n = [], 0
    for _ in range(200):
        q = measurable_batch(model, model.params.nominal, rng, 5000, cos_max)
        found.append(q)
        n += len(q)
        if n >= samples:
            break
    q = np.vstack(found)
    if not len(q) or not scene.count:
        return {}
    margins = np.array(feasibility_function(cell, scene).map(len(q))(q.T))[1:].T
    rate = np.mean(margins < 0.0, axis=0)
    return {lab: float(r) for lab, r in zip(scene.labels, rate) if r >= threshold}


def scene_without(scene: CollisionScene, labels: tuple[str, ...]) -> CollisionScene:
    """Return the same scene with the pairs ``'a~b'`` in ``labels`` ignored."""
    extra = {frozenset(lab.split('~')) for lab in labels}
    return CollisionScene(scene.robot_capsules, scene.obstacles, scene.chain_links,
                          ignore_pairs=scene.ignore_pairs | extra,
                          beam_radius=scene.beam_radius,
                          beam_end_clearance=scene.beam_end_clearance)


# ---------------------------------------------------------------------- verifier
@dataclass(frozen=True)
class DesignVerification:
    """Independent check of every configuration of a design.

    Attributes
    ----------
    ok : bool
        No violation at all.
    violations : tuple of str
        One readable line per violated constraint, e.g.
        ``'configuration 3: link_2~car_body -0.0041 m'``.
    min_margin : (N,) ndarray
        Smallest coal distance over the scene's pairs per configuration (m).
    incidence_deg : (N,) ndarray
        Incidence angle between beam and reflector axis per configuration.
    constraint_count : int
        Constraints per configuration: capsule pairs + incidence (+ 2 n joint bounds
        are variable bounds, not counted).
    """

    ok: bool
    violations: tuple[str, ...]
    min_margin: np.ndarray
    incidence_deg: np.ndarray
    constraint_count: int


def verify_design(cell: DesignCell, scene: CollisionScene | None, q: np.ndarray,
                  max_incidence: float | None = None) -> DesignVerification:
    """Check joint limits, incidence and every capsule pair of each configuration.

    Parameters
    ----------
    cell : DesignCell
    scene : CollisionScene or None
        Pairs to check (None: no collision check).
    q : (N, n) ndarray
        Configurations in chain order (rad).
    max_incidence : float, optional
        Largest admissible incidence angle (rad); default the cell's.
    """
    robot = cell.robot
    q = np.atleast_2d(q)
    limit = cell.max_incidence if max_incidence is None else max_incidence
    tracker = cell.tracker_in_base[:3, 3]
    lower, upper = sampling_bounds(cell.model)
    violations: list[str] = []
    margins, angles = np.full(len(q), np.inf), np.zeros(len(q))
    for i, qi in enumerate(q):
        poses, tip = robot.pin_link_poses(qi)  # Pinocchio, not the optimiser's CasADi chain
        reflector = reflector_point(tip, cell.reflector_offset)
        beam = (tracker - reflector) / np.linalg.norm(tracker - reflector)
        axis = tip[:3, :3] @ cell.reflector_axis
        angles[i] = np.degrees(np.arccos(np.clip(axis @ beam / np.linalg.norm(axis), -1, 1)))
        if angles[i] > np.degrees(limit) + 1e-9:
            violations.append(f'configuration {i}: incidence {angles[i]:.2f} deg > '
                              f'{np.degrees(limit):.2f} deg')
        for j in np.flatnonzero((qi < lower - 1e-9) | (qi > upper + 1e-9)):
            violations.append(f'configuration {i}: {robot.joint_names[j]} = {qi[j]:.4f} rad '
                              f'outside [{lower[j]:.4f}, {upper[j]:.4f}]')
        off = robot.mimic_residual(qi)
        for j in np.flatnonzero(off > 1e-9):
            violations.append(f'configuration {i}: mimic joint {robot.joint_names[j]} is '
                              f'{off[j]:.3g} off its relation to {robot.joints[j].mimic}')
        if scene is not None and scene.count:
            check = verify_configuration(scene, poses, tracker, reflector)
            margins[i] = check.min_distance
            violations += [f'configuration {i}: {lab} {check.distances[lab]:.4f} m'
                           for lab in check.violated]
    count = 1 + (scene.count if scene is not None else 0)
    return DesignVerification(not violations, tuple(violations), margins, angles, count)

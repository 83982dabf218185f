"""General effects for a misfit no named effect explains: periodic joint errors, link bending.

Both still mean something physical, and both go through the diagnosis's screen,
plausibility check and before/after like the library (:mod:`kpi_calib_ros.core.effects.registry`)::

    periodic_joint_error:<joint>:k=<k>   δq_j = a · sin k q_j + b · cos k q_j   a, b  rad
    link_bending:<joint>                 the frame of <joint> turns by c_u·M_u about u
                                         and c_v·M_v about v        c_u, c_v  rad/(N m)

**Periodic joint error.** Gear stages, harmonic drives and encoders make joint-angle
errors periodic in the joint angle at 10–30 and more cycles per revolution (k, an integer,
a constant of the effect, not a parameter); ``cyclic_joint_error`` (k = 1) and
``cyclic_joint_error_h2`` (k = 2) are its named first harmonics. The diagnosis finds k
from the residuals (:mod:`kpi_calib_ros.core.diagnosis.periodic_search`). Parameters
``periodic_joint_error.<joint>.k<k>.a`` and ``.b``.

**Link bending.** The links beyond joint j load it with the static gravity moment
M_j = Σ_k (p_k − o_j) × m_k a (a = +9.81 m/s² up, the holding convention of
``joint_compliance``; masses and centres of mass from the URDF's ``<inertial>`` and the
cell's payload, nominal geometry). Its component along the axis is the gravity torque
(which the joint's compliance answers); the two components perpendicular to the axis bend
the link (and tilt the joint's bearings). The effect turns joint j's frame, after its
motion, by c_u·M_u about u and c_v·M_v about v, u and v the link frame's axes perpendicular
to the joint axis (M in that frame). A link that sags along gravity turns against the
holding moment: physical compliances are negative, c = −1/k with bending stiffnesses of
industrial links and bearings k ≈ 1e4 … 1e7 N m/rad (|c| ≤ 1e-4 rad/(N m) plausible).
Parameters ``link_bending.<joint>.c<u>``, ``.c<v>`` (``cx``, ``cy`` for a z axis).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.effects.registry import (
    ARGUMENT_EFFECTS,
    CHAIN_EFFECTS,
    BoundEffect,
    EffectType,
)
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.payload import PAYLOAD_COM, PAYLOAD_MASS
from kpi_calib_ros.core.model.kinematics import SymbolicChain, axis_rotation
from kpi_calib_ros.core.model.parameters import geometric_parameters
from kpi_calib_ros.core.model.robot import RobotModel, frame_id

PERIODIC = 'periodic_joint_error'
BENDING = 'link_bending'
MAX_CYCLES = 200  # cycles per revolution a spec may name
HOLDING = np.array([0.0, 0.0, 9.81])  # m/s², URDF root frame: the force per kg that holds
AXES = 'xyz'


# ------------------------------------------------------------ periodic joint error
@dataclass(frozen=True)
class PeriodicJointError(BoundEffect):
    """δq_j = a·sin(k q_j) + b·cos(k q_j) at ``cycles`` = k cycles per revolution."""

    cycles: int = 1

    def __post_init__(self) -> None:
        """Name the effect and its parameters after the joint and the number of cycles k."""
        super().__post_init__()
        object.__setattr__(self, 'name', f'{PERIODIC}:{self.joint}:k={self.cycles}')
        object.__setattr__(self, 'parameter_names', tuple(
            f'{PERIODIC}.{self.joint}.k{self.cycles}.{s}' for s in self.kind.parameters))


@functools.lru_cache(maxsize=None)
def periodic_kind(cycles: int) -> EffectType:
    """Return the effect type of a periodic joint error at ``cycles`` cycles per revolution.

    One object per k, so effects bound from the same spec compare equal.
    """
    k = int(cycles)

    def correction(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX) -> ca.SX:
        return theta[0] * ca.sin(k * q_j) + theta[1] * ca.cos(k * q_j)

    return EffectType(
        PERIODIC, ('a', 'b'), ('rad', 'rad'), correction, typical=(1e-4, 1e-4),
        joint_kinds=('revolute', 'continuous'), plausible=(5e-3, 5e-3), general=True,
        description=f'joint-angle error periodic at {k} cycles per revolution, '
                    f'a·sin {k}q + b·cos {k}q (a gear stage, a harmonic drive, an encoder)',
        hint=f'spread {{joint}} over its range with several poses in each 1/{k} of a '
             'revolution',
        signature=f'{k}-cycle-per-revolution error of {{joint}}')


# Periodic effects of the library and their frequency (cycles per revolution).
NAMED_CYCLES = {'cyclic_joint_error': 1, 'cyclic_joint_error_h2': 2}


def periodic_cycles(effect: BoundEffect) -> int | None:
    """Return the cycles per revolution k of a periodic joint error.

    ``periodic_joint_error`` or its named harmonics ``cyclic_joint_error`` k = 1,
    ``cyclic_joint_error_h2`` k = 2; None for any other effect.
    """
    if isinstance(effect, PeriodicJointError):
        return effect.cycles
    return NAMED_CYCLES.get(effect.kind.name)


def frequency_resolution(q_j: np.ndarray) -> float:
    """Resolution (cycles per revolution) of a frequency search over the angles ``q_j`` (rad).

    2π/Δq, Δq the measured range of the joint: over that range sin(k q) and sin(k' q) with
    |k − k'| below it differ by less than one period, so the data see them as one peak
    (a second frequency that close is the first one aliased, not a second gear stage).
    Infinite when the joint does not move.
    """
    span = float(np.ptp(np.asarray(q_j, float))) if len(q_j) else 0.0
    return 2.0 * np.pi / span if span > 0 else float('inf')


def aliased_frequency(effect: BoundEffect, others: Any, q_j: np.ndarray) -> str:
    """Why the periodic ``effect`` is refused next to the periodic ``others`` of its joint.

    '' when ``effect`` is not periodic or its frequency is at least the resolution
    (:func:`frequency_resolution`) away from every periodic effect of ``others`` on the same
    joint.
    """
    k = periodic_cycles(effect)
    if k is None:
        return ''
    resolution = frequency_resolution(q_j)
    for other in others:
        if not isinstance(other, BoundEffect):
            continue
        k0 = periodic_cycles(other)
        if k0 is None or other.joint != effect.joint or other.name == effect.name:
            continue
        if abs(k - k0) < resolution:
            return (f'{effect.name} is within the frequency resolution of {other.name}: '
                    f'|{k} - {k0}| < 2π/Δq = {resolution:.3g} cycles per revolution '
                    f'(Δq = {2 * np.pi / resolution:.3g} rad measured on {effect.joint}); '
                    'over that range the two are one aliased peak, not two gear stages. '
                    f'To tell them apart, measure {effect.joint} over a range of at least '
                    f'2π/|{k} - {k0}| = {2 * np.pi / max(abs(k - k0), 1e-9):.3g} rad')
    return ''


def periodic_joint_error(robot: RobotModel, joint: str | None, cycles: int | str,
                         key: str = 'effects') -> PeriodicJointError:
    """Bind ``periodic_joint_error:<joint>:k=<cycles>`` to ``robot``.

    Raises
    ------
    ConfigError
        Unknown or prismatic joint, or k not an integer in 1..:data:`MAX_CYCLES`.
    """
    text = str(cycles).strip()
    value = text[2:] if text.startswith('k=') else text
    # ASCII digits only: str.isdigit also accepts '²' or '٣', which int() refuses.
    if not (value.isascii() and value.isdigit()) or not 1 <= int(value) <= MAX_CYCLES:
        raise ConfigError(key, f'{PERIODIC} needs its frequency: write {PERIODIC}:<joint>:k=<k> '
                          f'with k an integer of cycles per revolution in 1..{MAX_CYCLES} '
                          f'(not {text!r})')
    names = robot.joint_names
    if joint not in names:
        raise ConfigError(key, f'effect {PERIODIC!r} acts on one joint: write '
                          f'{PERIODIC}:<joint>:k=<k> with a joint of {names}'
                          + (f' (not {joint!r})' if joint else ''))
    index = names.index(joint)
    kind = periodic_kind(int(value))
    joint_kind = robot.joints[index].kind
    if not kind.applies_to(joint_kind):
        raise ConfigError(key, f'effect {PERIODIC!r} is periodic in an angle; {joint!r} is '
                          f'{joint_kind}')
    return PeriodicJointError(kind, joint, index, len(names), joint_kind, cycles=int(value))


# ------------------------------------------------------------------- link bending
def _no_joint_value(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX, *z: ca.SX) -> ca.SX:
    return 0 * theta[0]  # link bending turns the frame (frame_correction), not the joint


# The payload a row carries (core.measurement.payload): the moment of its own load, the cell's
# where it states none (MeasurementModel.input_values).
PAYLOAD_INPUTS = (PAYLOAD_MASS, *PAYLOAD_COM)


@dataclass(frozen=True)
class LinkBending(BoundEffect):
    """Joint j's frame turned by c_u·M_u about u and c_v·M_v about v.

    u and v are its link frame's axes perpendicular to the joint axis, M the gravity moment of
    the links it carries.
    """

    # (q (n,), payload (4,): mass, centre in the tip frame) -> M (3,), N m
    moment: ca.Function | None = field(default=None, compare=False)
    bend_axes: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))

    def frame_correction(self, q: ca.SX, tau: ca.SX, theta: ca.SX, z: Any = None) -> Any:
        """``(joint index, rotation (3x3))``: the bend of this joint's frame after its motion.

        ``z``: the row's payload (:data:`PAYLOAD_INPUTS`).
        """
        assert self.moment is not None and self.joint_index is not None  # set by the binder
        m = self.moment(q, z)
        u, v = (np.array(a) for a in self.bend_axes)
        rotation = (axis_rotation(u, theta[0] * ca.dot(ca.DM(u), m))
                    @ axis_rotation(v, theta[1] * ca.dot(ca.DM(v), m)))
        return self.joint_index, rotation


def _carried_masses(robot: RobotModel) -> list[tuple[int, float, np.ndarray]]:
    """(chain index a, mass kg, centre of mass (3,) in chain joint a's frame) of carried bodies.

    Every Pinocchio body a chain joint carries: the chain's links (the payload on the last) and
    the branches hanging off them (at their neutral values).
    """
    model = robot.pin_model
    data = model.createData()
    pin.forwardKinematics(model, data, pin.neutral(model))
    chain = {jid: i for i, jid in enumerate(robot._pin_joint_ids)}
    out = []
    for jid in range(1, model.njoints):
        mass = float(model.inertias[jid].mass)
        if mass <= 0.0:
            continue
        anc = jid
        while anc not in chain and anc != 0:
            anc = model.parents[anc]
        if anc == 0:
            continue  # not carried by the chain
        relative = data.oMi[anc].inverse() * data.oMi[jid]
        out.append((chain[anc], mass, np.array(relative.act(model.inertias[jid].lever))))
    return out


def gravity_moment(robot: RobotModel, joint: int) -> ca.Function:
    """CasADi Function (q (n,), payload (4,)) -> (3,): the static gravity (holding) moment, N m.

    The moment of the bodies chain joint ``joint`` carries, about its origin, in its frame after
    its motion, at the nominal geometry, with the payload (mass kg, centre m in the tip frame)
    in place of the cell's. Its component along the joint axis is
    :meth:`~kpi_calib_ros.core.model.robot.RobotModel.gravity_torques` with that payload.
    """
    chain = SymbolicChain(robot, geometric_parameters(robot, np.zeros(6), np.zeros(3)))
    q = ca.SX.sym('q', robot.n_joints)
    frames = chain.link_transforms(ca.DM(chain.params.nominal), q)
    model = robot.pin_model
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    base = data.oMf[frame_id(model, robot.base_frame)].rotation
    up = ca.DM(base.T @ HOLDING)  # the holding acceleration in the chain's base frame
    origin = frames[joint][:3, 3]
    moment = ca.SX.zeros(3)
    for index, mass, com in _carried_masses(robot):
        if index < joint:
            continue
        point = frames[index][:3, :3] @ ca.DM(com) + frames[index][:3, 3]
        moment += ca.cross(point - origin, mass * up)
    # the cell's payload (in the tip body above) out, the row's in, both on the last joint
    load = ca.SX.sym('payload', 4)
    tip = frames[robot.n_joints - 1]
    place = robot._tip_in_joint

    def carried(mass: Any, centre: Any) -> Any:
        point = tip[:3, :3] @ (ca.DM(place.rotation) @ centre + ca.DM(place.translation)) \
            + tip[:3, 3]
        return ca.cross(point - origin, mass * up)
    moment += carried(load[0], load[1:]) - carried(robot.payload.mass, ca.DM(robot.payload.com))
    return ca.Function('gravity_moment', [q, load], [frames[joint][:3, :3].T @ moment])


def _bend_axes(axis: np.ndarray) -> tuple[tuple[np.ndarray, str], tuple[np.ndarray, str]]:
    """Two unit axes (joint frame) perpendicular to ``axis``.

    From the frame axes other than the one closest to it, each with the letter of the frame axis
    it comes from.
    """
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    first, second = [k for k in range(3) if k != int(np.argmax(np.abs(axis)))]
    u = np.eye(3)[first] - axis[first] * axis
    u /= np.linalg.norm(u)
    return (u, AXES[first]), (np.cross(axis, u), AXES[second])


def link_bending(robot: RobotModel, joint: str | None, key: str = 'effects') -> LinkBending:
    """Bind ``link_bending:<joint>`` to ``robot``.

    Raises
    ------
    ConfigError
        Unknown joint, or nothing with mass beyond it (no ``<inertial>``, no payload).
    """
    names = robot.joint_names
    if joint not in names:
        raise ConfigError(key, f'effect {BENDING!r} acts on one joint: write {BENDING}:<joint> '
                          f'with a joint of {names}' + (f' (not {joint!r})' if joint else ''))
    index = names.index(joint)
    if not any(a >= index for a, _, _ in _carried_masses(robot)):
        raise ConfigError(key, f'{BENDING}:{joint}: nothing with mass beyond {joint} (no '
                          '<inertial> in the URDF, no payload), so no moment bends it; add '
                          'the link inertials or the payload')
    (u, lu), (v, lv) = _bend_axes(robot.joints[index].axis)
    kind = EffectType(
        BENDING, (f'c{lu}', f'c{lv}'), ('rad/(N m)', 'rad/(N m)'), _no_joint_value,
        typical=(1e-6, 1e-6), plausible=(1e-4, 1e-4), prismatic_plausible=(1e-4, 1e-4),
        prismatic_units=('rad/(N m)', 'rad/(N m)'), general=True,
        description='link bending: the frame of the joint turns about the two axes '
                    'perpendicular to it in proportion to the gravity moment the links beyond '
                    'it exert',
        hint='pose the arm so the moment on {joint} varies (stretched and folded, turned '
             'about its axis)',
        signature='gravity bending moment on {joint}', inputs=PAYLOAD_INPUTS)
    return LinkBending(kind, joint, index, len(names), robot.joints[index].kind,
                       moment=gravity_moment(robot, index),
                       bend_axes=(tuple(u.tolist()), tuple(v.tolist())))


def general_candidates(robot: RobotModel, exclude: set[str] | frozenset[str] = frozenset()
                       ) -> list[BoundEffect]:
    """Return the general effects screened without a search.

    ``link_bending`` of every chain joint that carries mass (names in ``exclude`` left out).
    """
    out: list[BoundEffect] = []
    for name in robot.joint_names:
        try:
            effect = link_bending(robot, name)
        except ConfigError:
            continue  # nothing with mass beyond it
        if effect.name not in exclude:
            out.append(effect)
    return out


CHAIN_EFFECTS[BENDING] = link_bending
ARGUMENT_EFFECTS[PERIODIC] = periodic_joint_error

__all__ = ['LinkBending', 'PeriodicJointError', 'general_candidates', 'gravity_moment',
           'link_bending', 'periodic_joint_error', 'periodic_kind']

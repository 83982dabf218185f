"""Gravity compliance without link masses: the ``gravity_compliance:<joint>`` effect.

Stock industrial URDFs carry no ``<inertial>``; the gravity torque Pinocchio computes
is then the payload's alone and ``joint_compliance`` (δq = c·τ) has the wrong
signature. With unknown masses the gravity torque of joint j is still linear in the
unknown mass moments of the links it carries (the holding torque, Pinocchio's g(q);
base frame level, a = +9.81 m/s² ẑ the acceleration that holds a link up):

    τ_j(q) = Σ_{k ≥ j} z_j · ((m_k (p_k − o_j) + R_k h_k) × a)
           = Σ_{k ≥ j} m_k · z_j·((p_k − o_j) × a) + Σ_i h_k,i · z_j·((R_k e_i) × a)

with z_j, o_j the axis and origin of joint j, p_k, R_k the frame of link k (the child
of joint k; the payload belongs to the last link) and h_k = m_k c_k its first mass
moment in its own frame: four unknowns per link, each multiplying a trigonometric
function of the joint angles (for joint 2 of a 6-axis arm: cos q2, sin q2,
cos(q2+q3), ... terms). The compliance deflection δq_j = c_j τ_j is then a linear
combination of those functions with the unknowns c_j m_k, c_j h_k. Many combinations
coincide (links whose frames move together, axes parallel to gravity); the effect
keeps an orthonormal basis of the functions the chain can produce, found by an SVD of
the regressor over joint configurations, and fits one coefficient (rad) per basis
function. Its parameters are ``gravity_compliance.<joint>.g0, g1, …``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np

from kpi_calib_ros.core.effects.registry import CHAIN_EFFECTS, BoundEffect, EffectType
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.model.kinematics import SymbolicChain
from kpi_calib_ros.core.model.parameters import geometric_parameters
from kpi_calib_ros.core.model.robot import RobotModel

# The force per kg that holds a link against gravity (URDF root frame level, as in
# Pinocchio): torques below are holding torques, Pinocchio's g(q), the convention of
# joint_compliance's τ.
HOLDING = np.array([0.0, 0.0, 9.81])  # m/s²
BASIS_SAMPLES = 400
BASIS_TOLERANCE = 1e-8  # singular values below this fraction of the largest: dependent
NAME = 'gravity_compliance'
# The largest plausible rms deflection a basis function carries (ψ has rms 1): 10 mrad (m on
# a prismatic joint), 10 mm at a metre; an industrial arm sags below 2 mrad under gravity,
# a servo-stiff or cable-driven one (1/kp ≈ 1e-3 rad/(N m)) more, and the cell's
# identification.bounds.gravity_compliance widens it.
PLAUSIBLE_DEFLECTION = 1e-2


def torque_regressor(robot: RobotModel, joint: int) -> ca.Function:
    """CasADi Function q (n,) -> (1, 4·m) with τ_joint = Y(q) · π.

    π = (m_k, h_k) of the links k the joint carries (kg, kg m), at the nominal geometry.
    """
    chain = SymbolicChain(robot, geometric_parameters(robot, np.zeros(6), np.zeros(3)))
    q = ca.SX.sym('q', robot.n_joints)
    p = ca.DM(chain.params.nominal)
    frames = chain.link_transforms(p, q)
    g = ca.DM(HOLDING)
    axis = frames[joint][:3, :3] @ ca.DM(robot.joints[joint].axis)
    origin = frames[joint][:3, 3]
    prismatic = robot.joints[joint].kind == 'prismatic'
    terms = []
    for k in range(joint, robot.n_joints):
        rot, pos = frames[k][:3, :3], frames[k][:3, 3]
        if prismatic:  # a force along the axis; the moments do not load it
            terms += [ca.dot(axis, g), 0, 0, 0]
        else:
            terms.append(ca.dot(axis, ca.cross(pos - origin, g)))
            terms += [ca.dot(axis, ca.cross(rot[:, i], g)) for i in range(3)]
    return ca.Function('gravity_regressor', [q], [ca.horzcat(*terms)])


def _whole_configuration(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX) -> ca.SX:
    """Never called: :meth:`MassFreeCompliance.joint_correction` computes the correction.

    The correction needs the whole configuration.
    """
    raise TypeError(f'{NAME} needs the whole configuration (MassFreeCompliance)')


@dataclass(frozen=True)
class MassFreeCompliance(BoundEffect):
    """δq_j = Σ_i g_i ψ_i(q): compliance of joint j under its gravity torque, link masses unknown.

    ψ (r functions, dimensionless, rms 1 over the joint ranges) span the torques the chain can
    produce.
    """

    basis: ca.Function | None = field(default=None, compare=False)

    def joint_correction(self, q: ca.SX, tau: ca.SX, theta: ca.SX, z: Any = None) -> ca.SX:
        """Joint-value correction SX (n,).

        ``θ · ψ(q)`` (rad or m) on this effect's joint, 0 elsewhere.
        """
        assert self.basis is not None and self.joint_index is not None  # set by the binder
        out = ca.SX.zeros(self.n_joints)
        out[self.joint_index] = ca.dot(self.basis(q), theta)
        return out


def mass_free_compliance(robot: RobotModel, joint: str | None,
                         key: str = 'effects') -> MassFreeCompliance:
    """Bind ``gravity_compliance:<joint>`` to ``robot``.

    Raises
    ------
    ConfigError
        Unknown joint, or a joint gravity never loads (a vertical first axis).
    """
    names = robot.joint_names
    if joint not in names:
        raise ConfigError(key, f'effect {NAME!r} acts on one joint: write {NAME}:<joint> '
                          f'with a joint of {names}' + (f' (not {joint!r})' if joint else ''))
    index = names.index(joint)
    regressor = torque_regressor(robot, index)
    rng = np.random.default_rng(0)
    lower = np.maximum(robot.actuated_lower, -np.pi)
    upper = np.minimum(robot.actuated_upper, np.pi)
    samples = robot.chain_values(rng.uniform(lower, upper, (BASIS_SAMPLES, len(lower))))
    y = np.vstack([np.array(regressor(s)).ravel() for s in samples])
    _, s, vt = np.linalg.svd(y, full_matrices=False)
    rank = int(np.sum(s > BASIS_TOLERANCE * s[0])) if s.size and s[0] > 0 else 0
    if rank == 0:
        raise ConfigError(key, f'{NAME}:{joint}: gravity never loads {joint} (its axis is '
                          'vertical or it carries nothing); choose a joint gravity loads')
    # Orthonormal functions over the samples: ψ = Y V_r diag(√S / s_r), rms 1 each.
    weights = vt[:rank].T * (np.sqrt(len(samples)) / s[:rank])
    q = ca.SX.sym('q', robot.n_joints)
    basis = ca.Function('gravity_basis', [q], [(regressor(q) @ ca.DM(weights)).T])
    kind = EffectType(
        NAME, tuple(f'g{i}' for i in range(rank)), ('rad',) * rank,
        joint_function=_whole_configuration, typical=(1e-4,) * rank, prismatic_units=('m',) * rank,
        plausible=(PLAUSIBLE_DEFLECTION,) * rank,
        prismatic_plausible=(PLAUSIBLE_DEFLECTION,) * rank,
        description='joint deflection under its gravity torque, link masses unknown: '
                    'a combination of the trigonometric functions the chain makes',
        hint='pose the arm so the gravity torque of {joint} varies widely (arm stretched '
             'and folded, both sides of vertical)',
        signature='gravity torque functions of {joint} (masses unknown)')
    return MassFreeCompliance(kind, joint, index, len(names), robot.joints[index].kind,
                              basis=basis)





CHAIN_EFFECTS[NAME] = mass_free_compliance


# Joint stiffness of industrial arms, N m/rad: a small harmonic-drive wrist ~5e3-1e4, a
# heavy-payload shoulder ~1e7 (as joint_compliance's default bound). Outside, a fitted
# compliance more likely absorbs something else (or the arm is servo-stiff: a cell bound).
STIFFNESS_RANGE = (5e3, 1e8)


def massless_links(robot: RobotModel) -> list[str]:
    """Chain links (children of the chain joints) without mass.

    Without mass means no ``<inertial>`` (the cell payload counts as mass of the last link).
    """
    ids = robot._pin_joint_ids  # the chain's Pinocchio joints, base to tip
    return [name for name, jid in zip(robot.link_names[1:], ids)
            if float(robot.pin_model.inertias[jid].mass) <= 0.0]


def mass_warning(robot: RobotModel, effects: Sequence[Any]) -> str:
    """Why torque-driven effects (``joint_compliance``, ``joint_backlash``) are wrong here, or ''.

    Without link masses the gravity torque is the payload's alone.
    """
    users = [e.name for e in effects if e.uses_torque]
    missing = massless_links(robot)
    if not users or not missing:
        return ''
    return (f'links {missing} have no mass (no <inertial> in the URDF): the gravity torques '
            f'that {users} use come from the payload alone and their signature is wrong; '
            'add the link inertials, or use gravity_compliance:<joint> (link masses '
            'unknown, fitted)')


def compliance_warnings(names: Sequence[str], values: Sequence[float],
                        stds: Sequence[float],
                        softest: Mapping[str, float] | None = None) -> list[str]:
    """Fitted ``joint_compliance`` values outside physical sense.

    A positive c (the joint deflecting along its holding torque, beyond 3 std) or |c| outside
    the stiffness range of industrial joints (:data:`STIFFNESS_RANGE`); ``softest`` {name:
    largest |c|} the cell's bound where it widens that range (a servo-stiff or cable-driven
    arm, ``identification.bounds``).
    """
    out = []
    lo = 1.0 / STIFFNESS_RANGE[1]
    for name, c, std in zip(names, values, stds):
        if not (name.startswith('joint_compliance.') and name.endswith('.c')):
            continue
        hi = max(1.0 / STIFFNESS_RANGE[0], (softest or {}).get(name, 0.0))
        if c > 3 * std:
            out.append(f'{name} = {c:.3g} rad/(N m) > 0: the joint would deflect along its '
                       'holding torque; a physical compliance is negative (δq = c·τ, τ the '
                       'holding torque): check the joint axis sign and the link masses')
        if abs(c) > 3 * std and not lo <= abs(c) <= hi:
            out.append(f'{name} = {c:.3g} rad/(N m) means a stiffness {1 / abs(c):.3g} N m/rad, '
                       f'outside {1 / hi:.3g}..{STIFFNESS_RANGE[1]:.0e}: it absorbs another '
                       'effect, or the masses are wrong, or the arm is that soft (a '
                       'servo-stiff or cable-driven joint: state it with identification.bounds.'
                       f'joint_compliance:<joint>)')
    return out
__all__ = ['MassFreeCompliance', 'compliance_warnings', 'mass_free_compliance', 'mass_warning',
           'massless_links', 'torque_regressor']

"""The library of physical effects: the corrections of each shipped effect type.

The joint and point corrections of each
:class:`~kpi_calib_ros.core.effects.effect_types.EffectType` the package ships (their formulas
and units in :mod:`kpi_calib_ros.core.effects.registry`), with the sizes a fit may take and the
hints that tell a user how to make each distinguishable.
"""
from __future__ import annotations

import math

import casadi as ca

from kpi_calib_ros.core.effects.effect_types import EffectType
from kpi_calib_ros.core.measurement.covariates import DELTA_TEMPERATURE

__all__ = [
    'BACKLASH_TORQUE_SCALE', 'PLAY_TORQUE_UNIT', 'PLAY_GRID', 'THERMAL_EXPANSION_BOUND',
    'LIBRARY',
]

# joint_backlash is b·tanh(τ/τ_b) with τ_b = BACKLASH_TORQUE_SCALE, N m (N for a prismatic
# joint): a smooth sign. Physically the joint settles on the side its load pushes to (b·sgn τ)
# once the load overcomes the friction in the play; near zero load the side is undecided, and
# a differentiable step keeps the Gauss-Newton fit well posed. Wherever |τ| > 3 τ_b it is the
# sign within 0.5 %; a joint whose gravity torque stays below τ_b is never loaded out of its
# play, and there b·tanh(τ/τ_b) ≈ (b/τ_b)·τ is a compliance, not a backlash: the screen does
# not propose it there (core.diagnosis.candidate_plausibility.backlash_unloaded).
BACKLASH_TORQUE_SCALE = 0.01
PLAY_TORQUE_UNIT = 1.0        # N m (N for a prismatic joint): joint_play's τ0 = e^u of it
# joint_play's screened transition torques τ0: 0.01 ... 10 N m, three per decade
PLAY_GRID = tuple((math.log(t),) for t in (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0,
                                                5.0, 10.0))


# ------------------------------------------------------------------ the library
def _compliance(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX) -> ca.SX:
    return theta[0] * tau_j


def _cyclic(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX) -> ca.SX:
    return theta[0] * ca.sin(q_j) + theta[1] * ca.cos(q_j)


def _cyclic_h2(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX) -> ca.SX:
    return theta[0] * ca.sin(2 * q_j) + theta[1] * ca.cos(2 * q_j)


def _backlash(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX) -> ca.SX:
    return theta[0] * ca.tanh(tau_j / BACKLASH_TORQUE_SCALE)


def _play(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX) -> ca.SX:
    return theta[0] * ca.tanh(tau_j / (PLAY_TORQUE_UNIT * ca.exp(theta[1])))


def _scale(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX) -> ca.SX:
    return theta[0] * q_j


def _tracker_scale(point: ca.SX, theta: ca.SX) -> ca.SX:
    return (1 + theta[0]) * point


# Linear expansion of the materials arms are made of, 1/K: steel 11-13e-6, cast iron ~10e-6,
# aluminium 23-24e-6. A fitted α beyond THERMAL_EXPANSION_BOUND is flagged.
THERMAL_EXPANSION_BOUND = 30e-6


def _thermal_drift(q_j: ca.SX, tau_j: ca.SX, theta: ca.SX, z: ca.SX) -> ca.SX:
    return theta[0] * z[0]


def _thermal_growth(origin: ca.DM, theta: ca.SX, z: ca.SX) -> ca.SX:
    return ca.vertcat(theta[0] * z[0] * origin, ca.SX.zeros(3))


LIBRARY: tuple[EffectType, ...] = (
    EffectType('joint_compliance', ('c',), ('rad/(N m)',), _compliance, uses_torque=True,
               typical=(1e-6,), prismatic_units=('m/N',), screen=True,
               # stiffness >= 5e3 N m/rad: harmonic drives of small arms 1e4-1e5 (a UR10
               # joint measured 8.6e3), industrial gearboxes 1e5-1e7. A servo-stiff or
               # cable-driven arm is softer (1/kp ~ 1e-3): identification.bounds widens it.
               plausible=(2e-4,), prismatic_plausible=(1e-5,),
               description='joint deflection proportional to its gravity torque',
               hint='gravity must load {joint} with a torque that varies over the poses; '
                    'a joint with a vertical axis or an unloaded wrist carries none '
                    '(a tilted base or a heavier, off-axis payload would)',
               signature='gravity torque of {joint}'),
    EffectType('cyclic_joint_error', ('a', 'b'), ('rad', 'rad'), _cyclic,
               typical=(2e-4, 2e-4), screen=True,
               joint_kinds=('revolute', 'continuous'), plausible=(5e-3, 5e-3),
               description='first-harmonic gear/encoder error a·sin q + b·cos q',
               hint='spread {joint} over most of a revolution so sin q and cos q vary '
                    'independently of the joint offset',
               signature='first harmonic a·sin q + b·cos q of {joint}'),
    EffectType('cyclic_joint_error_h2', ('a', 'b'), ('rad', 'rad'), _cyclic_h2,
               typical=(1e-4, 1e-4),
               joint_kinds=('revolute', 'continuous'), plausible=(5e-3, 5e-3),
               description='second-harmonic gear/encoder error a·sin 2q + b·cos 2q',
               hint='spread {joint} over at least half a revolution',
               signature='second harmonic of {joint}'),
    EffectType('joint_backlash', ('b',), ('rad',), _backlash, uses_torque=True,
               typical=(2.5e-4,), screen=True,
               # b is half the free play. Industrial gearboxes: below 1 mrad; service and
               # cable/belt-driven arms show tens of mrad of play in their wrists (the TIAGo
               # data's origin documents ~40 mrad in arm_6, b ~ 20 mrad). 50 mrad (a play
               # of ~6 deg) is where a joint is broken rather than loose.
               plausible=(5e-2,), prismatic_plausible=(5e-3,),
               description='backlash: the joint settles on the side its gravity torque '
                           'pushes to, b·tanh(τ/τ_b) with τ_b = 0.01 N m (a smooth sgn τ: '
                           'the sign within 0.5 % where |τ| > 0.03 N m)',
               hint='measure poses where the gravity torque of {joint} changes sign '
                    '(the arm on both sides of its balance point) and exceeds 0.01 N m '
                    'in size; with one sign only, backlash is a constant the joint offset '
                    'absorbs, and below 0.01 N m it is a compliance',
               signature='sign of the gravity torque of {joint}'),
    EffectType('joint_play', ('b', 'u'), ('rad', '1'), _play, uses_torque=True,
               typical=(2.5e-4, 0.0), screen=True, prismatic_units=('m', '1'),
               # b as joint_backlash; τ0 from 1 mN m (a sharp step) to 1 kN m (never loaded
               # out of its play), |u| <= ln 1000
               plausible=(5e-2, 6.91), prismatic_plausible=(5e-3, 6.91),
               shape_grid=PLAY_GRID, nests=('joint_backlash', 'joint_compliance'),
               description='free play crossed smoothly with the gravity torque, '
                           'b·tanh(τ/τ0), τ0 = e^u N m identified: the joint sits inside its '
                           'play where the load is small (friction, a cable, the unmodelled '
                           'part of the load decide) and at ±b where it is large',
               hint='measure poses where the gravity torque of {joint} changes sign and '
                    'poses where it is small and large, so the size b and the transition '
                    'torque τ0 of the play show apart from the offset and a compliance',
               signature='saturating function b·tanh(τ/τ0) of the gravity torque of {joint}'),
    EffectType('joint_scale', ('k',), ('1',), _scale, typical=(1e-4,), screen=True,
               prismatic_units=('1',), plausible=(1e-2,), prismatic_plausible=(1e-2,),
               description='transmission-ratio error k·q',
               hint='move {joint} over a wide range; over a narrow one k·q looks like '
                    'the joint offset',
               signature='reading of {joint}'),
    EffectType('tracker_scale', ('s',), ('1',), point_function=_tracker_scale,
               per_joint=False, typical=(1e-5,), screen=True,
               plausible=(1e-3,),  # 1000 ppm: far beyond any tracker's or camera's scale
               description='length scale error of the tracker (temperature, refractive '
                           'index), η = (1 + s)·h',
               hint='a global scale is absorbed by the free link lengths and the base '
                    'distance; measure a reference length (a calibrated scale bar) or '
                    'fix the link lengths'),
    EffectType('thermal_zero_drift', ('d',), ('rad/K',), _thermal_drift, typical=(2e-6,),
               screen=True, inputs=(DELTA_TEMPERATURE,), prismatic_units=('m/K',),
               # 1e-4 rad/K: 2 mrad over a 20 K shift, far beyond a drifting encoder zero
               plausible=(1e-4,), prismatic_plausible=(1e-4,),
               description='joint-zero drift in proportion to the temperature change d·ΔT '
                           '(screened where a temperature is recorded)',
               hint='measure while the temperature changes (a warm-up, a shift), with '
                    'the poses spread over the temperatures, not one temperature per region',
               signature='temperature change (zero of {joint})'),
    EffectType('thermal_link_growth', ('alpha',), ('1/K',),
               placement_function=_thermal_growth, typical=(12e-6,), screen=True,
               inputs=(DELTA_TEMPERATURE,), plausible=(THERMAL_EXPANSION_BOUND,),
               prismatic_plausible=(THERMAL_EXPANSION_BOUND,), prismatic_units=('1/K',),
               description='thermal growth α·ΔT of the link before the joint, its origin '
                           'translation (screened where a temperature is recorded)',
               hint='measure while the temperature changes, with poses that stretch the '
                    'link before {joint} in different directions at each temperature',
               signature='temperature change (length of the link before {joint})'),
    EffectType('thermal_growth', ('alpha',), ('1/K',), placement_function=_thermal_growth,
               per_joint=False, typical=(12e-6,), screen=True, inputs=(DELTA_TEMPERATURE,),
               plausible=(THERMAL_EXPANSION_BOUND,),
               description='thermal growth α·ΔT of every link, one material (screened where a '
                           'temperature is recorded)',
               hint='measure while the temperature changes, over a wide workspace at each '
                    'temperature',
               signature='temperature change (every link length)'),
)

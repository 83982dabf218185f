"""Physical effects the geometric model lacks: a library, specs and a user API.

An effect is a small model with its own parameters that plugs into the
measurement model (:class:`~kpi_calib_ros.core.measurement.MeasurementModel`)
either as an additive correction of one joint value or as a correction of the
measured point. Its parameters get stable names (``joint_compliance.joint_2.c``)
and nominal value 0, so "no effect" is the geometric model.

Library (per joint ``j`` unless noted; ``τ_j`` is the gravity torque from
Pinocchio, payload included)::

    joint_compliance      δq_j = c · τ_j                   c  rad/(N m)
    gravity_compliance    δq_j = Σ g_i ψ_i(q), link masses unknown (see
                          :mod:`kpi_calib_ros.core.gravity_compliance`)  g_i  rad
    cyclic_joint_error    δq_j = a · sin q_j + b · cos q_j  a, b  rad
    cyclic_joint_error_h2 δq_j = a · sin 2q_j + b · cos 2q_j
    joint_backlash        δq_j = b · sgn(τ_j)              b  rad
    joint_play            δq_j = b · tanh(τ_j / τ0),       b  rad, u = ln(τ0 / 1 N m)
                          τ0 = e^u N m identified
    joint_scale           δq_j = k · q_j                   k  1 (transmission ratio)
    tracker_scale         η = (1 + s) · h  (global)        s  1 (tracker length scale)

Thermal effects read the covariate ``delta_temperature`` (ΔT, K: the arm's temperature
minus the cell's reference, :mod:`kpi_calib_ros.core.covariates`); they are candidates only
where the measurements carry it::

    thermal_zero_drift    δq_j = d · ΔT                    d  rad/K
    thermal_link_growth   t_j -> (1 + α ΔT) · t_j          α  1/K (linear expansion)
    thermal_growth        every t_j -> (1 + α ΔT) · t_j    α  1/K  (global: one material)

``t_j`` is the nominal translation of joint j's origin from its parent (the URDF
``<origin xyz>``: the link before the joint); the growth is written into that joint's
placement error, so the geometric placement stays what it is at the reference temperature.
Steel grows 11–13 µm/(m K), aluminium 23–24 µm/(m K): α outside ±30e-6 /K is flagged.

Sign of ``joint_compliance``: τ_j is Pinocchio's generalised gravity g(q), the torque
the drive must apply to *hold* the arm, and the model puts the joint at q + δq. A
joint of stiffness k sags along gravity, against its holding torque, so a physical
compliance is c = −1/k < 0. Industrial joints have k ≈ 1e4 … 1e7 N m/rad, hence
|c| ≈ 1e-7 … 1e-4 rad/(N m); :func:`compliance_warnings` flags fitted values outside.

``sgn`` is ``tanh(τ/τ0)`` with τ0 = 0.01 N m: the sign wherever gravity loads
the joint measurably, and 0 where it exerts no torque at all (a vertical first
axis), so a joint without load shows no backlash instead of numerical noise.

User effects
------------
Describe the effect with :class:`EffectType` and a CasADi function of the joint
state and the parameters, then make it known in one of three ways::

    import casadi as ca
    from kpi_calib_ros.core.effects import EffectType, register_effect

    def _thermal(q_j, tau_j, theta):          # SX scalars, theta (k,) SX
        return theta[0] * ca.cos(q_j) ** 2    # additive joint correction, rad

    THERMAL = EffectType('thermal_bend', parameters=('g',), units=('rad',),
                         joint_function=_thermal, typical=(1e-4,),
                         description='bending that grows with cos² of the joint')
    register_effect(THERMAL)                  # 1. in-process

    # 2. setup.py: entry_points={'kpi_calib_ros.effects': ['thermal = my_pkg.fx:THERMAL']}
    # 3. cell file: effects: ['my_pkg.fx:THERMAL:joint_2'] (or 'fx.py:THERMAL:joint_2',
    #    a file next to the cell file)

The entry point or cell reference may name an :class:`EffectType` or a callable
without arguments that returns one (or a list of them).
"""
from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import math
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import casadi as ca
import numpy as np

from kpi_calib_ros.core.covariates import DELTA_TEMPERATURE
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.robot import RobotModel

ENTRY_POINT_GROUP = 'kpi_calib_ros.effects'
BACKLASH_TORQUE_SCALE = 0.01  # N m: below this a joint counts as unloaded
PLAY_TORQUE_UNIT = 1.0        # N m (N for a prismatic joint): joint_play's τ0 = e^u of it
# joint_play's screened transition torques τ0: 0.01 ... 10 N m, three per decade
PLAY_GRID = tuple((math.log(t),) for t in (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0,
                                                5.0, 10.0))


@dataclass(frozen=True)
class EffectType:
    """A kind of physical effect, before it is bound to a joint.

    Parameters
    ----------
    name : str
        Registry name, used in specs (``name:joint``) and parameter names.
    parameters : tuple of str
        Parameter suffixes, e.g. ``('c',)``; full names are
        ``<name>.<joint>.<suffix>`` (per joint) or ``<name>.<suffix>`` (global).
    units : tuple of str
        Units of the parameters for a revolute joint (or a global effect).
    joint_function : callable, optional
        Per joint: ``f(q_j, tau_j, theta) -> SX scalar``, the additive
        correction of joint j (rad, or m for a prismatic joint). Global:
        ``f(q, tau, theta) -> SX (n,)``. Use CasADi operations.
    point_function : callable, optional
        ``g(point, theta) -> SX (3,)``: the measured point (tracker frame, m)
        given the model point; for effects of the measuring instrument.
    per_joint : bool
        One instance per chain joint (``name:joint``) or one global instance.
    uses_torque : bool
        The function reads gravity torques; the model then supplies them.
    typical : tuple of float
        A realistic size of each parameter: used to simulate the effect and to
        decide whether it changes the measurements at all.
    prismatic_units : tuple of str, optional
        Units for a prismatic joint (default: ``units`` with rad -> m, N m -> N).
    description : str
        One line for reports.
    hint : str
        What would make the effect distinguishable from the geometry when the
        data cannot; ``{joint}`` is replaced by the joint name.
    signature : str
        What the fitted joint correction follows, for explanations
        (``'gravity torque of {joint}'``).
    screen : bool
        Whether :func:`candidate_effects` includes it by default.
    joint_kinds : tuple of str, optional
        Joint kinds (``revolute``, ``continuous``, ``prismatic``) it applies to; None: any.
        A cyclic error is a function of an angle: it has no meaning on a prismatic joint.
    plausible : tuple of float
        Largest physically plausible |value| of each parameter (revolute units); a fit
        beyond it is flagged (see :func:`implausible`). Empty: no bound.
    prismatic_plausible : tuple of float, optional
        The same for a prismatic joint (its units); None: no bound there.
    shape_grid : tuple of tuple of float
        For an effect nonlinear in its last parameters (they set the shape, not the size:
        their Jacobian column vanishes at zero size), the values of those shape parameters
        the linear screening tries (:func:`kpi_calib_ros.core.diagnosis.screen_effects`
        keeps the best, counting them in the F-test's degrees of freedom); the
        identification then fits them from there. Empty: linear at zero (every column
        non-zero at θ = 0).
    nests : tuple of str
        Simpler effects (names) this one contains as limits on the same joint; the
        diagnosis counts it only when it fits significantly better than them.
    inputs : tuple of str
        Covariates (``Measurements.covariates`` names) the effect reads; with any, its
        functions take them as one more argument ``z`` (SX (len(inputs),), in this order):
        ``joint_function(q_j, tau_j, theta, z)``, ``placement_function(t, theta, z)``. Every
        input is 0 at the reference condition. Candidates only where the data carry them.
    placement_function : callable, optional
        ``f(t, theta, z) -> SX (6,)``: additive correction of a joint's placement error
        (tx, ty, tz m in the joint's placement frame; rx, ry, rz rad) given ``t`` (3,), the
        joint's nominal origin translation expressed in that frame (``M_jᵀ`` applied). Per
        joint it moves its joint; global, every joint.
    """

    name: str
    parameters: tuple[str, ...]
    units: tuple[str, ...]
    joint_function: Callable | None = None
    point_function: Callable | None = None
    per_joint: bool = True
    uses_torque: bool = False
    typical: tuple[float, ...] = ()
    prismatic_units: tuple[str, ...] | None = None
    description: str = ''
    hint: str = ''
    signature: str = 'fitted correction of {joint}'
    screen: bool = False
    joint_kinds: tuple[str, ...] | None = None
    plausible: tuple[float, ...] = ()
    prismatic_plausible: tuple[float, ...] | None = None
    shape_grid: tuple[tuple[float, ...], ...] = ()
    nests: tuple[str, ...] = ()
    inputs: tuple[str, ...] = ()
    placement_function: Callable | None = None

    def __post_init__(self) -> None:
        if not self.name or ':' in self.name or '.' in self.name:
            raise ValueError(f'effect name {self.name!r} must be non-empty without ":" or "."')
        given = [f for f in (self.joint_function, self.point_function,
                             self.placement_function) if f is not None]
        if len(given) != 1:
            raise ValueError(f'effect {self.name!r}: give exactly one of joint_function, '
                             'point_function and placement_function')
        if self.point_function is not None and self.inputs:
            raise ValueError(f'effect {self.name!r}: a point correction reads no covariates')
        if self.point_function is not None and self.per_joint:
            raise ValueError(f'effect {self.name!r}: a point correction is global; '
                             'set per_joint=False')
        if len(self.units) != len(self.parameters) or not self.parameters:
            raise ValueError(f'effect {self.name!r}: need one unit per parameter, '
                             'at least one parameter')
        if self.typical and len(self.typical) != len(self.parameters):
            raise ValueError(f'effect {self.name!r}: typical needs one value per parameter')
        if any(len(g) >= len(self.parameters) or len(g) != len(self.shape_grid[0])
               for g in self.shape_grid):
            raise ValueError(f'effect {self.name!r}: every shape_grid entry gives the same '
                             'number of (last) parameters, fewer than all')
        for bound in (self.plausible, self.prismatic_plausible or ()):
            if bound and len(bound) != len(self.parameters):
                raise ValueError(f'effect {self.name!r}: plausible bounds need one value per '
                                 'parameter')

    @property
    def n_shape(self) -> int:
        """Number of shape parameters (the last ones), see ``shape_grid``."""
        return len(self.shape_grid[0]) if self.shape_grid else 0

    def applies_to(self, joint_kind: str | None) -> bool:
        """Whether the effect has a meaning on a joint of this kind (global: always)."""
        return joint_kind is None or self.joint_kinds is None or joint_kind in self.joint_kinds

    def units_for(self, joint_kind: str | None) -> tuple[str, ...]:
        """Units of the parameters on a joint of this kind (rad -> m, N m -> N if prismatic)."""
        if joint_kind != 'prismatic':
            return self.units
        if self.prismatic_units is not None:
            return self.prismatic_units
        return tuple(u.replace('N m', 'N').replace('rad', 'm') for u in self.units)


@dataclass(frozen=True)
class BoundEffect:
    """An effect type bound to one joint (or global): implements the ``Effect`` protocol.

    ``name`` is the spec (``joint_compliance:joint_2``), unique within a model.
    """

    kind: EffectType
    joint: str | None
    joint_index: int | None
    n_joints: int
    name: str = field(init=False)
    parameter_names: tuple[str, ...] = field(init=False)
    units: tuple[str, ...] = field(init=False)
    uses_torque: bool = field(init=False)
    joint_kind: str | None = None
    # Nominal origin translation of every chain joint in its placement frame (M_jᵀ t_j),
    # (n, 3), for a placement effect; set by bind_effect.
    origins: np.ndarray | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        prefix = self.kind.name if self.joint is None else f'{self.kind.name}.{self.joint}'
        object.__setattr__(self, 'name', self.kind.name if self.joint is None
                           else f'{self.kind.name}:{self.joint}')
        object.__setattr__(self, 'parameter_names',
                           tuple(f'{prefix}.{s}' for s in self.kind.parameters))
        object.__setattr__(self, 'units', self.kind.units_for(self.joint_kind))
        object.__setattr__(self, 'uses_torque', self.kind.uses_torque)

    @property
    def inputs(self) -> tuple[str, ...]:
        """Covariates the effect reads (``Measurements.covariates`` names)."""
        return self.kind.inputs

    @property
    def typical(self) -> tuple[float, ...]:
        """Typical magnitude of each parameter (its units), 1 where the kind states none."""
        return self.kind.typical or (1.0,) * len(self.kind.parameters)

    @property
    def shape_names(self) -> tuple[str, ...]:
        """Names of its shape parameters (the last ``kind.n_shape``; empty when linear)."""
        return self.parameter_names[len(self.parameter_names) - self.kind.n_shape:] \
            if self.kind.n_shape else ()

    def joint_correction(self, q: ca.SX, tau: ca.SX, theta: ca.SX, z: Any = None) -> Any:
        """Additive joint-value correction, SX (n,), or None for a point or placement
        effect; ``z`` the covariates :attr:`inputs` (SX, an effect with inputs only)."""
        fn = self.kind.joint_function
        if fn is None:
            return None
        extra = (z,) if self.kind.inputs else ()
        if self.joint_index is None:
            return fn(q, tau, theta, *extra)
        out = ca.SX.zeros(self.n_joints)
        out[self.joint_index] = fn(q[self.joint_index], tau[self.joint_index], theta, *extra)
        return out

    def placement_correction(self, theta: ca.SX, z: Any = None) -> list[tuple[int, Any]]:
        """Additive corrections of joint placement errors: [(joint index, SX (6,))]; empty
        unless the kind has a ``placement_function``."""
        fn = self.kind.placement_function
        if fn is None or self.origins is None:
            return []
        extra = (z,) if self.kind.inputs else ()
        joints = range(self.n_joints) if self.joint_index is None else (self.joint_index,)
        return [(j, fn(ca.DM(self.origins[j]), theta, *extra)) for j in joints
                if np.any(self.origins[j] != 0)]

    def point_correction(self, point: ca.SX, theta: ca.SX) -> Any:
        """Corrected measured point, SX (3,), or None for a joint effect."""
        fn = self.kind.point_function
        return None if fn is None else fn(point, theta)

    def hint(self) -> str:
        """What would make this effect distinguishable, with the joint named."""
        return self.kind.hint.replace('{joint}', self.joint or 'the joint')

    def signature(self) -> str:
        """What the fitted correction follows, with the joint named."""
        return self.kind.signature.replace('{joint}', self.joint or 'the joint')


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
               # stiffness >= 1e4 N m/rad (a small cobot joint; industrial 1e5-1e7)
               plausible=(1e-4,), prismatic_plausible=(1e-5,),
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
                           'pushes to, b·sgn(τ)',
               hint='measure poses where the gravity torque of {joint} changes sign '
                    '(the arm on both sides of its balance point); with one sign only, '
                    'backlash is a constant the joint offset absorbs',
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
               signature='angle of {joint}'),
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

_REGISTRY: dict[str, EffectType] = {e.name: e for e in LIBRARY}
_entry_points_loaded = False


def register_effect(effect_type: EffectType, replace: bool = False) -> EffectType:
    """Make ``effect_type`` available to specs, the CLI and the diagnosis.

    Raises
    ------
    ValueError
        If the name is taken and ``replace`` is False.
    """
    if not isinstance(effect_type, EffectType):
        raise ValueError(f'register_effect needs an EffectType, got {type(effect_type).__name__}')
    if effect_type.name in _REGISTRY and not replace \
            and _REGISTRY[effect_type.name] is not effect_type:
        raise ValueError(f'effect {effect_type.name!r} is already registered; '
                         'pass replace=True to override it')
    _REGISTRY[effect_type.name] = effect_type
    return effect_type


def available_effects() -> dict[str, EffectType]:
    """All known effect types: the library, registered ones and entry points."""
    global _entry_points_loaded
    if not _entry_points_loaded:
        _entry_points_loaded = True
        for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
            try:
                for effect_type in _as_effect_types(ep.load(), ep.value):
                    register_effect(effect_type, replace=True)
            except Exception as exc:  # a broken plugin must not break the tool
                warnings.warn(f'effect entry point {ep.name!r} ({ep.value}) ignored: {exc}',
                              stacklevel=2)
    return dict(_REGISTRY)


def _as_effect_types(obj: Any, where: str) -> list[EffectType]:
    if isinstance(obj, EffectType):
        return [obj]
    if callable(obj):
        made = obj()
        items = [made] if isinstance(made, EffectType) else list(made)
        if items and all(isinstance(i, EffectType) for i in items):
            return items
    raise ValueError(f'{where} must be an EffectType or a callable without arguments '
                     'returning EffectType(s)')


# ------------------------------------------------------------------------ specs
def bind_effect(effect_type: EffectType, robot: RobotModel, joint: str | None,
                key: str = 'effects') -> BoundEffect:
    """Bind ``effect_type`` to ``joint`` of ``robot`` (None for a global effect)."""
    names = robot.joint_names
    if effect_type.per_joint:
        if joint not in names:
            raise ConfigError(key, f'effect {effect_type.name!r} acts on one joint: write '
                              f'{effect_type.name}:<joint> with a joint of {names}'
                              + (f' (not {joint!r})' if joint else ''))
        index = names.index(joint)
        kind = robot.joints[index].kind
        if not effect_type.applies_to(kind):
            raise ConfigError(key, f'effect {effect_type.name!r} applies to '
                              f'{list(effect_type.joint_kinds or ())} joints; {joint!r} is '
                              f'{kind}')
        return BoundEffect(effect_type, joint, index, len(names), kind,
                           origins=_origins(effect_type, robot))
    if joint is not None:
        raise ConfigError(key, f'effect {effect_type.name!r} is global; write '
                          f'{effect_type.name!r} without a joint')
    return BoundEffect(effect_type, None, None, len(names), origins=_origins(effect_type, robot))


def _origins(effect_type: EffectType, robot: RobotModel) -> np.ndarray | None:
    """(n, 3) nominal origin translation of every joint in its placement frame, m (for a
    placement effect; None otherwise)."""
    if effect_type.placement_function is None:
        return None
    return np.array([np.asarray(j.placement)[:3, :3].T @ np.asarray(j.placement)[:3, 3]
                     for j in robot.joints])


# Effects built from the whole chain rather than one joint's (q_j, τ_j): spec name ->
# binder(robot, joint, key) -> BoundEffect. core.gravity_compliance registers its own.
CHAIN_EFFECTS: dict[str, Callable[[RobotModel, str | None, str], BoundEffect]] = {}


def parse_effect_spec(spec: str, robot: RobotModel, key: str = 'effects',
                      base_dir: str | Path | None = None,
                      allow_code: bool = False) -> BoundEffect:
    """Resolve ``'effect[:joint]'`` or ``'module:attribute[:joint]'`` to an effect.

    ``module`` is an importable module or a ``.py`` file (relative to
    ``base_dir``, the cell file's folder); ``attribute`` names an
    :class:`EffectType` or a callable returning one. Loading it runs its code, so
    this form needs ``allow_code=True`` (``--allow-code-effects`` on the command
    line, ``allow_code_effects`` on the node): a data file alone never runs code.
    Built-in effects and installed entry points need no opt-in.

    Raises
    ------
    ConfigError
        Naming ``key`` and the spec, listing the valid effects and joints.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(key, f'effect spec must be a non-empty string, got {spec!r}')
    parts = [s.strip() for s in spec.strip().split(':')]
    known = available_effects()
    where = f'{key}: {spec!r}'
    if parts[0] in CHAIN_EFFECTS and len(parts) <= 2:
        return CHAIN_EFFECTS[parts[0]](robot, parts[1] if len(parts) == 2 else None, where)
    if parts[0] in known:
        if len(parts) > 2:
            raise ConfigError(key, f'{spec!r}: write effect:joint, e.g. {parts[0]}:'
                              f'{robot.joint_names[min(1, robot.n_joints - 1)]}')
        return bind_effect(known[parts[0]], robot, parts[1] if len(parts) == 2 else None, where)
    if len(parts) in (2, 3) and ('.' in parts[0] or parts[0].endswith('.py')):
        if not allow_code:
            raise ConfigError(key, f'{spec!r} names Python code ({parts[0]}), which is not run '
                              'unless asked: pass --allow-code-effects to kpi-calib, or set '
                              'the node parameter allow_code_effects:=true, if you trust '
                              f'it; built-in effects are {sorted(known)}')
        effect_type = _load_user_effect(parts[0], parts[1], key, spec, base_dir)
        return bind_effect(effect_type, robot, parts[2] if len(parts) == 3 else None, where)
    raise ConfigError(key, f'{spec!r}: unknown effect {parts[0]!r}; valid effects are '
                      f'{sorted(set(known) | set(CHAIN_EFFECTS))}, written effect:joint with a '
                      'joint of '
                      f'{robot.joint_names} (global effects without a joint), or '
                      'module:EffectType[:joint] for your own')


def _load_user_effect(module: str, attribute: str, key: str, spec: str,
                      base_dir: str | Path | None) -> EffectType:
    try:
        if module.endswith('.py'):
            path = Path(module)
            if not path.is_absolute() and base_dir is not None:
                path = Path(base_dir) / path
            name = f'kpi_calib_user_effects_{path.stem}'
            mod_spec = importlib.util.spec_from_file_location(name, path)
            if mod_spec is None or mod_spec.loader is None or not path.is_file():
                raise FileNotFoundError(f'no file {str(path)!r}')
            mod = importlib.util.module_from_spec(mod_spec)
            sys.modules[name] = mod
            mod_spec.loader.exec_module(mod)
        else:
            mod = importlib.import_module(module)
        obj = getattr(mod, attribute)
        types = _as_effect_types(obj, f'{module}:{attribute}')
    except Exception as exc:
        raise ConfigError(key, f'{spec!r}: cannot load user effect {module}:{attribute} '
                          f'({exc})') from exc
    if len(types) != 1:
        raise ConfigError(key, f'{spec!r}: {module}:{attribute} gives {len(types)} effect '
                          'types; name exactly one')
    return register_effect(types[0], replace=True)


def resolve_effects(specs: Iterable[str | BoundEffect], robot: RobotModel,
                    key: str = 'effects', base_dir: str | Path | None = None,
                    allow_code: bool = False) -> tuple[BoundEffect, ...]:
    """Resolve specs (or pass bound effects through); duplicates are an error.
    ``allow_code``: see :func:`parse_effect_spec`."""
    out: list[BoundEffect] = []
    for i, spec in enumerate(specs):
        effect = spec if not isinstance(spec, str) else parse_effect_spec(
            spec, robot, f'{key}[{i}]', base_dir, allow_code)
        if any(e.name == effect.name for e in out):
            raise ConfigError(f'{key}[{i}]', f'effect {effect.name!r} is given twice')
        out.append(effect)
    return tuple(out)


def split_specs(text: str) -> list[str]:
    """``'a:j1,b:j2'`` -> ``['a:j1', 'b:j2']`` (command-line form)."""
    return [s.strip() for s in text.split(',') if s.strip()]


def candidate_effects(robot: RobotModel, kinds: Sequence[str] | None = None,
                      exclude: Iterable[str] = (),
                      covariates: Iterable[str] = ()) -> list[BoundEffect]:
    """Every (effect × joint) to screen: the ``screen`` library effects by default.

    ``exclude`` holds effect names (specs) already in the model; ``covariates`` the names
    the measurements carry: by default an effect that reads covariates is a candidate only
    where all its inputs are among them.
    """
    known = available_effects()
    if kinds is None:
        present = set(covariates)
        chosen = [t for t in known.values() if t.screen and set(t.inputs) <= present]
    else:
        unknown = [k for k in kinds if k not in known]
        if unknown:
            raise ConfigError('candidates', f'unknown effect(s) {unknown}; valid effects are '
                              f'{sorted(known)}')
        chosen = [known[k] for k in kinds]
    skip = set(exclude)
    out = []
    for effect_type in chosen:
        joints = robot.joint_names if effect_type.per_joint else [None]
        for joint in joints:
            if joint is not None and not effect_type.applies_to(
                    robot.joints[robot.joint_names.index(joint)].kind):
                continue  # e.g. no cyclic (angle) error on a prismatic joint
            effect = bind_effect(effect_type, robot, joint)
            if effect.name not in skip:
                out.append(effect)
    return out


def implausible(effect: BoundEffect, values: Sequence[float],
                tau: np.ndarray | None = None) -> str:
    """'' when every fitted value is within the effect's plausible range, else a warning
    naming the parameter, its value and the bound.

    ``tau``: (N, n) gravity torques of the measured poses (N m); the effect's joint's are
    used. An effect that contains ``joint_compliance`` as a limit of its shape (``joint_play``) is
    that compliance, b·τ/τ0, where every torque is below :data:`LINEAR_PLAY` τ0 (tanh
    within 4 % of linear): there b/τ0 must also be a plausible compliance."""
    kind = effect.kind
    bounds = kind.prismatic_plausible if effect.joint_kind == 'prismatic' else kind.plausible
    out = [f'{name} = {value:.3g} {unit} beyond the plausible ±{bound:.3g}'
           for name, value, unit, bound in zip(effect.parameter_names, values, effect.units,
                                               bounds or ())
           if abs(value) > bound]
    if not out and tau is not None and effect.joint_index is not None and len(tau) \
            and 'joint_compliance' in kind.nests and kind.n_shape == 1:
        out += _compliance_limit(effect, values, np.atleast_2d(tau)[:, effect.joint_index])
    return ('physically implausible: ' + '; '.join(out) +
            ' (the fit uses the effect to absorb something else)') if out else ''


LINEAR_PLAY = 1.0 / 3.0


def _compliance_limit(effect: BoundEffect, values: Sequence[float],
                      tau: np.ndarray) -> list[str]:
    compliance = _REGISTRY['joint_compliance']
    bound = (compliance.prismatic_plausible if effect.joint_kind == 'prismatic'
             else compliance.plausible)
    tau0 = PLAY_TORQUE_UNIT * math.exp(float(values[-1]))
    largest = float(np.max(np.abs(tau)))
    if not bound or largest >= LINEAR_PLAY * tau0:
        return []
    c = float(values[0]) / tau0
    if abs(c) <= bound[0]:
        return []
    unit = 'm/N' if effect.joint_kind == 'prismatic' else 'rad/(N m)'
    return [f'at the measured torques (|τ| ≤ {largest:.3g}, τ0 = {tau0:.3g}) it is the '
            f'compliance b/τ0 = {c:.3g} {unit}, beyond the plausible ±{bound[0]:.3g}']


# ----------------------------------------------------------------- simulation
def hidden_effects(doc: Any, robot: RobotModel, key: str = 'simulation.hidden_effects',
                   base_dir: str | Path | None = None, allow_code: bool = False
                   ) -> tuple[tuple[BoundEffect, ...], dict[str, float]]:
    """Effects the simulated "true" robot has and the model lacks.

    ``doc`` maps specs to parameter values, as in a cell file::

        simulation:
          hidden_effects:
            joint_compliance:joint_2: {c: 8.0e-7}
            tracker_scale: {s: 5.0e-6}

    A parameter left out takes the effect's typical size.

    Returns
    -------
    effects : tuple of BoundEffect
    overrides : dict
        Parameter name -> true value, for :func:`~kpi_calib_ros.core.simulation.true_parameters`.
    """
    if not doc:
        return (), {}
    if not isinstance(doc, dict):
        raise ConfigError(key, 'must be a mapping {effect:joint: {parameter: value}}')
    effects, overrides = [], {}
    for spec, values in doc.items():
        effect = parse_effect_spec(str(spec), robot, f'{key}.{spec}', base_dir, allow_code)
        values = values or {}
        if not isinstance(values, dict):
            raise ConfigError(f'{key}.{spec}',
                              f'must map parameters {list(effect.kind.parameters)} to values')
        unknown = set(values) - set(effect.kind.parameters)
        if unknown:
            raise ConfigError(f'{key}.{spec}.{sorted(unknown)[0]}', 'unknown parameter; '
                              f'{effect.kind.name} has {list(effect.kind.parameters)}')
        for suffix, name, typical in zip(effect.kind.parameters, effect.parameter_names,
                                         effect.typical):
            value = values.get(suffix, typical)
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise ConfigError(f'{key}.{spec}.{suffix}', f'must be a number, got {value!r}')
            overrides[name] = float(value)
        effects.append(effect)
    return tuple(effects), overrides

"""Physical effects the geometric model lacks: the registry, specs and the user API.

An effect is a small model with its own parameters that plugs into the
measurement model (:class:`~kpi_calib_ros.core.measurement.tracker.MeasurementModel`)
either as an additive correction of one joint value or as a correction of the
measured point. Its parameters get stable names (``joint_compliance.joint_2.c``)
and nominal value 0, so "no effect" is the geometric model.

Library (:mod:`kpi_calib_ros.core.effects.library`; per joint ``j`` unless noted; ``τ_j``
is the gravity torque from Pinocchio, payload included)::

    joint_compliance      δq_j = c · τ_j                   c  rad/(N m)
    gravity_compliance    δq_j = Σ g_i ψ_i(q), link masses unknown (see
                          :mod:`kpi_calib_ros.core.effects.gravity_compliance`)  g_i  rad
    cyclic_joint_error    δq_j = a · sin q_j + b · cos q_j  a, b  rad
    cyclic_joint_error_h2 δq_j = a · sin 2q_j + b · cos 2q_j
    joint_backlash        δq_j = b · tanh(τ_j / τ_b),      b  rad, τ_b = 0.01 N m
    joint_play            δq_j = b · tanh(τ_j / τ0),       b  rad, u = ln(τ0 / 1 N m)
                          τ0 = e^u N m identified
    joint_scale           δq_j = k · q_j                   k  1 (transmission ratio)
    tracker_scale         η = (1 + s) · h  (global)        s  1 (tracker length scale)

Thermal effects read the covariate ``delta_temperature`` (ΔT, K: the arm's temperature
minus the cell's reference, :mod:`kpi_calib_ros.core.measurement.covariates`); they are candidates
only where the measurements carry it::

    thermal_zero_drift    δq_j = d · ΔT_j                  d  rad/K
    thermal_link_growth   t_j -> (1 + α ΔT_j) · t_j        α  1/K (linear expansion)
    thermal_growth        every t_j -> (1 + α ΔT_j) · t_j  α  1/K  (global: one material)

``t_j`` is the nominal translation of joint j's origin from its parent (the URDF
``<origin xyz>``: the link before the joint); the growth is written into that joint's
placement error, so the geometric placement stays what it is at the reference temperature.
``ΔT_j`` is the mean ΔT, or, where the cell assigns joint j to a temperature sensor (its
``temperature.sensors`` mapping), that sensor's own ΔT (``delta_temperature.<frame_id>``):
binding with ``temperatures`` (joint name -> covariate name; :func:`bind_effect`) puts any
effect input ``delta_temperature`` of joint j onto it. The spec stays ``name:joint``.
Steel grows 11–13 µm/(m K), aluminium 23–24 µm/(m K): α outside ±30e-6 /K is flagged.

Sign of ``joint_compliance``: τ_j is Pinocchio's generalised gravity g(q), the torque
the drive must apply to *hold* the arm, and the model puts the joint at q + δq. A
joint of stiffness k sags along gravity, against its holding torque, so a physical
compliance is c = −1/k < 0. Industrial joints have k ≈ 1e4 … 1e7 N m/rad, harmonic drives
of small arms 5e3 … 1e5, hence |c| ≤ 2e-4 rad/(N m) plausible by default; a servo-stiff or
cable-driven arm yields to its position servo, 1/kp ≈ 1e-3 rad/(N m): the cell's
``identification.bounds`` widens the bound per effect and joint (:func:`effect_bounds`).

``joint_backlash`` is ``b·tanh(τ/τ_b)`` with τ_b = 0.01 N m (0.01 N for a prismatic joint,
:data:`~kpi_calib_ros.core.effects.library.BACKLASH_TORQUE_SCALE`), a smooth sgn τ: the sign
within 0.5 % wherever |τ| > 3 τ_b, and 0 where gravity exerts no torque at all (a vertical
first axis), so a joint without load shows no backlash instead of numerical noise. A joint
whose gravity torque stays below τ_b is never loaded out of its play: there the formula is
(b/τ_b)·τ, a compliance, and the diagnosis does not propose a backlash for it.

User effects
------------
Describe the effect with :class:`EffectType` and a CasADi function of the joint
state and the parameters, then make it known in one of three ways::

    import casadi as ca
    from kpi_calib_ros.core.effects.registry import EffectType, register_effect

    def _thermal(q_j, tau_j, theta):          # SX scalars, theta (k,) SX
        return theta[0] * ca.cos(q_j) ** 2    # additive joint correction, rad

    THERMAL = EffectType('thermal_bend', parameters=('g',), units=('rad',),
                         joint_function=_thermal, typical=(1e-4,),
                         plausible=(2e-3,),   # the largest physical |g|: without a
                         # bound the plausibility gate cannot judge the effect, and a
                         # calibration with it is not valid
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
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.effects.effect_types import BoundEffect, EffectType
from kpi_calib_ros.core.effects.library import LIBRARY, PLAY_TORQUE_UNIT
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.covariates import DELTA_TEMPERATURE
from kpi_calib_ros.core.model.robot import RobotModel

__all__ = [
    'ENTRY_POINT_GROUP', 'register_effect', 'available_effects', 'bind_effect', 'CHAIN_EFFECTS',
    'ARGUMENT_EFFECTS', 'parse_effect_spec', 'resolve_effects', 'split_specs',
    'candidate_effects', 'implausible', 'LINEAR_PLAY', 'COMPLIANCE_LIMIT', 'effect_bounds',
    'bound_key',
    'COVARIATE_CANDIDATES',
]

ENTRY_POINT_GROUP = 'kpi_calib_ros.effects'


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
                key: str = 'effects', temperatures: Mapping[str, str] | None = None
                ) -> BoundEffect:
    """Bind ``effect_type`` to ``joint`` of ``robot`` (None for a global effect).

    ``temperatures`` maps joint names to the covariate their thermal effects read in place of
    the arm's mean ``delta_temperature`` (``delta_temperature.<frame_id>`` of the sensor on
    that joint's link, the cell's ``temperature.sensors`` mapping): an input
    ``delta_temperature`` of the effect at such a joint reads it (per joint; for a global
    placement effect, at each joint it moves). Joints left out read the mean.
    """
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
                           origins=_origins(effect_type, robot),
                           joint_inputs=_joint_inputs(effect_type, names, temperatures,
                                                      joint))
    if joint is not None:
        raise ConfigError(key, f'effect {effect_type.name!r} is global; write '
                          f'{effect_type.name!r} without a joint')
    return BoundEffect(effect_type, None, None, len(names), origins=_origins(effect_type, robot),
                       joint_inputs=_joint_inputs(effect_type, names, temperatures))


def _joint_inputs(effect_type: EffectType, names: Sequence[str],
                  temperatures: Mapping[str, str] | None, joint: str | None = None
                  ) -> tuple[tuple[str, ...], ...] | None:
    """Return the covariates each joint reads with ``temperatures`` (see :func:`bind_effect`).

    None where nothing changes: no temperature input, no assignment, or (per joint) its joint
    not assigned; a global joint correction is one function of every joint and reads the
    kind's inputs. Per joint, the other joints keep the kind's inputs, so one effect bound
    for two cells that assign its joint alike is the same effect.
    """
    if not temperatures or DELTA_TEMPERATURE not in effect_type.inputs:
        return None
    if joint is None and effect_type.placement_function is None:
        return None
    unknown = sorted(set(temperatures) - set(names))
    if unknown:
        raise ValueError(f'temperatures name joints {unknown} not on the chain {list(names)}')
    out = tuple(tuple(temperatures.get(name, i)
                      if i == DELTA_TEMPERATURE and joint in (None, name) else i
                      for i in effect_type.inputs) for name in names)
    return None if all(t == effect_type.inputs for t in out) else out


def _origins(effect_type: EffectType, robot: RobotModel) -> np.ndarray | None:
    """(n, 3) nominal origin translation of every joint in its placement frame, m.

    For a placement effect; None otherwise.
    """
    if effect_type.placement_function is None:
        return None
    return np.array([np.asarray(j.placement)[:3, :3].T @ np.asarray(j.placement)[:3, 3]
                     for j in robot.joints])


# Effects built from the whole chain rather than one joint's (q_j, τ_j): spec name ->
# binder(robot, joint, key) -> BoundEffect. core.effects.gravity_compliance registers its own.
CHAIN_EFFECTS: dict[str, Callable[[RobotModel, str | None, str], BoundEffect]] = {}
# Effects with a constant of their own in the spec, ``name:joint:argument``
# (``periodic_joint_error:joint_2:k=17``): spec name -> binder(robot, joint, argument,
# key) -> BoundEffect. core.effects.general registers its own.
ARGUMENT_EFFECTS: dict[str, Callable[[RobotModel, str | None, str, str], BoundEffect]] = {}
# Effects proposed only where the measurements carry the covariates they read, with names
# derived from those covariates (a tilt sensor's): candidates(robot, covariate names) ->
# bound effects. core.effects.tilt registers its own.
COVARIATE_CANDIDATES: list[Callable[[RobotModel, Iterable[str]], list[BoundEffect]]] = []


def parse_effect_spec(spec: str, robot: RobotModel, key: str = 'effects',
                      base_dir: str | Path | None = None,
                      allow_code: bool = False,
                      temperatures: Mapping[str, str] | None = None) -> BoundEffect:
    """Resolve ``'effect[:joint]'`` or ``'module:attribute[:joint]'`` to an effect.

    ``module`` is an importable module or a ``.py`` file (relative to
    ``base_dir``, the cell file's folder); ``attribute`` names an
    :class:`EffectType` or a callable returning one. Loading it runs its code, so
    this form needs ``allow_code=True`` (``--allow-code-effects`` on the command
    line, ``allow_code_effects`` on the node): a data file alone never runs code.
    Built-in effects and installed entry points need no opt-in. ``temperatures``: the
    temperature each joint's thermal effects read (:func:`bind_effect`; a cell's model keeps
    it as ``MeasurementModel.joint_temperatures``).

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
    if parts[0] in ARGUMENT_EFFECTS:
        return ARGUMENT_EFFECTS[parts[0]](robot, parts[1] if len(parts) > 1 else None,
                                          ':'.join(parts[2:]), where)
    if parts[0] in known:
        if len(parts) > 2:
            raise ConfigError(key, f'{spec!r}: write effect:joint, e.g. {parts[0]}:'
                              f'{robot.joint_names[min(1, robot.n_joints - 1)]}')
        return bind_effect(known[parts[0]], robot, parts[1] if len(parts) == 2 else None, where,
                           temperatures)
    if len(parts) in (2, 3) and ('.' in parts[0] or parts[0].endswith('.py')):
        if not allow_code:
            raise ConfigError(key, f'{spec!r} names Python code ({parts[0]}), which is not run '
                              'unless asked: pass --allow-code-effects to kpi-calib, or set '
                              'the node parameter allow_code_effects:=true, if you trust '
                              f'it; built-in effects are {sorted(known)}')
        effect_type = _load_user_effect(parts[0], parts[1], key, spec, base_dir)
        return bind_effect(effect_type, robot, parts[2] if len(parts) == 3 else None, where,
                           temperatures)
    every = sorted(set(known) | set(CHAIN_EFFECTS) | set(ARGUMENT_EFFECTS))
    raise ConfigError(key, f'{spec!r}: unknown effect {parts[0]!r}; valid effects are '
                      f'{every}, written effect:joint with a '
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
                    allow_code: bool = False, temperatures: Mapping[str, str] | None = None
                    ) -> tuple[BoundEffect, ...]:
    """Resolve specs (or pass bound effects through); duplicates are an error.

    ``allow_code``, ``temperatures``: see :func:`parse_effect_spec`.
    """
    out: list[BoundEffect] = []
    for i, spec in enumerate(specs):
        effect = spec if not isinstance(spec, str) else parse_effect_spec(
            spec, robot, f'{key}[{i}]', base_dir, allow_code, temperatures)
        if any(e.name == effect.name for e in out):
            raise ConfigError(f'{key}[{i}]', f'effect {effect.name!r} is given twice')
        out.append(effect)
    return tuple(out)


def split_specs(text: str) -> list[str]:
    """``'a:j1,b:j2'`` -> ``['a:j1', 'b:j2']`` (command-line form)."""
    return [s.strip() for s in text.split(',') if s.strip()]


def candidate_effects(robot: RobotModel, kinds: Sequence[str] | None = None,
                      exclude: Iterable[str] = (),
                      covariates: Iterable[str] = (),
                      temperatures: Mapping[str, str] | None = None) -> list[BoundEffect]:
    """Every (effect × joint) to screen: the ``screen`` library effects by default.

    ``exclude`` holds effect names (specs) already in the model; ``covariates`` the names
    the measurements carry: by default an effect that reads covariates is a candidate only
    where all the inputs it reads as bound are among them, and the effects named after the
    covariates (:data:`COVARIATE_CANDIDATES`: a tilt sensor's) are proposed where they are
    recorded. ``temperatures``: the temperature
    each joint's thermal effects read (:func:`bind_effect`).
    """
    known = available_effects()
    present = set(covariates)
    if kinds is None:
        chosen = [t for t in known.values() if t.screen]
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
            effect = bind_effect(effect_type, robot, joint, temperatures=temperatures)
            if effect.name in skip or (kinds is None and not set(effect.inputs) <= present):
                continue
            out.append(effect)
    if kinds is None:
        out += [effect for propose in COVARIATE_CANDIDATES for effect in propose(robot, present)
                if effect.name not in skip]
    return out


# A cell's ``identification.bounds``: an effect spec (``joint_play:joint_4``), a kind and
# joint, or a kind alone -> the largest plausible |value| of each of its parameters.
Bounds = Mapping[str, Sequence[float]]


def bound_key(effect: BoundEffect) -> str:
    """Return the cell key that widens ``effect``'s bounds at its joint.

    ``identification.bounds.joint_compliance:joint_2``; the kind alone for a global effect.
    """
    kind = effect.kind.name
    return 'identification.bounds.' + (kind if effect.joint is None else f'{kind}:{effect.joint}')


def effect_bounds(effect: BoundEffect, overrides: Bounds | None = None) -> tuple[float, ...]:
    """Largest physically plausible |value| of each parameter of ``effect`` (its units).

    The cell's ``overrides`` (``identification.bounds``) first: the effect's own spec
    (``periodic_joint_error:joint_2:k=17``), then its kind at its joint
    (``joint_compliance:joint_2``), then its kind (``joint_compliance``, every joint); one
    number stands for every parameter. Else the kind's ``plausible`` (``prismatic_plausible``
    on a prismatic joint); () when the kind states none.
    """
    kind = effect.kind
    for key in (effect.name, None if effect.joint is None else f'{kind.name}:{effect.joint}',
                kind.name):
        if key is not None and overrides and key in overrides:
            given = tuple(float(b) for b in overrides[key])
            n = len(effect.parameter_names)
            if len(given) not in (1, n):
                # A chain effect's parameters are counted only once bound to the robot
                # (gravity_compliance: the rank of its joint's torque functions).
                raise ConfigError(f'identification.bounds.{key}', f'{len(given)} bounds for '
                                  f'the {n} parameters {list(effect.parameter_names)} of '
                                  f'{effect.name}: give one bound (every parameter) or {n}')
            return given * n if len(given) == 1 else given
    bounds = kind.prismatic_plausible if effect.joint_kind == 'prismatic' else kind.plausible
    return tuple(bounds or ())


def implausible(effect: BoundEffect, values: Sequence[float] | np.ndarray,
                tau: np.ndarray | None = None, bounds: Bounds | None = None) -> str:
    """Return '' when every fitted value is within the effect's plausible range, else a warning.

    The warning names the parameter, its value and the bound.

    ``tau``: (N, n) gravity torques of the measured poses (N m); the effect's joint's are
    used. An effect that contains ``joint_compliance`` as a limit of its shape (``joint_play``) is
    that compliance, b·τ/τ0, where every torque is below :data:`LINEAR_PLAY` τ0 (tanh
    within 4 % of linear): there b/τ0 must also be a plausible compliance. ``bounds``: the
    cell's ``identification.bounds`` (:func:`effect_bounds`).
    """
    kind = effect.kind
    limits = effect_bounds(effect, bounds)
    out = [f'{name} = {value:.3g} {unit} beyond the plausible ±{bound:.3g}'
           for name, value, unit, bound in zip(effect.parameter_names, values, effect.units,
                                               limits)
           if abs(value) > bound]
    if kind.gains:
        out += [f'{name} = {value:.3g}, below the plausible magnitude {1 / bound:.3g} (the '
                'input in other units than stated, e.g. milliradians as radians, or reading '
                'something else)'
                for name, value, bound in zip(effect.parameter_names, values, limits)
                if bound > 0 and abs(value) < 1 / bound]
    if not out and tau is not None and effect.joint_index is not None and len(tau) \
            and 'joint_compliance' in kind.nests and kind.n_shape == 1:
        out += _compliance_limit(effect, values, np.atleast_2d(tau)[:, effect.joint_index],
                                 bounds)
    return ('physically implausible: ' + '; '.join(out) +
            ' (the fit uses the effect to absorb something else, or the bound is too '
            'tight for this arm)') if out else ''


LINEAR_PLAY = 1.0 / 3.0
# The words of a play judged as the compliance it is (the gate names the compliance's key).
COMPLIANCE_LIMIT = 'it is the compliance'


def _compliance_limit(effect: BoundEffect, values: Sequence[float] | np.ndarray,
                      tau: np.ndarray, bounds: Bounds | None = None) -> list[str]:
    compliance = BoundEffect(_REGISTRY['joint_compliance'], effect.joint, effect.joint_index,
                             effect.n_joints, effect.joint_kind)
    bound = effect_bounds(compliance, bounds)
    tau0 = PLAY_TORQUE_UNIT * math.exp(float(values[-1]))
    largest = float(np.max(np.abs(tau)))
    if not bound or largest >= LINEAR_PLAY * tau0:
        return []
    c = float(values[0]) / tau0
    if abs(c) <= bound[0]:
        return []
    unit = 'm/N' if effect.joint_kind == 'prismatic' else 'rad/(N m)'
    return [f'at the measured torques (|τ| ≤ {largest:.3g}, τ0 = {tau0:.3g}) '
            f'{COMPLIANCE_LIMIT} b/τ0 = {c:.3g} {unit}, beyond the plausible ±{bound[0]:.3g}']

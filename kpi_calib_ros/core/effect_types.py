"""Types of physical effects: :class:`EffectType`, a kind of effect before it is bound to a
joint, and :class:`BoundEffect`, one bound to a joint of a robot (or global), the form the
measurement model uses. The library of effects is :mod:`kpi_calib_ros.core.effect_library`;
specs, the registry and the user API are :mod:`kpi_calib_ros.core.effects`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import casadi as ca


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

    def __post_init__(self) -> None:
        if not self.name or ':' in self.name or '.' in self.name:
            raise ValueError(f'effect name {self.name!r} must be non-empty without ":" or "."')
        if (self.joint_function is None) == (self.point_function is None):
            raise ValueError(f'effect {self.name!r}: give exactly one of joint_function '
                             'and point_function')
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

    def __post_init__(self) -> None:
        prefix = self.kind.name if self.joint is None else f'{self.kind.name}.{self.joint}'
        object.__setattr__(self, 'name', self.kind.name if self.joint is None
                           else f'{self.kind.name}:{self.joint}')
        object.__setattr__(self, 'parameter_names',
                           tuple(f'{prefix}.{s}' for s in self.kind.parameters))
        object.__setattr__(self, 'units', self.kind.units_for(self.joint_kind))
        object.__setattr__(self, 'uses_torque', self.kind.uses_torque)

    @property
    def typical(self) -> tuple[float, ...]:
        """Typical magnitude of each parameter (its units), 1 where the kind states none."""
        return self.kind.typical or (1.0,) * len(self.kind.parameters)

    @property
    def shape_names(self) -> tuple[str, ...]:
        """Names of its shape parameters (the last ``kind.n_shape``; empty when linear)."""
        return self.parameter_names[len(self.parameter_names) - self.kind.n_shape:] \
            if self.kind.n_shape else ()

    def joint_correction(self, q: ca.SX, tau: ca.SX, theta: ca.SX) -> Any:
        """Additive joint-value correction, SX (n,), or None for a point effect."""
        fn = self.kind.joint_function
        if fn is None:
            return None
        if self.joint_index is None:
            return fn(q, tau, theta)
        out = ca.SX.zeros(self.n_joints)
        out[self.joint_index] = fn(q[self.joint_index], tau[self.joint_index], theta)
        return out

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

"""Types of physical effects: :class:`EffectType` and :class:`BoundEffect`.

:class:`EffectType` is a kind of effect before it is bound to a joint, and :class:`BoundEffect`
one bound to a joint of a robot (or global), the form the measurement model uses. The library of
effects is :mod:`kpi_calib_ros.core.effects.library`; specs, the registry and the user API are
:mod:`kpi_calib_ros.core.effects.registry`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import casadi as ca
import numpy as np

__all__ = ['EffectType', 'BoundEffect']


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
        beyond it is flagged (see :func:`implausible`). Empty: no bound, and the
        plausibility gate refuses a calibration with the effect (it cannot tell an
        impossible or undetermined value) unless the cell's ``identification.bounds`` gives
        one (for a registered or installed effect).
    prismatic_plausible : tuple of float, optional
        The same for a prismatic joint (its units); None: no bound there.
    shape_grid : tuple of tuple of float
        For an effect nonlinear in its last parameters (they set the shape, not the size:
        their Jacobian column vanishes at zero size), the values of those shape parameters
        the linear screening tries (:func:`kpi_calib_ros.core.diagnosis.screening.screen_effects`
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
        ``f(t, theta[, z]) -> SX (6,)``: additive correction of a joint's placement error
        (tx, ty, tz m in the joint's placement frame; rx, ry, rz rad) given ``t`` (3,), the
        joint's nominal origin translation expressed in that frame (``M_jᵀ`` applied). Per
        joint it moves its joint; global, every joint.
    general : bool
        A general effect (a periodic joint error at a frequency found from the data, link
        bending; :mod:`kpi_calib_ros.core.effects.general`) rather than a named mechanism:
        the diagnosis ranks it after the significant, plausible named effects.
    gains : bool
        Its parameters are gains of a measured input (a sensor reading the turn it models):
        plausible between 1/bound and bound in magnitude. A gain far below 1/bound says the
        input is in other units than stated (milliradians given as radians fit a gain of
        1e-3) or measures something else.
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
    general: bool = False
    gains: bool = False

    def __post_init__(self) -> None:
        """Check the name, the single correction function, parameters, units, sizes, bounds."""
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
    ``searched``: the number of alternatives a search on the same data chose this
    candidate from (a frequency of :mod:`kpi_calib_ros.core.diagnosis.periodic_search`); the screen
    multiplies its p-value by it, so the search counts in the test's level.
    ``joint_inputs``: the covariates each chain joint's correction reads in place of the
    kind's ``inputs`` (one tuple per joint, in the order of ``kind.inputs``), or None: the
    kind's inputs at every joint. :func:`~kpi_calib_ros.core.effects.registry.bind_effect` sets
    it from the cell's temperature sensors (a joint's thermal effect reads the ΔT of the sensor
    on its link); the spec and the parameter names stay those of the kind and joint.
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
    searched: int = field(default=1, compare=False)
    joint_inputs: tuple[tuple[str, ...], ...] | None = None

    def __post_init__(self) -> None:
        """Derive the name, parameter names, units and torque use from the kind and joint."""
        prefix = self.kind.name if self.joint is None else f'{self.kind.name}.{self.joint}'
        object.__setattr__(self, 'name', self.kind.name if self.joint is None
                           else f'{self.kind.name}:{self.joint}')
        object.__setattr__(self, 'parameter_names',
                           tuple(f'{prefix}.{s}' for s in self.kind.parameters))
        object.__setattr__(self, 'units', self.kind.units_for(self.joint_kind))
        object.__setattr__(self, 'uses_torque', self.kind.uses_torque)
        if self.joint_inputs is not None and (
                len(self.joint_inputs) != self.n_joints
                or any(len(names) != len(self.kind.inputs) for names in self.joint_inputs)):
            raise ValueError(f'effect {self.name!r}: joint_inputs needs one tuple of '
                             f'{len(self.kind.inputs)} covariate names per joint '
                             f'({self.n_joints})')

    def _joints(self) -> tuple[int, ...]:
        """Chain indices of the joints the correction acts on."""
        if self.joint_index is not None:
            return (self.joint_index,)
        if self.kind.placement_function is not None and self.origins is not None:
            return tuple(j for j in range(self.n_joints) if np.any(self.origins[j] != 0))
        return tuple(range(self.n_joints))

    def inputs_at(self, joint: int) -> tuple[str, ...]:
        """Covariates the correction of chain joint ``joint`` reads (``kind.inputs`` order)."""
        return self.kind.inputs if self.joint_inputs is None else self.joint_inputs[joint]

    @property
    def inputs(self) -> tuple[str, ...]:
        """Covariates the effect reads (``Measurements.covariates`` names).

        The kind's, or with ``joint_inputs`` those its joints read, each once, in chain
        order: the order of the argument ``z`` of its corrections.
        """
        if self.joint_inputs is None or not self.kind.inputs:
            return self.kind.inputs
        return tuple(dict.fromkeys(n for j in self._joints() for n in self.inputs_at(j)))

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
        """Additive joint-value correction, SX (n,), or None for a point or placement effect.

        ``z`` the covariates :attr:`inputs` (SX, an effect with inputs only).
        """
        fn = self.kind.joint_function
        if fn is None:
            return None
        extra = (z,) if self.kind.inputs else ()
        if self.joint_index is None:
            # a global joint correction reads the kind's inputs (bind_effect maps none)
            return fn(q, tau, theta, *extra)
        out = ca.SX.zeros(self.n_joints)
        # No torques (the design's symbolic refinement, which runs only when no effect reads
        # them): an effect of an angle or an input gets a zero torque it does not read.
        torque = tau[self.joint_index] if tau is not None else ca.SX.zeros(1)
        out[self.joint_index] = fn(q[self.joint_index], torque, theta, *extra)
        return out

    def placement_correction(self, theta: ca.SX, z: Any = None) -> list[tuple[int, Any]]:
        """Additive corrections of joint placement errors: [(joint index, SX (6,))].

        Empty unless the kind has a ``placement_function``.
        """
        fn = self.kind.placement_function
        if fn is None or self.origins is None:
            return []
        names = self.inputs
        out = []
        for j in self._joints():
            if not np.any(self.origins[j] != 0):
                continue
            # each joint's own covariates, picked from z (in the order of ``inputs``)
            extra = (ca.vertcat(*[z[names.index(n)] for n in self.inputs_at(j)]),) \
                if self.kind.inputs else ()
            out.append((j, fn(ca.DM(self.origins[j]), theta, *extra)))
        return out

    def point_correction(self, point: ca.SX, theta: ca.SX) -> Any:
        """Corrected measured point, SX (3,), or None for a joint effect."""
        fn = self.kind.point_function
        return None if fn is None else fn(point, theta)

    def frame_correction(self, q: ca.SX, tau: ca.SX, theta: ca.SX, z: Any = None) -> Any:
        """``(joint index, SX (3, 3) rotation)`` applied to that joint's frame after its motion.

        For link bending (:class:`kpi_calib_ros.core.effects.general.LinkBending`); None
        otherwise: the library's effects correct joint values or the point only. ``z`` the
        covariates :attr:`inputs`.
        """
        return None

    def hint(self) -> str:
        """Say what would make this effect distinguishable, with the joint named."""
        return self.kind.hint.replace('{joint}', self.joint or 'the joint')

    def signature(self) -> str:
        """Say what the fitted correction follows, with the joint named."""
        return self.kind.signature.replace('{joint}', self.joint or 'the joint')

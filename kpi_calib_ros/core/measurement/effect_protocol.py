"""The protocol of a physical effect in the measurement model, and its optional members.

An effect states its parameters (names, units) and CasADi corrections: of the joint values
(``joint_correction``) and of the measured point (``point_correction``), both required
(either may return None). It may add any of the members of :class:`OptionalEffect`: the
covariates it reads (``inputs``), corrections of the joints' placement, a rotation of a
joint's frame after its motion (link bending) or before it (a measured tilt). The model reads
them through :func:`effect_inputs` and :func:`optional_correction`, so an effect without them
corrects joint values or the point only. See :mod:`kpi_calib_ros.core.effects.registry` for
the library.
"""
from __future__ import annotations

from typing import Any, Callable, Protocol, Sequence

import casadi as ca

__all__ = ['Effect', 'OptionalEffect', 'OPTIONAL_CORRECTIONS', 'effect_inputs', 'bound_arguments',
           'optional_correction']


class Effect(Protocol):
    """A physical effect that the geometric model lacks.

    Implementations give parameter names/units/nominal values and CasADi
    expressions; see :mod:`kpi_calib_ros.core.effects.registry` for the library.
    """

    # Read-only: implementations may be frozen dataclasses.
    @property
    def name(self) -> str:
        """Stable name, the prefix of its parameters' names."""

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of its parameters, in the order of their slice of p."""

    @property
    def units(self) -> tuple[str, ...]:
        """Unit of each parameter."""

    @property
    def uses_torque(self) -> bool:
        """Whether its expressions read the gravity torques (the model then supplies them)."""

    def joint_correction(self, q: ca.SX, tau: ca.SX, theta: ca.SX) -> ca.SX | None:
        """Additive joint-value correction (n,) or None."""

    def point_correction(self, point: ca.SX, theta: ca.SX) -> ca.SX | None:
        """Measured point (3,) in the tracker frame after the effect, or None."""


class OptionalEffect(Effect, Protocol):
    """The optional members an :class:`Effect` may add, any of them or none.

    An effect with ``inputs`` gets them as one more argument ``z`` (SX (len(inputs),), in
    that order) of ``joint_correction(q, tau, theta, z)``, ``placement_correction`` and
    ``tilt_correction``. Read through :func:`effect_inputs` and :func:`optional_correction`.
    """

    @property
    def inputs(self) -> tuple[str, ...]:
        """Names of the covariates it reads (default ()).

        See :mod:`kpi_calib_ros.core.measurement.covariates`.
        """

    def placement_correction(self, theta: ca.SX, *z: ca.SX) -> Sequence[tuple[int, ca.SX]]:
        """Additive corrections ``[(joint index, SX (6,))]`` of joint placement errors.

        (tx, ty, tz m; rx, ry, rz rad).
        """

    def frame_correction(self, q: ca.SX, tau: ca.SX, theta: ca.SX, *z: ca.SX
                         ) -> tuple[int, ca.SX] | None:
        """Rotation ``(joint index, SX (3, 3))`` of that joint's frame after its motion, or None.

        Link bending.
        """

    def tilt_correction(self, theta: ca.SX, *z: ca.SX) -> tuple[int, ca.SX] | None:
        """Rotation ``(joint index, SX (3, 3))`` of that joint's frame as placed, or None.

        In the base frame's axes, before its motion, about its origin (a measured tilt,
        :mod:`kpi_calib_ros.core.effects.tilt`).
        """


# The optional corrections of :class:`OptionalEffect`, read by :func:`optional_correction`.
OPTIONAL_CORRECTIONS = ('placement_correction', 'frame_correction', 'tilt_correction')


def effect_inputs(effect: Effect) -> tuple[str, ...]:
    """Names of the covariates ``effect`` reads (its optional ``inputs``; () if none)."""
    return tuple(getattr(effect, 'inputs', ()) or ())


def optional_correction(effect: Effect, name: str) -> Callable[..., Any] | None:
    """Return ``effect``'s optional correction ``name`` (a bound method), None if it has none.

    Raises
    ------
    ValueError
        ``name`` is not one of :data:`OPTIONAL_CORRECTIONS`.
    """
    if name not in OPTIONAL_CORRECTIONS:
        raise ValueError(f'{name!r} is not an optional correction of an effect; one of '
                         f'{OPTIONAL_CORRECTIONS}')
    return getattr(effect, name, None)


def bound_arguments(effects: Sequence[Effect], p: Any, offset: int, z: Any,
                    inputs: Sequence[str]) -> list[tuple[Effect, Any, tuple]]:
    """Return each effect with its parameter slice and its optional fourth argument.

    The slices of ``p`` follow one another from ``offset`` on, in order; the fourth argument
    is the covariates the effect reads, picked from ``z`` (ordered as ``inputs``), or () for
    an effect that reads none.
    """
    out = []
    for effect in effects:
        names = effect_inputs(effect)
        extra = (ca.vertcat(*[z[list(inputs).index(m)] for m in names]),) if names else ()
        out.append((effect, p[offset:offset + len(effect.parameter_names)], extra))
        offset += len(effect.parameter_names)
    return out

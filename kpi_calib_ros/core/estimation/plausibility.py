"""The plausibility gate: every identified quantity physically possible and determined.

A fit can converge, pass χ² and estimate the TCP while a quantity in it is impossible: a
reflector 2.6 m from the one the cell states, a link origin moved by metres, a joint play
of b = −0.56 ± 820 rad. Such a model predicts the measured poses and nothing else (the
quantities trade against each other along a direction the poses do not determine). The gate
checks every identified quantity against what the cell states about it:

* the base pose in the tracker frame (``base.*``): within ``base_translation`` /
  ``base_rotation`` of the placement the identification started from (the cell's
  ``tracker.base_in_tracker``, or its registration from the points); the base pose of every
  further recording (``recording.<name>.base.*``) likewise within those tolerances of its own
  registration, and a remounted probe's offsets (``recording.<name>.reflector.*``, registered,
  not stated) determined by the data (std within ``reflector_offset``);
* every reflector offset (``reflector[.<name>].{x,y,z}``): within ``reflector_offset`` of the
  cell's ``reflector.offset`` (a prior with a tolerance, never a start to throw away); when
  the cell leaves it out, determined by the postures (the registration's std);
* every joint placement correction: within ``translation`` (m) / ``rotation`` (rad) of the
  URDF; every joint zero offset within ``offset`` (rad, m for a prismatic joint);
* every effect parameter: within its bound
  (:func:`kpi_calib_ros.core.effects.registry.effect_bounds`: the library's ``plausible``
  sizes, widened per effect and joint by the cell's ``identification.bounds``).

An effect parameter whose std exceeds its bound is *undetermined*: the data cannot say where
it is, whatever its value; a placement or geometric parameter moved beyond its tolerance with
a std beyond it too is undetermined as well (within its tolerance it is a plausible robot,
however loosely a near-gauge pair of parameters is pinned). Each violation names the
quantity, why, and the fix (poses of a kind, a tolerance key, a bound key). A calibration with
any is not valid.

Defaults (:class:`Tolerances`) are what a calibration engineer accepts from a nominal model:
an arm built to its drawing is off by millimetres and tenths of a degree, so a placement
correction of 5 cm or 0.05 rad (~3°) is a wrong model, not a calibration; a joint zero is set
by homing or mastering and may be off by degrees (a TIAGo wrist: 3.2°), not by more than 0.2
rad (~11°); a surveyed base pose is good to a few cm (10 cm, 0.1 rad allowed); a reflector
nest on a drawn tool to a few mm (2 cm allowed).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.effects.registry import (
    COMPLIANCE_LIMIT,
    BoundEffect,
    bound_key,
    effect_bounds,
    implausible,
)
from kpi_calib_ros.core.estimation.identifiability import select_identifiable
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.measurement.pose import orientation_names
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.model.parameters import RECORDING_PREFIX, reflector_prefixes

__all__ = ['Tolerances', 'Violation', 'gate', 'geometric_violations', 'effect_violations',
           'registration_violations', 'reflector_shift', 'moved_beyond',
           'gauge_free_deviation', 'observed_std', 'structural_jacobian', 'TURN_RANGE_RAD',
           'STRUCTURAL_POSES']

# A wrist joint measured over less than this range (rad) hardly turns the tool: named in the
# fix of an undetermined reflector offset.
TURN_RANGE_RAD = 1.0


@dataclass(frozen=True)
class Tolerances:
    """How far an identified quantity may be from what the cell states (m, rad).

    ``bounds``: the cell's ``identification.bounds`` (effect spec, ``kind:joint`` or kind ->
    the largest |value| of each parameter; see
    :func:`~kpi_calib_ros.core.effects.registry.effect_bounds`).
    """

    base_translation: float = 0.1
    base_rotation: float = 0.1
    reflector_offset: float = 0.02
    translation: float = 0.05
    rotation: float = 0.05
    offset: float = 0.2
    bounds: Mapping[str, tuple[float, ...]] = field(default_factory=dict)


@dataclass(frozen=True)
class Violation:
    """A quantity the gate refuses: which, why and the fix."""

    quantity: str
    reason: str
    fix: str

    def text(self) -> str:
        """One line: the quantity, why, and what to do."""
        return f'{self.quantity}: {self.reason}; fix: {self.fix}'


# Poses drawn uniformly in the joint limits that stand for "poses spread over every joint"
# (the structural rank of the model), and the seed they are drawn with.
STRUCTURAL_POSES = 60


def structural_jacobian(model: MeasurementModel, values: np.ndarray, seed: int = 0
                        ) -> np.ndarray:
    """Return the Jacobian (3 M, P) of every parameter at ``values`` over spread poses.

    :data:`STRUCTURAL_POSES` joint values drawn uniformly in the limits (each reflector at
    each): the directions poses spread over every joint determine; its null space is what no
    pose can see.
    """
    robot = model.robot
    spread = robot.sample_configurations(np.random.default_rng(seed), STRUCTURAL_POSES)
    n_ref = max(model.n_reflectors, 1)
    ref_s = np.repeat(np.arange(n_ref), len(spread))
    blocks = []
    # Every recording at every spread pose: each one's placement is seen by its own rows.
    for k in range(len(model.recordings) + 1):
        # The model's other inputs (a measured tilt, a temperature) at zero: the structure
        # is the robot's; with any recording, covariates must carry every input.
        z = {name: np.zeros(len(ref_s)) for name in model.inputs}
        z.update({f'{RECORDING_PREFIX}{name}': np.full(len(ref_s), float(i + 1 == k))
                  for i, name in enumerate(model.recordings)})
        _, jac = model.jacobian(np.asarray(values, float), np.tile(spread, (n_ref, 1)), None,
                                ref_s if n_ref > 1 else None, covariates=z or None)
        blocks.append(jac.reshape(-1, len(model.params)))
    return np.vstack(blocks)


def gauge_free_deviation(model: MeasurementModel, values: np.ndarray, reference: np.ndarray,
                         scale: np.ndarray, n_geometric: int) -> np.ndarray:
    """Return the geometric deviation ``values − reference`` (n_geometric,) closest to zero.

    Closest in units of ``scale`` (the tolerances), among the parameter vectors no pose can
    tell apart. Where a design leaves a parameter out (held at its nominal value), a structurally
    equivalent one carries its part: a joint-6 zero and a reflector offset along its
    circle show up as a tilt of joint 6's placement of 0.14 rad that predicts every point to
    the noise. The physics is judged on the representative of the whole equivalence class:
    the deviation minus its component in the null space of the
    :func:`structural_jacobian` of the geometric parameters (at the reference robot), the
    least-squares one in tolerance units.
    """
    d = np.asarray(values[:n_geometric], float) - np.asarray(reference[:n_geometric], float)
    units = model.params.units[:n_geometric]
    d = np.array([_wrapped(x, u) for x, u in zip(d, units)])
    # The null space of the reference robot: where the structure is the one the URDF
    # describes (at an estimate metres off, the linearisation would be of another robot).
    at = np.array(values, float)
    at[:n_geometric] = reference[:n_geometric]
    jac = structural_jacobian(model, at)[:, :n_geometric] * scale
    _, sv, vt = np.linalg.svd(jac, full_matrices=False)
    null = vt[sv < 1e-9 * sv[0]] if len(sv) and sv[0] > 0 else vt[:0]
    u = d / scale
    return (u - null.T @ (null @ u)) * scale


def observed_std(model: MeasurementModel, result: CalibrationResult, names: Sequence[str],
                 q: np.ndarray, reflector: np.ndarray | None = None,
                 tau: np.ndarray | None = None, seed: int = 0,
                 covariates: Mapping[str, np.ndarray] | None = None) -> dict[str, float]:
    """Std (parameter units) of each of ``names`` as the poses ``q`` (N, n) determine it.

    Beside every other direction of the model that poses spread over every joint determine.

    The parameters those spread poses identify (:func:`~kpi_calib_ros.core.estimation.
    identifiability.select_identifiable` on :data:`STRUCTURAL_POSES` joint values drawn in
    the limits, ``names`` first) are fitted, in the linearisation at the estimate, to the
    measured poses at the result's σ: the std of a name is its std in that fit, inf when the
    measured poses cannot tell it from the others at all. A name the spread poses do not
    identify either (a gauge another parameter carries) is left out. Unlike the fit's own std
    this does not depend on which parameters the fit kept: a reflector offset the fit kept in
    place of the wrist geometry the poses never moved is as undetermined as one it dropped.
    ``reflector``: (N,) reflector index of each row; ``tau``: (N, n) gravity torques;
    ``covariates``: the rows' covariates (their recording, :attr:`MeasurementModel.inputs`).
    """
    params = model.params
    values = np.asarray(result.values, float)
    n_ref = max(model.n_reflectors, 1)
    structural = select_identifiable(structural_jacobian(model, values, seed), params.names,
                                     method='priority', priority=list(names),
                                     explain=False).kept
    wanted = [n for n in names if n in structural]
    if not wanted:
        return {}
    q = np.atleast_2d(q)
    rows = np.ones(len(q), bool) if reflector is None else np.asarray(reflector) < n_ref
    _, jac = model.jacobian(values, q[rows], None if tau is None else np.atleast_2d(tau)[rows],
                            None if reflector is None else np.asarray(reflector)[rows],
                            covariates=None if covariates is None else {
                                k: np.asarray(v)[rows] for k, v in covariates.items()})
    sigma = np.broadcast_to(np.asarray(result.sigma, float), (int(rows.sum()), 3))
    f = (jac / sigma[:, :, None]).reshape(-1, len(params))[:, params.indices(list(structural))]
    norms = np.linalg.norm(f, axis=0)
    norms[norms == 0] = 1.0
    _, sv, vt = np.linalg.svd(f / norms, full_matrices=False)
    weak = sv < 1e-10 * sv[0]
    inverse = np.where(weak, 0.0, 1.0 / np.where(weak, 1.0, sv) ** 2)
    var = (vt.T ** 2) @ inverse / norms ** 2
    var[np.any(np.abs(vt[weak]) > 1e-6, axis=0)] = np.inf
    return {n: float(np.sqrt(var[structural.index(n)])) for n in wanted}


def _wrapped(d: float, unit: str) -> float:
    return float((d + np.pi) % (2 * np.pi) - np.pi) if unit == 'rad' else float(d)


def _tolerance_key(name: str, unit: str) -> str:
    """Return the :class:`Tolerances` field of a geometric parameter."""
    if name.startswith(RECORDING_PREFIX):
        # a further recording's placement: its base pose, or its remounted reflector's
        # offset (m) or tracked body's orientation (rad), judged as the first recording's
        if '.reflector' in name:
            return 'reflector_offset' if unit == 'm' else 'rotation'
        return 'base_' + ('translation' if unit == 'm' else 'rotation')
    if name.startswith('reflector'):  # an offset, or a tracked body's orientation (rad)
        return 'reflector_offset' if unit == 'm' else 'rotation'
    base = name.startswith('base.')
    if name.endswith('.offset') and not base:
        return 'offset'
    return ('base_' if base else '') + ('translation' if unit == 'm' else 'rotation')


def _tolerance(tolerances: Tolerances, name: str, unit: str) -> float:
    return float(getattr(tolerances, _tolerance_key(name, unit)))


def moved_beyond(model: MeasurementModel, values: np.ndarray, reference: np.ndarray,
                 tolerances: Tolerances = Tolerances()) -> list[str]:
    """Return the geometric and placement parameters of ``values`` moved beyond tolerance.

    Each is compared with ``reference`` and its tolerance, no gauge taken out: a quick screen
    of an estimate (a warm start), not the gate's judgement.
    """
    params = model.params
    n_geo = len(model.geometric)
    return [n for n, u, v, r in zip(params.names[:n_geo], params.units[:n_geo],
                                    values[:n_geo], reference[:n_geo])
            if abs(_wrapped(float(v) - float(r), u)) > _tolerance(tolerances, n, u)]


def _tool_joints(model: MeasurementModel, q: np.ndarray | None) -> str:
    """Name the wrist joints to turn, with the ranges the data gave them."""
    revolute = [i for i, j in enumerate(model.robot.joints) if j.kind != 'prismatic'][-3:]
    names = model.robot.joint_names
    if q is None or not len(q):
        return ', '.join(names[i] for i in revolute)
    span = np.ptp(np.atleast_2d(q)[:, revolute], axis=0)
    narrow = [f'{names[i]} (measured over {s:.2g} rad)' for i, s in zip(revolute, span)
              if s < TURN_RANGE_RAD]
    return ', '.join(narrow) if narrow else ', '.join(names[i] for i in revolute)


def reflector_shift(model: MeasurementModel, names: Sequence[str], after: np.ndarray,
                    before: np.ndarray) -> dict[str, float]:
    """Return how far (m) each reflector offset among the re-fitted ``names`` moved.

    Keyed by the offset's prefix (``reflector``, ``reflector.<name>``, a recording's); the
    distance between its ``after`` and ``before`` values (full parameter vectors).
    """
    shift: dict[str, float] = {}
    for prefix in sorted({n.rsplit('.', 1)[0] for n in names
                          if (n.startswith('reflector') or '.reflector' in n)
                          and n.rsplit('.', 1)[1] in ('x', 'y', 'z')}):
        idx = model.params.indices([f'{prefix}.{c}' for c in 'xyz'])
        shift[prefix] = float(np.linalg.norm(np.asarray(after)[idx] - np.asarray(before)[idx]))
    return shift


def registration_violations(model: MeasurementModel, names: Sequence[str],
                            std: Sequence[float] | np.ndarray,
                            tolerances: Tolerances = Tolerances(),
                            q: np.ndarray | None = None,
                            shift: Mapping[str, float] | None = None) -> list[Violation]:
    """Violations of a placement re-fitted on a new recording (``validate --register``).

    A new set-up's base pose and a remounted probe's offsets are the new recording's to
    say, whatever their value; what the gate asks is that its poses determine them:
    each re-fitted parameter's ``std`` (from the new recording alone, the calibration held)
    within its tolerance (``base_translation`` / ``base_rotation`` / ``reflector_offset``,
    ``rotation`` for a tracked body's orientation). Poses that never turn the tool leave
    the base position and the reflector offset trading: the registered placement would be
    a guess, and so would a learned residual carried into it.

    Parameters
    ----------
    names, std : sequences
        The re-fitted parameters and their std (m, rad; inf: not determined at all).
    q : (N, n) ndarray, optional
        The new recording's joint values (the fix names the wrist joints it hardly turned).
    shift : mapping, optional
        How far each re-fitted reflector offset moved from the calibration's
        (:func:`reflector_shift`), judged when the base is not re-fitted with it: beyond
        ``reflector_offset`` it is no remount of a probe (millimetres) but the tracker
        moved and the offset took it up: 686 mm with ``--register reflector`` from another
        station was called a valid registration.
    """
    units = dict(zip(model.params.names, model.params.units))
    groups: dict[bool, list[str]] = {}  # reflector or not -> '<name> (<std>)'
    keys: dict[bool, list[str]] = {}
    for name, spread in zip(names, std):
        unit = units[name]
        key = _tolerance_key(name, unit)
        tol = float(getattr(tolerances, key))
        if spread <= tol:
            continue
        probe = name.startswith('reflector') or '.reflector' in name
        groups.setdefault(probe, []).append(
            f'{name} (' + ('not determined at all' if not np.isfinite(spread)
                           else f'std {spread:.3g} {unit} > {tol:g} {unit}') + ')')
        if f'identification.tolerances.{key}' not in keys.setdefault(probe, []):
            keys[probe].append(f'identification.tolerances.{key}')
    out: list[Violation] = []
    for probe, undetermined in groups.items():
        fix = (f'measure poses that turn the wrist ({_tool_joints(model, q)}) over wide '
               'ranges' if probe else 'measure poses spread over the workspace in every '
               'direction')
        out.append(Violation(
            ', '.join(undetermined),
            'undetermined by the new recording: its poses cannot place '
            + ('the probe' if probe else 'the base'),
            f'{fix}, or re-register less (--register base when the probe was not remounted, '
            f'--register reflector when the tracker did not move), or widen '
            + ' / '.join(keys[probe])))
    base = any(n.startswith('base.') or '.base.' in n for n in names)
    for prefix, moved in ({} if base else shift or {}).items():
        if moved > tolerances.reflector_offset:
            out.append(Violation(
                f'{prefix} offset', f'moved {moved:.4g} m from the calibration\'s, beyond '
                f'{tolerances.reflector_offset:g} m: a probe remount moves it by millimetres, '
                'so either the tracker was set up elsewhere and the offset took it up, or the '
                'marker was truly remounted this far',
                'register the base too (--register base+reflector); a new mount truly this '
                'far: widen identification.tolerances.reflector_offset'))
    return out


def geometric_violations(model: MeasurementModel, result: CalibrationResult,
                         reference: np.ndarray, tolerances: Tolerances = Tolerances(),
                         reflector_stated: bool = True,
                         q: np.ndarray | None = None,
                         n_geometric: int | None = None,
                         reflector: np.ndarray | None = None,
                         tau: np.ndarray | None = None,
                         covariates: Mapping[str, np.ndarray] | None = None,
                         orientation_stated: Sequence[str] = ()
                         ) -> list[Violation]:
    """Violations of the placement and geometric quantities of ``result``.

    Parameters
    ----------
    model : MeasurementModel
        The model ``result`` belongs to.
    result : CalibrationResult
    reference : (n_geometric,) ndarray
        What each geometric quantity is compared with (m, rad): the start of the
        identification (the cell's or registered base pose), the cell's reflector offsets,
        0 for the joint corrections.
    tolerances : Tolerances
    reflector_stated : bool
        The cell states the reflector offsets; False: they were registered from the points,
        and the measured poses ``q`` must determine them (:func:`observed_std`).
    q : (N, n) ndarray, optional
        Measured joint values (the fix of an undetermined reflector names the wrist joints
        the data hardly turned).
    n_geometric : int, optional
        Number of geometric parameters (default: those of ``model.params`` before its
        effects).
    reflector, tau : ndarray, optional
        (N,) reflector index and (N, n) gravity torques of the rows of ``q``.
    covariates : mapping, optional
        The rows' covariates (their recording, :attr:`MeasurementModel.inputs`).
    orientation_stated : sequence of str
        Reflector prefixes whose tracked body's orientation the cell states and identifies
        from there (``identify: true``): its rotation from the stated one is held within
        ``tolerances.rotation``, as a stated reflector offset within its tolerance.
    """
    params = model.params
    n_geo = len(model.geometric) if n_geometric is None else n_geometric
    values = dict(zip(result.names, result.values))
    std = dict(zip(result.estimated, result.std))
    # How far each geometric quantity moved, judged on the equivalent robot closest to the
    # reference (a gauge the design left free is no physical deviation).
    scale = np.array([_tolerance(tolerances, n, u)
                      for n, u in zip(params.names[:n_geo], params.units[:n_geo])])
    deviation = gauge_free_deviation(model, np.asarray(result.values, float),
                                     np.asarray(reference, float), scale, n_geo)
    out: list[Violation] = []
    turn = (f'turn the tool: measure poses that turn the wrist ({_tool_joints(model, q)}) '
            'over wide ranges')
    for prefix in reflector_prefixes(params):
        names = [f'{prefix}.{c}' for c in 'xyz']
        idx = params.indices(names)
        label = f'reflector offset {prefix} ({", ".join(names)})'
        moved = float(np.linalg.norm(deviation[idx]))
        spread = max((std.get(n, 0.0) for n in names), default=0.0)
        tol = tolerances.reflector_offset
        determined = ({} if reflector_stated or q is None
                      else observed_std(model, result, names, q, reflector, tau,
                                        covariates=covariates))
        loose = max(determined.values(), default=0.0)
        if loose > tol:
            out.append(Violation(label, 'undetermined: these poses cannot tell it from the '
                                 f'geometry of the arm (std {loose:.3g} m > {tol:g} m with every '
                                 'direction that poses spread over every joint determine), and '
                                 'the cell does not state it: its value is a guess',
                                 f'{turn}, or state reflector.offset in the cell'))
        elif spread > tol:
            out.append(Violation(label, f'undetermined: std {spread:.3g} m > the tolerance '
                                 f'{tol:g} m', f'{turn} (identification.tolerances.'
                                 'reflector_offset widens the tolerance)'))
        elif reflector_stated and moved > tol:
            out.append(Violation(label, f'identified {moved:.3g} m from its reference (the '
                                 'offset the cell states, or the one registered from the '
                                 f'points when it leaves it out), beyond the tolerance {tol:g} m',
                                 'check reflector.offset (units, the tip frame) or widen '
                                 'identification.tolerances.reflector_offset'))
    for prefix in reflector_prefixes(params):
        names = orientation_names(prefix)
        if names[0] not in params.names:
            continue
        if not all(n in std for n in names):
            out.append(Violation(
                f'body orientation {prefix} ({", ".join(names)})',
                'not identified: the data hold no rotation of this body that determines it, '
                'so it stays at the stated guess', 'record its 6-DoF poses (PoseStamped) over '
                'poses that turn the tool, or state its orientation'))
            continue
        spread = max(std[n] for n in names)
        turned = float(np.linalg.norm([values[n] for n in names]))  # from the stated guess
        if spread > tolerances.rotation:  # identified (orientation: identify), not determined
            out.append(Violation(
                f'body orientation {prefix} ({", ".join(names)})',
                f'undetermined: std {spread:.3g} rad > the tolerance {tolerances.rotation:g} '
                'rad', 'measure poses of the tracked body (6-DoF) that turn the tool, or state '
                'its orientation (identification.tolerances.rotation widens the tolerance)'))
        elif prefix in orientation_stated and turned > tolerances.rotation:
            out.append(Violation(
                f'body orientation {prefix} ({", ".join(names)})',
                f'identified {turned:.3g} rad from the orientation the cell states, beyond the '
                f'tolerance {tolerances.rotation:g} rad', 'check the stated orientation (rpy '
                'order and units, the tip frame), or identify it without a guess '
                "(orientation: identify); identification.tolerances.rotation widens the "
                'tolerance'))
    for i, (name, unit) in enumerate(zip(params.names[:n_geo], params.units[:n_geo])):
        if name.startswith('reflector.') or name not in values:
            continue
        base = name.startswith(('base.', RECORDING_PREFIX))
        key = _tolerance_key(name, unit)
        tol = getattr(tolerances, key)
        moved = abs(float(deviation[i]))
        where = ('the placement the identification started from' if base else 'the URDF')
        if name.startswith(RECORDING_PREFIX):
            where = 'the registration of its recording'
            if key == 'reflector_offset':
                # A remounted probe is registered, not stated (as a reflector the cell
                # leaves out): where it sits is the data's to say; undetermined it is not.
                if name in std and std[name] > tol:
                    out.append(Violation(name, f'undetermined: std {std[name]:.3g} m > the '
                                         f'tolerance {tol:g} m', f'{turn} in this recording '
                                         '(identification.tolerances.reflector_offset widens '
                                         'the tolerance)'))
                continue
        if moved <= tol:
            # Within its tolerance it is a plausible robot, however loosely the data pin it
            # (a near-gauge pair such as a placement translation and rotation the points
            # hardly tell apart): what cannot be is a joint the fit moved beyond it.
            continue
        if name in std and std[name] > tol:
            out.append(Violation(name, f'undetermined: moved {moved:.3g} ± {std[name]:.3g} '
                                 f'{unit} from {where}, the std above the tolerance {tol:g} '
                                 f'{unit}',
                                 'measure poses that move it (spread every joint over its range), '
                                 'or identify fewer parameters (identification.model); '
                                 f'identification.tolerances.{key} widens the tolerance'))
        else:
            out.append(Violation(name, f'moved {moved:.3g} {unit} from {where}, beyond the '
                                 f'tolerance {tol:g} {unit}',
                                 'check the URDF and the cell (joint order, units, tip frame), '
                                 'or an effect in the model absorbs the geometry; if the nominal '
                                 f'is truly this far off, widen identification.tolerances.{key}'))
    return out


def effect_violations(effects: Sequence[Any], result: CalibrationResult,
                      bounds: Mapping[str, tuple[float, ...]] | None = None,
                      tau: np.ndarray | None = None,
                      free: Sequence[str] | None = None) -> list[Violation]:
    """Violations of the effect parameters of ``result``.

    Beyond their bounds, or undetermined (std above the bound). ``tau`` (N, n): the measured
    gravity torques (a play inside its linear range is judged as the compliance it is).
    ``free``: the parameters the fit was asked to identify; one of them the data left out
    (the identifiability selection found no direction for it) is undetermined as well.
    """
    values = dict(zip(result.names, result.values))
    std = dict(zip(result.estimated, result.std))
    out: list[Violation] = []
    for effect in effects:
        if not isinstance(effect, BoundEffect):
            continue
        limits = effect_bounds(effect, bounds)
        key = bound_key(effect)
        unbounded = effect.parameter_names[len(limits):]
        if unbounded:
            # Without a bound the gate can tell neither an impossible value nor an
            # undetermined one: the result is not to be trusted until one is stated.
            out.append(Violation(effect.name, f'no physical bound for {list(unbounded)}: '
                                 'the gate cannot judge them', 'give the effect type '
                                 f'plausible=(...), or state {key} (one bound, or one per '
                                 'parameter; a registered or installed effect)'))
            continue
        loose = [f'{n} std {std[n]:.3g} {u} > its bound {b:.3g}'
                 for n, u, b in zip(effect.parameter_names, effect.units, limits)
                 if n in std and std[n] > b]
        loose += [f'{n} not determined by the data (left out of the fit)'
                  for n in effect.parameter_names if free is not None and n in free
                  and n not in std]
        if loose:
            out.append(Violation(effect.name, 'undetermined: ' + '; '.join(loose),
                                 f'{effect.hint()}; or leave the effect out'))
            continue
        why = implausible(effect, [values[n] for n in effect.parameter_names], tau, bounds)
        if why:
            if COMPLIANCE_LIMIT in why and effect.joint is not None:
                # A play within its linear range is the compliance it is: its bound decides.
                key = f'{key} and identification.bounds.joint_compliance:{effect.joint}'
            fix = (f'state the input in the units the cell says (a column\'s unit in the '
                   f'CSV mapping, a source\'s field), or widen {key} if the sensor sits '
                   'where it reads that share of the turn; else leave the effect out'
                   if effect.kind.gains else
                   f'widen {key} if this arm is that soft or loose (servo-stiff or '
                   'cable-driven joints: compliance ~1e-3 rad/(N m)); else leave the effect out')
            out.append(Violation(effect.name, why, fix))
    return out


def gate(model: MeasurementModel, result: CalibrationResult, reference: np.ndarray,
         tolerances: Tolerances = Tolerances(), reflector_stated: bool = True,
         q: np.ndarray | None = None, tau: np.ndarray | None = None,
         n_geometric: int | None = None, reflector: np.ndarray | None = None,
         free: Sequence[str] | None = None,
         covariates: Mapping[str, np.ndarray] | None = None,
         orientation_stated: Sequence[str] = ()) -> tuple[Violation, ...]:
    """Every violation of ``result`` (:func:`geometric_violations`, :func:`effect_violations`).

    () when every identified quantity is plausible and determined. ``q``, ``tau``,
    ``reflector``: the measured rows (joint values, gravity torques, reflector index);
    ``free``: the parameters the fit was asked to identify (:func:`effect_violations`);
    ``covariates``: the rows' covariates (their recording); ``orientation_stated``: as for
    :func:`geometric_violations`.
    """
    return tuple(geometric_violations(model, result, reference, tolerances, reflector_stated,
                                      q, n_geometric, reflector, tau, covariates,
                                      orientation_stated)
                 + effect_violations(model.effects, result, tolerances.bounds, tau, free))

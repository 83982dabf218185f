"""Collision avoidance with capsules (Jost et al. 2017, Sec. 2.2, eq. 20-22).

Robot links, obstacles and the laser beam are capsules (a segment swept by a
ball); floor and wall are half-spaces. A pair's *margin* is its signed distance
(metres, >= 0 means free): ``d_P - r1 - r2`` for two capsules (eq. 20) and
``min_endpoints(n.x - offset) - r`` for a capsule and a half-space.

The margins are written once with CasADi operations so the same code gives
IPOPT exact derivatives on SX/MX symbols and plain numbers on DM.
:func:`kpi_calib_ros.core.collision.check.verify_configuration` recomputes every
margin with coal (hpp-fcl) so a design can be checked independently of this code;
:mod:`kpi_calib_ros.core.collision.capsule_fit` fits capsules to URDF collision geometry.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import AbstractSet, Any, Mapping, Sequence, Union

import casadi as ca
import numpy as np

__all__ = [
    'BASE', 'BEAM', 'Capsule', 'HalfSpace', 'segment_distance', 'capsule_margin',
    'halfspace_margin', 'CollisionScene',
]

BASE = 'base'
BEAM = 'beam'
# Squared lengths below this (m^2) count as a point / as parallel: far below any
# geometry we model, far above the round-off of the products that are compared.
_EPS2 = 1e-20
# Floor under the squared distance so the gradient exists at exact contact;
# shifts a 1 mm distance by 5e-22 m.
_TINY2 = 1e-24


# A 3-vector as callers give it (tuple, list, ndarray); Capsule and HalfSpace store it as a
# tuple of 3 floats.
Vector3 = Union[Sequence[float], np.ndarray]


def _vec3(value: Any, name: str) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be 3 finite numbers, got {value!r}')
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class Capsule:
    """Segment ``a``-``b`` swept by a ball of ``radius``.

    Attributes
    ----------
    name : str
        Stable name used in constraint labels, e.g. ``'link_2'`` or ``'car_roof'``.
    frame : str
        Link whose frame ``a`` and ``b`` are expressed in, or ``'base'``.
    a, b : (3,) tuple of float
        Segment endpoints in ``frame`` (m); ``a == b`` gives a sphere.
    radius : float
        Ball radius (m), >= 0.
    """

    name: str
    frame: str
    a: Vector3
    b: Vector3
    radius: float

    def __post_init__(self) -> None:
        """Check the radius and store the end points as 3-tuples (m)."""
        object.__setattr__(self, 'a', _vec3(self.a, f'capsule {self.name}.a'))
        object.__setattr__(self, 'b', _vec3(self.b, f'capsule {self.name}.b'))
        if not np.isfinite(self.radius) or self.radius < 0:
            raise ValueError(f'capsule {self.name}.radius must be >= 0, got {self.radius}')
        object.__setattr__(self, 'radius', float(self.radius))


@dataclass(frozen=True)
class HalfSpace:
    """Free side ``{x : normal . x >= offset}`` in the base frame.

    Attributes
    ----------
    name : str
        Stable name, e.g. ``'floor'`` or ``'wall'``.
    normal : (3,) tuple of float
        Normal pointing into the free side; stored normalised (offset rescaled).
    offset : float
        Signed distance of the boundary from the origin along ``normal`` (m).
    """

    name: str
    normal: Vector3
    offset: float

    def __post_init__(self) -> None:
        """Check the normal and store the plane with a unit normal (offset scaled to match)."""
        n = np.array(_vec3(self.normal, f'half-space {self.name}.normal'))
        length = float(np.linalg.norm(n))
        if length < 1e-12:
            raise ValueError(f'half-space {self.name}.normal must be non-zero')
        object.__setattr__(self, 'normal', _vec3(n / length, 'normal'))
        object.__setattr__(self, 'offset', float(self.offset) / length)


Obstacle = Union[Capsule, HalfSpace]


# ------------------------------------------------------------------ casadi distances
def _as_casadi(x: Any) -> Any:
    return x if isinstance(x, (ca.SX, ca.MX, ca.DM)) else ca.DM(np.asarray(x, dtype=float))


def _safe_div(num: Any, den: Any, eps: float) -> Any:
    """``num/den`` where ``den > eps`` else 0, with no inf/nan in either branch."""
    ok = den > eps
    return ca.if_else(ok, num / ca.if_else(ok, den, 1.0), 0.0)


def _clamp01(x: Any) -> Any:
    return ca.fmin(ca.fmax(x, 0.0), 1.0)


def segment_distance(p1: Any, q1: Any, p2: Any, q2: Any) -> Any:
    """Distance between segments ``p1-q1`` and ``p2-q2`` (eq. 21).

    Closest points of the two lines, clamped to the segments in turn (Lumelsky
    1985, in Ericson's form); point segments and parallel segments take their
    own branch. Every division is guarded, so symbolic derivatives contain no
    inf/nan from the branches not taken.

    Parameters
    ----------
    p1, q1, p2, q2 : (3,) array_like, casadi DM, SX or MX
        Segment endpoints (m), all in one frame.

    Returns
    -------
    casadi DM, SX or MX (1x1)
        The distance d_P (m).
    """
    p1, q1, p2, q2 = (_as_casadi(v) for v in (p1, q1, p2, q2))
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = ca.dot(d1, d1), ca.dot(d2, d2)
    b, c, f = ca.dot(d1, d2), ca.dot(d1, r), ca.dot(d2, r)
    # a*e - b^2 and b*f - c*e written as cross products: the differences cancel
    # catastrophically for nearly parallel segments, the cross products do not.
    normal = ca.cross(d1, d2)
    denom = ca.dot(normal, normal)  # = a*e*sin^2(angle)
    s_line = _clamp01(_safe_div(-ca.dot(normal, ca.cross(r, d2)), denom, _EPS2 * a * e + _EPS2))
    # Parallel lines: any s works; s = 0 and the clamping below find the minimum.
    t = _safe_div(b * s_line + f, e, _EPS2)
    # t <= 0 (not < 0) so a point second segment (t == 0) re-optimises s.
    s = ca.if_else(t <= 0.0, _clamp01(_safe_div(-c, a, _EPS2)),
                   ca.if_else(t > 1.0, _clamp01(_safe_div(b - c, a, _EPS2)), s_line))
    t = _clamp01(t)
    # Point segments: _safe_div already gives s = 0 (a ~ 0) or t = 0 (e ~ 0).
    diff = r + d1 * s - d2 * t
    return ca.sqrt(ca.dot(diff, diff) + _TINY2)


def capsule_margin(a1: Any, b1: Any, r1: float, a2: Any, b2: Any, r2: float) -> Any:
    """Signed distance of two capsules, ``d_P - r1 - r2`` (eq. 20), in m."""
    return segment_distance(a1, b1, a2, b2) - r1 - r2


def halfspace_margin(a: Any, b: Any, radius: float, normal: Any, offset: float) -> Any:
    """Signed distance of capsule ``a-b`` (m) to the free side of a half-space.

    A capsule is in ``{x : n.x >= offset}`` iff both ball centres at its ends are
    ``radius`` inside, so ``min(n.a, n.b) - offset - radius`` (m).
    """
    n = _as_casadi(normal)
    return ca.fmin(ca.dot(n, _as_casadi(a)), ca.dot(n, _as_casadi(b))) - offset - radius


def _beam_end(tracker: Any, reflector: Any, clearance: float) -> Any:
    """Reflector end of the beam pulled back by ``clearance`` towards the tracker."""
    ray = reflector - tracker
    length = ca.sqrt(ca.dot(ray, ray))
    return tracker + ray * _safe_div(ca.fmax(length - clearance, 0.0), length, 1e-12)


# ---------------------------------------------------------------------------- scene
@dataclass(frozen=True)
class _Pair:
    label: str
    first: Capsule | None  # None is the beam
    second: Obstacle
    # The beam against an obstacle: the whole beam, to the reflector's centre (against the
    # robot it is shortened by the scene's beam_end_clearance).
    whole_beam: bool = False


def _names(item: Capsule | HalfSpace | None) -> set[str]:
    if item is None:
        return {BEAM}
    return {item.name, item.frame} if isinstance(item, Capsule) else {item.name}


class CollisionScene:
    """Constraint pairs of one measurement configuration and their margins.

    Pairs, in this order: robot capsules on non-adjacent links of
    ``chain_links`` (eq. 22: neighbours are kept apart by the joint limits);
    every robot capsule vs every obstacle; the beam (tracker to reflector,
    shortened by ``beam_end_clearance`` at the reflector, where the tool carrying it is)
    vs every robot capsule, and the whole beam, to the reflector's centre, vs every
    obstacle, capsule or half-space (line of sight; the reflector itself outside every
    obstacle; the tracker on the free side of every half-space). The beam's last
    ``beam_end_clearance`` was left out against obstacles too, half-spaces were not
    checked, and the capsules of the reflector's own link were skipped: a design put a
    probe's reflector 25 mm inside a conveyor, a tracker below the floor was designed for,
    and a Unitree Z1's beam crossed its own gripper 6-9 cm from the reflector.
    A pair is dropped when ``frozenset({x, y})`` is in ``ignore_pairs`` for x, y
    a capsule name, its frame, a half-space name or ``'beam'``.

    Parameters
    ----------
    robot_capsules : list of Capsule
        Capsules on the links (frame in ``chain_links``, or ``'base'``).
    obstacles : list of Capsule or HalfSpace
        Environment; capsules in frame ``'base'``.
    chain_links : list of str
        Links in kinematic order from base to tip.
    ignore_pairs : set of frozenset of str
        Pairs that never collide, e.g. ``{frozenset({'base_link', 'floor'})}``.
    beam_radius, beam_end_clearance : float
        Laser beam capsule radius and the length left out next to the reflector (m).
    """

    def __init__(self, robot_capsules: Sequence[Capsule], obstacles: Sequence[Obstacle],
                 chain_links: Sequence[str],
                 ignore_pairs: AbstractSet[frozenset[str]] = frozenset(),
                 beam_radius: float = 0.005, beam_end_clearance: float = 0.05) -> None:
        self.chain_links = list(chain_links)
        if not self.chain_links:
            raise ValueError('chain_links must name at least one link')
        order = {link: i for i, link in enumerate(self.chain_links)}
        order.setdefault(BASE, -1)
        for cap in robot_capsules:
            if cap.frame not in order:
                raise ValueError(f'robot_capsules: {cap.name!r} is on {cap.frame!r}, '
                                 f'not in chain_links {self.chain_links}')
        for obs in obstacles:
            if isinstance(obs, Capsule) and obs.frame != BASE:
                raise ValueError(f'obstacles: capsule {obs.name!r} must be in frame '
                                 f"'base', got {obs.frame!r}")
        names = [c.name for c in robot_capsules] + [o.name for o in obstacles]
        if len(set(names)) != len(names) or BEAM in names:
            raise ValueError(f"names must be unique and not 'beam': {names}")
        if beam_radius < 0 or beam_end_clearance < 0:
            raise ValueError('beam_radius and beam_end_clearance must be >= 0')
        self.robot_capsules = list(robot_capsules)
        self.obstacles = list(obstacles)
        self.ignore_pairs = set(ignore_pairs)
        self.beam_radius = float(beam_radius)
        self.beam_end_clearance = float(beam_end_clearance)
        self.frames = [link for link in self.chain_links
                       if any(c.frame == link for c in robot_capsules)]

        candidates: list[_Pair] = []
        for i, c1 in enumerate(self.robot_capsules):
            for c2 in self.robot_capsules[i + 1:]:
                if abs(order[c1.frame] - order[c2.frame]) > 1:
                    candidates.append(_Pair(f'{c1.name}~{c2.name}', c1, c2))
        for cap in self.robot_capsules:
            for obs in self.obstacles:
                candidates.append(_Pair(f'{cap.name}~{obs.name}', cap, obs))
        candidates += [_Pair(f'{BEAM}~{c.name}', None, c) for c in self.robot_capsules]
        candidates += [_Pair(f'{BEAM}~{o.name}', None, o, whole_beam=True)
                       for o in self.obstacles]
        self._pairs = [p for p in candidates if not any(
            frozenset({x, y}) in self.ignore_pairs
            for x in _names(p.first) for y in _names(p.second))]
        self._function: ca.Function | None = None

    @property
    def labels(self) -> list[str]:
        """Pair names in margin order, e.g. ``'link_2~link_4'``, ``'beam~link_3'``."""
        return [p.label for p in self._pairs]

    @property
    def count(self) -> int:
        """Number of constraints per configuration (the eq. 22 analog)."""
        return len(self._pairs)

    def margins(self, link_transforms: Mapping[str, Any], tracker_point: Any,
                reflector_point: Any) -> Any:
        """Signed distance of every pair (m), >= 0 means free.

        Parameters
        ----------
        link_transforms : mapping of str to (4, 4)
            Pose of each link in :attr:`frames` in the base frame (m); numbers
            or casadi SX/MX. ``'base'`` is the identity.
        tracker_point, reflector_point : (3,)
            Beam origin and reflector centre in the base frame (m).

        Returns
        -------
        (count,) ndarray if every input is numeric, else a casadi column.
        """
        missing = [f for f in self.frames if f not in link_transforms]
        if missing:
            raise ValueError(f'link_transforms lacks {missing}')
        inputs = [link_transforms[f] for f in self.frames] + [tracker_point, reflector_point]
        if any(isinstance(x, (ca.SX, ca.MX)) for x in inputs):
            return self._margins(link_transforms, tracker_point, reflector_point)
        # Numbers go through the compiled Function: same expressions, far faster.
        out = self.function()(self.stack_transforms(link_transforms),
                              np.asarray(tracker_point, float), np.asarray(reflector_point, float))
        return np.asarray(out, dtype=float).reshape(-1)

    def _margins(self, transforms: Mapping[str, Any], tracker: Any, reflector: Any) -> Any:
        world: dict[str, tuple[Any, Any]] = {}
        for cap in self.robot_capsules:
            if cap.frame == BASE:
                world[cap.name] = (_as_casadi(cap.a), _as_casadi(cap.b))
                continue
            t = _as_casadi(transforms[cap.frame])
            rot, pos = t[0:3, 0:3], t[0:3, 3]
            world[cap.name] = tuple(ca.mtimes(rot, _as_casadi(p)) + pos for p in (cap.a, cap.b))
        tracker, reflector = _as_casadi(tracker), _as_casadi(reflector)
        beam = (tracker, _beam_end(tracker, reflector, self.beam_end_clearance))
        out = []
        for pair in self._pairs:
            a1, b1 = ((tracker, reflector) if pair.whole_beam else beam) if pair.first is None \
                else world[pair.first.name]
            r1 = self.beam_radius if pair.first is None else pair.first.radius
            obs = pair.second
            if isinstance(obs, HalfSpace):
                out.append(halfspace_margin(a1, b1, r1, obs.normal, obs.offset))
            else:
                a2, b2 = world[obs.name] if obs.name in world else (obs.a, obs.b)
                out.append(capsule_margin(a1, b1, r1, a2, b2, obs.radius))
        return ca.vertcat(*out) if out else ca.DM.zeros(0, 1)

    def stack_transforms(self, link_transforms: Mapping[str, Any]) -> np.ndarray:
        """(4 * len(frames), 4) vertical stack of the :attr:`frames` poses."""
        if not self.frames:
            return np.zeros((0, 4))
        return np.vstack([np.asarray(link_transforms[f], dtype=float).reshape(4, 4)
                          for f in self.frames])

    def function(self, name: str = 'collision_margins') -> ca.Function:
        """CasADi Function ``(T (4L x 4), tracker (3), reflector (3)) -> margins (count)``.

        ``T`` stacks the poses of :attr:`frames` vertically (L = len(frames)), as
        :meth:`stack_transforms` does. Built once on SX and cached.
        """
        if self._function is None or self._function.name() != name:
            stack = ca.SX.sym('T', 4 * len(self.frames), 4)
            tracker, reflector = ca.SX.sym('tracker', 3), ca.SX.sym('reflector', 3)
            transforms = {f: stack[4 * i:4 * i + 4, :] for i, f in enumerate(self.frames)}
            self._function = ca.Function(name, [stack, tracker, reflector],
                                         [self._margins(transforms, tracker, reflector)],
                                         ['T', 'tracker', 'reflector'], ['margins'])
        return self._function

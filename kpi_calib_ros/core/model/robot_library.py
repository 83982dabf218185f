"""Robot library: URDFs of the arms this package is developed and tested against.

Three KUKA-class industrial arms (KR 15, KR 300, KR 500), the 90 notional
manipulators of Jost et al. (2017) and a UR5e-class collaborative arm; any arm's URDF
set on a two-stage lifting column whose stages are mimic joints of one drive
(:func:`with_lifting_column`), as construction and mobile robots ship them. Geometry
is given by data-sheet values; every link has an inertial computed from box and
cylinder primitives that also serve as its visual and collision geometry, so
gravity torques and collision checks use one consistent body.

KUKA-class conventions (ROS-Industrial, REP-103: x forward, z up)
-----------------------------------------------------------------
Joints ``joint_1`` .. ``joint_6`` turn about -z, +y, +y, -x, +y, -x like the
KUKA axes A1..A6 in ``kuka_experimental``; all joint origins carry rpy = 0, so
at q = 0 every link frame is parallel to ``base_link``. At q = 0 the upper arm
points straight up (joint_3 at ``(a1, 0, d1 + a2)``) and the forearm points
forward with the wrist centre ``a3`` below the joint_3 axis: the KUKA HOME pose
A = (0, -90, 90, 0, 0, 0) deg, far from singularities. Hence ``q = A + offset``
with ``KUKA_CONTROLLER_OFFSET`` (rad). ``tool0`` is the flange frame, ``d6``
beyond the wrist centre with z along the flange normal (x down at q = 0).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from kpi_calib_ros.core.errors import ConfigError

__all__ = [
    'DATA_DIR', 'SHIPPED_ROBOTS', 'KUKA_CONTROLLER_OFFSET', 'Industrial6RGeometry',
    'industrial_6r_urdf', 'kr15_class', 'kr300_class', 'kr500_class', 'notional_manipulators',
    'ur_class_urdf', 'shipped_urdfs', 'shipped_urdf_path',
    'COLUMN_JOINTS', 'with_lifting_column',
]

DATA_DIR = Path(__file__).resolve().parents[2] / 'data' / 'robots'
SHIPPED_ROBOTS = ('kr15_class', 'kr300_class', 'kr500_class', 'ur_class')
KUKA_CONTROLLER_OFFSET = (0.0, math.pi / 2, -math.pi / 2, 0.0, 0.0, 0.0)
_AXIS_RPY = {0: (0.0, math.pi / 2, 0.0), 1: (math.pi / 2, 0.0, 0.0), 2: (0.0, 0.0, 0.0)}


@dataclass(frozen=True)
class Industrial6RGeometry:
    """Data-sheet description of a KUKA-like 6R arm (SI: m, rad, kg, N m, rad/s).

    Attributes
    ----------
    name : str
        Robot name used in the URDF.
    d1 : float
        Height of the joint-2 axis above the floor (``base_link`` origin).
    a1 : float
        Shoulder offset: joint-2 axis ahead of the joint-1 axis.
    a2 : float
        Segment two (upper arm), joint-2 axis to joint-3 axis.
    a3 : float
        Elbow offset: forearm axis (joint 4) below the joint-3 axis, forearm horizontal.
    d4 : float
        Segment four (forearm), joint-3 axis to the wrist centre along joint 4.
    d6 : float
        Flange distance from the wrist centre.
    lower, upper : tuple of 6 float
        Joint limits in this module's q convention (not the controller's A).
    velocity, effort : tuple of 6 float
        Joint speed (rad/s) and torque (N m) limits.
    masses : tuple of 7 float
        Masses of ``base_link``, ``link_1`` .. ``link_6``.
    radius : float
        Half-width of the upper arm; scales every primitive body.
    """

    name: str
    d1: float
    a1: float
    a2: float
    a3: float
    d4: float
    d6: float
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    velocity: tuple[float, ...]
    effort: tuple[float, ...]
    masses: tuple[float, ...]
    radius: float

    def __post_init__(self) -> None:
        """Check dimensions, limits (which must contain q = 0), masses, velocities, efforts."""
        for key in ('d1', 'a1', 'a2', 'd4', 'd6', 'radius'):
            if not getattr(self, key) > 0.0:
                raise ConfigError(f'geometry.{key}', f'must be > 0, got {getattr(self, key)}')
        for key, size in (('lower', 6), ('upper', 6), ('velocity', 6), ('effort', 6),
                          ('masses', 7)):
            if len(getattr(self, key)) != size:
                raise ConfigError(f'geometry.{key}', f'needs {size} values')
        for i, (lo, hi) in enumerate(zip(self.lower, self.upper)):
            # q = 0 is the reference pose of tests and designs; it must be reachable.
            if not lo < 0.0 < hi:
                raise ConfigError(f'geometry.lower[{i}]', f'limits ({lo}, {hi}) must contain 0')
        if min(self.masses + self.velocity + self.effort) <= 0.0:
            raise ConfigError('geometry.masses', 'masses, velocities and efforts must be > 0')


@dataclass(frozen=True)
class _Shape:
    """Box (``dims`` = full extents) or cylinder (``dims`` = radius, length) in a link frame."""

    kind: str
    center: tuple[float, float, float]
    dims: tuple[float, ...]
    axis: int = 2  # cylinder axis: 0 = x, 1 = y, 2 = z


def _box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> _Shape:
    return _Shape('box', ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2),
                  tuple(b - a for a, b in zip(lo, hi)))


def _cyl(axis: int, start: float, end: float, radius: float,
         offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> _Shape:
    center = list(offset)
    center[axis] = (start + end) / 2
    return _Shape('cylinder', (center[0], center[1], center[2]), (radius, abs(end - start)), axis)


def _volume(s: _Shape) -> float:
    return float(np.prod(s.dims)) if s.kind == 'box' else math.pi * s.dims[0] ** 2 * s.dims[1]


def _own_inertia(s: _Shape, mass: float) -> np.ndarray:
    """Inertia (kg m^2) of a solid primitive about its centre, link axes."""
    if s.kind == 'box':
        sq = np.square(s.dims)
        return mass / 12.0 * np.diag([sq[1] + sq[2], sq[0] + sq[2], sq[0] + sq[1]])
    r, length = s.dims
    diag = np.full(3, mass * (3 * r ** 2 + length ** 2) / 12.0)
    diag[s.axis] = mass * r ** 2 / 2.0
    return np.diag(diag)


def _composite_inertia(mass: float, shapes: list[_Shape]) -> tuple[np.ndarray, np.ndarray]:
    """Centre of mass (3,) and inertia (3, 3) about it, mass spread by volume."""
    volumes = np.array([_volume(s) for s in shapes])
    masses = mass * volumes / volumes.sum()
    centers = np.array([s.center for s in shapes])
    com = masses @ centers / mass
    inertia = np.zeros((3, 3))
    for s, m, c in zip(shapes, masses, centers):
        d = c - com  # parallel-axis theorem
        inertia += _own_inertia(s, m) + m * (d @ d * np.eye(3) - np.outer(d, d))
    return com, inertia


def _f(values: ArrayLike) -> str:
    # 12 significant digits keep FK exact to ~1e-12 m while the files stay readable;
    # adding 0.0 turns -0.0 into 0.0 so regenerated files never drift.
    return ' '.join(f'{float(v) + 0.0:.12g}' for v in np.atleast_1d(values))


def _geometry_xml(s: _Shape) -> str:
    rpy = _AXIS_RPY[s.axis] if s.kind == 'cylinder' else (0.0, 0.0, 0.0)
    shape = (f'<box size="{_f(s.dims)}"/>' if s.kind == 'box' else
             f'<cylinder radius="{_f(s.dims[0])}" length="{_f(s.dims[1])}"/>')
    return (f'<origin xyz="{_f(s.center)}" rpy="{_f(rpy)}"/>\n'
            f'      <geometry>{shape}</geometry>')


def _link_xml(name: str, mass: float, shapes: list[_Shape]) -> str:
    com, inertia = _composite_inertia(mass, shapes)
    i = inertia
    parts = [f'  <link name="{name}">', '    <inertial>',
             f'      <origin xyz="{_f(com)}" rpy="0 0 0"/>', f'      <mass value="{_f(mass)}"/>',
             f'      <inertia ixx="{_f(i[0, 0])}" ixy="{_f(i[0, 1])}" ixz="{_f(i[0, 2])}" '
             f'iyy="{_f(i[1, 1])}" iyz="{_f(i[1, 2])}" izz="{_f(i[2, 2])}"/>',
             '    </inertial>']
    for s in shapes:
        geometry = _geometry_xml(s)
        parts += [f'    <visual>\n      {geometry}\n      <material name="body"/>\n    </visual>',
                  f'    <collision>\n      {geometry}\n    </collision>']
    return '\n'.join(parts + ['  </link>'])


def _joint_xml(name: str, parent: str, child: str, xyz: ArrayLike, rpy: ArrayLike,
               axis: ArrayLike | None = None,
               limits: tuple[float, float, float, float] | None = None) -> str:
    """Revolute joint if ``axis`` is given (limits: lower, upper, effort, velocity), else fixed."""
    kind = 'fixed' if axis is None else 'revolute'
    parts = [f'  <joint name="{name}" type="{kind}">',
             f'    <parent link="{parent}"/>', f'    <child link="{child}"/>',
             f'    <origin xyz="{_f(xyz)}" rpy="{_f(rpy)}"/>']
    if axis is not None:
        if limits is None:
            raise ValueError(f'joint {name!r}: a revolute joint needs limits')
        lo, hi, effort, velocity = limits
        parts += [f'    <axis xyz="{_f(axis)}"/>',
                  f'    <limit lower="{_f(lo)}" upper="{_f(hi)}" effort="{_f(effort)}" '
                  f'velocity="{_f(velocity)}"/>']
    return '\n'.join(parts + ['  </joint>'])


def _robot_xml(name: str, rgba: str, links: list[str], joints: list[str]) -> str:
    head = ['<?xml version="1.0"?>',
            '<!-- Generated by kpi_calib_ros.core.model.robot_library; do not edit. -->',
            f'<robot name="{name}">',
            f'  <material name="body"><color rgba="{rgba}"/></material>']
    return '\n'.join(head + links + joints + ['</robot>']) + '\n'


def _industrial_shapes(g: Industrial6RGeometry) -> list[list[_Shape]]:
    """Enclosing primitives of base_link, link_1..link_6 in their own frames."""
    r, base_h = g.radius, 0.35 * g.d1
    return [
        [_box((-1.6 * r, -1.6 * r, 0.0), (1.6 * r, 1.6 * r, base_h))],
        # Turntable and shoulder housing: from the base top up past the joint-2 axis.
        [_box((-1.4 * r, -1.3 * r, base_h - g.d1), (g.a1 + 1.1 * r, 1.3 * r, 1.1 * r))],
        [_box((-0.8 * r, -0.9 * r, -r), (0.8 * r, 0.9 * r, g.a2 + 0.8 * r))],
        # Elbow with the wrist motors behind the joint-3 axis.
        [_box((-1.3 * r, -0.9 * r, -g.a3 - 0.8 * r), (0.9 * r, 0.9 * r, 0.8 * r))],
        [_cyl(0, -(g.d4 - 0.9 * r), 0.0, 0.55 * r)],
        [_cyl(1, -0.6 * r, 0.6 * r, 0.45 * r)],
        [_cyl(0, 0.4 * r, g.d6, 0.35 * r)],  # overlaps the wrist hub: no gap
    ]


def industrial_6r_urdf(name: str, geometry: Industrial6RGeometry) -> str:
    """URDF of a KUKA-like 6R arm in the ROS-Industrial layout (see module docstring).

    Parameters
    ----------
    name : str
        ``<robot name>``.
    geometry : Industrial6RGeometry
        Lengths (m), limits (rad), masses (kg).

    Returns
    -------
    str
        URDF with ``base_link``, ``link_1`` .. ``link_6``, ``tool0`` and
        ``joint_1`` .. ``joint_6``; at q = 0, tool0 is at
        ``(a1 + d4 + d6, 0, d1 + a2 - a3)``.
    """
    g = geometry
    names = ['base_link'] + [f'link_{i}' for i in range(1, 7)]
    links = [_link_xml(n, m, s) for n, m, s in zip(names, g.masses, _industrial_shapes(g))]
    origins = [(0, 0, g.d1), (g.a1, 0, 0), (0, 0, g.a2), (g.d4, 0, -g.a3), (0, 0, 0), (0, 0, 0)]
    axes = [(0, 0, -1), (0, 1, 0), (0, 1, 0), (-1, 0, 0), (0, 1, 0), (-1, 0, 0)]
    joints = [_joint_xml(f'joint_{i + 1}', names[i], names[i + 1], origins[i], (0, 0, 0),
                         axes[i], (g.lower[i], g.upper[i], g.effort[i], g.velocity[i]))
              for i in range(6)]
    # Ry(+90 deg) turns tool0's z onto link_6's x, the flange normal.
    joints.append(_joint_xml('joint_6-tool0', 'link_6', 'tool0', (g.d6, 0, 0),
                             (0, math.pi / 2, 0)))
    return _robot_xml(name, '1 0.45 0 1', links + ['  <link name="tool0"/>'], joints)


def _kuka_limits(ranges_deg: list[tuple[float, float]]) -> tuple[tuple[float, ...], ...]:
    """Convert controller axis ranges A (deg) to (lower, upper) in q (rad), q = A + offset."""
    q = [[math.radians(a) + o for a in ab] for ab, o in zip(ranges_deg, KUKA_CONTROLLER_OFFSET)]
    return tuple(lo for lo, _ in q), tuple(hi for _, hi in q)


def _rad(*deg: float) -> tuple[float, ...]:
    return tuple(math.radians(v) for v in deg)


def kr15_class() -> Industrial6RGeometry:
    """KR 15 class: lengths and axis ranges of the KUKA KR 16-2 data sheet.

    Lengths as in ROS-Industrial ``kuka_kr16_support`` (kr16_2), ranges
    A1 +-185, A2 -155/+35, A3 -130/+154, A4 +-350, A5 +-130, A6 +-350 deg.
    Masses (231 kg total), efforts and radius are estimates, not KUKA data.
    """
    lower, upper = _kuka_limits([(-185, 185), (-155, 35), (-130, 154),
                                 (-350, 350), (-130, 130), (-350, 350)])
    return Industrial6RGeometry(
        'kr15_class', d1=0.675, a1=0.26, a2=0.68, a3=0.035, d4=0.67, d6=0.158,
        lower=lower, upper=upper, velocity=_rad(156, 156, 156, 330, 330, 615),
        effort=(1100.0, 1700.0, 800.0, 120.0, 120.0, 60.0),
        masses=(45.0, 75.0, 55.0, 35.0, 15.0, 5.0, 1.0), radius=0.12)


def kr300_class() -> Industrial6RGeometry:
    """KR 300 class: lengths and axis ranges of the KUKA KR 300 R2500 ultra data sheet.

    Ranges A1 +-185, A2 -140/-5, A3 -120/+155, A4 +-350, A5 +-122.5, A6 +-350 deg.
    Masses (1100 kg total), efforts and radius are estimates, not KUKA data.
    """
    lower, upper = _kuka_limits([(-185, 185), (-140, -5), (-120, 155),
                                 (-350, 350), (-122.5, 122.5), (-350, 350)])
    return Industrial6RGeometry(
        'kr300_class', d1=0.675, a1=0.35, a2=1.15, a3=0.041, d4=1.0, d6=0.215,
        lower=lower, upper=upper, velocity=_rad(105, 101, 107, 136, 129, 206),
        effort=(13000.0, 18000.0, 9000.0, 2000.0, 2000.0, 1100.0),
        masses=(260.0, 380.0, 210.0, 170.0, 50.0, 25.0, 5.0), radius=0.24)


def kr500_class() -> Industrial6RGeometry:
    """KR 500 class: lengths and axis ranges of the KUKA KR 500 R2830 data sheet.

    Ranges A1 +-185, A2 -130/+20, A3 -100/+144, A4 +-350, A5 +-120, A6 +-350 deg.
    Masses (2400 kg total), speeds, efforts and radius are estimates.
    """
    lower, upper = _kuka_limits([(-185, 185), (-130, 20), (-100, 144),
                                 (-350, 350), (-120, 120), (-350, 350)])
    return Industrial6RGeometry(
        'kr500_class', d1=1.045, a1=0.5, a2=1.3, a3=0.055, d4=1.025, d6=0.29,
        lower=lower, upper=upper, velocity=_rad(75, 70, 70, 90, 90, 130),
        effort=(28000.0, 40000.0, 20000.0, 4000.0, 4000.0, 2500.0),
        masses=(550.0, 850.0, 480.0, 350.0, 110.0, 50.0, 10.0), radius=0.30)


def notional_manipulators() -> list[Industrial6RGeometry]:
    """Return the 90 notional manipulators of Jost et al. (2017), Section 3.

    Segment two ``a2`` in 0.650 .. 1.100 m and segment four ``d4`` in
    0.600 .. 1.000 m, both in 0.050 m steps; everything else is the KR 15
    class, except that the upper-arm and forearm masses scale with their
    length (a tube of unchanged section). Ordered by a2, then d4.
    """
    base = kr15_class()
    out = []
    for i in range(10):
        for j in range(9):
            a2, d4 = round(0.65 + 0.05 * i, 3), round(0.60 + 0.05 * j, 3)
            masses = list(base.masses)
            masses[2] *= a2 / base.a2
            masses[4] *= d4 / base.d4
            out.append(replace(base, name=f'notional_a2_{round(a2 * 1000):04d}_d4_'
                               f'{round(d4 * 1000):04d}', a2=a2, d4=d4, masses=tuple(masses)))
    return out


def ur_class_urdf(name: str = 'ur_class') -> str:
    """URDF of a UR5e-class arm from its public DH table, ``ur_description`` layout.

    DH: d1 = 0.1625, a2 = -0.425, a3 = -0.3922, d4 = 0.1333, d5 = 0.0997,
    d6 = 0.0996 m; joint origins carry the DH twists as rpy and every axis is
    local z, so unlike the KUKA class the frames are rotated. ``base_link`` is
    turned by pi about z against the DH base, as in ``ur_description``; at q = 0
    tool0 is at ``(-(a2 + a3), d4 + d6, d1 - d5)``. Masses are UR5e values
    (21.7 kg with the base); limits +-2 pi, elbow +-pi.
    """
    d1, a2, a3, d4, d5, d6 = 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996
    names = ['base_link', 'shoulder_link', 'upper_arm_link', 'forearm_link',
             'wrist_1_link', 'wrist_2_link', 'wrist_3_link']
    masses = (4.0, 3.761, 8.058, 2.846, 1.37, 1.3, 0.365)
    shapes = [
        [_cyl(2, 0.0, 0.09, 0.076)],
        [_cyl(2, 0.09 - d1, 0.07, 0.064)],
        # The tube runs 0.138 m along the lift axis from the DH line, as on the real arm.
        [_cyl(2, -0.02, 0.19, 0.064), _cyl(0, 0.05, a2 - 0.05, 0.055, (0, 0, 0.138))],
        [_cyl(2, -0.01, 0.17, 0.05), _cyl(0, 0.04, a3, 0.042, (0, 0, 0.007))],
        [_cyl(2, -0.095, 0.045, 0.045)],
        [_cyl(2, 0.045 - d5, 0.045, 0.045)],
        [_cyl(2, -0.045, 0.0, 0.032)],
    ]
    links = [_link_xml(n, m, s) for n, m, s in zip(names, masses, shapes)]
    joint_names = ['shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint',
                   'wrist_1_joint', 'wrist_2_joint', 'wrist_3_joint']
    origins = [((0, 0, d1), (0, 0, math.pi)), ((0, 0, 0), (math.pi / 2, 0, 0)),
               ((a2, 0, 0), (0, 0, 0)), ((a3, 0, d4), (0, 0, 0)),
               ((0, -d5, 0), (math.pi / 2, 0, 0)), ((0, d6, 0), (-math.pi / 2, 0, 0))]
    effort = (150.0, 150.0, 150.0, 28.0, 28.0, 28.0)
    joints = []
    for i, (xyz, rpy) in enumerate(origins):
        bound = math.pi if joint_names[i] == 'elbow_joint' else 2 * math.pi
        joints.append(_joint_xml(joint_names[i], names[i], names[i + 1], xyz, rpy, (0, 0, 1),
                                 (-bound, bound, effort[i], math.pi)))
    # wrist_3_link's z already points out of the flange.
    joints.append(_joint_xml('wrist_3_link-tool0', 'wrist_3_link', 'tool0', (0, 0, 0), (0, 0, 0)))
    return _robot_xml(name, '0.7 0.75 0.8 1', links + ['  <link name="tool0"/>'], joints)


def shipped_urdfs() -> dict[str, str]:
    """Return the generator output of every shipped robot, keyed by name (``SHIPPED_ROBOTS``)."""
    out = {g.name: industrial_6r_urdf(g.name, g)
           for g in (kr15_class(), kr300_class(), kr500_class())}
    out['ur_class'] = ur_class_urdf('ur_class')
    return out


def shipped_urdf_path(name: str) -> Path:
    """Path of a shipped URDF, e.g. ``shipped_urdf_path('kr15_class')``.

    Raises
    ------
    ConfigError
        ``name`` is not one of ``SHIPPED_ROBOTS``.
    """
    stem = name[:-5] if name.endswith('.urdf') else name
    if stem not in SHIPPED_ROBOTS:
        raise ConfigError('robot.name', f'unknown robot {name!r}; shipped: {SHIPPED_ROBOTS}')
    return DATA_DIR / f'{stem}.urdf'


COLUMN_JOINTS = ('lift', 'stage_1', 'stage_2')


def with_lifting_column(urdf_xml: str, base_link: str, travel: float = 0.8,
                        stage_offset: float = 0.1, stage_upper: float = 0.25) -> str:
    """``urdf_xml`` with its ``base_link`` set on a two-stage telescopic lifting column.

    A new root link ``column_base`` carries the column drive ``lift`` (prismatic along
    z, ``[0, travel]`` m, moving the off-chain link ``column_drive``) and the stages
    ``stage_1`` (link ``column_stage_1`` on ``column_base``) and ``stage_2`` (link
    ``column_stage_2`` on stage 1), both
    prismatic along z and both ``<mimic joint="lift" multiplier="0.5"
    offset="-stage_offset"/>``: each stage rises by half the drive's stroke, the column
    by all of it. A stage's own range ``[-stage_offset, stage_upper]`` m narrows the
    drive's to ``[0, 2 (stage_upper + stage_offset)]`` when that is shorter than
    ``travel``. ``base_link`` sits on top of stage 2 by a fixed joint; a joint that held
    ``base_link`` (a ``world`` link's) holds ``column_base`` instead.

    Raises
    ------
    ConfigError
        ``base_link`` is not a link of ``urdf_xml``, or a column name is taken.
    """
    import xml.etree.ElementTree as ET

    root = ET.fromstring(urdf_xml)
    links = {e.get('name') for e in root.findall('link')}
    if base_link not in links:
        raise ConfigError('base_link', f'{base_link!r} is not a link of the URDF')
    taken = ({'column_base', 'column_drive', 'column_stage_1', 'column_stage_2'} & links) | (
        set(COLUMN_JOINTS) & {e.get('name') for e in root.findall('joint')})
    if taken:
        raise ConfigError('base_link', f'the URDF already has {sorted(taken)}')
    body = [_link_xml('column_base', 60.0, [_cyl(2, 0.0, 0.3, 0.16)]),
            _link_xml('column_drive', 2.0, [_box((-0.05, -0.05, 0.0), (0.05, 0.05, 0.1))]),
            _link_xml('column_stage_1', 25.0, [_cyl(2, 0.0, 0.4, 0.13)]),
            _link_xml('column_stage_2', 20.0, [_cyl(2, 0.0, 0.3, 0.10)])]
    mimic = f'<mimic joint="lift" multiplier="0.5" offset="{_f(-stage_offset)}"/>'

    def prismatic(name: str, parent: str, child: str, z: float, lo: float, hi: float,
                  extra: str = '') -> str:
        return '\n'.join([f'  <joint name="{name}" type="prismatic">',
                          f'    <parent link="{parent}"/>', f'    <child link="{child}"/>',
                          f'    <origin xyz="0 0 {_f(z)}" rpy="0 0 0"/>',
                          '    <axis xyz="0 0 1"/>',
                          f'    <limit lower="{_f(lo)}" upper="{_f(hi)}" effort="5000" '
                          'velocity="0.2"/>'] + ([f'    {extra}'] if extra else [])
                         + ['  </joint>'])

    body += [prismatic('lift', 'column_base', 'column_drive', 0.1, 0.0, travel),
             prismatic('stage_1', 'column_base', 'column_stage_1', 0.3,
                       -stage_offset, stage_upper, mimic),
             prismatic('stage_2', 'column_stage_1', 'column_stage_2', 0.4,
                       -stage_offset, stage_upper, mimic),
             _joint_xml('column_top', 'column_stage_2', base_link, (0, 0, 0.3), (0, 0, 0))]
    for joint in root.findall('joint'):  # a joint that held the base now holds the column
        child = joint.find('child')
        if child is not None and child.get('link') == base_link:
            child.set('link', 'column_base')
    wrapper = ET.fromstring('<robot>' + '\n'.join(body) + '</robot>')
    for k, element in enumerate(wrapper):
        root.insert(k, element)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding='unicode') + '\n'

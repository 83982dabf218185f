"""The physical sections of a cell file: reflectors and tracked bodies, the tracker pose,
joint-reading noise, working poses, obstacles and capsules, joint coupling; each parsed and
checked in SI units with the key path in every error. Obstacles and capsules are plain
shapes here (:class:`CapsuleSpec`, :class:`HalfSpaceSpec`); the collision objects are built
from them with the cell model (:mod:`kpi_calib_ros.app.cell_model`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.acquisition.coupling import JointCoupling
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.payload import PAYLOAD_COM_LIMIT_M, PAYLOAD_MASS_LIMIT_KG
from kpi_calib_ros.core.measurement.pose import rotation_from_quaternion, rotation_from_rpy
from kpi_calib_ros.core.model.robot import Mimic, RobotModel
from kpi_calib_ros.io.cell_values import (
    joint_value,
    non_negative,
    number,
    refuse_unknown,
    vector,
)

# Plausibility of SI values: beyond these a value is almost surely in other units.
MAX_TRACKER_RANGE_M = 50.0     # laser trackers measure to ~40-80 m; cells are far smaller
MAX_REFLECTOR_OFFSET_M = 2.0   # reflector from the flange: a tool, not a second robot


@dataclass(frozen=True)
class WorkingPose:
    """A working pose by joint name (``joints``) or in chain order (``values``, rad/m).

    ``payload``: (mass kg, centre of mass (3,) m in the tip frame or None for the cell's
    payload centre) the robot carries at this pose; None: the cell's payload.
    """

    name: str
    joints: dict[str, float]
    values: tuple[float, ...] = ()
    payload: tuple[float, tuple[float, float, float] | None] | None = None


def plausible_pose(pose: np.ndarray) -> np.ndarray:
    """``tracker.base_in_tracker`` in SI units, or a ConfigError with a units hint (a pose
    in millimetres or degrees would otherwise end in a design with no feasible pose)."""
    distance = float(np.linalg.norm(pose[:3]))
    if distance > MAX_TRACKER_RANGE_M:
        raise ConfigError('tracker.base_in_tracker', f'the robot base is {distance:g} m from '
                          f'the tracker, beyond any tracker range ({MAX_TRACKER_RANGE_M:g} m); '
                          'give x, y, z in SI metres (millimetres? divide by 1000)')
    if np.any(np.abs(pose[3:]) > 2 * np.pi):
        raise ConfigError('tracker.base_in_tracker', f'roll, pitch, yaw {pose[3:].tolist()} '
                          'exceed 2π; give them in radians (degrees? multiply by π/180)')
    return pose


def plausible_offset(offset: np.ndarray, key: str = 'reflector.offset') -> np.ndarray:
    """A reflector offset (``key``) in SI metres, or a ConfigError with a units hint."""
    length = float(np.linalg.norm(offset))
    if length > MAX_REFLECTOR_OFFSET_M:
        raise ConfigError(key, f'the reflector is {length:g} m from the tip '
                          f'frame (at most {MAX_REFLECTOR_OFFSET_M:g} m is plausible); give '
                          'it in SI metres (millimetres? divide by 1000; 30 mm is 0.03)')
    return offset


def parse_package_dirs(value: Any) -> tuple[str, ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError('robot.package_dirs', 'must be a list of directories (relative to the '
                          f'cell file) where package:// URIs are searched, got {value!r}')
    return tuple(value)


def parse_reflectors(doc: dict) -> tuple[tuple[str, ...], np.ndarray | None,
                                     tuple[tuple[int, np.ndarray], ...]]:
    """The ``reflectors:`` list: names, (R, 3) offsets (NaN row: offset omitted, to
    be registered from the data) and the orientations of tracked bodies.
    ``((), None, ())`` when the key is absent."""
    items = doc.get('reflectors')
    if items is None:
        if 'orientation' in (doc.get('reflector') or {}):
            raise ConfigError('reflector.orientation', 'a tracked 6-DoF body is a reflectors: '
                              'entry: reflectors: [{name: probe, offset: [x, y, z], '
                              'orientation: {rpy: [r, p, y]}}]')
        return (), None, ()
    if 'offset' in (doc.get('reflector') or {}):
        raise ConfigError('reflector.offset', 'give the offsets in reflectors: only (the '
                          'reflector: mapping then holds axis and max_incidence)')
    if not isinstance(items, list) or not items:
        raise ConfigError('reflectors', 'must be a list of {name, offset: [x, y, z]} (m, tip '
                          'frame); the first is the KPI point')
    names, offsets, orientations = [], [], []
    for i, item in enumerate(items):
        key = f'reflectors[{i}]'
        if not isinstance(item, dict) or not isinstance(item.get('name'), str):
            raise ConfigError(key, 'must be a mapping {name: str, offset: [x, y, z]}')
        unknown = sorted(set(item) - {'name', 'offset', 'orientation'})
        if unknown:
            raise ConfigError(f'{key}.{unknown[0]}', 'unknown key; allowed: name, offset, '
                              'orientation')
        name = item['name']
        if not name or not all(c.isalnum() or c == '_' for c in name) or name in names:
            raise ConfigError(f'{key}.name', f'{name!r}: give a unique name of letters, digits '
                              'and _ (it appears in parameter names reflector.<name>.x)')
        names.append(name)
        offset = item.get('offset')
        offsets.append(np.full(3, np.nan) if offset is None
                       else plausible_offset(vector(offset, f'{key}.offset', 3),
                                              f'{key}.offset'))
        if item.get('orientation') is not None:
            orientations.append((i, _orientation(item['orientation'], f'{key}.orientation')[0]))
    return tuple(names), np.array(offsets), tuple(orientations)


def identified_orientations(doc: Mapping[str, Any], stated_only: bool = False
                            ) -> tuple[int, ...]:
    """The reflectors (indices) whose tracked body's orientation is identified
    (``orientation: identify``, or a stated guess with ``identify: true``; with
    ``stated_only`` the latter alone: an orientation the cell states, identified from there,
    which the plausibility gate holds within its tolerance); the document checked by
    :func:`parse_reflectors` first."""
    out = []
    for i, item in enumerate(doc.get('reflectors') or []):
        raw = item.get('orientation') if isinstance(item, dict) else None
        if (raw == IDENTIFY and not stated_only) or (
                isinstance(raw, dict) and raw.get(IDENTIFY) is True):
            out.append(i)
    return tuple(out)


# ``reflectors[].orientation: identify``: the body's orientation is three identified
# parameters (reflector.<name>.r{x,y,z}, a rotation vector after the stated guess).
IDENTIFY = 'identify'


def _orientation(raw: Any, key: str) -> tuple[np.ndarray, bool]:
    """A tracked body's orientation in the tip frame, ``{rpy: [roll, pitch, yaw]}`` (rad,
    URDF convention) or ``{quaternion: [x, y, z, w]}``, as a (3, 3) rotation, and whether it
    is identified: ``identify`` (starting at the identity) or either form with
    ``identify: true`` (starting at it)."""
    if raw == IDENTIFY:
        return np.eye(3), True
    identify = False
    if isinstance(raw, dict) and IDENTIFY in raw:
        if not isinstance(raw[IDENTIFY], bool):
            raise ConfigError(f'{key}.{IDENTIFY}', f'must be true or false, got '
                              f'{raw[IDENTIFY]!r}')
        identify = raw[IDENTIFY]
        raw = {k: v for k, v in raw.items() if k != IDENTIFY}
    if not isinstance(raw, dict) or len(raw) != 1 or next(iter(raw)) not in ('rpy',
                                                                            'quaternion'):
        raise ConfigError(key, 'must be {rpy: [roll, pitch, yaw]} (rad, URDF convention) or '
                          f'{{quaternion: [x, y, z, w]}} of the tracked body in the tip frame '
                          "(with identify: true to identify it from there), or 'identify' "
                          f'(identified, starting at the tip frame\'s axes), got {raw!r}')
    if 'rpy' in raw:
        rpy = vector(raw['rpy'], f'{key}.rpy', 3)
        if np.any(np.abs(rpy) > 2 * np.pi):
            raise ConfigError(f'{key}.rpy', f'{rpy.tolist()}: angles beyond 2π; give radians '
                              '(degrees? multiply by π/180)')
        return rotation_from_rpy(rpy.tolist()), identify
    quaternion = vector(raw['quaternion'], f'{key}.quaternion', 4)
    try:
        return rotation_from_quaternion(quaternion.tolist()), identify
    except ValueError as exc:
        raise ConfigError(f'{key}.quaternion', f'{exc}; give a unit quaternion in the '
                          'order [x, y, z, w]') from None


MAX_JOINT_SIGMA = 0.01  # rad (0.57°); m for a prismatic joint


def parse_joint_sigma(value: Any) -> float | dict[str, float] | None:
    """noise.joint_sigma: None, a number for every joint or {joint name: number}, each in
    [0, MAX_JOINT_SIGMA]."""
    if value is None:
        return None
    fix = ('the standard deviation of the joint readings in rad (m for a prismatic joint), '
           'one number for every joint or {joint_name: value}; 0.03° is 5.2e-4')
    if isinstance(value, dict):
        out = {}
        for name, v in value.items():
            out[str(name)] = number(value, name, 'noise.joint_sigma', None, 'rad')
            if not 0 <= out[str(name)] <= MAX_JOINT_SIGMA:
                raise ConfigError(f'noise.joint_sigma.{name}', f'{v!r} must be in '
                                  f'[0, {MAX_JOINT_SIGMA}]: {fix}')
        return out
    sigma = number({'joint_sigma': value}, 'joint_sigma', 'noise', None, 'rad')
    if not 0 <= sigma <= MAX_JOINT_SIGMA:
        raise ConfigError('noise.joint_sigma', f'{value!r} must be in [0, {MAX_JOINT_SIGMA}]: '
                          f'{fix}')
    return sigma


def joint_sigma_vector(value: float | Mapping[str, float] | None,
                       joint_names: Sequence[str]) -> np.ndarray | None:
    """noise.joint_sigma in chain order (n,) rad, matched by joint name; None when unstated."""
    if value is None:
        return None
    if not isinstance(value, Mapping):
        return np.full(len(joint_names), float(value))
    unknown = [n for n in value if n not in joint_names]
    if unknown:
        raise ConfigError('noise.joint_sigma', f'unknown joint(s) {unknown}; the chain joints '
                          f'are {list(joint_names)}')
    return np.array([float(value.get(n, 0.0)) for n in joint_names])


def joint_noise_map(value: float | Mapping[str, float] | None, robot: RobotModel
                    ) -> np.ndarray | None:
    """noise.joint_sigma as the map of :class:`MeasurementModel`'s ``joint_sigma``.

    A robot without mimic joints: the (n,) σ of each chain joint (:func:`joint_sigma_vector`).
    With mimic joints the σ is stated for the actuated joints (a number: each; a mapping: by
    actuated joint name, the drive off the chain too) and a mimic joint's reading follows
    its leader's: the map M diag(σ_x) (n, m), M the robot's mimic matrix.

    Raises
    ------
    ConfigError
        ``noise.joint_sigma``: a name that is no actuated joint (a mimic joint: its leader
        is named).
    """
    if value is None or not robot.has_mimic:
        return joint_sigma_vector(value, robot.joint_names)
    actuated = list(robot.actuated_names)
    if isinstance(value, Mapping):
        leaders = {j.name: j.mimic.master for j in robot.joints if j.mimic is not None}
        for name in value:
            if name in leaders:
                raise ConfigError(f'noise.joint_sigma.{name}', f'{name!r} mimics '
                                  f'{leaders[name]!r}: state the reading noise of '
                                  f'{leaders[name]!r}, its mimic joints follow it')
        unknown = [n for n in value if n not in actuated]
        if unknown:
            raise ConfigError('noise.joint_sigma', f'unknown joint(s) {unknown}; the actuated '
                              f'joints are {actuated}')
        sigma = np.array([float(value.get(n, 0.0)) for n in actuated])
    else:
        sigma = np.full(len(actuated), float(value))
    return robot.mimic_matrix * sigma


def parse_working_poses(value: Any) -> tuple[WorkingPose, ...]:
    """``working_poses``: none (left out or empty: identify reports no TCP, design refuses),
    or a list of named or chain-ordered poses."""
    if value is None or value == []:
        return ()
    if not isinstance(value, list):
        raise ConfigError('working_poses', 'must be a list of working poses as '
                          '{name: ..., joints: {joint_name: value_rad, ...}} or as lists of '
                          'joint values in chain order (or left out: no TCP is reported)')
    poses = []
    for i, item in enumerate(value):
        key = f'working_poses[{i}]'
        if isinstance(item, list):  # joint values in chain order; length checked on the robot
            poses.append(WorkingPose(f'work_{i + 1}', {}, tuple(
                joint_value(v, f'{key}[{j}]') for j, v in enumerate(item))))
            continue
        if not isinstance(item, dict) or not isinstance(item.get('joints'), dict):
            raise ConfigError(key, 'must be a mapping with a joints: {name: rad} mapping, or a '
                              'list of joint values in chain order')
        joints = {str(name): joint_value(v, f'{key}.joints.{name}')
                  for name, v in item['joints'].items()}
        unknown = set(item) - {'name', 'joints', 'payload'}
        if unknown:
            raise ConfigError(f'{key}.{sorted(unknown)[0]}', 'unknown key; a working pose has '
                              'name, joints and payload')
        poses.append(WorkingPose(str(item.get('name', f'work_{i + 1}')), joints,
                                 payload=_working_payload(item.get('payload'), key)))
    return tuple(poses)


def checked_payload_mass(mass: float, key: str) -> float:
    """A payload mass in kg: 0 to :data:`PAYLOAD_MASS_LIMIT_KG` (grams or tonnes are refused)."""
    if not 0.0 <= mass <= PAYLOAD_MASS_LIMIT_KG:
        raise ConfigError(key, f'{mass!r} kg: a payload is 0 to {PAYLOAD_MASS_LIMIT_KG:g} kg '
                          '(SI kg; grams? divide by 1000)')
    return float(mass)


def checked_payload_com(value: Any, key: str) -> np.ndarray:
    """A payload's centre of mass [x, y, z] in the tip frame, m: each within
    :data:`PAYLOAD_COM_LIMIT_M` of the flange (millimetres written as metres are refused)."""
    com = vector(value, key, 3)
    if np.any(np.abs(com) > PAYLOAD_COM_LIMIT_M):
        raise ConfigError(key, f'{com.tolist()} m: a payload centre more than '
                          f'{PAYLOAD_COM_LIMIT_M:g} m from the tip frame (SI metres: 50 mm is '
                          '0.05)')
    return com


def _working_payload(value: Any, key: str
                     ) -> tuple[float, tuple[float, float, float] | None] | None:
    """A working pose's ``payload: {mass: kg, com: [x, y, z] m}`` (com optional: the cell's
    payload centre); None when left out (the cell's payload)."""
    if value is None:
        return None
    key = f'{key}.payload'
    if not isinstance(value, dict) or 'mass' not in value or set(value) - {'mass', 'com'}:
        raise ConfigError(key, 'must be {mass: kg, com: [x, y, z] m in the tip frame} (com '
                          'optional: the cell payload\'s centre), the load the robot carries '
                          'at this pose')
    mass = checked_payload_mass(number(value, 'mass', key, None, 'kg'), f'{key}.mass')
    if value.get('com') is None:
        return mass, None
    com = checked_payload_com(value['com'], f'{key}.com')
    return mass, (float(com[0]), float(com[1]), float(com[2]))


def working_poses_from_arrays(names: Sequence[str], values: Sequence[float],
                              names_key: str = 'working_joint_names',
                              values_key: str = 'working_poses') -> tuple[WorkingPose, ...]:
    """Working poses from a flat list of joint values, one block of ``len(names)`` per
    pose (the node's parameters); errors name ``names_key`` / ``values_key``."""
    names = [str(n) for n in names]
    if not names or len(set(names)) != len(names):
        raise ConfigError(names_key, f'give the unique joint names of {values_key}, '
                          f'got {names}')
    if not len(values) or len(values) % len(names):
        raise ConfigError(values_key, f'must hold finite values (rad), {len(names)} per pose '
                          f'(one per {names_key}), got {len(values)} values')
    poses = []
    for i in range(len(values) // len(names)):
        row = values[i * len(names):(i + 1) * len(names)]
        joints = {n: joint_value(v, f'{values_key}[{i * len(names) + j}]')
                  for j, (n, v) in enumerate(zip(names, row))}
        poses.append(WorkingPose(f'work_{i + 1}', joints))
    return tuple(poses)


Point3 = tuple[float, float, float]


def _point(value: np.ndarray) -> Point3:
    return (float(value[0]), float(value[1]), float(value[2]))


@dataclass(frozen=True)
class CapsuleSpec:
    """A capsule as the cell file states it: segment ``a``-``b`` (m, in ``frame``: a link,
    or ``'base'`` for an obstacle) swept by a ball of ``radius`` (m, >= 0)."""

    name: str
    frame: str
    a: Point3
    b: Point3
    radius: float


@dataclass(frozen=True)
class HalfSpaceSpec:
    """An obstacle half-space as the cell file states it: free side ``normal · x >= offset``
    in the base frame (``normal`` non-zero, as written; ``offset`` m along it)."""

    name: str
    normal: Point3
    offset: float


_CAPSULE_KEYS = {'name', 'a', 'b', 'radius'}


def parse_capsule(item: Any, key: str, frame_key: str = 'link') -> CapsuleSpec:
    """A robot capsule ``{name, link, a, b, radius}`` in the frame of ``link``."""
    if not isinstance(item, dict):
        raise ConfigError(key, 'must be a mapping {name, link, a, b, radius}')
    refuse_unknown(item, key, _CAPSULE_KEYS | {frame_key})
    frame = str(item.get(frame_key, 'base'))
    return _capsule(item, key, frame, frame)


def _capsule(item: dict, key: str, frame: str, default_name: str) -> CapsuleSpec:
    radius = non_negative(number(item, 'radius', key, unit='m'), f'{key}.radius', 'm')
    return CapsuleSpec(str(item.get('name', default_name)), frame,
                       _point(vector(item.get('a'), f'{key}.a', 3)),
                       _point(vector(item.get('b'), f'{key}.b', 3)), float(radius))


def parse_obstacle(item: Any, key: str) -> CapsuleSpec | HalfSpaceSpec:
    """An obstacle in the robot base frame: ``{name, type: halfspace, normal, offset}`` or
    ``{name, type: capsule, a, b, radius}``; a key of the other type is refused."""
    if not isinstance(item, dict) or 'name' not in item:
        raise ConfigError(key, 'must be a mapping with name and type (capsule or halfspace)')
    kind = item.get('type', 'capsule')
    if kind == 'halfspace':
        refuse_unknown(item, key, {'name', 'type', 'normal', 'offset'})
        normal = vector(item.get('normal'), f'{key}.normal', 3)
        if np.linalg.norm(normal) < 1e-9:
            raise ConfigError(f'{key}.normal', 'must be non-zero')
        return HalfSpaceSpec(str(item['name']), _point(normal),
                             float(number(item, 'offset', key, 0.0, 'm')))
    if kind == 'capsule':
        refuse_unknown(item, key, _CAPSULE_KEYS | {'type'})
        return _capsule(item, key, 'base', key)
    raise ConfigError(f'{key}.type', f"must be 'capsule' or 'halfspace', got {kind!r}")


def parse_ignore_pair(item: Any, key: str) -> frozenset:
    if not isinstance(item, (list, tuple)) or len(item) != 2:
        raise ConfigError(key, 'must be a pair [name_a, name_b] of links/capsules/obstacles')
    return frozenset(str(x) for x in item)


def parse_coupling(raw: Any) -> dict[str, Any]:
    """``robot.joint_coupling`` as a plain mapping; names are checked against the chain
    when the model is built (:func:`~kpi_calib_ros.app.cell_model.build_cell_model`)."""
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ConfigError('robot.joint_coupling', 'must map URDF joints to {controller_joint: '
                          'factor, offset: value}, e.g. {joint_3: {joint_3: 1.0, joint_2: 1.0}}')
    return {str(k): v for k, v in raw.items()}


def parse_working_poses_in(value: Any) -> str:
    if value not in ('controller', 'urdf'):
        raise ConfigError('robot.working_poses_in', "must be 'controller' (values as the "
                          f"controller reports them) or 'urdf', got {value!r}")
    return str(value)


# Below this the map is too close to singular to invert at joint-reading precision
# (1e-6 rad readings would come back with errors > 1e-6 · cond).
MAX_CONDITION = 1e6


def coupling_from_mapping(raw: Mapping[str, Any] | None, joint_names: Sequence[str],
                          key: str = 'robot.joint_coupling',
                          mimics: Mapping[str, Mimic] | None = None) -> JointCoupling:
    """Validate ``{urdf_joint: {controller_joint: factor, ..., offset: value}, ...}``.

    A listed URDF joint is exactly the given combination plus ``offset`` (rad or m,
    default 0; list the joint itself with 1.0 to keep its own reading); an unlisted one
    equals its controller value. ``joint_names`` are the robot's actuated joints (the
    chain's when nothing mimics): the master of a mimic joint is one of them, on the
    chain or not. ``mimics`` ({joint: its URDF relation}) names the mimic joints, which
    are neither targets nor sources: their values follow from their masters'.

    Raises
    ------
    ConfigError
        Unknown joint names, a mimic joint, non-numeric factors, or a map that cannot be
        inverted.
    """
    names = list(joint_names)
    mimics = mimics or {}
    matrix = np.eye(len(names))
    offset = np.zeros(len(names))
    if not raw:
        return JointCoupling(tuple(names), matrix)
    if not isinstance(raw, Mapping):
        raise ConfigError(key, 'must map URDF joints to {controller_joint: factor}, e.g. '
                          '{joint_3: {joint_3: 1.0, joint_2: 1.0, offset: 0.0}}')

    def check_name(name: str, where: str) -> None:
        if name in mimics:
            m = mimics[name]
            raise ConfigError(where, f'{name!r} is a mimic joint: the URDF states its value, '
                              f'{m.multiplier:g} · {m.master} {m.offset:+g}, and the tool '
                              f'applies it; couple its master {m.master!r} instead (or edit '
                              'the <mimic> tag)')
        if name not in names:
            raise ConfigError(where, f'not a chain joint; joints are {names}')

    for urdf_joint, row in raw.items():
        check_name(urdf_joint, f'{key}.{urdf_joint}')
        if not isinstance(row, Mapping) or not row:
            raise ConfigError(f'{key}.{urdf_joint}', 'must map controller joints to factors, '
                              f'e.g. {{{urdf_joint}: 1.0, joint_2: 1.0, offset: 0.0}}')
        i = names.index(urdf_joint)
        matrix[i] = 0.0
        for source, factor in row.items():
            if source != 'offset':
                check_name(source, f'{key}.{urdf_joint}.{source}')
            if isinstance(factor, bool) or not isinstance(factor, (int, float)) \
                    or not np.isfinite(factor):
                raise ConfigError(f'{key}.{urdf_joint}.{source}',
                                  f'must be a finite number, got {factor!r}')
            if source == 'offset':
                offset[i] = float(factor)
            else:
                matrix[i, names.index(source)] = float(factor)
    cond = np.linalg.cond(matrix)
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise ConfigError(key, f'the map is not invertible (condition {cond:.3g}): each URDF '
                          'joint must be recoverable from the controller joints and back; '
                          'a listed joint usually keeps itself with factor 1.0')
    return JointCoupling(tuple(names), matrix, tuple(names), offset)

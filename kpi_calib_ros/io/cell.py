"""Cell file: the robot, tracker, reflector, noise, payload, working poses and obstacles.

A YAML document validated in one place; every error names the key path and the
fix. Paths are relative to the cell file. Units are SI (m, rad, kg). Example::

    robot: {urdf: ../robots/kr15_class.urdf, base_frame: base_link, tip_frame: tool0,
            package_dirs: [../src],    # optional: where package:// meshes are searched first
            joint_coupling: {joint_3: {joint_3: 1.0, joint_2: 1.0}},  # optional
            working_poses_in: controller}                              # or urdf
    tracker: {frame_id: laser_tracker, base_in_tracker: [x, y, z, roll, pitch, yaw]}  # optional
    reflector: {offset: [0, 0, 0.03], axis: [0, 0, 1], max_incidence: 0.5236}  # offset optional
    # or several reflectors / markers (the first one is the KPI point; offsets optional):
    # reflectors: [{name: a, offset: [0, 0, 0.03]}, {name: b, offset: [0.05, 0, 0.03]}]
    # a tracked 6-DoF body: its origin is the reflector, orientation in the tip frame
    # reflectors: [{name: probe, offset: [0, 0, 0.1], orientation: {rpy: [0, 0, 0]}}]
    noise: {sigma: 2.0e-5}          # sigma_rotation: 5.0e-5 (rad) with an orientation
    # joint-reading noise (rad), all joints or by name: joint_sigma: 5.2e-4
    # or joint_sigma: {joint_1: 5.2e-4, joint_2: 5.2e-4}   (joints left out read exactly)
    payload: {mass: 5.0, com: [0, 0, 0.05]}
    working_poses:                  # optional for identify (no TCP then); design needs them
      - {name: roof, joints: {joint_1: 0.0, joint_2: 0.3, ...}}
      - [0.0, -1.2, 1.7, -2.07, -1.57, 0.0]   # or joint values in chain order
    obstacles:                      # in the robot base frame
      - {name: floor, type: halfspace, normal: [0, 0, 1], offset: -0.5}
      - {name: car_roof, type: capsule, a: [1.6, -1.5, 0.9], b: [1.6, 1.5, 0.9], radius: 0.5}
    collision: {capsules: [...], ignore_pairs: [[base_link, floor]], beam_radius: 0.005}
    identification: {method: pivoted, model: geometric, loss: linear, max_iterations: 500,
                     outliers: {exclude: true, threshold: null}, cv_folds: 5,
                     prior: {translation: 1.0e-3, rotation: 1.0e-3, offset: 1.0e-3}}
    topics: {joint_states: /joint_states, point: /laser_tracker/point,   # bags read
             pose: /laser_tracker/pose}
    design: {candidates: 4000, weights: {roof: 2.0}}        # see DesignSettings
    simulation: {hidden_effects: {joint_compliance:joint_2: {c: 4.0e-7}}}
"""
from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np
import yaml

from kpi_calib_ros.core.collision import Capsule, CollisionScene, HalfSpace
from kpi_calib_ros.core.coupling import JointCoupling, coupling_from_mapping, identity_coupling
from kpi_calib_ros.core.design import DesignSettings
from kpi_calib_ros.core.design_cell import DesignCell
from kpi_calib_ros.core.effects import resolve_effects
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation import DEFAULT_MAX_ITERATIONS
from kpi_calib_ros.core.gravity_compliance import mass_warning
from kpi_calib_ros.core.kinematics import pose6
from kpi_calib_ros.core.measurement import MeasurementModel
from kpi_calib_ros.core.model_selection import DEFAULT_FOLDS, MODEL_CHOICES
from kpi_calib_ros.core.parameters import ParameterSet, geometric_parameters
from kpi_calib_ros.core.pose_measurement import rotation_from_quaternion, rotation_from_rpy
from kpi_calib_ros.core.robot import Payload, RobotModel
from kpi_calib_ros.core.robust import LOSSES, OutlierSettings
from kpi_calib_ros.io.cell_temperature import TemperatureSettings, temperature_settings
from kpi_calib_ros.io.names import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC, DEFAULT_POSE_TOPIC
from kpi_calib_ros.io.resources import resolve_uri
from kpi_calib_ros.io.results import write_atomic
from kpi_calib_ros.io.robot_geometry import RobotGeometry, robot_geometry
from kpi_calib_ros.io.yaml_bounded import read_yaml_file

_TOP_KEYS = {'robot', 'tracker', 'reflector', 'reflectors', 'noise', 'payload', 'working_poses',
             'obstacles', 'collision', 'identification', 'effects', 'simulation', 'design',
             'topics', 'temperature'}
_TOPIC_KEYS = {'joint_states': DEFAULT_JOINT_TOPIC, 'point': DEFAULT_POINT_TOPIC,
               'pose': DEFAULT_POSE_TOPIC}
# Plausibility of SI values: beyond these a value is almost surely in other units.
MAX_TRACKER_RANGE_M = 50.0     # laser trackers measure to ~40-80 m; cells are far smaller
MAX_REFLECTOR_OFFSET_M = 2.0   # reflector from the flange: a tool, not a second robot
DEFAULT_CELL = Path(__file__).resolve().parent.parent / 'data' / 'cells' / 'default_cell.yaml'


@dataclass(frozen=True)
class WorkingPose:
    """A working pose by joint name (``joints``) or in chain order (``values``, rad/m)."""

    name: str
    joints: dict[str, float]
    values: tuple[float, ...] = ()


@dataclass(frozen=True)
class SimulationSettings:
    """The ``simulation:`` section: what the simulated robot has beyond the model.

    ``hidden_effects`` maps effect specs to their true parameter values; it is
    checked against the robot by :func:`kpi_calib_ros.core.effects.hidden_effects`.
    """

    hidden_effects: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class IdentificationSettings:
    """The model size, loss and outlier keys of ``identification:``.

    model : ``auto`` (chosen by the predicted out-of-sample error) or a level of
    :mod:`kpi_calib_ros.core.model_selection`; loss : ``linear``, ``huber`` or ``soft_l1``
    (:mod:`kpi_calib_ros.core.robust`); outliers : exclusion settings; cv_folds : folds of
    the cross-validated rms reported beside the model choice; prior : std (m, rad, rad)
    of the joint placement translations, rotations and joint offsets around the nominal
    (:func:`kpi_calib_ros.core.prior.tolerance_prior`), None: no prior; max_iterations :
    iteration limit of every fit (:func:`kpi_calib_ros.core.estimation.identify`).
    """

    model: str = 'geometric'
    loss: str = 'linear'
    outliers: OutlierSettings = field(default_factory=OutlierSettings)
    cv_folds: int = DEFAULT_FOLDS
    prior: tuple[float, float, float] | None = None
    max_iterations: int = DEFAULT_MAX_ITERATIONS


@dataclass(frozen=True)
class Cell:
    """Validated content of a cell file (SI units; obstacles in the robot base frame)."""

    urdf_xml: str
    urdf_path: str
    base_frame: str
    tip_frame: str
    tracker_frame: str
    base_in_tracker: np.ndarray
    reflector_offset: np.ndarray
    reflector_axis: np.ndarray
    max_incidence: float
    sigma: np.ndarray
    payload_mass: float
    payload_com: np.ndarray
    working_poses: tuple[WorkingPose, ...]
    obstacles: tuple[Capsule | HalfSpace, ...]
    robot_capsules: tuple[Capsule, ...]
    ignore_pairs: tuple[frozenset, ...]
    beam_radius: float
    identification_method: str
    identification_priority: tuple[str, ...]
    effects: tuple[str, ...]
    joint_topic: str = DEFAULT_JOINT_TOPIC   # bag topics (topics: section)
    point_topic: str = DEFAULT_POINT_TOPIC
    pose_topic: str = DEFAULT_POSE_TOPIC
    design: DesignSettings = field(default_factory=DesignSettings)
    simulation: SimulationSettings = field(default_factory=SimulationSettings)
    identification: IdentificationSettings = field(default_factory=IdentificationSettings)
    source_dir: str = field(default='', compare=False)  # folder of the cell file
    # robot.package_dirs as written (relative to source_dir): searched first for package://
    package_dirs: tuple[str, ...] = ()
    # False when the cell leaves tracker.base_in_tracker / reflector.offset out: the
    # stored zeros are then placeholders, registered from the data before identifying.
    base_in_tracker_given: bool = True
    reflector_offset_given: bool = True
    # robot.joint_coupling: {urdf_joint: {controller_joint: factor}} (validated against
    # the chain in build_cell_model); robot.working_poses_in: 'controller' or 'urdf'.
    joint_coupling: Mapping[str, Any] = field(default_factory=dict)
    working_poses_in: str = 'controller'
    # ``reflectors:`` form: names and (R, 3) offsets (zeros where the offset is left out
    # and registered from the data); () for the single ``reflector:`` form.
    reflector_names: tuple[str, ...] = ()
    reflector_offsets: np.ndarray | None = field(default=None, compare=False)
    # Tracked 6-DoF bodies: (reflector index, (3, 3) body rotation in the tip frame) of
    # every reflector with an ``orientation``, and noise.sigma_rotation (rad).
    reflector_orientations: tuple[tuple[int, np.ndarray], ...] = field(default=(),
                                                                        compare=False)
    sigma_rotation: float | None = None
    # noise.joint_sigma: a number (rad, every joint) or {joint name: rad}; None: exact
    # joint readings. Matched to the chain by name in build_cell_model.
    joint_sigma: float | Mapping[str, float] | None = None
    # temperature: section (io.cell_temperature); None: no temperature read.
    temperature: TemperatureSettings | None = None

    @property
    def offsets(self) -> np.ndarray:
        """(R, 3) nominal offsets of every reflector."""
        if self.reflector_offsets is not None:
            return self.reflector_offsets
        return self.reflector_offset.reshape(1, 3)
    # Set by the caller (--allow-code-effects, node parameter), never by the file: may
    # effects name Python code to run (see core.effects.parse_effect_spec)?
    allow_code_effects: bool = field(default=False, compare=False)


def load_cell(path: str | Path, urdf_xml: str | None = None,
              allow_code_effects: bool = False) -> Cell:
    """Read and validate a cell file; relative paths resolve against its folder.

    ``urdf_xml`` replaces ``robot.urdf`` (a URDF from a ROS topic); ``''`` means
    "given later by :func:`with_overrides`" and leaves ``Cell.urdf_xml`` empty.
    ``allow_code_effects``: effects may name Python files or modules, whose code runs
    when the model is built; off, such an effect is a ConfigError naming the opt-in.
    """
    path = Path(path)
    return cell_from_dict(read_cell_document(path), path.parent, urdf_xml=urdf_xml,
                          allow_code_effects=allow_code_effects)


def read_cell_document(path: str | Path) -> Any:
    """The parsed YAML of a cell file, not yet validated (see :func:`cell_from_dict`)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError('cell', f'file {str(path)!r} does not exist')
    # A cell is a few kB; 4 MiB and 1e6 nodes bound a hostile or wrong file (an alias bomb
    # in a capsule list) to a quick refusal.
    return read_yaml_file(path, 'cell', 'give a cell file (see the cell-file reference)',
                          loader=CellLoader, max_bytes=4 * 2 ** 20, max_nodes=1_000_000)


class CellLoader(yaml.SafeLoader):
    """PyYAML's safe loader with the YAML 1.2 float rule.

    YAML 1.1 (PyYAML) reads ``2e-06`` as the *string* '2e-06' (it wants ``2.0e-06``);
    every other YAML reader and every user reads a number. Here any plain scalar that
    YAML 1.2 calls a float is one, so ``noise: {sigma: 2e-06}`` means 2 µm.
    """


CellLoader.yaml_implicit_resolvers = {
    k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
CellLoader.add_implicit_resolver(
    'tag:yaml.org,2002:float',
    re.compile(r'''^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                   |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                   |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                   |[-+]?\.(?:inf|Inf|INF)
                   |\.(?:nan|NaN|NAN))$''', re.X),
    list('-+0123456789.'))


def write_cell_document(path: str | Path, doc: dict[str, Any]) -> Path:
    """Write a cell document as YAML (atomically); :func:`load_cell` reads it back."""
    return write_atomic(path, yaml.safe_dump(doc, sort_keys=False))


def cell_from_dict(doc: Any, base_dir: Path, urdf_xml: str | None = None,
                   allow_code_effects: bool = False) -> Cell:
    """Validate a parsed cell document. ``urdf_xml`` overrides ``robot.urdf`` (ROS topic);
    ``allow_code_effects`` as for :func:`load_cell`."""
    if not isinstance(doc, dict):
        raise ConfigError('cell', 'the document must be a mapping with keys '
                          f'{sorted(_TOP_KEYS)}')
    unknown = set(doc) - _TOP_KEYS
    if unknown:
        raise ConfigError(sorted(unknown)[0], f'unknown key; allowed keys are {sorted(_TOP_KEYS)}')
    robot = _mapping(doc, 'robot')
    if urdf_xml is None:
        urdf_rel = _str(robot, 'robot.urdf', 'urdf')
        urdf_path = (base_dir / urdf_rel).resolve()
        if urdf_rel.startswith(('package://', 'file://')):  # resolved the ROS way
            urdf_path = resolve_uri(urdf_rel, _package_dirs(robot.get('package_dirs')),
                                    base_dir, key='robot.urdf', referenced_by='robot.urdf')
        if not urdf_path.is_file():
            raise ConfigError('robot.urdf', f'file {str(urdf_path)!r} does not exist; paths are '
                              'relative to the cell file')
        urdf_xml = urdf_path.read_text()
    else:
        urdf_path = Path('<robot_description>')
    tracker: dict[str, Any] = doc.get('tracker') or {}
    names, offsets, orientations = _reflectors(doc)
    reflector: dict[str, Any] = doc.get('reflector') or {}
    for key, section in (('tracker', tracker), ('reflector', reflector)):
        if not isinstance(section, dict):
            raise ConfigError(key, 'must be a mapping')
    noise = _mapping(doc, 'noise')
    payload = _optional_mapping(doc, 'payload')
    axis = _vector(reflector.get('axis', [0, 0, 1]), 'reflector.axis', 3)
    if np.linalg.norm(axis) < 1e-9:
        raise ConfigError('reflector.axis', 'must be a non-zero vector in the tip frame')
    sigma = np.broadcast_to(np.asarray(_number_or_vector(noise.get('sigma'), 'noise.sigma'),
                                       float), (3,)).copy()
    if np.any(sigma <= 0) or np.any(sigma > 0.01):
        raise ConfigError('noise.sigma', f'{sigma.tolist()} must be in (0, 0.01] m per axis '
                          '(SI metres: 20 µm is 2.0e-5)')
    sigma_rotation = None
    if orientations or 'sigma_rotation' in noise:
        sigma_rotation = number(noise, 'sigma_rotation', 'noise', None, 'rad')
        if not 0 < sigma_rotation <= 0.1:
            raise ConfigError('noise.sigma_rotation', f'{sigma_rotation!r} must be in (0, 0.1] '
                              'rad: the orientation noise of the tracked body (SI radians: '
                              '0.01° is 1.75e-4)')
    joint_sigma = _joint_sigma(noise.get('joint_sigma'))
    max_inc = number(reflector, 'max_incidence', 'reflector', np.deg2rad(30.0), 'rad')
    if not 0 < max_inc <= np.pi / 2:
        raise ConfigError('reflector.max_incidence', 'must be in (0, π/2] rad (30° = 0.5236)')
    collision = _optional_mapping(doc, 'collision')
    ident = _optional_mapping(doc, 'identification')
    method = ident.get('method', 'pivoted')
    if method not in ('pivoted', 'priority'):
        raise ConfigError('identification.method', "must be 'pivoted' or 'priority'")
    mass = number(payload, 'mass', 'payload', 0.0, 'kg')
    if mass < 0:
        raise ConfigError('payload.mass', 'must be >= 0 kg')
    return Cell(
        urdf_xml=urdf_xml, urdf_path=str(urdf_path),
        base_frame=_str(robot, 'robot.base_frame', 'base_frame'),
        tip_frame=_str(robot, 'robot.tip_frame', 'tip_frame'),
        tracker_frame=str(tracker.get('frame_id', 'laser_tracker')),
        base_in_tracker=_plausible_pose(_optional_vector(tracker.get('base_in_tracker'),
                                                         'tracker.base_in_tracker', 6)),
        reflector_offset=_plausible_offset(
            np.nan_to_num(offsets[0]) if offsets is not None else
            _optional_vector(reflector.get('offset'), 'reflector.offset', 3)),
        reflector_axis=axis / np.linalg.norm(axis), max_incidence=max_inc, sigma=sigma,
        payload_mass=mass,
        payload_com=_vector(payload.get('com', [0, 0, 0]), 'payload.com', 3),
        working_poses=_working_poses(doc.get('working_poses')),
        obstacles=tuple(_obstacle(o, f'obstacles[{i}]')
                        for i, o in enumerate(doc.get('obstacles') or [])),
        robot_capsules=tuple(_capsule(c, f'collision.capsules[{i}]', frame_key='link')
                             for i, c in enumerate(collision.get('capsules') or [])),
        ignore_pairs=tuple(_pair(p, f'collision.ignore_pairs[{i}]')
                           for i, p in enumerate(collision.get('ignore_pairs') or [])),
        beam_radius=_non_negative(number(collision, 'beam_radius', 'collision', 0.005, 'm'),
                                  'collision.beam_radius', 'm'),
        identification_method=method,
        identification_priority=_priority(ident, method),
        effects=tuple(str(e) for e in (doc.get('effects') or [])),
        **_topics(doc.get('topics')),
        design=design_settings(doc.get('design')),
        simulation=simulation_settings(doc.get('simulation')),
        identification=identification_settings(ident), source_dir=str(base_dir),
        package_dirs=_package_dirs(robot.get('package_dirs')),
        base_in_tracker_given=tracker.get('base_in_tracker') is not None,
        reflector_offset_given=(bool(not np.isnan(offsets).any()) if offsets is not None
                                else reflector.get('offset') is not None),
        reflector_names=names,
        reflector_offsets=np.nan_to_num(offsets) if offsets is not None else None,
        reflector_orientations=orientations, sigma_rotation=sigma_rotation,
        joint_sigma=joint_sigma,
        joint_coupling=_coupling_mapping(robot.get('joint_coupling')),
        working_poses_in=_working_poses_in(robot.get('working_poses_in', 'controller')),
        temperature=temperature_settings(doc.get('temperature')),
        allow_code_effects=allow_code_effects)


def _coupling_mapping(raw: Any) -> dict[str, Any]:
    """``robot.joint_coupling`` as a plain mapping; names are checked against the chain
    when the model is built (:func:`build_cell_model`)."""
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ConfigError('robot.joint_coupling', 'must map URDF joints to {controller_joint: '
                          'factor}, e.g. {joint_3: {joint_3: 1.0, joint_2: 1.0}}')
    return {str(k): v for k, v in raw.items()}


def _working_poses_in(value: Any) -> str:
    if value not in ('controller', 'urdf'):
        raise ConfigError('robot.working_poses_in', "must be 'controller' (values as the "
                          f"controller reports them) or 'urdf', got {value!r}")
    return str(value)


def _reflectors(doc: dict) -> tuple[tuple[str, ...], np.ndarray | None,
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
                       else _plausible_offset(_vector(offset, f'{key}.offset', 3),
                                              f'{key}.offset'))
        if item.get('orientation') is not None:
            orientations.append((i, _orientation(item['orientation'], f'{key}.orientation')))
    return tuple(names), np.array(offsets), tuple(orientations)


def _orientation(raw: Any, key: str) -> np.ndarray:
    """A tracked body's orientation in the tip frame, ``{rpy: [roll, pitch, yaw]}`` (rad,
    URDF convention) or ``{quaternion: [x, y, z, w]}``, as a (3, 3) rotation."""
    if not isinstance(raw, dict) or len(raw) != 1 or next(iter(raw)) not in ('rpy',
                                                                            'quaternion'):
        raise ConfigError(key, 'must be {rpy: [roll, pitch, yaw]} (rad, URDF convention) or '
                          f'{{quaternion: [x, y, z, w]}} of the tracked body in the tip frame, '
                          f'got {raw!r}')
    if 'rpy' in raw:
        rpy = _vector(raw['rpy'], f'{key}.rpy', 3)
        if np.any(np.abs(rpy) > 2 * np.pi):
            raise ConfigError(f'{key}.rpy', f'{rpy.tolist()}: angles beyond 2π; give radians '
                              '(degrees? multiply by π/180)')
        return rotation_from_rpy(rpy.tolist())
    quaternion = _vector(raw['quaternion'], f'{key}.quaternion', 4)
    try:
        return rotation_from_quaternion(quaternion.tolist())
    except ValueError as exc:
        raise ConfigError(f'{key}.quaternion', f'{exc}; give a unit quaternion in the '
                          'order [x, y, z, w]') from None


def with_overrides(cell: Cell, urdf_xml: str | None = None,
                   working_poses: tuple[WorkingPose, ...] | None = None) -> Cell:
    """``cell`` with a URDF document (e.g. from ``/robot_description``) and/or working
    poses (e.g. node parameters) in place of the cell file's; both are checked against
    the robot when the cell model is built (:func:`build_cell_model`)."""
    changes: dict[str, Any] = {}
    if urdf_xml is not None:
        changes.update(urdf_xml=urdf_xml, urdf_path='<robot_description>')
    if working_poses:
        changes['working_poses'] = tuple(working_poses)
    return replace(cell, **changes)


def design_settings(raw: Mapping[str, Any] | None) -> DesignSettings:
    """Validate the ``design:`` mapping of a cell file; errors name the key."""
    raw = dict(raw or {})
    defaults = DesignSettings()
    known = set(defaults.__dataclass_fields__)
    for key in raw:
        if key not in known:
            raise ConfigError(f'design.{key}', f'unknown key; allowed: {sorted(known)}')
    values: dict[str, Any] = {}
    for key, value in raw.items():
        default = getattr(defaults, key)
        path = f'design.{key}'
        if key == 'weights':
            if not isinstance(value, Mapping) or not all(
                    isinstance(v, (int, float)) and v >= 0 for v in value.values()):
                raise ConfigError(path, 'must map working pose names to weights >= 0')
            values[key] = {str(k): float(v) for k, v in value.items()}
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(path, f'must be true or false, got {value!r}')
            values[key] = value
        elif isinstance(default, int):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(path, f'must be a positive integer, got {value!r}')
            values[key] = value
        else:
            values[key] = _non_negative(number(raw, key, 'design'), path, '')
    if values.get('flag_threshold', 0.5) > 1:
        raise ConfigError('design.flag_threshold', 'must be a fraction in [0, 1]')
    return replace(defaults, **values)


_IDENT_KEYS = {'method', 'priority', 'model', 'loss', 'outliers', 'cv_folds', 'prior',
               'max_iterations'}
PRIOR_KEYS = ('translation', 'rotation', 'offset')


def identification_settings(raw: Mapping[str, Any]) -> IdentificationSettings:
    """Validate the model-size, loss and outlier keys of ``identification:``."""
    unknown = set(raw) - _IDENT_KEYS
    if unknown:
        raise ConfigError(f'identification.{sorted(unknown)[0]}',
                          f'unknown key; allowed: {sorted(_IDENT_KEYS)}')
    model = raw.get('model', 'geometric')
    if model not in MODEL_CHOICES:
        raise ConfigError('identification.model', f'must be one of {list(MODEL_CHOICES)}, '
                          f'got {model!r}')
    loss = raw.get('loss', 'linear')
    if loss not in LOSSES:
        raise ConfigError('identification.loss', f'must be one of {list(LOSSES)}, got {loss!r}')
    folds = raw.get('cv_folds', DEFAULT_FOLDS)
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 2:
        raise ConfigError('identification.cv_folds', f'must be an integer >= 2, got {folds!r}')
    out = raw.get('outliers') or {}
    if not isinstance(out, dict):
        raise ConfigError('identification.outliers', 'must be a mapping {exclude: true, '
                          'threshold: null}')
    bad = set(out) - {'exclude', 'threshold', 'max_fraction'}
    if bad:
        raise ConfigError(f'identification.outliers.{sorted(bad)[0]}', 'unknown key; allowed: '
                          "['exclude', 'max_fraction', 'threshold']")
    exclude = out.get('exclude', True)
    if not isinstance(exclude, bool):
        raise ConfigError('identification.outliers.exclude', f'must be true or false, got '
                          f'{exclude!r}')
    threshold = out.get('threshold')
    if threshold is not None and (isinstance(threshold, bool) or
                                  not isinstance(threshold, (int, float)) or threshold <= 1):
        raise ConfigError('identification.outliers.threshold', 'must be a distance in units of '
                          f'the robust σ greater than 1 (e.g. 5.0), or null; got {threshold!r}')
    fraction = out.get('max_fraction', 0.2)
    if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or \
            not 0 <= fraction < 1:
        raise ConfigError('identification.outliers.max_fraction', f'must be in [0, 1), got '
                          f'{fraction!r}')
    limit = raw.get('max_iterations', DEFAULT_MAX_ITERATIONS)
    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        raise ConfigError('identification.max_iterations', 'must be a positive integer (the '
                          f'iteration limit of every fit, default {DEFAULT_MAX_ITERATIONS}), '
                          f'got {limit!r}')
    return IdentificationSettings(model, loss, OutlierSettings(
        exclude, None if threshold is None else float(threshold), float(fraction)), folds,
        _tolerance_prior(raw.get('prior')), limit)


def _tolerance_prior(raw: Any) -> tuple[float, float, float] | None:
    """``identification.prior``: {translation, rotation, offset} std (m, rad), or null."""
    if raw is None:
        return None
    fix = ('a mapping {translation: 1.0e-3, rotation: 1.0e-3, offset: 1.0e-3} of the '
           'tolerance std (m, rad, rad) of the joint placements and offsets, or null')
    if not isinstance(raw, dict):
        raise ConfigError('identification.prior', f'must be {fix}; got {raw!r}')
    bad = set(raw) ^ set(PRIOR_KEYS)
    if bad:
        raise ConfigError(f'identification.prior.{sorted(bad)[0]}',
                          f'unknown or missing key: give exactly {list(PRIOR_KEYS)}')
    values = []
    for key in PRIOR_KEYS:
        v = raw[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < float('inf'):
            raise ConfigError(f'identification.prior.{key}', 'must be a positive std in m '
                              f'or rad (e.g. 1.0e-3){_text_number_hint(v)}; got {v!r}')
        values.append(float(v))
    return values[0], values[1], values[2]


def simulation_settings(raw: Any) -> SimulationSettings:
    """Validate the ``simulation:`` mapping of a cell file."""
    if raw is None:
        return SimulationSettings()
    if not isinstance(raw, dict):
        raise ConfigError('simulation', 'must be a mapping, e.g. {hidden_effects: '
                          '{joint_compliance:joint_2: {c: 5.0e-7}}}')
    unknown = set(raw) - {'hidden_effects'}
    if unknown:
        raise ConfigError(f'simulation.{sorted(unknown)[0]}', "unknown key; allowed: "
                          "['hidden_effects']")
    hidden = raw.get('hidden_effects') or {}
    if not isinstance(hidden, dict):
        raise ConfigError('simulation.hidden_effects', 'must map effect specs to their '
                          'parameters, e.g. {joint_compliance:joint_2: {c: 5.0e-7}}')
    return SimulationSettings(dict(hidden))


def number(section: Mapping[str, Any], name: str, path: str,
           default: float | None = None, unit: str = '') -> float:
    """The finite number ``section[name]`` (``default`` when absent); the one reader of
    numeric cell values, so a wrong type (``beam_radius: wide``) names its key path
    ``path.name`` and the unit."""
    key = f'{path}.{name}' if path else name
    value = section.get(name, default)
    if value is None:
        raise ConfigError(key, f'missing; give a number{f" ({unit})" if unit else ""}')
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ConfigError(key, f'must be a finite number{f" in {unit}" if unit else ""} '
                          f'(SI units), got {value!r}')
    return float(value)


def _non_negative(value: float, key: str, unit: str) -> float:
    if value < 0:
        raise ConfigError(key, f'must be >= 0 {unit}, got {value}')
    return value


def _plausible_pose(pose: np.ndarray) -> np.ndarray:
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


def _plausible_offset(offset: np.ndarray, key: str = 'reflector.offset') -> np.ndarray:
    """A reflector offset (``key``) in SI metres, or a ConfigError with a units hint."""
    length = float(np.linalg.norm(offset))
    if length > MAX_REFLECTOR_OFFSET_M:
        raise ConfigError(key, f'the reflector is {length:g} m from the tip '
                          f'frame (at most {MAX_REFLECTOR_OFFSET_M:g} m is plausible); give '
                          'it in SI metres (millimetres? divide by 1000; 30 mm is 0.03)')
    return offset


def _topics(raw: Any) -> dict[str, str]:
    """The ``topics:`` section: which topics of a bag carry the joint states, the
    tracker points and the tracked 6-DoF poses (``--joint-topic`` / ``--point-topic`` /
    ``--pose-topic`` override it)."""
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError('topics', f'must be a mapping with keys {sorted(_TOPIC_KEYS)}')
    unknown = set(raw) - set(_TOPIC_KEYS)
    if unknown:
        raise ConfigError(f'topics.{sorted(unknown)[0]}', f'unknown key; allowed: '
                          f'{sorted(_TOPIC_KEYS)}')
    names = {}
    for key, default in _TOPIC_KEYS.items():
        value = raw.get(key, default)
        if not isinstance(value, str) or not value.strip() or ' ' in value:
            raise ConfigError(f'topics.{key}', f'must be a topic name such as {default!r}, '
                              f'got {value!r}')
        names[key] = value
    keys = list(names)
    for i, key in enumerate(keys):
        same = [k for k in keys[:i] if names[k] == names[key]]
        if same:
            raise ConfigError(f'topics.{key}', f'must differ from topics.{same[0]}')
    return {'joint_topic': names['joint_states'], 'point_topic': names['point'],
            'pose_topic': names['pose']}


def _priority(ident: dict, method: str) -> tuple[str, ...]:
    """``identification.priority``: parameter names, used only by ``method: priority``
    (their existence is checked against the model in :func:`build_cell_model`)."""
    raw = ident.get('priority')
    if raw is None:
        return ()
    if not isinstance(raw, list) or not all(isinstance(n, str) for n in raw):
        raise ConfigError('identification.priority', 'must be a list of parameter names, e.g. '
                          '[joint_1.offset, joint_2.offset]')
    if method != 'priority':
        raise ConfigError('identification.priority', "is used only with method: priority; "
                          'set it or remove the list')
    return tuple(raw)


MAX_JOINT_SIGMA = 0.01  # rad (0.57°); m for a prismatic joint


def _joint_sigma(value: Any) -> float | dict[str, float] | None:
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


def _optional_mapping(doc: dict, key: str) -> dict:
    value = doc.get(key)
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(key, f'must be a mapping, got {value!r}')
    return value


def _mapping(doc: dict, key: str) -> dict:
    value = doc.get(key)
    if not isinstance(value, dict):
        raise ConfigError(key, 'missing or not a mapping')
    return value


def _str(doc: dict, path: str, key: str) -> str:
    value = doc.get(key)
    if not isinstance(value, str) or not value:
        raise ConfigError(path, 'missing; give a non-empty string')
    return value


def _vector(value: Any, path: str, n: int) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        arr = np.array([])
    if value is None or arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ConfigError(path, f'must be a list of {n} finite numbers (SI units), got '
                          f'{value!r}{_text_number_hint(value)}')
    return arr


def _optional_vector(value: Any, path: str, n: int) -> np.ndarray:
    """``_vector``, or zeros when the key is left out (registered from the data later)."""
    return np.zeros(n) if value is None else _vector(value, path, n)


def _package_dirs(value: Any) -> tuple[str, ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError('robot.package_dirs', 'must be a list of directories (relative to the '
                          f'cell file) where package:// URIs are searched, got {value!r}')
    return tuple(value)


def _text_number_hint(value: Any) -> str:
    """Why a number arrived as text: quoted, or YAML 1.1's float rule (``2e-06`` is a
    string for PyYAML; ``2.0e-06`` a number), and the fix."""
    try:
        number = float(value) if isinstance(value, str) else None
    except ValueError:
        number = None
    if number is None:
        return ''
    return (f' (a string: a quoted number, or YAML 1.1 reading an exponent without a '
            f'decimal point as text; write {number:.1e} unquoted, e.g. sigma: {number:.1e})')


def _number_or_vector(value: Any, path: str) -> Any:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    return _vector(value, path, 3)


def _working_poses(value: Any) -> tuple[WorkingPose, ...]:
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
                _joint_value(v, f'{key}[{j}]') for j, v in enumerate(item))))
            continue
        if not isinstance(item, dict) or not isinstance(item.get('joints'), dict):
            raise ConfigError(key, 'must be a mapping with a joints: {name: rad} mapping, or a '
                              'list of joint values in chain order')
        joints = {str(name): _joint_value(v, f'{key}.joints.{name}')
                  for name, v in item['joints'].items()}
        poses.append(WorkingPose(str(item.get('name', f'work_{i + 1}')), joints))
    return tuple(poses)


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
        joints = {n: _joint_value(v, f'{values_key}[{i * len(names) + j}]')
                  for j, (n, v) in enumerate(zip(names, row))}
        poses.append(WorkingPose(f'work_{i + 1}', joints))
    return tuple(poses)


def _joint_value(v: Any, key: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise ConfigError(key, f'must be a finite number (rad), got {v!r}')
    return float(v)


def _capsule(item: Any, key: str, frame_key: str = 'frame') -> Capsule:
    if not isinstance(item, dict):
        raise ConfigError(key, 'must be a mapping {name, a, b, radius}')
    radius = _non_negative(number(item, 'radius', key, unit='m'), f'{key}.radius', 'm')
    frame = str(item.get(frame_key, 'base'))
    return Capsule(str(item.get('name', frame if frame_key == 'link' else key)), frame,
                   _vector(item.get('a'), f'{key}.a', 3), _vector(item.get('b'), f'{key}.b', 3),
                   radius)


def _obstacle(item: Any, key: str) -> Capsule | HalfSpace:
    if not isinstance(item, dict) or 'name' not in item:
        raise ConfigError(key, 'must be a mapping with name and type (capsule or halfspace)')
    kind = item.get('type', 'capsule')
    if kind == 'halfspace':
        normal = _vector(item.get('normal'), f'{key}.normal', 3)
        if np.linalg.norm(normal) < 1e-9:
            raise ConfigError(f'{key}.normal', 'must be non-zero')
        return HalfSpace(str(item['name']), normal, number(item, 'offset', key, 0.0, 'm'))
    if kind == 'capsule':
        cap = _capsule(item, key)
        return Capsule(cap.name, 'base', cap.a, cap.b, cap.radius)
    raise ConfigError(f'{key}.type', f"must be 'capsule' or 'halfspace', got {kind!r}")


def _pair(item: Any, key: str) -> frozenset:
    if not isinstance(item, (list, tuple)) or len(item) != 2:
        raise ConfigError(key, 'must be a pair [name_a, name_b] of links/capsules/obstacles')
    return frozenset(str(x) for x in item)


@dataclass(frozen=True)
class CellModel:
    """Numerical objects built from a :class:`Cell`.

    ``q_work`` (t, n) is in chain order, URDF values; ``tracker_in_base`` (4, 4) is the
    nominal tracker pose in the robot base frame (inverse of ``base_in_tracker``);
    ``coupling`` maps the controller's joint values to URDF values (``None``: uncoupled).
    """

    cell: Cell
    robot: RobotModel
    geometric: ParameterSet
    model: MeasurementModel
    q_work: np.ndarray
    working_pose_names: tuple[str, ...]
    tracker_in_base: np.ndarray
    coupling: JointCoupling | None = None

    @property
    def joint_names(self) -> list[str]:
        return self.robot.joint_names

    @property
    def joint_coupling(self) -> JointCoupling:
        """``robot.joint_coupling`` of the cell; the identity when it has none."""
        return self.coupling or identity_coupling(self.robot.joint_names)

    @property
    def needs_registration(self) -> bool:
        """The cell leaves the base pose or a reflector offset out: register them from
        the data before identifying."""
        return not (self.cell.base_in_tracker_given and self.cell.reflector_offset_given)

    def collision_scene(self) -> CollisionScene:
        """Robot capsules (cell file first, else fitted to URDF collision geometry) and
        obstacles; pairs skipped by the sampled collision matrix and ``ignore_pairs``."""
        geometry = self.robot_geometry()
        return CollisionScene(list(geometry.capsules), list(self.cell.obstacles),
                              self.robot.link_names,
                              ignore_pairs=set(self.cell.ignore_pairs) | geometry.skip_pairs(),
                              beam_radius=self.cell.beam_radius)

    def robot_geometry(self) -> RobotGeometry:
        """Capsules, collision matrix and resolved meshes (built on first use, cached)."""
        links = self.robot.link_names
        for cap in self.cell.robot_capsules:
            if cap.frame not in links:
                raise ConfigError('collision.capsules', f'link {cap.frame!r} is not on the chain '
                                  f'{links}')
        return robot_geometry(self.robot, self.cell.urdf_xml, self.cell.robot_capsules,
                              self.cell.obstacles, self.cell.package_dirs,
                              self.cell.source_dir or None, referenced_by=self.cell.urdf_path)

    def design_cell(self) -> DesignCell:
        """The typed design problem of this cell (core input of the design modules)."""
        if not self.cell.base_in_tracker_given:
            raise ConfigError('tracker.base_in_tracker', 'a design needs to know where the '
                              'tracker stands: give the robot base pose in the tracker frame '
                              '[x, y, z, roll, pitch, yaw] (m, rad) in the cell file (a tape '
                              'measure is enough; identification refines it from the data)')
        if not len(self.q_work):
            raise ConfigError('working_poses', 'a design optimises the TCP precision at the '
                              'working poses: give at least one as {name: ..., joints: '
                              '{joint_name: value_rad, ...}} (identify needs none)')
        return DesignCell(self.model, self.q_work, self.working_pose_names,
                          self.tracker_in_base, self.cell.reflector_offset,
                          self.cell.max_incidence, self.cell.sigma,
                          self.cell.identification_method, self.cell.identification_priority,
                          self.collision_scene())


def build_cell_model(cell: Cell, effects: tuple = ()) -> CellModel:
    """Robot, parameters, measurement model and working poses of ``cell``.

    The model holds the cell file's ``effects:`` followed by ``effects`` (specs
    such as ``'joint_compliance:joint_2'`` or bound effects); one given in both
    counts once.
    """
    if not cell.urdf_xml:
        raise ConfigError('robot.urdf', 'no robot description yet; give robot.urdf or the '
                          'URDF document (with_overrides)')
    robot = RobotModel(cell.urdf_xml, cell.base_frame, cell.tip_frame,
                       Payload(cell.payload_mass, tuple(cell.payload_com)))
    # Placements left out are zeros here; identification registers them first.
    geometric = geometric_parameters(robot, cell.base_in_tracker, cell.offsets,
                                     cell.reflector_names or None)
    code = cell.allow_code_effects
    resolved = resolve_effects(cell.effects, robot, 'effects', cell.source_dir or None, code)
    extra = resolve_effects(effects, robot, 'extra effects', cell.source_dir or None, code)
    resolved += tuple(e for e in extra if e.name not in {r.name for r in resolved})
    model = MeasurementModel(robot, geometric, resolved, cell.reflector_axis,
                             dict(cell.reflector_orientations),
                             None if cell.sigma_rotation is None
                             else cell.sigma / cell.sigma_rotation,
                             joint_sigma_vector(cell.joint_sigma, robot.joint_names))
    unknown = [n for n in cell.identification_priority if n not in model.params.names]
    if unknown:
        raise ConfigError('identification.priority', f'unknown parameter(s) {unknown}; valid '
                          f'names: {list(model.params.names)}')
    missing_masses = mass_warning(robot, resolved)
    if missing_masses:
        warnings.warn(missing_masses, stacklevel=2)
    coupling = coupling_from_mapping(cell.joint_coupling, robot.joint_names)
    q_work = np.array([_ordered(w, robot, f'working_poses[{i}].joints')
                       for i, w in enumerate(cell.working_poses)]).reshape(-1, robot.n_joints)
    if cell.working_poses_in == 'controller':
        q_work = coupling.to_urdf(q_work)
    inside = robot.within_limits(q_work)
    if not inside.all():
        bad = cell.working_poses[int(np.argmin(inside))].name
        raise ConfigError('working_poses', f'pose {bad!r} is outside the joint limits '
                          f'{robot.lower.round(3).tolist()} .. {robot.upper.round(3).tolist()}')
    b = cell.base_in_tracker
    base_in_tracker = np.array(ca.DM(pose6(ca.DM(b))))
    return CellModel(cell, robot, geometric, model, q_work,
                     tuple(w.name for w in cell.working_poses), np.linalg.inv(base_in_tracker),
                     coupling)


def _ordered(pose: WorkingPose, robot: RobotModel, key: str) -> list[float]:
    names = robot.joint_names
    if pose.values:
        if len(pose.values) != len(names):
            raise ConfigError(key.rsplit('.', 1)[0], f'{len(pose.values)} joint values given; '
                              f'the chain has {len(names)} joints, in this order: {names}')
        return list(pose.values)
    missing = [n for n in names if n not in pose.joints]
    extra = [n for n in pose.joints if n not in names]
    if missing or extra:
        raise ConfigError(key, f'joint names must be exactly {names}; missing {missing}, '
                          f'unknown {extra}')
    return [pose.joints[n] for n in names]

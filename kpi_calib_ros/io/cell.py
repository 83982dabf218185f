"""Cell file: the robot, tracker, reflector, noise, payload, working poses and obstacles.

A YAML document validated in one place into plain data (:class:`Cell`); every error names
the key path and the fix. Paths are relative to the cell file. Units are SI (m, rad, kg).
The numerical objects (robot, measurement model, design and collision problems) are built
from a :class:`Cell` by :mod:`kpi_calib_ros.app.cell_model`. Example::

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
    identification: {method: pivoted, model: geometric, loss: linear, max_iterations: null,
                     outliers: {exclude: true, threshold: null}, cv_folds: 5,
                     prior: {translation: 1.0e-3, rotation: 1.0e-3, offset: 1.0e-3}}
    topics: {joint_states: /joint_states, point: /laser_tracker/point,   # bags read
             pose: /laser_tracker/pose}
    design: {candidates: 4000, weights: {roof: 2.0}}        # see DesignSettings
    simulation: {hidden_effects: {joint_compliance:joint_2: {c: 4.0e-7}}}
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from kpi_calib_ros.core.effects.general import general_candidates  # noqa: F401  (registers specs)
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.cell_inputs import InputSettings, input_settings
from kpi_calib_ros.io.cell_sections import (
    CapsuleSpec,
    HalfSpaceSpec,
    WorkingPose,
    checked_payload_com,
    checked_payload_mass,
    identified_orientations,
    parse_capsule,
    parse_coupling,
    parse_ignore_pair,
    parse_joint_sigma,
    parse_obstacle,
    parse_package_dirs,
    parse_reflectors,
    parse_working_poses,
    parse_working_poses_in,
    plausible_offset,
    plausible_pose,
)
from kpi_calib_ros.io.cell_settings import (
    IdentificationSettings,
    SimulationSettings,
    design_settings,
    identification_settings,
    parse_priority,
    parse_topics,
    simulation_settings,
)
from kpi_calib_ros.io.cell_temperature import (
    TemperatureSettings,
    temperature_settings,
)
from kpi_calib_ros.io.cell_values import (
    non_negative,
    number,
    number_or_vector,
    optional_mapping,
    optional_vector,
    refuse_unknown,
    required_mapping,
    required_string,
    vector,
)
from kpi_calib_ros.io.names import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC, DEFAULT_POSE_TOPIC
from kpi_calib_ros.io.resources import resolve_uri
from kpi_calib_ros.io.results import write_atomic
from kpi_calib_ros.io.yaml_bounded import SAFE_LOADER, dump_yaml, read_yaml_file

_TOP_KEYS = {'robot', 'tracker', 'reflector', 'reflectors', 'noise', 'payload', 'working_poses',
             'obstacles', 'collision', 'identification', 'effects', 'simulation', 'design',
             'topics', 'temperature', 'inputs', 'compliance'}
# The keys of each section (documented in io/cell_schema.py; test_cell_schema.py checks both).
_ROBOT_KEYS = {'urdf', 'base_frame', 'tip_frame', 'package_dirs', 'joint_coupling',
               'working_poses_in'}
_SECTION_KEYS = {'tracker': {'frame_id', 'base_in_tracker'},
                 'reflector': {'offset', 'axis', 'max_incidence'},
                 'noise': {'sigma', 'sigma_rotation', 'joint_sigma'},
                 'payload': {'mass', 'com', 'limit'},
                 'collision': {'capsules', 'ignore_pairs', 'beam_radius'}}
DEFAULT_CELL = Path(__file__).resolve().parent.parent / 'data' / 'cells' / 'default_cell.yaml'


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
    obstacles: tuple[CapsuleSpec | HalfSpaceSpec, ...]
    robot_capsules: tuple[CapsuleSpec, ...]
    ignore_pairs: tuple[frozenset, ...]
    beam_radius: float
    identification_method: str
    identification_priority: tuple[str, ...]
    effects: tuple[str, ...]
    joint_topic: str = DEFAULT_JOINT_TOPIC   # bag topics (topics: section)
    point_topic: str = DEFAULT_POINT_TOPIC
    pose_topic: str = DEFAULT_POSE_TOPIC
    # design: keys given in the file, checked (io.cell_settings.DESIGN_KEYS); the cell model
    # makes them a core.design.optimum.DesignSettings (CellModel.design_settings).
    design: Mapping[str, Any] = field(default_factory=dict)
    simulation: SimulationSettings = field(default_factory=SimulationSettings)
    identification: IdentificationSettings = field(default_factory=IdentificationSettings)
    source_dir: str = field(default='', compare=False)  # folder of the cell file
    # robot.package_dirs as written (relative to source_dir): searched first for package://
    package_dirs: tuple[str, ...] = ()
    # False when the cell leaves tracker.base_in_tracker / reflector.offset out: the
    # stored zeros are then placeholders, registered from the data before identifying.
    base_in_tracker_given: bool = True
    reflector_offset_given: bool = True
    # payload.limit (kg): the most the robot carries; None: its moving links' mass.
    payload_limit: float | None = None
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
    # Reflectors whose body orientation is identified (reflectors[].orientation: identify):
    # three parameters reflector.<name>.r{x,y,z} after the stated rotation.
    identified_orientations: tuple[int, ...] = ()
    # Of those, the ones the cell states a guess of (identify: true): held within tolerance.
    stated_orientations: tuple[int, ...] = ()
    # noise.joint_sigma: a number (rad, every joint) or {joint name: rad}; None: exact
    # joint readings. Matched to the chain by name in build_cell_model.
    joint_sigma: float | Mapping[str, float] | None = None
    # temperature: section (io.cell_temperature); None: no temperature read.
    temperature: TemperatureSettings | None = None
    # inputs: and compliance: sections (io.cell_inputs): measured inputs, torque source.
    inputs: InputSettings = field(default_factory=InputSettings)

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


class CellLoader(SAFE_LOADER):
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
    return write_atomic(path, dump_yaml(doc))


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
    robot = required_mapping(doc, 'robot')
    refuse_unknown(robot, 'robot', _ROBOT_KEYS)
    if urdf_xml is None:
        urdf_rel = required_string(robot, 'robot.urdf', 'urdf')
        urdf_path = (base_dir / urdf_rel).resolve()
        if urdf_rel.startswith(('package://', 'file://')):  # resolved the ROS way
            urdf_path = resolve_uri(urdf_rel, parse_package_dirs(robot.get('package_dirs')),
                                    base_dir, key='robot.urdf', referenced_by='robot.urdf')
        if not urdf_path.is_file():
            raise ConfigError('robot.urdf', f'file {str(urdf_path)!r} does not exist; paths are '
                              'relative to the cell file')
        urdf_xml = urdf_path.read_text()
    else:
        urdf_path = Path('<robot_description>')
    tracker: dict[str, Any] = doc.get('tracker') or {}
    names, offsets, orientations = parse_reflectors(doc)
    reflector: dict[str, Any] = doc.get('reflector') or {}
    for key, section in (('tracker', tracker), ('reflector', reflector)):
        if not isinstance(section, dict):
            raise ConfigError(key, 'must be a mapping')
    noise = required_mapping(doc, 'noise')
    payload = optional_mapping(doc, 'payload')
    collision = optional_mapping(doc, 'collision')
    for key, section in (('tracker', tracker), ('reflector', reflector), ('noise', noise),
                         ('payload', payload), ('collision', collision)):
        refuse_unknown(section, key, _SECTION_KEYS[key])
    axis = vector(reflector.get('axis', [0, 0, 1]), 'reflector.axis', 3)
    if np.linalg.norm(axis) < 1e-9:
        raise ConfigError('reflector.axis', 'must be a non-zero vector in the tip frame')
    sigma = np.broadcast_to(np.asarray(number_or_vector(noise.get('sigma'), 'noise.sigma'),
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
    joint_sigma = parse_joint_sigma(noise.get('joint_sigma'))
    max_inc = number(reflector, 'max_incidence', 'reflector', np.deg2rad(30.0), 'rad')
    if not 0 < max_inc <= np.pi / 2:
        raise ConfigError('reflector.max_incidence', 'must be in (0, π/2] rad (30° = 0.5236)')
    ident = optional_mapping(doc, 'identification')
    method = ident.get('method', 'pivoted')
    if method not in ('pivoted', 'priority'):
        raise ConfigError('identification.method', "must be 'pivoted' or 'priority'")
    mass = checked_payload_mass(number(payload, 'mass', 'payload', 0.0, 'kg'), 'payload.mass')
    return Cell(
        urdf_xml=urdf_xml, urdf_path=str(urdf_path),
        base_frame=required_string(robot, 'robot.base_frame', 'base_frame'),
        tip_frame=required_string(robot, 'robot.tip_frame', 'tip_frame'),
        tracker_frame=str(tracker.get('frame_id', 'laser_tracker')),
        base_in_tracker=plausible_pose(optional_vector(tracker.get('base_in_tracker'),
                                                         'tracker.base_in_tracker', 6)),
        reflector_offset=plausible_offset(
            np.nan_to_num(offsets[0]) if offsets is not None else
            optional_vector(reflector.get('offset'), 'reflector.offset', 3)),
        reflector_axis=axis / np.linalg.norm(axis), max_incidence=max_inc, sigma=sigma,
        payload_mass=mass,
        payload_com=checked_payload_com(payload.get('com', [0, 0, 0]), 'payload.com'),
        working_poses=parse_working_poses(doc.get('working_poses')),
        obstacles=tuple(parse_obstacle(o, f'obstacles[{i}]')
                        for i, o in enumerate(doc.get('obstacles') or [])),
        robot_capsules=tuple(parse_capsule(c, f'collision.capsules[{i}]')
                             for i, c in enumerate(collision.get('capsules') or [])),
        ignore_pairs=tuple(parse_ignore_pair(p, f'collision.ignore_pairs[{i}]')
                           for i, p in enumerate(collision.get('ignore_pairs') or [])),
        beam_radius=non_negative(number(collision, 'beam_radius', 'collision', 0.005, 'm'),
                                  'collision.beam_radius', 'm'),
        identification_method=method,
        identification_priority=parse_priority(ident, method),
        effects=tuple(str(e) for e in (doc.get('effects') or [])),
        **parse_topics(doc.get('topics')),
        design=design_settings(doc.get('design')),
        simulation=simulation_settings(doc.get('simulation')),
        identification=identification_settings(ident), source_dir=str(base_dir),
        package_dirs=parse_package_dirs(robot.get('package_dirs')),
        payload_limit=(None if payload.get('limit') is None else _payload_limit(
            checked_payload_mass(number(payload, 'limit', 'payload', None, 'kg'),
                                 'payload.limit'), mass)),
        base_in_tracker_given=tracker.get('base_in_tracker') is not None,
        reflector_offset_given=(bool(not np.isnan(offsets).any()) if offsets is not None
                                else reflector.get('offset') is not None),
        reflector_names=names,
        reflector_offsets=np.nan_to_num(offsets) if offsets is not None else None,
        reflector_orientations=orientations, sigma_rotation=sigma_rotation,
        identified_orientations=identified_orientations(doc),
        stated_orientations=identified_orientations(doc, stated_only=True),
        joint_sigma=joint_sigma,
        joint_coupling=parse_coupling(robot.get('joint_coupling')),
        working_poses_in=parse_working_poses_in(robot.get('working_poses_in', 'controller')),
        temperature=temperature_settings(doc.get('temperature')),
        inputs=input_settings(doc.get('inputs'), doc.get('compliance')),
        allow_code_effects=allow_code_effects)


def with_overrides(cell: Cell, urdf_xml: str | None = None,
                   working_poses: tuple[WorkingPose, ...] | None = None) -> Cell:
    """``cell`` with a URDF document (e.g. from ``/robot_description``) and/or working
    poses (e.g. node parameters) in place of the cell file's; both are checked against
    the robot when the cell model is built
    (:func:`~kpi_calib_ros.app.cell_model.build_cell_model`)."""
    changes: dict[str, Any] = {}
    if urdf_xml is not None:
        changes.update(urdf_xml=urdf_xml, urdf_path='<robot_description>')
    if working_poses:
        changes['working_poses'] = tuple(working_poses)
    return replace(cell, **changes)


def _payload_limit(limit: float, mass: float) -> float:
    """``payload.limit`` (kg), positive and no less than the cell's ``payload.mass``."""
    if limit <= 0.0 or limit < mass:
        raise ConfigError('payload.limit', f'{limit!r} kg: the most the robot carries, '
                          f'positive and at least payload.mass ({mass:g} kg)')
    return limit

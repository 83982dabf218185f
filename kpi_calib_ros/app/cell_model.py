"""The cell model: the numerical objects built from a validated cell file.

:func:`build_cell_model` turns a :class:`~kpi_calib_ros.io.cell.Cell` (plain data from
:mod:`kpi_calib_ros.io.cell`) into the robot, its error parameters, the measurement model
and the working poses (:class:`CellModel`); the cell model then builds the design problem
(:meth:`CellModel.design_cell`), the collision scene and the robot geometry from the
cell's obstacles, capsules and ``design:`` settings when a design needs them.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np

from kpi_calib_ros.app.robot_geometry import RobotGeometry, mesh_check, robot_geometry
from kpi_calib_ros.core.acquisition.coupling import JointCoupling, mimic_coupling
from kpi_calib_ros.core.collision.capsules import Capsule, CollisionScene, HalfSpace
from kpi_calib_ros.core.design.cell import DesignCell
from kpi_calib_ros.core.design.optimum import DesignSettings
from kpi_calib_ros.core.effects.general import general_candidates  # noqa: F401  (registers specs)
from kpi_calib_ros.core.effects.gravity_compliance import mass_warning
from kpi_calib_ros.core.effects.registry import resolve_effects
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.payload import gravity_input
from kpi_calib_ros.core.measurement.pose import orientation_names, pose_matrix
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.model.parameters import ParameterSet, geometric_parameters
from kpi_calib_ros.core.model.robot import Payload, RobotModel
from kpi_calib_ros.io.cell import Cell
from kpi_calib_ros.io.cell_sections import (
    CapsuleSpec,
    HalfSpaceSpec,
    WorkingPose,
    coupling_from_mapping,
    joint_noise_map,
)
from kpi_calib_ros.io.cell_temperature import joint_temperatures


def collision_shape(spec: CapsuleSpec | HalfSpaceSpec) -> Capsule | HalfSpace:
    """The collision object of a capsule or half-space as the cell file states it."""
    if isinstance(spec, HalfSpaceSpec):
        return HalfSpace(spec.name, spec.normal, spec.offset)
    return Capsule(spec.name, spec.frame, spec.a, spec.b, spec.radius)


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
        """The joints the controller reports (joint states, designed poses, plans): the
        robot's actuated joints, the chain's when nothing mimics."""
        return list(self.joint_coupling.controller_names)

    @property
    def tau_work(self) -> np.ndarray | None:
        """Gravity torques (t, n) at the working poses, each with the payload the cell states
        for it (``working_poses[i].payload``, else the cell's); None when no effect reads a
        torque or no working pose states its own payload (the cell's is the robot's)."""
        poses = self.cell.working_poses
        if not self.model.uses_torque or not any(w.payload for w in poses) \
                or len(poses) != len(self.q_work):
            return None
        cell_payload = self.robot.payload
        payloads = [cell_payload if w.payload is None else
                    Payload(w.payload[0], w.payload[1] or cell_payload.com) for w in poses]
        return gravity_input(self.robot, self.q_work, payloads)

    @property
    def joint_coupling(self) -> JointCoupling:
        """``robot.joint_coupling`` of the cell followed by the URDF's mimic relations;
        the identity when it has neither."""
        return self.coupling or mimic_coupling(self.robot)

    @property
    def obstacles(self) -> tuple[Capsule | HalfSpace, ...]:
        """The cell's obstacles (robot base frame) as collision objects."""
        return tuple(collision_shape(o) for o in self.cell.obstacles)

    @property
    def robot_capsules(self) -> tuple[Capsule, ...]:
        """The cell file's robot capsules (``collision.capsules``, link frames)."""
        return tuple(Capsule(c.name, c.frame, c.a, c.b, c.radius)
                     for c in self.cell.robot_capsules)

    @property
    def design_settings(self) -> DesignSettings:
        """The cell's ``design:`` section over the defaults of :class:`DesignSettings`."""
        return DesignSettings(**self.cell.design)

    @property
    def needs_registration(self) -> bool:
        """The cell leaves the base pose or a reflector offset out: register them from
        the data before identifying."""
        return not (self.cell.base_in_tracker_given and self.cell.reflector_offset_given)

    def collision_scene(self) -> CollisionScene:
        """Robot capsules (cell file first, else fitted to URDF collision geometry) and
        obstacles; pairs skipped by the sampled collision matrix and ``ignore_pairs``."""
        geometry = self.robot_geometry()
        return CollisionScene(list(geometry.capsules), list(self.obstacles),
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
        return robot_geometry(self.robot, self.cell.urdf_xml, self.robot_capsules,
                              self.obstacles, self.cell.package_dirs,
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
                          self.collision_scene(), self.tau_work, self.mesh_free())

    def mesh_free(self) -> Callable[[np.ndarray], np.ndarray] | None:
        """(N, n) -> (N,) bool: the configurations in no contact on the collision meshes, as
        the design's verification judges them; None without meshes."""
        geometry = self.robot_geometry()
        if not geometry.has_meshes:
            return None
        ignore = self.cell.ignore_pairs
        return lambda q: np.array([not pairs for pairs in mesh_check(
            geometry, self.robot, q, ignore)[0].collisions], bool)


def carried_limit(stated: float | None, robot: RobotModel) -> tuple[float, str] | None:
    """The most the robot carries (kg) and where that figure comes from: ``stated`` (the
    cell's ``payload.limit``), else the mass of the robot's moving links in the URDF (no
    serial arm carries more than its own arm weighs); None when the URDF states no masses."""
    if stated is not None:
        return stated, 'payload.limit'
    mass = robot.moving_mass_kg
    if mass > 0.0:
        return mass, f"the mass of the robot's moving links in the URDF ({mass:.3g} kg)"
    return None


def build_cell_model(cell: Cell, effects: tuple = ()) -> CellModel:
    """Robot, parameters, measurement model and working poses of ``cell``.

    The model holds the cell file's ``effects:`` followed by ``effects`` (specs
    such as ``'joint_compliance:joint_2'`` or bound effects); one given in both
    counts once. Specs are bound with the cell's ``temperature.sensors`` mapping (joint names
    checked against the chain): a listed joint's thermal effects read its sensor's ΔT, and
    the model keeps the mapping (``MeasurementModel.joint_temperatures``) for effects bound
    later.
    """
    if not cell.urdf_xml:
        raise ConfigError('robot.urdf', 'no robot description yet; give robot.urdf or the '
                          'URDF document (with_overrides)')
    robot = RobotModel(cell.urdf_xml, cell.base_frame, cell.tip_frame,
                       Payload(cell.payload_mass, tuple(cell.payload_com)))
    # A payload beyond what the arm carries (its rating, else its moving links' own mass) is a
    # unit slip, as a row's is (app.measurements.check_payload_limit): a 500 kg payload on a
    # Baxter arm was accepted without a word.
    limit = carried_limit(cell.payload_limit, robot)
    stated = [('payload.mass', cell.payload_mass)] + [
        (f'working_poses[{i}].payload', w.payload[0])
        for i, w in enumerate(cell.working_poses) if w.payload is not None]
    for key, mass in stated:
        if limit is not None and mass > limit[0]:
            raise ConfigError(key, f'{mass:g} kg is beyond what the robot carries, '
                              f'{limit[0]:.3g} kg ({limit[1]}): a payload is in kg (grams? '
                              'divide by 1000); if the robot truly carries it, state its '
                              'rating as payload.limit (kg)')
    # Placements left out are zeros here; identification registers them first.
    geometric = geometric_parameters(robot, cell.base_in_tracker, cell.offsets,
                                     cell.reflector_names or None)
    for k in cell.identified_orientations:  # a tracked body's orientation identified
        names = orientation_names(f'reflector.{cell.reflector_names[k]}')
        geometric = geometric.extended(names, np.zeros(3), ['rad'] * 3)
    code = cell.allow_code_effects
    # the temperature each joint's thermal effects read (temperature.sensors mapping)
    temperatures = joint_temperatures(cell.temperature, robot.joint_names)
    resolved = resolve_effects(cell.effects, robot, 'effects', cell.source_dir or None, code,
                               temperatures)
    extra = resolve_effects(effects, robot, 'extra effects', cell.source_dir or None, code,
                            temperatures)
    resolved += tuple(e for e in extra if e.name not in {r.name for r in resolved})
    model = MeasurementModel(robot, geometric, resolved, cell.reflector_axis,
                             dict(cell.reflector_orientations),
                             None if cell.sigma_rotation is None
                             else cell.sigma / cell.sigma_rotation,
                             joint_noise_map(cell.joint_sigma, robot),
                             temperatures)
    for spec in cell.identification.tolerances.bounds:
        parts = spec.split(':')
        if len(parts) > 1 and parts[1] not in robot.joint_names:
            raise ConfigError(f'identification.bounds.{spec}', f'joint {parts[1]!r} is not on '
                              f'the chain; write kind:joint with a joint of {robot.joint_names}')
    unknown = [n for n in cell.identification_priority if n not in model.params.names]
    if unknown:
        raise ConfigError('identification.priority', f'unknown parameter(s) {unknown}; valid '
                          f'names: {list(model.params.names)}')
    missing_masses = mass_warning(robot, resolved)
    if missing_masses:
        warnings.warn(missing_masses, stacklevel=2)
    mimic = mimic_coupling(robot)
    coupling = coupling_from_mapping(cell.joint_coupling, robot.actuated_names,
                                     mimics={j.name: j.mimic for j in robot.joints
                                             if j.mimic is not None}).then(mimic)
    names = list(robot.actuated_names)
    q_work = np.array([_ordered(w, names, f'working_poses[{i}].joints')
                       for i, w in enumerate(cell.working_poses)]).reshape(-1, len(names))
    # Values as the controller reports them, or the URDF's actuated joints' (mimic
    # joints follow either way).
    q_work = (coupling if cell.working_poses_in == 'controller' else mimic).to_urdf(q_work)
    inside = robot.within_limits(q_work)
    if not inside.all():
        bad = cell.working_poses[int(np.argmin(inside))].name
        raise ConfigError('working_poses', f'pose {bad!r} is outside the joint limits '
                          f'{robot.lower.round(3).tolist()} .. {robot.upper.round(3).tolist()}')
    base_in_tracker = pose_matrix(cell.base_in_tracker)
    return CellModel(cell, robot, geometric, model, q_work,
                     tuple(w.name for w in cell.working_poses), np.linalg.inv(base_in_tracker),
                     coupling)


def _ordered(pose: WorkingPose, names: list[str], key: str) -> list[float]:
    if pose.values:
        if len(pose.values) != len(names):
            raise ConfigError(key.rsplit('.', 1)[0], f'{len(pose.values)} joint values given; '
                              f'the robot has {len(names)} joints, in this order: {names}')
        return list(pose.values)
    missing = [n for n in names if n not in pose.joints]
    extra = [n for n in pose.joints if n not in names]
    if missing or extra:
        raise ConfigError(key, f'joint names must be exactly {names}; missing {missing}, '
                          f'unknown {extra}')
    return [pose.joints[n] for n in names]


# How far beyond its URDF limits a joint reading may be: encoder noise and a controller's
# overshoot at a limit, not a pose the calibration has any knowledge of (a measurement
# beyond is refused as `outside_joint_limits`, a TCP query unanswered).
LIMIT_TOLERANCE_RAD = 0.01
LIMIT_TOLERANCE_M = 0.001
# A continuous joint has no limit; beyond 16 turns a value is a unit or driver fault.
CONTINUOUS_MAX_RAD = 32 * np.pi


def joint_range_problem(cm: CellModel, q: np.ndarray) -> str:
    """Why the URDF joint values ``q`` (n,) cannot be a pose of ``cm``'s robot ('' when they
    can): the first joint not finite, beyond its limits by more than the tolerance, or a
    continuous joint beyond ±CONTINUOUS_MAX_RAD, named with its value and range."""
    for joint, value in zip(cm.robot.joints, np.asarray(q, float).reshape(-1)):
        if not np.isfinite(value):
            return f'joint {joint.name} position {value} is not finite'
        if joint.kind == 'continuous':
            if abs(value) > CONTINUOUS_MAX_RAD:
                return (f'joint {joint.name} (continuous) at {value:.6g} rad is beyond '
                        f'±{CONTINUOUS_MAX_RAD:.4g} rad (16 turns): a unit or driver fault')
            continue
        tol = LIMIT_TOLERANCE_M if joint.kind == 'prismatic' else LIMIT_TOLERANCE_RAD
        unit = 'm' if joint.kind == 'prismatic' else 'rad'
        if not joint.lower - tol <= value <= joint.upper + tol:
            return (f'joint {joint.name} at {value:.6g} {unit} is outside its URDF limits '
                    f'[{joint.lower:.6g}, {joint.upper:.6g}] {unit} (tolerance {tol:g} {unit})')
    return ''


def reading_check(cm: CellModel) -> Callable[[np.ndarray], str]:
    """Why a still pose's controller readings (m,) cannot be a pose of ``cm``'s robot ('' when
    they can): :func:`joint_range_problem` of their URDF joint values, for the pairing."""
    return lambda q: joint_range_problem(cm, cm.joint_coupling.to_urdf(q))

"""kpi_calib_node: measurement design, live pairing, durable logging and re-identification.

A thin layer over the core: it converts messages, calls the same functions as
``kpi-calib`` and publishes. Pairing uses :class:`~kpi_calib_ros.core.streams.Pairer`,
the code that pairs bags, so a replayed bag and ``kpi-calib identify`` agree.

Services (std_srvs/srv/Trigger): ``~/design``, ``~/identify``, ``~/reset``.
One executor thread serves callbacks in arrival order; long work (design,
identification) runs in a worker thread while the service callback awaits it, so
pairing continues, and a call while another job runs answers
``success=False, message='busy: ...'``. (rclpy's MultiThreadedExecutor could not keep
up with 1 kHz joint states on two cores.)

Pairing clock: a point waits for joint states up to the pairer's timeout past its
stamp on a clock that follows the joint stream (newest joint stamp + time since it
arrived), so live streams, backlogs and replayed recordings (old stamps) behave alike.
"""
from __future__ import annotations

import shutil
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

from kpi_calib_ros.core.collision import Capsule
from kpi_calib_ros.core.design import DESIGN_CRITERIA, design_measurements
from kpi_calib_ros.core.errors import ConfigError, DataError, KpiCalibError
from kpi_calib_ros.core.estimation import CalibrationResult
from kpi_calib_ros.core.measurement import Measurements
from kpi_calib_ros.core.streams import (REJECTION_REASONS, JointSample, PairedMeasurement,
                                        Pairer, PairingResult, PointSample, Rejection)
from kpi_calib_ros.io.bag import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC, MeasurementLog
from kpi_calib_ros.io.cell import DEFAULT_CELL, CellModel, build_cell_model, cell_from_dict
from kpi_calib_ros.io.results import calibration_to_dict, write_atomic, write_calibration
from kpi_calib_ros.io.urdf_export import calibrated_urdf
from kpi_calib_ros.pipeline import identify_cell
from kpi_calib_ros.ros import conversions as cv

NODE_NAME = 'kpi_calib_node'
CALIBRATED_URDF_FILE = 'robot_description_calibrated.urdf'


@dataclass(frozen=True)
class NodeSettings:
    """Validated node parameters (see :data:`PARAMETERS` for meaning and units)."""

    robot_description: str
    robot_description_topic: str
    cell_file: str
    working_poses: tuple[float, ...]
    working_joint_names: tuple[str, ...]
    num_measurements: int
    criterion: str
    design_seed: int
    joint_states_topic: str
    point_topic: str
    min_measurements: int
    auto_identify: bool
    data_dir: str


# name: (default or parameter type when empty, read only, description)
PARAMETERS: dict[str, tuple[Any, bool, str]] = {
    'robot_description': ('', True, 'URDF document; empty: taken from the latched '
                          'robot_description_topic (as robot_state_publisher provides it)'),
    'robot_description_topic': ('/robot_description', True,
                                'latched std_msgs/String topic with the URDF'),
    'cell_file': ('', True, 'cell YAML (tracker, reflector, noise, working poses, obstacles); '
                  'empty: the built-in simulated cell'),
    'working_poses': (Parameter.Type.DOUBLE_ARRAY, True,
                      'working poses overriding the cell file: flat list, one block of '
                      'len(working_joint_names) joint values (rad) per pose'),
    'working_joint_names': (Parameter.Type.STRING_ARRAY, True,
                            'joint order of working_poses'),
    'num_measurements': (30, False, 'number of measurement poses ~/design computes'),
    'criterion': ('kpi', False, f'design criterion, one of {list(DESIGN_CRITERIA)}'),
    'design_seed': (0, False, 'seed of the design random generator'),
    'joint_states_topic': (DEFAULT_JOINT_TOPIC, True, 'sensor_msgs/JointState topic'),
    'point_topic': (DEFAULT_POINT_TOPIC, True, 'geometry_msgs/PointStamped tracker topic'),
    'min_measurements': (20, False, 'accepted measurements before automatic identification'),
    'auto_identify': (True, False, 'identify when min_measurements is reached, and again '
                      'as more measurements arrive'),
    'data_dir': ('~/.ros/kpi_calib', True, 'measurement log and results (created if missing)'),
}


def settings_from_parameters(values: dict[str, Any]) -> NodeSettings:
    """Validate raw parameter values; ConfigError names the parameter and the fix."""
    def text(key: str, allow_empty: bool = False) -> str:
        value = values[key]
        if not isinstance(value, str) or (not allow_empty and not value.strip()):
            raise ConfigError(key, f'must be a non-empty string, got {value!r}')
        return value

    def integer(key: str, minimum: int) -> int:
        value = values[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise ConfigError(key, f'must be an integer >= {minimum}, got {value!r}')
        return value

    poses = tuple(float(v) for v in values['working_poses'] or ())
    names = tuple(str(v) for v in values['working_joint_names'] or ())
    if poses or names:
        if not names or len(set(names)) != len(names):
            raise ConfigError('working_joint_names', f'give the unique joint names of '
                              f'working_poses, got {list(names)}')
        if not poses or len(poses) % len(names) or not np.all(np.isfinite(poses)):
            raise ConfigError('working_poses', f'must hold finite values (rad), '
                              f'{len(names)} per pose (one per working_joint_names), '
                              f'got {len(poses)} values')
    if values['criterion'] not in DESIGN_CRITERIA:
        raise ConfigError('criterion', f'must be one of {list(DESIGN_CRITERIA)}, '
                          f'got {values["criterion"]!r}')
    if not isinstance(values['auto_identify'], bool):
        raise ConfigError('auto_identify', 'must be true or false')
    topics = {k: text(k) for k in ('robot_description_topic', 'joint_states_topic',
                                   'point_topic')}
    if topics['joint_states_topic'] == topics['point_topic']:
        raise ConfigError('point_topic', 'must differ from joint_states_topic')
    cell_file = text('cell_file', allow_empty=True) or str(DEFAULT_CELL)
    if not Path(cell_file).expanduser().is_file():
        raise ConfigError('cell_file', f'file {cell_file!r} does not exist')
    return NodeSettings(
        robot_description=text('robot_description', allow_empty=True),
        cell_file=str(Path(cell_file).expanduser()), working_poses=poses,
        working_joint_names=names, num_measurements=integer('num_measurements', 1),
        criterion=values['criterion'], design_seed=integer('design_seed', 0),
        min_measurements=integer('min_measurements', 1),
        auto_identify=values['auto_identify'],
        data_dir=str(Path(text('data_dir')).expanduser()), **topics)


def _latched(depth: int = 1) -> QoSProfile:
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _stream_qos(depth: int) -> QoSProfile:
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)


class CalibrationNode(Node):
    """The calibration node; see the module docstring and the README's cell controller
    section for its interface."""

    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        for name, (default, read_only, description) in PARAMETERS.items():
            self.declare_parameter(name, default, ParameterDescriptor(
                description=description, read_only=read_only))
        self.settings = settings_from_parameters(self._parameter_values())
        self.add_on_set_parameters_callback(self._on_set_parameters)
        try:
            self._cell_doc = yaml.safe_load(Path(self.settings.cell_file).read_text())
        except yaml.YAMLError as exc:
            raise ConfigError('cell_file', f'not valid YAML: {exc}') from exc
        self.data_dir = Path(self.settings.data_dir)

        self._state = threading.RLock()      # pairer, log, measurements, results
        self._job = threading.Lock()         # one long job (design / identify / reset)
        self._job_name = ''
        self._cm: CellModel | None = None
        self._urdf = ''
        self._model_error = ''
        self._pairer: Pairer | None = None
        self._early: deque[JointSample | PointSample] = deque(maxlen=20_000)
        # Per stream (points, joint states): newest stamp and monotonic ns of its arrival.
        self._clocks: list[tuple[int, int] | None] = [None, None]
        self._received = [0, 0]
        self._rejections: Counter[str] = Counter()
        self._store_failures = 0
        self._auto_pending = False
        self._result: CalibrationResult | None = None
        self._result_error = ''
        self._identified_with = 0
        self._measured: np.ndarray | None = None
        self._design_points: np.ndarray | None = None
        self._capsules: list[Capsule] = []
        self._last_diagnostics = (None, 0)

        self._measurements: dict[int, tuple[JointSample, PointSample]] = {}
        if self.data_dir.is_dir():
            for joint, point in MeasurementLog.load_all(self.data_dir):
                self._measurements[point.stamp_ns] = (joint, point)
        self.restored = len(self._measurements)
        self._log = MeasurementLog(self.data_dir)
        self.get_logger().info(f'{self.restored} measurement(s) restored from {self.data_dir}; '
                               f'logging to {self._log.path}')

        # One executor thread: pairing callbacks run in arrival order; services await
        # their worker threads in a reentrant group so a second call gets 'busy'.
        streams = MutuallyExclusiveCallbackGroup()
        services = ReentrantCallbackGroup()
        self._pub_poses = self.create_publisher(JointTrajectory, '~/measurement_poses',
                                                _latched())
        self._pub_calibration = self.create_publisher(String, '~/calibration', _latched())
        self._pub_urdf = self.create_publisher(String, '~/robot_description_calibrated',
                                               _latched())
        self._pub_markers = self.create_publisher(MarkerArray, '~/markers', _latched())
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._pub_tcp = None
        self.create_subscription(JointState, self.settings.joint_states_topic,
                                 self._on_joint_state, _stream_qos(1000), callback_group=streams)
        self.create_subscription(PointStamped, self.settings.point_topic, self._on_point,
                                 _stream_qos(100), callback_group=streams)
        for name, doing, work in (('design', 'designing', self._design),
                                  ('identify', 'identifying', self._identify_service),
                                  ('reset', 'resetting', self._reset)):
            self.create_service(Trigger, f'~/{name}', self._service(name, doing, work),
                                callback_group=services)
        self.create_timer(0.1, self._tick, callback_group=streams)
        if self.settings.robot_description:
            self._set_robot_description(self.settings.robot_description)
        else:
            self.create_subscription(String, self.settings.robot_description_topic,
                                     self._on_robot_description, _latched(),
                                     callback_group=streams)
            self.get_logger().info(f'waiting for {self.settings.robot_description_topic}')

    # ------------------------------------------------------------------ parameters
    def _parameter_values(self, changes: dict[str, Any] | None = None) -> dict[str, Any]:
        values = {}
        for name in PARAMETERS:
            try:
                values[name] = self.get_parameter(name).value
            except ParameterUninitializedException:
                values[name] = []
        values.update(changes or {})
        return values

    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        try:
            settings = settings_from_parameters(self._parameter_values(
                {p.name: p.value for p in parameters}))
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.settings = settings
        with self._state:
            self._auto_pending = self._auto_wanted()
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ robot model
    def _on_robot_description(self, msg: String) -> None:
        if msg.data != self._urdf:
            try:
                self._set_robot_description(msg.data)
            except KpiCalibError as exc:
                self._model_error = str(exc)
                self.get_logger().error(f'robot description rejected: {exc}')

    def _set_robot_description(self, urdf_xml: str) -> None:
        doc = dict(self._cell_doc or {})
        if self.settings.working_poses:
            names = self.settings.working_joint_names
            values = np.reshape(self.settings.working_poses, (-1, len(names)))
            doc['working_poses'] = [{'joints': dict(zip(names, map(float, row)))}
                                    for row in values]
        cell = cell_from_dict(doc, Path(self.settings.cell_file).parent, urdf_xml=urdf_xml)
        cm = build_cell_model(cell)
        scene = cm.collision_scene()
        with self._state:
            if self._pairer is not None:
                self._handle(self._pairer.flush())
            self._cm, self._urdf, self._model_error = cm, urdf_xml, ''
            self._capsules = scene.robot_capsules + [o for o in scene.obstacles
                                                     if isinstance(o, Capsule)]
            self._pairer = Pairer(cm.joint_names, cm.cell.tracker_frame)
            if self._pub_tcp is not None:
                self.destroy_publisher(self._pub_tcp)
            self._pub_tcp = self.create_publisher(PoseWithCovarianceStamped, '~/tcp',
                                                  _latched(len(cm.working_pose_names)))
            early, self._early = list(self._early), deque(maxlen=self._early.maxlen)
            for sample in early:  # all of them before any timeout is judged
                self._add(sample)
            if early:
                self._handle(self._pairer.poll(self._now_ns()))
            self._auto_pending = self._auto_wanted()
        self.get_logger().info(f'robot model ready: joints {cm.joint_names}, tracker frame '
                               f"'{cm.cell.tracker_frame}', working poses "
                               f'{list(cm.working_pose_names)}')

    # ------------------------------------------------------------------ live pairing
    def _on_joint_state(self, msg: JointState) -> None:
        self._receive(cv.joint_sample_from_msg(msg))

    def _on_point(self, msg: PointStamped) -> None:
        self._receive(cv.point_sample_from_msg(msg))

    def _receive(self, sample: JointSample | PointSample) -> None:
        with self._state:
            joint = isinstance(sample, JointSample)
            self._received[joint] += 1
            # The joint stream is the clock: points wait for joint states as long as
            # they keep coming, however far behind real time (a backlog, a replay).
            # Only before the first joint state do points set it.
            clock = self._clocks[joint]
            if clock is None or sample.stamp_ns > clock[0]:
                self._clocks[joint] = (sample.stamp_ns, time.monotonic_ns())
            if self._pairer is None:
                self._early.append(sample)  # paired once the robot model is known
                return
            self._add(sample)
            self._handle(self._pairer.poll(self._now_ns()))

    def _add(self, sample: JointSample | PointSample) -> None:
        if isinstance(sample, JointSample):
            self._pairer.add_joint_sample(sample)
        else:
            self._pairer.add_point(sample)

    def _now_ns(self) -> int:
        stamp, arrived = self._clocks[1] or self._clocks[0]
        return stamp + time.monotonic_ns() - arrived

    def _handle(self, decisions: list[PairedMeasurement | Rejection]) -> None:
        for d in decisions:
            if isinstance(d, Rejection):
                self._rejections[d.reason] += 1
                self.get_logger().warning(f'rejected ({d.reason}): {d.detail}',
                                          throttle_duration_sec=1.0)
            elif d.stamp_ns in self._measurements:
                self._rejections['duplicate_stamp'] += 1
            else:
                joint, point = d.joint_sample(), d.point_sample()
                try:
                    self._log.append(joint, point)  # on disk before it counts
                except OSError as exc:
                    self._store_failures += 1
                    self.get_logger().error(f'measurement at {d.stamp_ns} ns not stored: {exc}')
                    continue
                self._measurements[d.stamp_ns] = (joint, point)
                self._auto_pending = self._auto_pending or self._auto_wanted()

    def _auto_wanted(self) -> bool:
        return (self.settings.auto_identify and self._cm is not None
                and len(self._measurements) >= self.settings.min_measurements)

    def _tick(self) -> None:
        with self._state:
            if self._pairer is not None and any(self._clocks):
                self._handle(self._pairer.poll(self._now_ns()))
            start = self._auto_pending and self._job.acquire(blocking=False)
            if start:
                self._auto_pending = False
                self._job_name = 'identifying (automatic)'
        if start:
            threading.Thread(target=self._run_job, daemon=True,
                             args=('automatic identification', self._identify_service)).start()
        self._publish_diagnostics()

    # ------------------------------------------------------------------ jobs
    def _service(self, name: str, doing: str, work: Callable[[], tuple[bool, str]]):
        """A Trigger callback that runs ``work`` in a worker thread and answers when it is
        done; the executor keeps serving meanwhile (the callback awaits, it does not block)."""
        async def callback(request: Trigger.Request,
                           response: Trigger.Response) -> Trigger.Response:
            if not self._job.acquire(blocking=False):
                response.success, response.message = False, f'busy: {self._job_name}'
                return response
            self._job_name = doing
            done = Future(executor=self.executor)
            done.add_done_callback(lambda _: None)  # its scheduling wakes the executor
            threading.Thread(target=self._run_job, args=(name, work, done), daemon=True).start()
            response.success, response.message = await done
            return response
        return callback

    def _run_job(self, name: str, work: Callable[[], tuple[bool, str]],
                 done: Future | None = None) -> None:
        """Run ``work`` holding the job lock (acquired by the caller), then release it."""
        try:
            outcome = work()
        except Exception as exc:  # job boundary: answer, log, keep the node up
            self.get_logger().error(f'{name} failed: {exc}')
            outcome = (False, f'{name} failed: {exc}')
        else:
            self.get_logger().info(f'{name}: {outcome[1]}')
        self._job_name = ''
        self._job.release()
        if done is not None:
            done.set_result(outcome)

    def _model(self) -> CellModel:
        if self._cm is None:
            raise DataError(self._model_error or 'no robot model yet: waiting for '
                            f'{self.settings.robot_description_topic}')
        return self._cm

    def _design(self) -> tuple[bool, str]:
        cm, s = self._model(), self.settings
        design = design_measurements(cm, s.num_measurements, s.criterion,
                                     np.random.default_rng(s.design_seed))
        self._pub_poses.publish(cv.joint_trajectory_msg(design.joint_names,
                                                        design.configurations))
        self._design_points = cm.model.predict(cm.model.params.nominal, design.configurations)
        self._publish_markers()
        std_um = np.sqrt((design.tcp_std ** 2).sum(axis=1)).max() * 1e6
        ok = design.verification.ok
        return ok, (f'{len(design.configurations)} poses ({design.criterion}), predicted TCP '
                    f'sqrt(trace) <= {std_um:.1f} µm; {design.status}; published on '
                    f'{self.resolve_topic_name("~/measurement_poses")}')

    def _identify_service(self) -> tuple[bool, str]:
        message = self._identify()
        return self._result is not None and self._result.converged, message

    def _identify(self) -> str:
        """Identify from every accepted measurement; write and publish the results."""
        cm = self._model()
        with self._state:
            pairs = [self._measurements[k] for k in sorted(self._measurements)]
            rejections = dict(self._rejections)
        if not pairs:
            raise DataError('no accepted measurement yet')
        try:
            q = np.array([[dict(zip(j.names, j.positions))[n] for n in cm.joint_names]
                          for j, _ in pairs])
        except KeyError as exc:
            raise DataError(f'a stored measurement lacks joint {exc}; the robot model '
                            f'joints are {cm.joint_names}: ~/reset to start over') from None
        eta = np.array([p.xyz for _, p in pairs])
        stamps = np.array([p.stamp_ns for _, p in pairs], dtype=np.int64)
        pairing = PairingResult(tuple(cm.joint_names), cm.cell.tracker_frame, q, eta, stamps,
                                rejections=rejections)
        try:
            result = identify_cell(cm, Measurements(q=q, eta=eta, stamps_ns=stamps))
        except KpiCalibError as exc:
            self._result_error = str(exc)
            raise
        doc = calibration_to_dict(result, pairing)
        urdf = calibrated_urdf(cm.cell.urdf_xml, cm.robot, dict(zip(result.names,
                                                                    result.values)))
        write_calibration(self.data_dir, doc)
        write_atomic(self.data_dir / CALIBRATED_URDF_FILE, urdf)
        with self._state:
            self._result, self._identified_with = result, len(pairs)
            self._result_error = '' if result.converged else result.status
            self._measured = eta
        stamp = int(stamps[-1])
        self._pub_calibration.publish(String(data=yaml.safe_dump(doc, sort_keys=False)))
        self._pub_urdf.publish(String(data=urdf))
        for msg in cv.tcp_pose_msgs(result.tcp, result.tcp_covariance,
                                    cm.cell.tracker_frame, stamp):
            self._pub_tcp.publish(msg)
        self._publish_markers()
        self._publish_diagnostics(force=True)
        tcp_um = np.sqrt(np.trace(result.tcp_covariance, axis1=1, axis2=2)).max() * 1e6
        return (f'identified from {len(pairs)} measurements: {result.status}; rms '
                f'{result.rms_m * 1e6:.1f} µm, p = {result.p_value:.3g}, TCP sqrt(trace) <= '
                f'{tcp_um:.1f} µm; written to {self.data_dir}')

    def _reset(self) -> tuple[bool, str]:
        """Start a new campaign: archive (never delete) the log and results."""
        with self._state:
            archive = self.data_dir / 'archive' / time.strftime('%Y%m%dT%H%M%S')
            while archive.exists():
                archive = archive.with_name(archive.name + '_')
            archive.mkdir(parents=True)
            self._log.close()
            moved = [p for p in self.data_dir.glob('measurements_*.mcap')]
            moved += [p for p in (self.data_dir / 'calibration.yaml',
                                  self.data_dir / CALIBRATED_URDF_FILE) if p.exists()]
            for path in moved:
                shutil.move(str(path), archive / path.name)
            count = len(self._measurements)
            self._measurements.clear()
            self._rejections.clear()
            self._store_failures = 0
            self._result, self._result_error, self._identified_with = None, '', 0
            self._auto_pending = False
            self._log = MeasurementLog(self.data_dir)
            if self._cm is not None:
                self._pairer = Pairer(self._cm.joint_names, self._cm.cell.tracker_frame)
        self._publish_markers()
        self._publish_diagnostics(force=True)
        return True, f'archived {count} measurement(s) and results to {archive}'

    # ------------------------------------------------------------------ outputs
    def _publish_markers(self) -> None:
        cm = self._cm
        if cm is None:
            return
        result = self._result
        # Stamp 0: RViz draws latched markers with the latest transforms.
        self._pub_markers.publish(cv.marker_array_msg(
            0, cm.cell.tracker_frame, cm.cell.base_frame,
            design_points=self._design_points,
            tcp=None if result is None else result.tcp,
            tcp_covariance=None if result is None else result.tcp_covariance,
            capsules=self._capsules,
            measured=None if result is None else self._measured,
            residuals=None if result is None else result.residuals))

    def status(self) -> tuple[str, str, dict[str, Any]]:
        """(level, message, key values) of the node as /diagnostics reports it."""
        with self._state:
            result, n = self._result, len(self._measurements)
            rejected = sum(self._rejections.values())
            values: dict[str, Any] = {
                'state': self._job_name or ('waiting for robot description'
                                            if self._cm is None else 'idle'),
                'accepted': n, 'restored': self.restored, 'rejected': rejected,
                'received.joint_states': self._received[1],
                'received.points': self._received[0]}
            values.update({f'rejected.{r}': self._rejections.get(r, 0)
                           for r in REJECTION_REASONS})
            values.update({'ignored_joint_samples':
                           self._pairer.ignored_joint_samples if self._pairer else 0,
                           'pending_points': self._pairer.pending if self._pairer else 0,
                           'store_failures': self._store_failures,
                           'identified_with': self._identified_with,
                           'log_file': str(self._log.path)})
            error = self._model_error or self._result_error
        if result is not None:
            values.update({'rms_um': round(result.rms_m * 1e6, 3),
                           'p_value': float(result.p_value), 'converged': result.converged})
        if error or self._store_failures:
            return 'ERROR', error or 'measurements could not be stored', values
        if result is not None and result.p_value <= 0.01:
            return 'WARN', f'model inadequate (p = {result.p_value:.2g})', values
        if rejected:
            return 'WARN', f'{n} accepted, {rejected} rejected', values
        if self._cm is None:
            return 'OK', 'waiting for robot description', values
        return 'OK', f'{n} accepted' + (f', rms {result.rms_m * 1e6:.1f} µm'
                                        if result is not None else ''), values

    def _publish_diagnostics(self, force: bool = False) -> None:
        level, message, values = self.status()
        key, now = (level, message, tuple(values.items())), time.monotonic()
        last_key, last_time = self._last_diagnostics
        if force or key != last_key or now - last_time >= 1.0:
            self._last_diagnostics = (key, now)
            self._pub_diagnostics.publish(cv.diagnostic_array_msg(
                self.get_clock().now().nanoseconds, f'{self.get_name()}: calibration', level,
                message, values, hardware_id='laser_tracker'))

    def destroy_node(self) -> None:
        with self._state:
            self._log.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    node = None
    try:
        node = CalibrationNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except KpiCalibError as exc:
        print(f'{NODE_NAME}: error: {exc}', file=sys.stderr)
        return 2
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""kpi_calib_node: measurement design, live pairing, durable logging and re-identification.

A thin layer over the core: it converts messages, calls the same functions as
``kpi-calib`` and publishes. Live samples and each point's stated σ go to a
:class:`~kpi_calib_ros.ros.measurement_store.MeasurementStore`, which pairs them with the code that
pairs bags and logs every accepted measurement to disk before counting it, so a
replayed bag and ``kpi-calib identify`` agree and a killed node loses nothing.

Services (std_srvs/srv/Trigger): ``~/design``, ``~/identify``, ``~/diagnose``, ``~/validate``,
``~/reset``, run as jobs one at a time (:mod:`~kpi_calib_ros.ros.job_node`; identify,
diagnose and validate in :mod:`~kpi_calib_ros.ros.calibration_jobs`, the sequential
campaign's in :mod:`~kpi_calib_ros.ros.sequential_jobs`; the last valid calibration.yaml
is restored at start by :mod:`~kpi_calib_ros.ros.restore`). One executor thread serves
callbacks in arrival order; long work runs in a worker thread while the job coroutine
awaits it, so pairing continues. (rclpy's MultiThreadedExecutor could not keep up with
1 kHz joint states on two cores.)

Threads: the executor thread owns the node. Every node attribute (robot model, the run's
results in one :class:`~kpi_calib_ros.ros.run_state.RunState`, design points, job name,
settings) and every publisher is read and written on the executor thread only. A job
takes what it needs from the node, hands plain inputs to a worker thread with
``await self._offload(fn, ...)``, and when the worker's value comes back (the
coroutine resumes on the executor) it updates the state and publishes. Worker
functions (:mod:`kpi_calib_ros.ros.job_work`) compute and write result files, and never
see the node. The one object both sides touch is the :class:`MeasurementStore`, which is
thread-safe by its own lock. Hence no node lock: ``~/tcp`` is created when the first
robot model gives its number of working poses and replaced (on the executor, where
nothing else can be publishing on it) only if a later model has a different number.
/diagnostics is :func:`~kpi_calib_ros.ros.status.node_status` of that state.

Parameters follow ros2/demos ``set_parameters_callback.py``: the on-set callback only
validates (every value, through :func:`settings_from_parameters`, and rejects with the
reason); the post-set callback applies the accepted values.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PoseStamped, PoseWithCovarianceStamped, Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

from kpi_calib_ros.app.cell_model import CellModel, build_cell_model, reading_check
from kpi_calib_ros.core.acquisition.outcomes import Decision, Rejection
from kpi_calib_ros.core.collision.capsules import Capsule
from kpi_calib_ros.core.errors import ConfigError, DataError, KpiCalibError
from kpi_calib_ros.core.measurement.covariates import TEMPERATURE_RANGE_C
from kpi_calib_ros.io.calibration_file import calibration_recordings
from kpi_calib_ros.io.cell import load_cell, with_overrides
from kpi_calib_ros.io.names import (
    CALIBRATED_URDF_TOPIC,
    CALIBRATION_TOPIC,
    CAMPAIGN_STATUS_TOPIC,
    CHANGE_TEST_TOPIC,
    DIAGNOSIS_TOPIC,
    DIAGNOSTICS_TOPIC,
    LEARNED_RESIDUAL_FILE,
    MARKERS_TOPIC,
    MEASUREMENT_POSES_TOPIC,
    TCP_TOPIC,
    VALIDATION_TOPIC,
    point_sigma_topic,
)
from kpi_calib_ros.io.yaml_bounded import SAFE_LOADER
from kpi_calib_ros.ros import conversions as cv
from kpi_calib_ros.ros import job_work
from kpi_calib_ros.ros.answers import design_answer
from kpi_calib_ros.ros.calibration_jobs import CalibrationJobs
from kpi_calib_ros.ros.delivery import (
    JOINT_STATES_MAX_HZ,
    POINTS_MAX_HZ,
    STREAM_BUFFER_S,
    MessageSequence,
    latched,
    stream_qos,
)
from kpi_calib_ros.ros.inputs import subscribe_inputs
from kpi_calib_ros.ros.measurement_store import MeasurementStore
from kpi_calib_ros.ros.parameters import (
    declare_parameters,
    parameter_values,
    settings_from_parameters,
    working_poses,
)
from kpi_calib_ros.ros.restore import CalibrationRestore
from kpi_calib_ros.ros.run_state import CAMPAIGN_FIXED, RunState
from kpi_calib_ros.ros.sequential_jobs import SequentialCampaignJobs
from kpi_calib_ros.ros.status import StreamHealth, node_status
from kpi_calib_ros.ros.stop_request import POLL_S, StopRequest
from kpi_calib_ros.ros.tcp_query import TcpQuery
from kpi_calib_ros.ros.temperature import subscribe_temperature

NODE_NAME = 'kpi_calib_node'


# The parameters that name the station of the arriving measurements.
STATION_PARAMETERS = {'station', 'station_reflector_remounted'}


class CalibrationNode(CalibrationJobs, CalibrationRestore, SequentialCampaignJobs):
    """The calibration node; the README's "cell controller" section lists its interface."""

    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        declare_parameters(self)
        self.settings = settings_from_parameters(parameter_values(self))
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        # The cell once, validated; the URDF comes from the parameter or the topic.
        self._cell = load_cell(self.settings.cell_file, urdf_xml='',
                               allow_code_effects=self.settings.allow_code_effects)
        self.data_dir = Path(self.settings.data_dir)
        measured_torques = self._cell.inputs.torque_source == 'measured'
        try:
            self.store = MeasurementStore(
                self.data_dir, sigma_topic=point_sigma_topic(self.settings.point_topic),
                temperature_topic=(self._cell.temperature.topic if self._cell.temperature
                                   else None),
                temperature_range_c=(self._cell.temperature.valid_range_c
                                     if self._cell.temperature else TEMPERATURE_RANGE_C),
                # The named inputs topic always: identify reads a bag's rows from it, and
                # a replayed bag (or a controller) publishes them there.
                inputs_topic=self._cell.inputs.topic,
                record_efforts=measured_torques, station=self.settings.station,
                reflector_remounted=self.settings.station_reflector_remounted)
        except OSError as exc:  # missing parent, read-only, a file in the way, no space
            raise ConfigError('data_dir', f'cannot log measurements in {str(self.data_dir)!r}: '
                              f'{exc.strerror or exc}; give a writable folder') from None
        except ValueError as exc:  # a station measured before with the other remount
            raise ConfigError('station_reflector_remounted', str(exc)) from None
        self.get_logger().info(f'{self.store.restored} measurement(s) restored from '
                               f'{self.data_dir}; logging to {self.store.log.path} (station '
                               f'{self.store.station[0]!r})')

        # Executor-thread state (see the module docstring): never touched by a worker.
        self._cm: CellModel | None = None
        self._urdf = ''
        self._model_error = ''
        self._design_points: np.ndarray | None = None
        self._capsules: list[Capsule] = []
        self._last_diagnostics: tuple[Any, float] = (None, 0.0)
        # This campaign's results and sequential campaign, replaced whole by ~/reset.
        self._run = RunState()
        self._find_campaign_state()
        self._find_calibration()  # the last valid calibration.yaml, restored (ros/restore.py)

        # One executor thread: pairing callbacks run in arrival order; services await
        # their worker threads in a reentrant group so a second call gets 'busy'.
        streams = MutuallyExclusiveCallbackGroup()
        services = ReentrantCallbackGroup()
        self._pub_poses = self.create_publisher(JointTrajectory, MEASUREMENT_POSES_TOPIC,
                                                latched())
        self._pub_calibration = self.create_publisher(String, CALIBRATION_TOPIC, latched())
        self._pub_change_test = self.create_publisher(String, CHANGE_TEST_TOPIC, latched())
        self._pub_urdf = self.create_publisher(String, CALIBRATED_URDF_TOPIC, latched())
        self._pub_markers = self.create_publisher(MarkerArray, MARKERS_TOPIC, latched())
        self._pub_diagnosis = self.create_publisher(String, DIAGNOSIS_TOPIC, latched())
        self._pub_validation = self.create_publisher(String, VALIDATION_TOPIC, latched())
        self._pub_campaign_status = self.create_publisher(String, CAMPAIGN_STATUS_TOPIC,
                                                          latched())
        self._calibration_text = ''            # the published calibration.yaml
        self._identified_stamps: set[int] = set()  # stamps the calibration was fitted to
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        # Latched, one message per working pose: made when a model gives their number.
        self._pub_tcp: Publisher | None = None
        self._tcp_depth = 0
        self._sequences = {'joint_states': MessageSequence(), 'points': MessageSequence(),
                           'poses': MessageSequence(), 'sigma': MessageSequence()}
        self._identifications = 0
        # Callbacks with (message, message info); rclpy 7.1's annotation omits that form.
        self.create_subscription(JointState, self.settings.joint_states_topic,
                                 self._on_joint_state,  # type: ignore[arg-type]
                                 stream_qos(int(JOINT_STATES_MAX_HZ * STREAM_BUFFER_S)),
                                 callback_group=streams)
        self.create_subscription(PointStamped, self.settings.point_topic,
                                 self._on_point,  # type: ignore[arg-type]
                                 stream_qos(int(POINTS_MAX_HZ * STREAM_BUFFER_S)),
                                 callback_group=streams)
        self.create_subscription(PoseStamped, self.settings.pose_topic,
                                 self._on_pose,  # type: ignore[arg-type]
                                 stream_qos(int(POINTS_MAX_HZ * STREAM_BUFFER_S)),
                                 callback_group=streams)
        # Each point's stated σ, paired with it by stamp and frame id (ros/measurement_store.py).
        self.create_subscription(Vector3Stamped, point_sigma_topic(self.settings.point_topic),
                                 self._on_point_sigma,  # type: ignore[arg-type]
                                 stream_qos(int(POINTS_MAX_HZ * STREAM_BUFFER_S)),
                                 callback_group=streams)
        subscribe_temperature(self, self.store, callback_group=streams)
        subscribe_inputs(self, self.store, self._cell.inputs.sources, callback_group=streams,
                         named_topic=self._cell.inputs.topic)
        for name, doing, work in (('design', 'designing', self._design),
                                  ('identify', 'identifying', self._identify),
                                  ('diagnose', 'diagnosing', self._diagnose),
                                  ('validate', 'validating', self._validate),
                                  ('reset', 'resetting', self._reset)):
            self.create_service(Trigger, f'~/{name}', self._service(name, doing, work),
                                callback_group=services)
        # The calibration's own model (with the effects identification.model auto added).
        self.tcp_query = TcpQuery(self, lambda: self._run.cell or self._cm,
                                  lambda: self._run.result or self._run.restored,
                                  self.data_dir / LEARNED_RESIDUAL_FILE)
        self.create_timer(0.1, self._tick, callback_group=streams)
        if self.settings.robot_description:
            self._set_robot_description(self.settings.robot_description)
        else:
            self.create_subscription(String, self.settings.robot_description_topic,
                                     self._on_robot_description, latched(),
                                     callback_group=streams)
            self.get_logger().info(f'waiting for {self.settings.robot_description_topic}')

    # ------------------------------------------------------------------ parameters
    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """On-set callback: judge the values as they would be after the change; no side
        effect (another callback may still reject the change)."""
        try:
            settings_from_parameters(parameter_values(
                self, {p.name: p.value for p in parameters}))
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        refused = self._run.refused_change([p.name for p in parameters if p.name in
                                            CAMPAIGN_FIXED and p.value != getattr(
                                                self.settings, p.name)])
        changes = {p.name: p.value for p in parameters}
        if not refused and STATION_PARAMETERS & set(changes):
            station = changes.get('station', self.settings.station)
            refused = self.store.station_conflict(station, self._station_remount(
                changes, station))
        return SetParametersResult(successful=not refused, reason=refused)

    def _station_remount(self, changes: dict[str, Any], station: str) -> bool:
        """Whether ``station`` is remounted after the parameter ``changes``: as stated with
        them, else, the station set alone, the station's own (its recorded remount; a new
        station is not remounted). A parameter keeps its value, and a new station set alone
        after a remounted one took its remount: its probe got offsets of its own silently."""
        if 'station_reflector_remounted' in changes:
            return bool(changes['station_reflector_remounted'])
        if 'station' in changes:
            return self.store.station_remount(station)
        return self.settings.station_reflector_remounted

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        """Post-set callback: the values are set (and were validated); use them. A new
        station (or remount) starts its log file now: the measurements stored from here on
        belong to it."""
        self.settings = settings_from_parameters(parameter_values(self))
        names = {p.name for p in parameters}
        if STATION_PARAMETERS & names:
            remount = self._station_remount({p.name: p.value for p in parameters},
                                            self.settings.station)
            before = self.store.station
            try:
                changed = self.store.set_station(self.settings.station, remount)
            except (OSError, ValueError) as exc:  # validated: only a disk that fails now
                self.get_logger().error(f'station not changed, still '
                                        f'{self.store.station[0]!r}: {exc}')
            else:
                if changed:
                    self.get_logger().info(f'station {self.store.station[0]!r} (probe '
                                           f'remounted: {self.store.station[1]}) from now on; '
                                           f'logging to {self.store.log.path}')
                if changed and self._run.sequential_running():
                    self._stop_for_station(before, self.store.station)
                if remount != self.settings.station_reflector_remounted:
                    # The parameter follows the station set alone (its own remount).
                    self.set_parameters([Parameter('station_reflector_remounted',
                                                   Parameter.Type.BOOL, remount)])
        self._run.auto_pending = self._auto_wanted()

    # ------------------------------------------------------------------ robot model
    def _on_robot_description(self, msg: String) -> None:
        if msg.data != self._urdf:
            try:
                self._set_robot_description(msg.data)
            except (KpiCalibError, ValueError) as exc:  # bad URDF / cell: report, keep waiting
                self._model_error = f'robot description rejected: {exc}'
                self.get_logger().error(self._model_error)

    def _set_robot_description(self, urdf_xml: str) -> None:
        cm = build_cell_model(with_overrides(self._cell, urdf_xml=urdf_xml,
                                             working_poses=working_poses(self.settings)))
        # Robot capsules need the collision geometry, which only a design needs (and may
        # not be findable): drawn once a design has built them (see _design).
        self._capsules = [o for o in cm.obstacles if isinstance(o, Capsule)]
        self._tcp_publisher(len(cm.working_pose_names))
        self._cm, self._urdf, self._model_error = cm, urdf_xml, ''
        self._report(self.store.set_chain(cm.joint_names, cm.cell.tracker_frame,
                                          cm.cell.reflector_names or ('',),
                                          cm.joint_coupling.derived(), reading_check(cm)))
        self._run.auto_pending = self._auto_wanted()
        self.get_logger().info(f'robot model ready: joints {cm.joint_names}, tracker frame '
                               f"'{cm.cell.tracker_frame}', working poses "
                               f'{list(cm.working_pose_names)}')

    def _tcp_publisher(self, depth: int) -> Publisher:
        """``~/tcp``, latched with ``depth`` messages (one per working pose), so a late
        subscriber gets the latest identification's poses and no older ones. Replaced
        only when the depth changes; safe because only the executor publishes."""
        if self._pub_tcp is None or depth != self._tcp_depth:
            if self._pub_tcp is not None:
                self.destroy_publisher(self._pub_tcp)
            # A cell without working poses publishes no TCP; depth 0 is no valid history.
            self._pub_tcp = self.create_publisher(PoseWithCovarianceStamped, TCP_TOPIC,
                                                  latched(max(depth, 1)))
            self._tcp_depth = depth
        return self._pub_tcp

    # ------------------------------------------------------------------ live pairing
    def _on_joint_state(self, msg: JointState, info: dict[str, Any]) -> None:
        self._sequences['joint_states'].see(info)
        sample = cv.joint_sample_from_msg(msg)
        if self.store.record_efforts:  # before the point it may complete is paired
            self.store.receive_efforts(sample.stamp_ns, sample.names, np.asarray(msg.effort))
        self._report(self.store.receive(sample))

    def _on_point(self, msg: PointStamped, info: dict[str, Any]) -> None:
        self._sequences['points'].see(info)
        self._report(self.store.receive(cv.point_sample_from_msg(msg)))

    def _on_pose(self, msg: PoseStamped, info: dict[str, Any]) -> None:
        """A tracked 6-DoF body: a point with its orientation, paired like any point."""
        self._sequences['poses'].see(info)
        self._report(self.store.receive(cv.pose_sample_from_msg(msg)))

    def _on_point_sigma(self, msg: Vector3Stamped, info: dict[str, Any]) -> None:
        """A point's stated σ per axis (m): stored with its measurement, which then
        weighs by it instead of the cell's noise.sigma."""
        self._sequences['sigma'].see(info)
        self._report(self.store.receive_sigma(*cv.point_sigma_from_msg(msg)))

    def _report(self, decisions: list[Decision]) -> None:
        for d in decisions:
            if isinstance(d, Rejection):
                self.get_logger().warning(f'rejected ({d.reason}): {d.detail}',
                                          throttle_duration_sec=1.0)
            elif self._auto_wanted():
                self._run.auto_pending = True

    def _auto_wanted(self) -> bool:
        # A sequential campaign re-identifies in its own steps and publishes its own
        # calibration when it stops (none after 'model inadequate').
        return (self.settings.auto_identify and self._cm is not None
                and self._run.sequential is None and self._run.sequential_state is None
                and len(self.store) >= self.settings.min_measurements)

    def _tick(self) -> None:
        self._report(self.store.poll())
        # Before anything is identified: a new calibration replaces the restored one.
        if (self._run.restore_pending and self._cm is not None
                and self._claim_job('restoring the calibration')):
            self._run.restore_pending = False
            self._create_task('restoring the calibration', self._restore)
        if (self._run.resume_pending and self._cm is not None
                and self._claim_job('resuming the sequential campaign')):
            self._create_task('resuming the sequential campaign', self._resume)
        state = self._run.sequential_state
        if (self._run.sequential_due(self.store.station_count(state.station if state else ''))
                and self._claim_job('planning the next pose')):
            self._create_task('sequential campaign step', self._sequential_step)
        if self._run.auto_pending and self._claim_job('identifying (automatic)'):
            self._run.auto_pending = False
            self._create_task('automatic identification', self._identify)
        self._publish_diagnostics()

    def _model(self) -> CellModel:
        if self._cm is None:
            raise DataError(self._model_error or 'no robot model yet: waiting for '
                            f'{self.settings.robot_description_topic}')
        return self._cm

    async def _design(self) -> tuple[bool, str]:
        cm = self._model()
        if self.settings.campaign == 'sequential':
            return await self._design_sequential(cm)
        station, held, note = self._design_station()
        if held:
            design, points, path, not_estimable, note = await self._offload(
                job_work.station_design_work, cm, self.settings, self.data_dir,
                self._calibration_text, station, child=True)
        else:
            design, points, path, not_estimable = await self._offload(
                job_work.design_work, cm, self.settings, self.data_dir, child=True)
        self._pub_poses.publish(cv.joint_trajectory_msg(design.joint_names,
                                                        design.configurations))
        self._design_points = points
        # Built (and cached) by the design: fitted and hand-given robot capsules.
        self._capsules = list(cm.robot_geometry().capsules) + [
            o for o in cm.obstacles if isinstance(o, Capsule)]
        self._publish_markers()
        return design.verification.ok and not not_estimable, design_answer(
            design, not_estimable, self.resolve_topic_name(MEASUREMENT_POSES_TOPIC),
            path) + (f'; {note}' if note else '')

    def _design_station(self) -> tuple[str, bool, str]:
        """The current station, whether the published calibration identified it with
        others (then ~/design plans it with that calibration as prior, from where it
        places the station), and what the answer says otherwise."""
        station = self.store.station[0]
        if not self._calibration_text:
            return station, False, ''
        names = [r.name for r in calibration_recordings(
            yaml.load(self._calibration_text, Loader=SAFE_LOADER), 'the calibration')]
        if len(names) < 2:
            return station, False, ''
        if station in names:
            return station, True, ''
        return station, False, (
            f'station {station!r} is not in the calibration (stations {", ".join(names)}): '
            'designed where the cell file places the robot; measure a few poses from it '
            'and call ~/identify, then ~/design plans it from where it stands with the '
            'stations before it as prior')

    async def _reset(self) -> tuple[bool, str]:
        """Start a new campaign: archive (never delete) the logs and results."""
        count, archive = await self._offload(self.store.reset)
        self._run = RunState()
        self._publish_markers()
        self._publish_diagnostics(force=True)
        return True, f'archived {count} measurement(s) and the results to {archive}'

    # ------------------------------------------------------------------ outputs
    def _publish_markers(self) -> None:
        cm = self._cm
        if cm is None:
            return
        tcp, tcp_covariance = self._run.published_tcp()
        measured, residuals = self._run.residual_arrows()
        # Stamp 0: RViz draws latched markers with the latest transforms.
        self._pub_markers.publish(cv.marker_array_msg(
            0, cm.cell.tracker_frame, cm.cell.base_frame, design_points=self._design_points,
            tcp=tcp, tcp_covariance=tcp_covariance,
            capsules=self._capsules, measured=measured, residuals=residuals))

    def status(self) -> tuple[str, str, dict[str, Any]]:
        """(level, message, key values) as /diagnostics reports them (:func:`node_status`)."""
        seq = self._sequences
        return node_status(self._run, self.store.counts(), StreamHealth(
            seq['joint_states'].lost, seq['points'].lost + seq['poses'].lost + seq['sigma'].lost,
            seq['joint_states'].max_lag_ns), job=self._job_name, model_ready=self._cm is not None,
            model_error=self._model_error, identifications=self._identifications,
            log_file=str(self.store.log.path), tcp_query=self.tcp_query.source,
            station=self.store.station[0])

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
        self.store.close()  # finalise the log; it is complete on disk anyway
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    # SIGINT/SIGTERM end the spin between callbacks (ros/stop_request.py says why not
    # rclpy's handlers and KeyboardInterrupt).
    stop = StopRequest()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        node = CalibrationNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.requested:
            executor.spin_once(timeout_sec=POLL_S)
    except ExternalShutdownException:  # the context shut down by another part of the process
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
